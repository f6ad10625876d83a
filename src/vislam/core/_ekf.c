/*
 * vislam.core._ekf: compiled kernels of the SLAM EKF's per-frame arithmetic.
 *
 * Each function here is the compiled twin of a numpy function of vislam.core.updaters
 * or vislam.core.propagation (named in its comment); those numpy functions are the
 * reference, and tests/test_kernels.py checks every kernel against its twin on random
 * and on near-degenerate inputs. The Python side (vislam.core.kernels) checks shapes
 * and dtypes and allocates every output; this file only computes.
 *
 * Conventions: every array is float64 (int64 for indices, uint8 for masks), C order
 * (row-major). The covariance Sigma is the top-left n x n block of the state's
 * row-major buffer with leading dimension ld. Tangent order (v, w); the pose variable
 * is imu_T_world, perturbed on the left (see vislam.core.lie and vislam.core.state).
 *
 * The large products of the update (Cholesky of S, the triangular solve for B, the
 * rank-m downdate of Sigma) call BLAS/LAPACK through the function pointers of
 * scipy.linalg.cython_blas / cython_lapack, handed over once by set_lapack(). Those
 * routines are column-major: a row-major r x c array is the column-major c x r array
 * of its transpose, which is how every call below reads its arguments.
 *
 * Compiled with -DEKF_TIMING, update() accumulates the time of each of its stages and
 * timings() returns them (for profiling; docs/benchmarks.md "Where a frame's time goes").
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

typedef void (*dsyrk_t)(char *, char *, int *, int *, double *, double *, int *, double *, double *, int *);
typedef void (*dtrsm_t)(char *, char *, char *, char *, int *, int *, double *, double *, int *, double *, int *);
typedef void (*dgemm_t)(char *, char *, int *, int *, int *, double *, double *, int *, double *, int *, double *,
                        double *, int *);
typedef void (*dpotrf_t)(char *, int *, double *, int *, int *);
typedef void (*dgemv_t)(char *, int *, int *, double *, double *, int *, double *, int *, double *, double *, int *);

static dsyrk_t p_dsyrk = NULL;
static dtrsm_t p_dtrsm = NULL;
static dgemm_t p_dgemm = NULL;
static dpotrf_t p_dpotrf = NULL;
static dgemv_t p_dgemv = NULL;

#define SMALL_ANGLE 1e-2

#ifdef EKF_TIMING
#include <time.h>
static double tacc[16];
static double tnow(void) { struct timespec ts; clock_gettime(CLOCK_MONOTONIC, &ts); return ts.tv_sec + 1e-9 * ts.tv_nsec; }
#define TMARK(i) do { double _t = tnow(); tacc[i] += _t - tlast; tlast = _t; } while (0)
#define TSTART double tlast = tnow()
#else
#define TMARK(i) do { } while (0)
#define TSTART do { } while (0)
#endif

/* ------------------------------------------------------------------ buffers */

/* One argument as a C-contiguous buffer of at least `count` items of `itemsize` bytes. */
static int get_buf(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t itemsize, Py_ssize_t count,
                   const char *name) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) return -1;
    if (view->itemsize != itemsize || view->len < itemsize * count) {
        PyErr_Format(PyExc_ValueError, "_ekf: argument %s: expected %zd items of %zd bytes, got %zd bytes of %zd",
                     name, count, itemsize, view->len, view->itemsize);
        PyBuffer_Release(view);
        view->obj = NULL;
        return -1;
    }
    return 0;
}

/* How many items of `itemsize` bytes the C-contiguous buffer of `obj` holds (-1 with an
 * exception set when it has none). */
static Py_ssize_t items_of(PyObject *obj, Py_ssize_t itemsize) {
    Py_buffer view;
    if (PyObject_GetBuffer(obj, &view, PyBUF_C_CONTIGUOUS) < 0) return -1;
    Py_ssize_t n = view.len / itemsize;
    PyBuffer_Release(&view);
    return n;
}

/* 0 when every index of idx (k) is in [0, limit), else -1 with an IndexError naming `what`. */
static int check_indices(const long long *idx, Py_ssize_t k, Py_ssize_t limit, const char *what) {
    for (Py_ssize_t i = 0; i < k; i++)
        if (idx[i] < 0 || idx[i] >= limit) {
            PyErr_Format(PyExc_IndexError, "_ekf: %s index %lld out of range (0..%zd)", what, idx[i], limit - 1);
            return -1;
        }
    return 0;
}

#define MAXBUF 24
typedef struct {
    Py_buffer v[MAXBUF];
    int n;
} Bufs;

static void release_all(Bufs *b) {
    for (int i = 0; i < b->n; i++)
        if (b->v[i].obj) PyBuffer_Release(&b->v[i]);
    b->n = 0;
}

/* Pointer to the data of argument `obj` (NULL for None when `optional`). */
static void *arg(Bufs *b, PyObject *obj, int writable, Py_ssize_t itemsize, Py_ssize_t count, const char *name,
                 int optional, int *err) {
    if (*err) return NULL;
    if (optional && obj == Py_None) return NULL;
    if (b->n >= MAXBUF) {
        PyErr_SetString(PyExc_RuntimeError, "_ekf: too many buffers");
        *err = 1;
        return NULL;
    }
    Py_buffer *v = &b->v[b->n];
    if (get_buf(obj, v, writable, itemsize, count, name) < 0) {
        *err = 1;
        return NULL;
    }
    b->n++;
    return v->buf;
}

/* Σ's buffer: n x n used rows and columns of a row-major buffer of leading dimension ld
 * (the pose block, 6 x 6, always there); an impossible shape asks for more items than
 * any buffer has, so get_buf refuses it. */
#define COV_ITEMS(n, ld) (((n) < 6 || (ld) < (n)) ? PY_SSIZE_T_MAX / 8 : (ld) * ((n) - 1) + (n))

#define D(o, cnt, name) ((double *)arg(&bufs, (o), 0, 8, (cnt), (name), 0, &err))
#define DW(o, cnt, name) ((double *)arg(&bufs, (o), 1, 8, (cnt), (name), 0, &err))
#define DOPT(o, cnt, name) ((double *)arg(&bufs, (o), 0, 8, (cnt), (name), 1, &err))
#define I64(o, cnt, name) ((const long long *)arg(&bufs, (o), 0, 8, (cnt), (name), 0, &err))
#define U8(o, cnt, name) ((const unsigned char *)arg(&bufs, (o), 0, 1, (cnt), (name), 0, &err))
#define U8W(o, cnt, name) ((unsigned char *)arg(&bufs, (o), 1, 1, (cnt), (name), 0, &err))

/* ------------------------------------------------------------------ small linear algebra */

/* C (r x c) = A (r x k) B (k x c), all row-major and dense. */
static void matmul(const double *A, const double *B, double *C, int r, int k, int c) {
    for (int i = 0; i < r; i++)
        for (int j = 0; j < c; j++) {
            double s = 0.0;
            for (int l = 0; l < k; l++) s += A[i * k + l] * B[l * c + j];
            C[i * c + j] = s;
        }
}

/* C (r x c) = A (r x k) B^T, B (c x k). */
static void matmul_bt(const double *A, const double *B, double *C, int r, int k, int c) {
    for (int i = 0; i < r; i++)
        for (int j = 0; j < c; j++) {
            double s = 0.0;
            for (int l = 0; l < k; l++) s += A[i * k + l] * B[j * k + l];
            C[i * c + j] = s;
        }
}

/* Solve A X = B in place (A n x n, B n x nrhs, row-major), LU with partial pivoting as
 * LAPACK's gesv (numpy.linalg.solve): returns 1 where gesv reports a singular matrix (an
 * exactly zero pivot), else 0. A is overwritten. */
static int lu_solve(double *A, int n, double *B, int nrhs) {
    for (int c = 0; c < n; c++) {
        int p = c;
        double best = fabs(A[c * n + c]);
        for (int i = c + 1; i < n; i++) {
            double v = fabs(A[i * n + c]);
            if (v > best) {
                best = v;
                p = i;
            }
        }
        if (A[p * n + c] == 0.0) return 1;
        if (p != c) {
            for (int j = 0; j < n; j++) {
                double t = A[c * n + j];
                A[c * n + j] = A[p * n + j];
                A[p * n + j] = t;
            }
            for (int j = 0; j < nrhs; j++) {
                double t = B[c * nrhs + j];
                B[c * nrhs + j] = B[p * nrhs + j];
                B[p * nrhs + j] = t;
            }
        }
        double inv = 1.0 / A[c * n + c];
        for (int i = c + 1; i < n; i++) {
            double f = A[i * n + c] * inv;
            if (f == 0.0) continue;
            A[i * n + c] = f;
            for (int j = c + 1; j < n; j++) A[i * n + j] -= f * A[c * n + j];
            for (int j = 0; j < nrhs; j++) B[i * nrhs + j] -= f * B[c * nrhs + j];
        }
    }
    for (int c = n - 1; c >= 0; c--) {
        for (int j = 0; j < nrhs; j++) {
            double s = B[c * nrhs + j];
            for (int l = c + 1; l < n; l++) s -= A[c * n + l] * B[l * nrhs + j];
            B[c * nrhs + j] = s / A[c * n + c];
        }
    }
    return 0;
}

/* Cholesky A = L L^T in place (n x n, row-major, lower triangle read and written, the
 * strict upper triangle set to zero); returns 1 when A is not positive definite (a
 * pivot that is not > 0, NaN included, as LAPACK's potrf). */
static int chol_small(double *A, int n) {
    for (int j = 0; j < n; j++) {
        double d = A[j * n + j];
        for (int l = 0; l < j; l++) d -= A[j * n + l] * A[j * n + l];
        if (!(d > 0.0)) return 1;
        d = sqrt(d);
        A[j * n + j] = d;
        for (int i = j + 1; i < n; i++) {
            double s = A[i * n + j];
            for (int l = 0; l < j; l++) s -= A[i * n + l] * A[j * n + l];
            A[i * n + j] = s / d;
        }
        for (int i = 0; i < j; i++) A[i * n + j] = 0.0;
    }
    return 0;
}

/* x = L^-1 b for a lower-triangular row-major L (n x n, leading dimension ld). */
static void forward_subst(const double *L, int n, int ld, const double *b, double *x) {
    for (int a = 0; a < n; a++) {
        double s = b[a];
        const double *row = L + (size_t)a * ld;
        for (int c = 0; c < a; c++) s -= row[c] * x[c];
        x[a] = s / row[a];
    }
}

/* out (n) = Bt y for a row-major n x m Bt (column-major: the m x n matrix B, out = B^T y). */
static void bt_times(const double *Bt, int n, int m, const double *y, double *out) {
    char tr = 'T';
    int inc = 1;
    double one = 1.0, zero = 0.0;
    p_dgemv(&tr, &m, &n, &one, (double *)Bt, &m, (double *)y, &inc, &zero, out, &inc);
}

/* ------------------------------------------------------------------ Lie groups (vislam.core.lie) */

/* A = sin t/t, B = (1 - cos t)/t^2, C = (t - sin t)/t^3 with the small-angle series. */
static void angle_coefficients(double t2, double *A, double *B, double *C) {
    double theta = sqrt(t2);
    if (theta < SMALL_ANGLE) {
        if (A) *A = 1.0 - t2 / 6.0 + t2 * t2 / 120.0 - t2 * t2 * t2 / 5040.0;
        if (B) *B = 0.5 - t2 / 24.0 + t2 * t2 / 720.0 - t2 * t2 * t2 / 40320.0;
        if (C) *C = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0 - t2 * t2 * t2 / 362880.0;
    } else {
        double s = sin(theta);
        if (A) *A = s / theta;
        if (B) {
            double sh = sin(0.5 * theta) / (0.5 * theta);
            *B = 0.5 * sh * sh;
        }
        if (C) *C = (theta - s) / (theta * t2);
    }
}

static void hat3(const double *w, double *K) {
    K[0] = 0.0, K[1] = -w[2], K[2] = w[1];
    K[3] = w[2], K[4] = 0.0, K[5] = -w[0];
    K[6] = -w[1], K[7] = w[0], K[8] = 0.0;
}

/* se3_exp: twist (v, w) -> 4x4 pose [[R, J v], [0, 1]]. */
static void se3_exp(const double *xi, double *T) {
    double K[9], KK[9], A, B, C;
    const double *w = xi + 3;
    angle_coefficients(w[0] * w[0] + w[1] * w[1] + w[2] * w[2], &A, &B, &C);
    hat3(w, K);
    matmul(K, K, KK, 3, 3, 3);
    for (int i = 0; i < 3; i++) {
        double t = 0.0;
        for (int j = 0; j < 3; j++) {
            double e = (i == j) ? 1.0 : 0.0;
            T[i * 4 + j] = e + A * K[i * 3 + j] + B * KK[i * 3 + j];
            t += (e + B * K[i * 3 + j] + C * KK[i * 3 + j]) * xi[j];
        }
        T[i * 4 + 3] = t;
    }
    T[12] = T[13] = T[14] = 0.0;
    T[15] = 1.0;
}

/* so3_left_jacobian: I + B w^ + C (w^)^2. */
static void so3_left_jacobian(const double *w, double *J) {
    double K[9], KK[9], B, C;
    angle_coefficients(w[0] * w[0] + w[1] * w[1] + w[2] * w[2], NULL, &B, &C);
    hat3(w, K);
    matmul(K, K, KK, 3, 3, 3);
    for (int i = 0; i < 9; i++) J[i] = ((i % 4) == 0 ? 1.0 : 0.0) + B * K[i] + C * KK[i];
}

/* se3_adjoint: 4x4 pose -> 6x6 [[R, p^ R], [0, R]]. */
static void se3_adjoint(const double *T, double *Ad) {
    double R[9], P[9], PR[9];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) R[i * 3 + j] = T[i * 4 + j];
    double p[3] = {T[3], T[7], T[11]};
    hat3(p, P);
    matmul(P, R, PR, 3, 3, 3);
    for (int i = 0; i < 36; i++) Ad[i] = 0.0;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            Ad[i * 6 + j] = R[i * 3 + j];
            Ad[(i + 3) * 6 + j + 3] = R[i * 3 + j];
            Ad[i * 6 + j + 3] = PR[i * 3 + j];
        }
}

/* se3_inverse of a rigid transform. */
static void se3_inverse(const double *T, double *out) {
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) out[i * 4 + j] = T[j * 4 + i];
        out[i * 4 + 3] = -(T[0 * 4 + i] * T[3] + T[1 * 4 + i] * T[7] + T[2 * 4 + i] * T[11]);
    }
    out[12] = out[13] = out[14] = 0.0;
    out[15] = 1.0;
}

/* se3_log for rotation angles below 3 rad (returns 1 beyond: the caller falls back). */
static int se3_log(const double *T, double *xi) {
    double w0 = 0.5 * (T[9] - T[6]), w1 = 0.5 * (T[2] - T[8]), w2 = 0.5 * (T[4] - T[1]);
    double s = sqrt(w0 * w0 + w1 * w1 + w2 * w2);
    double c = 0.5 * (T[0] + T[5] + T[10] - 1.0);
    double theta = atan2(s, c);
    if (!(theta < 3.0)) return 1;
    double t2 = theta * theta;
    double factor = theta < SMALL_ANGLE ? 1.0 + t2 / 6.0 + 7.0 * t2 * t2 / 360.0 : theta / s;
    double phi[3] = {factor * w0, factor * w1, factor * w2};
    theta = sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]);
    t2 = theta * theta;
    double Dc;
    if (theta < SMALL_ANGLE) {
        Dc = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0;
    } else {
        double half = 0.5 * theta;
        Dc = (1.0 - half / tan(half)) / (theta * theta);
    }
    double K[9], KK[9];
    hat3(phi, K);
    matmul(K, K, KK, 3, 3, 3);
    for (int i = 0; i < 3; i++) {
        double v = 0.0;
        for (int j = 0; j < 3; j++) {
            double e = (i == j) ? 1.0 : 0.0;
            v += (e - 0.5 * K[i * 3 + j] + Dc * KK[i * 3 + j]) * T[j * 4 + 3];
        }
        xi[i] = v;
    }
    xi[3] = phi[0], xi[4] = phi[1], xi[5] = phi[2];
    return 0;
}

/* ------------------------------------------------------------------ set_lapack */

static void *capsule_pointer(PyObject *cap) {
    if (!PyCapsule_CheckExact(cap)) {
        PyErr_SetString(PyExc_TypeError, "_ekf.set_lapack: expected capsules of scipy.linalg.cython_blas/lapack");
        return NULL;
    }
    return PyCapsule_GetPointer(cap, PyCapsule_GetName(cap));
}

static PyObject *py_set_lapack(PyObject *self, PyObject *args) {
    PyObject *syrk, *trsm, *gemm, *potrf, *gemv;
    if (!PyArg_ParseTuple(args, "OOOOO", &syrk, &trsm, &gemm, &potrf, &gemv)) return NULL;
    void *a = capsule_pointer(syrk), *b = capsule_pointer(trsm), *c = capsule_pointer(gemm),
         *d = capsule_pointer(potrf), *e = capsule_pointer(gemv);
    if (!a || !b || !c || !d || !e) return NULL;
    p_dgemv = (dgemv_t)e;
    p_dsyrk = (dsyrk_t)a;
    p_dtrsm = (dtrsm_t)b;
    p_dgemm = (dgemm_t)c;
    p_dpotrf = (dpotrf_t)d;
    Py_RETURN_NONE;
}

static int need_lapack(void) {
    if (!p_dsyrk || !p_dtrsm || !p_dgemm || !p_dpotrf || !p_dgemv) {
        PyErr_SetString(PyExc_RuntimeError, "_ekf: set_lapack() was not called");
        return -1;
    }
    return 0;
}

/* ------------------------------------------------------------------ predict */

/* propagation.prediction_twist + pose_transition + predict_state (no IMU-error state):
 *
 *   u_body = R_bw Rz(psi) v_level (level: the 6 rotations exp(+-h e_j) R_bw give du by
 *            central differences, h = 1e-6), mu' = exp(-tau u^) mu,
 *   F = Ad(exp(-tau u^)) [- tau J_l(-tau w) du] [Ad(exp(eps))],
 *   Sigma_pp <- F Sigma_pp F^T + tau^2 W (symmetrized),  Sigma_pl <- F Sigma_pl.
 *
 * predict(T, T_out, P, n, ld, tau, u, W, eps|None, level, jacobian, perturb) */
static void level_to_body(const double *R, const double *v, double *out) {
    double psi = atan2(R[1], R[0]);
    double c = cos(psi), s = sin(psi);
    double vw[3] = {c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]};
    for (int i = 0; i < 3; i++) out[i] = R[i * 3] * vw[0] + R[i * 3 + 1] * vw[1] + R[i * 3 + 2] * vw[2];
}

static PyObject *py_predict(PyObject *self, PyObject *args) {
    PyObject *oT, *oTo, *oP, *ou, *oW, *oeps, *opert;
    Py_ssize_t n, ld;
    double tau;
    int level, jac;
    if (!PyArg_ParseTuple(args, "OOOnndOOOiiO", &oT, &oTo, &oP, &n, &ld, &tau, &ou, &oW, &oeps, &level, &jac,
                          &opert))
        return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    const double *T = D(oT, 16, "T");
    double *To = DW(oTo, 16, "T_out");
    double *P = DW(oP, COV_ITEMS(n, ld), "P");
    const double *u_in = D(ou, 6, "u");
    const double *W = D(oW, 36, "W");
    const double *eps = DOPT(oeps, 6, "eps");
    const double *pert = D(opert, 54, "perturb");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    double u[6], du[18]; /* du: rows 0:3 of the 6x6 du, i.e. dv/d(delta), only columns 3:6 nonzero */
    memcpy(u, u_in, sizeof u);
    int have_du = 0;
    double R[9];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) R[i * 3 + j] = T[i * 4 + j];
    if (level) {
        level_to_body(R, u_in, u);
        if (jac) {
            const double h = 1e-6;
            double vb[6][3];
            for (int k = 0; k < 6; k++) {
                double Rk[9];
                matmul(pert + 9 * k, R, Rk, 3, 3, 3);
                level_to_body(Rk, u_in, vb[k]);
            }
            for (int i = 0; i < 18; i++) du[i] = 0.0;
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++) du[i * 6 + 3 + j] = (vb[j][i] - vb[3 + j][i]) / (2 * h);
            have_du = 1;
        }
    }
    double mtu[6], step[16], F[36];
    for (int i = 0; i < 6; i++) mtu[i] = -tau * u[i];
    se3_exp(mtu, step);
    se3_adjoint(step, F);
    if (have_du) {
        double Jl[9];
        so3_left_jacobian(mtu + 3, Jl);
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 6; j++) {
                double s = 0.0;
                for (int l = 0; l < 3; l++) s += Jl[i * 3 + l] * du[l * 6 + j];
                F[i * 6 + j] -= tau * s;
            }
    }
    if (eps && (eps[0] != 0.0 || eps[1] != 0.0 || eps[2] != 0.0 || eps[3] != 0.0 || eps[4] != 0.0 || eps[5] != 0.0)) {
        double E[16], AdE[36], Fo[36];
        se3_exp(eps, E);
        se3_adjoint(E, AdE);
        matmul(F, AdE, Fo, 6, 6, 6);
        memcpy(F, Fo, sizeof F);
    }
    matmul(step, T, To, 4, 4, 4); /* mu' = exp(-tau u^) mu */
    /* Sigma_pp <- F Sigma_pp F^T + tau^2 W, symmetrized */
    double Ppp[36], FP[36], C[36];
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++) Ppp[i * 6 + j] = P[i * ld + j];
    matmul(F, Ppp, FP, 6, 6, 6);
    matmul_bt(FP, F, C, 6, 6, 6);
    double t2 = tau * tau;
    for (int i = 0; i < 36; i++) C[i] += t2 * W[i];
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++) P[i * ld + j] = 0.5 * (C[i * 6 + j] + C[j * 6 + i]);
    /* Sigma_pl <- F Sigma_pl (and its transpose) */
    if (n > 6) {
        double col[6];
        for (Py_ssize_t x = 6; x < n; x++) {
            for (int i = 0; i < 6; i++) col[i] = P[i * ld + x];
            for (int i = 0; i < 6; i++) {
                double s = 0.0;
                for (int l = 0; l < 6; l++) s += F[i * 6 + l] * col[l];
                P[i * ld + x] = s;
                P[x * ld + i] = s;
            }
        }
    }
    release_all(&bufs);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------ linearize */

/* updaters._linearize (StereoModel.predict, oc_project) and, with a prior, the iterated
 * update's residual z - h(x_i) - H_i (x_0 - x_i) (updaters._relinearized_residual).
 *
 * linearize(T, cam_T_imu, M, lm_mean, anchors|None, slots, z, N_pose|None, lm_null,
 *           mu0|None, lm0|None, r, Hp, Hl, front) -> status
 * status 0: done; 1: a non-finite projection Jacobian (the caller redoes it in numpy,
 * which raises its GeometryError); 2: the prior's rotation is 3 rad or more away. */
static PyObject *py_linearize(PyObject *self, PyObject *args) {
    PyObject *oT, *oC, *oM, *olm, *oanc, *oslots, *oz, *oN, *onull, *omu0, *olm0, *or, *oHp, *oHl, *ofront;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOOOO", &oT, &oC, &oM, &olm, &oanc, &oslots, &oz, &oN, &onull, &omu0,
                          &olm0, &or, &oHp, &oHl, &ofront))
        return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    Py_ssize_t k = items_of(oslots, 8);
    if (k < 0) return NULL;
    Py_ssize_t L = items_of(olm, 24);
    if (L < 0) return NULL;
    const double *T = D(oT, 16, "T");
    const double *CT = D(oC, 16, "cam_T_imu");
    const double *M = D(oM, 16, "M");
    const double *lm = D(olm, 3 * L, "lm_mean");
    const double *anc = DOPT(oanc, 16 * L, "anchors");
    const long long *slots = I64(oslots, k, "slots");
    const double *z = D(oz, 4 * k, "z");
    const double *N = DOPT(oN, 36, "N_pose");
    const double *nul = N ? D(onull, 18 * L, "lm_null") : NULL;
    const double *mu0 = DOPT(omu0, 16, "mu0");
    const double *lm0 = mu0 ? D(olm0, 3 * L, "lm0") : NULL;
    double *r = DW(or, 4 * k, "r");
    double *Hp = DW(oHp, 24 * k, "Hp");
    double *Hl = DW(oHl, 12 * k, "Hl");
    unsigned char *front = U8W(ofront, k, "front");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    if (check_indices(slots, k, L, "linearize: slot") < 0) {
        release_all(&bufs);
        return NULL;
    }
    int status = 0;
    double CW[16]; /* cam_T_world = cam_T_imu mu */
    matmul(CT, T, CW, 4, 4, 4);
    double dmu[6] = {0, 0, 0, 0, 0, 0};
    if (mu0) { /* log(mu0 mu^-1): the pose part of x0 - x_i */
        double Tinv[16], Rel[16];
        se3_inverse(T, Tinv);
        matmul(mu0, Tinv, Rel, 4, 4, 4);
        if (se3_log(Rel, dmu)) status = 2;
    }
    double NtN_pose[36];
    if (N) {
        for (int i = 0; i < 6; i++)
            for (int j = 0; j < 6; j++) {
                double s = 0.0;
                for (int l = 0; l < 6; l++) s += N[l * 6 + i] * N[l * 6 + j];
                NtN_pose[i * 6 + j] = s;
            }
    }
    for (Py_ssize_t i = 0; i < k && status != 1; i++) {
        long long s = slots[i];
        const double *p = lm + 3 * s;
        double mh[4];
        if (!anc) {
            mh[0] = p[0], mh[1] = p[1], mh[2] = p[2], mh[3] = 1.0;
        } else {
            const double *A = anc + 16 * s;
            double lh[4] = {p[0], p[1], 1.0, p[2]};
            for (int a = 0; a < 4; a++) mh[a] = A[a * 4] * lh[0] + A[a * 4 + 1] * lh[1] + A[a * 4 + 2] * lh[2] + A[a * 4 + 3] * lh[3];
        }
        double q[4];
        for (int a = 0; a < 4; a++) q[a] = CW[a * 4] * mh[0] + CW[a * 4 + 1] * mh[1] + CW[a * 4 + 2] * mh[2] + CW[a * 4 + 3] * mh[3];
        int inf = q[2] > 1e-6;
        if (anc) inf = inf && mh[3] > 0;
        front[i] = (unsigned char)inf;
        if (!inf) q[2] = 1.0;
        /* dpi/dq: [[1/z, 0, -x/z^2, 0], [0, 1/z, -y/z^2, 0], [0]*4, [0, 0, -w/z^2, 1/z]] */
        double iz = 1.0 / q[2];
        double dpi[16] = {iz, 0.0, -q[0] * iz * iz, 0.0, 0.0, iz, -q[1] * iz * iz, 0.0,
                          0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -q[3] * iz * iz, iz};
        for (int a = 0; a < 16; a++)
            if (!isfinite(dpi[a])) status = 1;
        if (status == 1) break;
        double J[16]; /* M dpi/dq */
        matmul(M, dpi, J, 4, 4, 4);
        /* z_hat = M (q / q_z) */
        double qn[4] = {q[0] / q[2], q[1] / q[2], q[2] / q[2], q[3] / q[2]};
        double *ri = r + 4 * i;
        for (int a = 0; a < 4; a++)
            ri[a] = z[4 * i + a] - (M[a * 4] * qn[0] + M[a * 4 + 1] * qn[1] + M[a * 4 + 2] * qn[2] + M[a * 4 + 3] * qn[3]);
        double *hl = Hl + 12 * i;
        if (!anc) { /* J[:, :3] cam_T_world[:3, :3] */
            for (int a = 0; a < 4; a++)
                for (int b = 0; b < 3; b++)
                    hl[a * 3 + b] = J[a * 4] * CW[b] + J[a * 4 + 1] * CW[4 + b] + J[a * 4 + 2] * CW[8 + b];
        } else { /* J (cam_T_world world_T_anchor)[:, (0, 1, 3)] */
            double Aca[16];
            matmul(CW, anc + 16 * s, Aca, 4, 4, 4);
            static const int cols[3] = {0, 1, 3};
            for (int a = 0; a < 4; a++)
                for (int b = 0; b < 3; b++) {
                    int c = cols[b];
                    hl[a * 3 + b] = J[a * 4] * Aca[c] + J[a * 4 + 1] * Aca[4 + c] + J[a * 4 + 2] * Aca[8 + c] + J[a * 4 + 3] * Aca[12 + c];
                }
        }
        /* H_pose = (J cam_T_imu) odot(mu m_h), odot([s, l]) = [[l I, -s^], [0, 0]] */
        double JC[16], qi[4];
        matmul(J, CT, JC, 4, 4, 4);
        for (int a = 0; a < 4; a++) qi[a] = T[a * 4] * mh[0] + T[a * 4 + 1] * mh[1] + T[a * 4 + 2] * mh[2] + T[a * 4 + 3] * mh[3];
        double od[18]; /* rows 0:3 of odot (row 3 is zero) */
        double sh[9];
        hat3(qi, sh);
        for (int a = 0; a < 3; a++)
            for (int b = 0; b < 3; b++) {
                od[a * 6 + b] = (a == b) ? qi[3] : 0.0;
                od[a * 6 + 3 + b] = -sh[a * 3 + b];
            }
        double *hp = Hp + 24 * i;
        for (int a = 0; a < 4; a++)
            for (int b = 0; b < 6; b++) hp[a * 6 + b] = JC[a * 4] * od[b] + JC[a * 4 + 1] * od[6 + b] + JC[a * 4 + 2] * od[12 + b];
        if (N) { /* H* = H - H N (N^T N)^-1 N^T, N = [N_pose; N_lm] */
            const double *Nl = nul + 18 * s; /* (3, 6) */
            double HN[24], NtN[36];
            for (int a = 0; a < 4; a++)
                for (int b = 0; b < 6; b++) {
                    double v = 0.0;
                    for (int l = 0; l < 6; l++) v += hp[a * 6 + l] * N[l * 6 + b];
                    for (int l = 0; l < 3; l++) v += hl[a * 3 + l] * Nl[l * 6 + b];
                    HN[a * 6 + b] = v;
                }
            for (int a = 0; a < 6; a++)
                for (int b = 0; b < 6; b++) {
                    double v = NtN_pose[a * 6 + b];
                    for (int l = 0; l < 3; l++) v += Nl[l * 6 + a] * Nl[l * 6 + b];
                    NtN[a * 6 + b] = v;
                }
            /* Z^T = (N^T N)^-1 (H N)^T  (6 x 4) */
            double Zt[24];
            for (int a = 0; a < 6; a++)
                for (int b = 0; b < 4; b++) Zt[a * 4 + b] = HN[b * 6 + a];
            if (lu_solve(NtN, 6, Zt, 4)) {
                status = 1; /* numpy raises LinAlgError there: let it */
                break;
            }
            double hp2[24], hl2[12];
            for (int a = 0; a < 4; a++) {
                for (int b = 0; b < 6; b++) {
                    double v = 0.0;
                    for (int l = 0; l < 6; l++) v += Zt[l * 4 + a] * N[b * 6 + l]; /* Z N_pose^T */
                    hp2[a * 6 + b] = hp[a * 6 + b] - v;
                }
                for (int b = 0; b < 3; b++) {
                    double v = 0.0;
                    for (int l = 0; l < 6; l++) v += Zt[l * 4 + a] * Nl[b * 6 + l]; /* Z N_lm^T */
                    hl2[a * 3 + b] = hl[a * 3 + b] - v;
                }
            }
            memcpy(hp, hp2, sizeof hp2);
            memcpy(hl, hl2, sizeof hl2);
        }
        if (mu0) { /* r - H_p log(mu0 mu^-1) - H_l (m0 - m) */
            const double *p0 = lm0 + 3 * s;
            double d[3] = {p0[0] - p[0], p0[1] - p[1], p0[2] - p[2]};
            for (int a = 0; a < 4; a++) {
                double v = 0.0, w = 0.0;
                for (int b = 0; b < 6; b++) v += hp[a * 6 + b] * dmu[b];
                for (int b = 0; b < 3; b++) w += hl[a * 3 + b] * d[b];
                ri[a] = ri[a] - v - w;
            }
        }
    }
    release_all(&bufs);
    return PyLong_FromLong(status);
}

/* ------------------------------------------------------------------ innovation */

/* updaters.slam_predict_nis's blocks, S_i and NIS (innovation_covariances,
 * innovation_nis) and, with `drift`, conditional_residual_model:
 *
 *   S_i = H_p S_pp H_p^T + H_p S_ps H_l^T + (..)^T + H_l S_ss H_l^T + V,  NIS_i = r^T S^-1 r
 *   G_i = S_sp S_pp^-1,  Ht_i = H_p + H_l G_i,  St_i = H_l (S_ss - G_i S_ps) H_l^T + V = Lt Lt^T
 *
 * innovation(P, n, ld, core, slots, r, Hp, Hl, front, V, nis, Ppp, Pps, Pss, drift, Ht, Lt)
 * -> status: 0, or 1 when the drift model could not be formed (a singular S_pp or an St
 * that is not positive definite: numpy raises LinAlgError there). */
static PyObject *py_innovation(PyObject *self, PyObject *args) {
    PyObject *oP, *oslots, *or, *oHp, *oHl, *ofront, *oV, *onis, *oPpp, *oPps, *oPss, *oHt, *oLt;
    Py_ssize_t n, ld, core;
    int drift;
    if (!PyArg_ParseTuple(args, "OnnnOOOOOOOOOOiOO", &oP, &n, &ld, &core, &oslots, &or, &oHp, &oHl, &ofront, &oV,
                          &onis, &oPpp, &oPps, &oPss, &drift, &oHt, &oLt))
        return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    Py_ssize_t k = items_of(oslots, 8);
    if (k < 0) return NULL;
    const double *P = D(oP, COV_ITEMS(n, ld), "P");
    const long long *slots = I64(oslots, k, "slots");
    const double *r = D(or, 4 * k, "r");
    const double *Hp = D(oHp, 24 * k, "Hp");
    const double *Hl = D(oHl, 12 * k, "Hl");
    const unsigned char *front = U8(ofront, k, "front");
    const double *V = D(oV, 16, "V");
    double *nis = DW(onis, k, "nis");
    double *Ppp = DW(oPpp, 36, "Ppp");
    double *Pps = DW(oPps, 18 * k, "Pps");
    double *Pss = DW(oPss, 9 * k, "Pss");
    double *Ht = drift ? DW(oHt, 24 * k, "Ht") : NULL;
    double *Lt = drift ? DW(oLt, 16 * k, "Lt") : NULL;
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    if (check_indices(slots, k, (n - core) / 3, "innovation: slot") < 0) {
        release_all(&bufs);
        return NULL;
    }
    for (int a = 0; a < 6; a++)
        for (int b = 0; b < 6; b++) Ppp[a * 6 + b] = P[a * ld + b];
    for (Py_ssize_t i = 0; i < k; i++) {
        Py_ssize_t row = core + 3 * slots[i];
        double *ps = Pps + 18 * i, *ss = Pss + 9 * i;
        for (int a = 0; a < 6; a++)
            for (int b = 0; b < 3; b++) ps[a * 3 + b] = P[a * ld + row + b];
        for (int a = 0; a < 3; a++)
            for (int b = 0; b < 3; b++) ss[a * 3 + b] = P[(row + a) * ld + row + b];
    }
    int status = 0;
    for (Py_ssize_t i = 0; i < k; i++) {
        const double *hp = Hp + 24 * i, *hl = Hl + 12 * i, *ps = Pps + 18 * i, *ss = Pss + 9 * i;
        double A[24], B[12], Cm[12], S[16];
        matmul(hp, Ppp, A, 4, 6, 6);  /* H_p S_pp */
        matmul(hp, ps, B, 4, 6, 3);   /* H_p S_ps */
        matmul(hl, ss, Cm, 4, 3, 3);  /* H_l S_ss */
        double AH[16], cross[16], CH[16];
        matmul_bt(A, hp, AH, 4, 6, 4);
        matmul_bt(B, hl, cross, 4, 3, 4);
        matmul_bt(Cm, hl, CH, 4, 3, 4);
        for (int a = 0; a < 4; a++)
            for (int b = 0; b < 4; b++) S[a * 4 + b] = AH[a * 4 + b] + cross[a * 4 + b] + cross[b * 4 + a] + CH[a * 4 + b] + V[a * 4 + b];
        if (!front[i]) {
            nis[i] = INFINITY;
        } else {
            double x[4] = {r[4 * i], r[4 * i + 1], r[4 * i + 2], r[4 * i + 3]};
            if (lu_solve(S, 4, x, 1)) {
                nis[i] = INFINITY;
            } else {
                nis[i] = r[4 * i] * x[0] + r[4 * i + 1] * x[1] + r[4 * i + 2] * x[2] + r[4 * i + 3] * x[3];
            }
        }
    }
    if (drift && k > 0) {
        /* X = (S_pp + 1e-12 I)^-1 [S_ps,0 | S_ps,1 | ...]  (6 x 3k) */
        double A[36];
        memcpy(A, Ppp, sizeof A);
        for (int a = 0; a < 6; a++) A[a * 6 + a] += 1e-12;
        double *X = (double *)PyMem_Malloc(sizeof(double) * 18 * k);
        if (!X) {
            release_all(&bufs);
            return PyErr_NoMemory();
        }
        for (int a = 0; a < 6; a++)
            for (Py_ssize_t i = 0; i < k; i++)
                for (int b = 0; b < 3; b++) X[a * 3 * k + 3 * i + b] = Pps[18 * i + a * 3 + b];
        if (lu_solve(A, 6, X, (int)(3 * k))) {
            status = 1;
        } else {
            for (Py_ssize_t i = 0; i < k; i++) {
                const double *hp = Hp + 24 * i, *hl = Hl + 12 * i, *ps = Pps + 18 * i, *ss = Pss + 9 * i;
                double G[18]; /* (3, 6): G[b][a] = X[a][3i + b] */
                for (int a = 0; a < 6; a++)
                    for (int b = 0; b < 3; b++) G[b * 6 + a] = X[a * 3 * k + 3 * i + b];
                double HG[24], GP[9], Cc[9], HC[12], St[16];
                matmul(hl, G, HG, 4, 3, 6);
                double *ht = Ht + 24 * i;
                for (int a = 0; a < 24; a++) ht[a] = hp[a] + HG[a];
                matmul(G, ps, GP, 3, 6, 3);
                for (int a = 0; a < 9; a++) Cc[a] = ss[a] - GP[a];
                matmul(hl, Cc, HC, 4, 3, 3);
                matmul_bt(HC, hl, St, 4, 3, 4);
                for (int a = 0; a < 16; a++) St[a] += V[a];
                double *lt = Lt + 16 * i;
                for (int a = 0; a < 4; a++)
                    for (int b = 0; b < 4; b++) lt[a * 4 + b] = 0.5 * (St[a * 4 + b] + St[b * 4 + a]);
                if (chol_small(lt, 4)) {
                    status = 1;
                    break;
                }
            }
        }
        PyMem_Free(X);
    }
    release_all(&bufs);
    return PyLong_FromLong(status);
}

/* ------------------------------------------------------------------ update */

/* P (n x n of a row-major buffer, leading dimension ld) += alpha Bt Bt^T for a row-major
 * n x m Bt: SYRK on the column-major view (Bt's memory is the m x n matrix B there, and
 * Bt Bt^T = B^T B), which writes the column-major lower = row-major upper triangle; that
 * triangle is then copied to the row-major lower one, so P stays exactly symmetric. */
static void add_gram(double *P, int n, int ld, const double *Bt, int m, double alpha) {
    char lo = 'L', tr = 'T';
    double beta = 1.0;
    p_dsyrk(&lo, &tr, &n, &m, &alpha, (double *)Bt, &m, &beta, P, &ld);
    for (Py_ssize_t x = 0; x < n; x++)
        for (Py_ssize_t y = x + 1; y < n; y++) P[y * ld + x] = P[x * ld + y];
}

/* inv (b x b, column-major) = L_bb^-1 for the lower-triangular row-major block
 * L_bb[i][j] = A[i * ld + j] (forward substitution on the identity). */
static void lower_inverse(const double *A, int b, int ld, double *inv) {
    for (int j = 0; j < b; j++) {
        for (int i = 0; i < j; i++) inv[i + j * b] = 0.0;
        inv[j + j * b] = 1.0 / A[(size_t)j * ld + j];
        for (int i = j + 1; i < b; i++) {
            const double *Ai = A + (size_t)i * ld;
            double acc = 0.0;
            for (int l = j; l < i; l++) acc += Ai[l] * inv[l + j * b];
            inv[i + j * b] = -acc / Ai[i];
        }
    }
}

/* Cholesky S = L L^T in place: S's lower triangle in row-major order (leading dimension
 * m), L written over it, by LAPACK's potrf (the same routine numpy.linalg.cholesky calls:
 * a blocked variant with explicit inverses of the diagonal blocks was 15 % faster at
 * m ~ 180 but lost positive definiteness on an S of condition 1e15 that potrf factors,
 * after an hour without frames). Returns 1 when S is not positive definite. */
static int chol_lower(double *Lf, int m) {
    char up = 'U';
    int info = 0;
    p_dpotrf(&up, &m, Lf, &m, &info); /* column-major upper = row-major lower */
    return info != 0;
}

/* The 1-norm condition number ||L_bb||_1 ||L_bb^-1||_1 of a lower-triangular row-major
 * block (leading dimension ld) and its column-major inverse. */
static double block_condition(const double *A, int b, int ld, const double *inv) {
    double na = 0.0, ni = 0.0;
    for (int j = 0; j < b; j++) {
        double ca = 0.0, ci = 0.0;
        for (int i = j; i < b; i++) {
            ca += fabs(A[(size_t)i * ld + j]);
            ci += fabs(inv[i + j * b]);
        }
        if (ca > na || isnan(ca)) na = ca;
        if (ci > ni || isnan(ci)) ni = ci;
    }
    return na * ni;
}

/* Largest condition number of a diagonal block that lower_solve multiplies by its
 * inverse (the error of that product grows with it; the shared dense drives' blocks
 * stay below 250). */
#define SOLVE_COND_MAX 1e4
static long long solve_fallbacks = 0; /* blocks solved by TRSM for their condition (counters()) */

/* X = L^-1 Y in place, L (m x m) the row-major lower Cholesky factor that potrf left in
 * Lf (column-major: its upper factor U = L^T), Y (m x n) column-major with leading
 * dimension m. Blocked forward substitution: for each block of SOLVE_BLOCK rows, the rows
 * above are subtracted with one GEMM, then the block is multiplied by the inverse of its
 * diagonal block (formed here, by forward substitution on the block's identity), or,
 * where that block is ill-conditioned (SOLVE_COND_MAX), solved by TRSM. BLAS's TRSM does
 * the whole of it in one call but at these sizes (m ~ 200) at a third of GEMM's speed;
 * small systems take TRSM itself. Returns -1 when out of memory. */
#ifndef SOLVE_BLOCK
#define SOLVE_BLOCK 32
#endif
static int lower_solve(const double *Lf, int m, double *Y, int n) {
    double one = 1.0, minus = -1.0, zero = 0.0;
    if (m <= 2 * SOLVE_BLOCK) {
        char side = 'L', up = 'U', tr = 'T', diag = 'N';
        p_dtrsm(&side, &up, &tr, &diag, &m, &n, &one, (double *)Lf, &m, Y, &m);
        return 0;
    }
    double *inv = (double *)PyMem_Malloc(sizeof(double) * ((size_t)SOLVE_BLOCK * SOLVE_BLOCK + (size_t)SOLVE_BLOCK * n));
    if (!inv) return -1;
    double *tmp = inv + SOLVE_BLOCK * SOLVE_BLOCK;
    for (int s0 = 0; s0 < m; s0 += SOLVE_BLOCK) {
        int b = m - s0 < SOLVE_BLOCK ? m - s0 : SOLVE_BLOCK;
        if (s0 > 0) { /* Y[s0:s0+b] -= L[s0:s0+b, :s0] X[:s0]; L[s0:, :s0] = (U[:s0, s0:])^T */
            char tt = 'T', tn = 'N';
            p_dgemm(&tt, &tn, &b, &n, &s0, &minus, (double *)Lf + (size_t)s0 * m, &m, Y, &m, &one, Y + s0, &m);
        }
        const double *Lbb = Lf + (size_t)s0 * m + s0;
        lower_inverse(Lbb, b, m, inv); /* L_bb^-1, column-major */
        if (block_condition(Lbb, b, m, inv) > SOLVE_COND_MAX) {
            /* an ill-conditioned block (a prior far wider than the pixel noise, e.g. after a
             * long time gap): TRSM's substitution, as numpy, instead of the explicit inverse */
            char side = 'L', up = 'U', tr = 'T', diag = 'N';
            p_dtrsm(&side, &up, &tr, &diag, &b, &n, &one, (double *)Lbb, &m, Y + s0, &m);
            solve_fallbacks++;
            continue;
        }
        /* X[s0:s0+b] = inv (Y[s0:s0+b]) */
        char tn = 'N';
        p_dgemm(&tn, &tn, &b, &n, &b, &one, inv, &b, Y + s0, &m, &zero, tmp, &b);
        for (int x = 0; x < n; x++) memcpy(Y + s0 + (size_t)x * m, tmp + (size_t)x * b, sizeof(double) * b);
    }
    PyMem_Free(inv);
    return 0;
}


/* updaters.slam_update (with compress_stereo) for k accepted observations:
 *
 *   Sigma H^T (n x m) from the blocks, S = H Sigma H^T + I (x) diag(var) = L L^T,
 *   Bt = (L^-1 H Sigma)^T (n x m), dx = Bt L^-1 r, Sigma <- Sigma - Bt Bt^T,
 *   mu <- exp(dx_pose^) mu, m <- m + dx_lm.
 *
 * update(P, n, ld, core, slots, r, Hp, Hl, compress, var, T, T_out, lm, lm_out, L_out,
 *        Bt_out, dx_out) -> status: 0, or 1 when S is not positive definite (Sigma and
 * the means are then untouched). L_out (m x m) receives L (its lower triangle; the
 * strict upper triangle is scratch), Bt_out (n x m) the gain factor, for gain_times and
 * restore. */
static PyObject *py_update(PyObject *self, PyObject *args) {
    PyObject *oP, *oslots, *or, *oHp, *oHl, *ovar, *oT, *oTo, *olm, *olmo, *oL, *oBt, *odx;
    Py_ssize_t n, ld, core;
    int compress;
    if (!PyArg_ParseTuple(args, "OnnnOOOOiOOOOOOOO", &oP, &n, &ld, &core, &oslots, &or, &oHp, &oHl, &compress, &ovar,
                          &oT, &oTo, &olm, &olmo, &oL, &oBt, &odx))
        return NULL;
    if (need_lapack() < 0) return NULL;
    TSTART;
    Bufs bufs = {.n = 0};
    int err = 0;
    Py_ssize_t k = items_of(oslots, 8);
    if (k < 0) return NULL;
    Py_ssize_t Lm = items_of(olm, 24);
    if (Lm < 0) return NULL;
    int mr = compress ? 3 : 4;
    Py_ssize_t m = mr * k;
    double *P = DW(oP, COV_ITEMS(n, ld), "P");
    const long long *slots = I64(oslots, k, "slots");
    const double *r = D(or, 4 * k, "r");
    const double *Hp = D(oHp, 24 * k, "Hp");
    const double *Hl = D(oHl, 12 * k, "Hl");
    const double *var = D(ovar, mr, "var");
    const double *T = D(oT, 16, "T");
    double *To = DW(oTo, 16, "T_out");
    const double *lm = D(olm, 3 * Lm, "lm_mean");
    double *lmo = DW(olmo, 3 * Lm, "lm_out");
    double *Lf = DW(oL, m * m, "L_out");
    double *Bt = DW(oBt, n * m, "Bt_out");
    double *dx = DW(odx, n, "dx_out");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    if (n != core + 3 * Lm) {
        release_all(&bufs);
        PyErr_SetString(PyExc_ValueError, "_ekf.update: n != core + 3 L");
        return NULL;
    }
    if (check_indices(slots, k, Lm, "update: slot") < 0) {
        release_all(&bufs);
        return NULL;
    }
    if (k == 0) {
        for (Py_ssize_t x = 0; x < n; x++) dx[x] = 0.0;
        memcpy(To, T, 16 * sizeof(double));
        memcpy(lmo, lm, 3 * Lm * sizeof(double));
        release_all(&bufs);
        return PyLong_FromLong(0);
    }
    TMARK(0);
    /* the compressed rows (compress_stereo): uL, (vL + vR)/2, uR */
    double *work = (double *)PyMem_Malloc(sizeof(double) * (size_t)m * 11);
    if (!work) {
        release_all(&bufs);
        return PyErr_NoMemory();
    }
    double *hpT = work;         /* (6, m): H_p^T, column j the row j of H_p */
    double *hlc = work + 6 * m; /* (m, 3) */
    double *rc = work + 9 * m;  /* (m,) */
    for (Py_ssize_t i = 0; i < k; i++) {
        const double *hp = Hp + 24 * i, *hl = Hl + 12 * i, *ri = r + 4 * i;
        for (int a = 0; a < mr; a++) {
            Py_ssize_t j = mr * i + a;
            for (int c = 0; c < 6; c++)
                hpT[c * m + j] = (compress && a == 1) ? 0.5 * (hp[6 + c] + hp[18 + c]) : hp[a * 6 + c];
            for (int c = 0; c < 3; c++)
                hlc[j * 3 + c] = (compress && a == 1) ? 0.5 * (hl[3 + c] + hl[9 + c]) : hl[a * 3 + c];
            rc[j] = (compress && a == 1) ? 0.5 * (ri[1] + ri[3]) : ri[a];
        }
    }
    TMARK(1);
    /* Sigma H^T (n x m, row-major) = Sigma[:, :6] H_p^T (GEMM) + Sigma[:, rows_i] H_l,i^T.
     * Column-major: C (m x n) = hpT^T-as-(m x 6)... written as C^T: Bt^T = H_p(m x 6) Sigma[:6, :]... */
    {
        /* row-major Bt (n x m) = P[:, :6] (n x 6, ld) * hpT (6 x m).  In column-major terms:
         * Bt^T (m x n) = hpT^T (m x 6) * P[:, :6]^T (6 x n): A = hpT viewed col-major (m x 6, lda m),
         * B = P viewed col-major (its rows are columns: 6 x n with ldb ld). */
        char tn = 'N';
        int M_ = (int)m, N_ = (int)n, K_ = 6, lda = (int)m, ldb = (int)ld, ldc = (int)m;
        double one = 1.0, zero = 0.0;
        p_dgemm(&tn, &tn, &M_, &N_, &K_, &one, hpT, &lda, P, &ldb, &zero, Bt, &ldc);
    }
    TMARK(2);
    for (Py_ssize_t x = 0; x < n; x++) {
        const double *px = P + x * ld;
        double *bx = Bt + x * m;
        for (Py_ssize_t i = 0; i < k; i++) {
            const double *pr = px + core + 3 * slots[i];
            for (int a = 0; a < mr; a++) {
                const double *h = hlc + (mr * i + a) * 3;
                bx[mr * i + a] += pr[0] * h[0] + pr[1] * h[1] + pr[2] * h[2];
            }
        }
    }
    TMARK(3);
    /* S = H (Sigma H^T) + R, lower triangle (row-major): the pose rows of Sigma H^T times
     * H_p (one GEMM, the whole square), then each observed landmark's three rows */
    {
        /* row-major S = Hpc (m x 6) PHt[:6] (6 x m) is column-major S^T = X Z: X (m x 6) the
         * rows 0:6 of Sigma H^T (Bt's memory, leading dimension m), Z = Hpc^T (hpT's memory
         * read column-major is Hpc itself, hence transposed) */
        char tn = 'N', tt = 'T';
        int M_ = (int)m, K_ = 6;
        double one = 1.0, zero = 0.0;
        p_dgemm(&tn, &tt, &M_, &M_, &K_, &one, Bt, &M_, hpT, &M_, &zero, Lf, &M_);
    }
    for (Py_ssize_t a = 0; a < m; a++) {
        Py_ssize_t ia = a / mr;
        const double *p0 = Bt + (core + 3 * slots[ia]) * m, *p1 = p0 + m, *p2 = p1 + m;
        const double *h = hlc + a * 3;
        const double h0 = h[0], h1 = h[1], h2 = h[2];
        double *Sa = Lf + a * m;
        for (Py_ssize_t b = 0; b <= a; b++) Sa[b] += h0 * p0[b] + h1 * p1[b] + h2 * p2[b];
        Sa[a] += var[a % mr];
    }
    TMARK(4);
    /* L: potrf on the column-major view (row-major lower = column-major upper) */
    {
        int st = chol_lower(Lf, (int)m);
        if (st != 0) {
            PyMem_Free(work);
            release_all(&bufs);
            if (st < 0) return PyErr_NoMemory();
            return PyLong_FromLong(1);
        }
    }
    TMARK(5);
    /* y = L^-1 r */
    double *y = work + 9 * m + m; /* (m,) after rc */
    forward_subst(Lf, (int)m, (int)m, rc, y);
    TMARK(6);
    /* B = L^-1 (Sigma H^T)^T: in column-major, Bt's memory is the m x n matrix Y = (Sigma H^T)^T;
     * L Y' = Y <=> U^T Y' = Y with U = L^T the column-major upper factor */
    if (lower_solve(Lf, (int)m, Bt, (int)n) < 0) {
        PyMem_Free(work);
        release_all(&bufs);
        return PyErr_NoMemory();
    }
    TMARK(7);
    bt_times(Bt, (int)n, (int)m, y, dx); /* dx = B^T y = Bt y */
    TMARK(8);
    add_gram(P, (int)n, (int)ld, Bt, (int)m, -1.0); /* Sigma <- Sigma - Bt Bt^T */
    TMARK(10);
    /* the means: mu <- exp(dx_pose^) mu, m <- m + dx_lm */
    double E[16];
    se3_exp(dx, E);
    matmul(E, T, To, 4, 4, 4);
    for (Py_ssize_t j = 0; j < 3 * Lm; j++) lmo[j] = lm[j] + dx[core + j];
    TMARK(11);
    PyMem_Free(work);
    release_all(&bufs);
    return PyLong_FromLong(0);
}

/* ------------------------------------------------------------------ restore, gain_times, step size */

/* updaters._restore_prior's Sigma_0 = Sigma + Bt Bt^T (in place).  restore(P, n, ld, Bt, m) */
static PyObject *py_restore(PyObject *self, PyObject *args) {
    PyObject *oP, *oBt;
    Py_ssize_t n, ld, m;
    if (!PyArg_ParseTuple(args, "OnnOn", &oP, &n, &ld, &oBt, &m)) return NULL;
    if (need_lapack() < 0) return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    double *P = DW(oP, COV_ITEMS(n, ld), "P");
    const double *Bt = D(oBt, n * m, "Bt");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    add_gram(P, (int)n, (int)ld, Bt, (int)m, 1.0); /* Sigma_0 = Sigma + Bt Bt^T */
    release_all(&bufs);
    Py_RETURN_NONE;
}

/* updaters.gain_times: K dr = Bt L^-1 dr (the rows compressed as the update did).
 * gain_times(L, Bt, n, dr, compress, out) */
static PyObject *py_gain_times(PyObject *self, PyObject *args) {
    PyObject *oL, *oBt, *odr, *oout;
    Py_ssize_t n;
    int compress;
    if (!PyArg_ParseTuple(args, "OOnOiO", &oL, &oBt, &n, &odr, &compress, &oout)) return NULL;
    if (need_lapack() < 0) return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    Py_ssize_t k = items_of(odr, 32);
    if (k < 0) return NULL;
    int mr = compress ? 3 : 4;
    Py_ssize_t m = mr * k;
    const double *L = D(oL, m * m, "L");
    const double *Bt = D(oBt, n * m, "Bt");
    const double *dr = D(odr, 4 * k, "dr");
    double *out = DW(oout, n, "out");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    double *w = (double *)PyMem_Malloc(sizeof(double) * (2 * m + 1));
    if (!w) {
        release_all(&bufs);
        return PyErr_NoMemory();
    }
    double *rc = w, *y = w + m;
    for (Py_ssize_t i = 0; i < k; i++)
        for (int a = 0; a < mr; a++)
            rc[mr * i + a] = (compress && a == 1) ? 0.5 * (dr[4 * i + 1] + dr[4 * i + 3]) : dr[4 * i + a];
    forward_subst(L, (int)m, (int)m, rc, y);
    bt_times(Bt, (int)n, (int)m, y, out);
    PyMem_Free(w);
    release_all(&bufs);
    Py_RETURN_NONE;
}

/* updaters._step_size: the largest Mahalanobis norm of the pose's and of each observed
 * landmark's part of dx (marginal blocks of Sigma), square-rooted. Returns -1.0 when a
 * block is singular (the caller then takes numpy's least-squares path).
 * step_size(P, n, ld, core, slots, dx) */
static PyObject *py_step_size(PyObject *self, PyObject *args) {
    PyObject *oP, *oslots, *odx;
    Py_ssize_t n, ld, core;
    if (!PyArg_ParseTuple(args, "OnnnOO", &oP, &n, &ld, &core, &oslots, &odx)) return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    Py_ssize_t k = items_of(oslots, 8);
    if (k < 0) return NULL;
    const double *P = D(oP, COV_ITEMS(n, ld), "P");
    const long long *slots = I64(oslots, k, "slots");
    const double *dx = D(odx, n, "dx");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    double A[36], x[6];
    for (int a = 0; a < 6; a++) {
        for (int b = 0; b < 6; b++) A[a * 6 + b] = P[a * ld + b];
        x[a] = dx[a];
    }
    double size;
    if (lu_solve(A, 6, x, 1)) {
        release_all(&bufs);
        return PyFloat_FromDouble(-1.0);
    }
    size = dx[0] * x[0] + dx[1] * x[1] + dx[2] * x[2] + dx[3] * x[3] + dx[4] * x[4] + dx[5] * x[5];
    /* as numpy: qmax = q.max() (NaN if any is), size = max(size, qmax), sqrt(max(size, 0)) */
    double qmax = -INFINITY;
    int qnan = 0;
    if (check_indices(slots, k, (n - core) / 3, "step_size: slot") < 0) {
        release_all(&bufs);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < k; i++) {
        Py_ssize_t row = core + 3 * slots[i];
        double B[9], e[3];
        for (int a = 0; a < 3; a++) {
            for (int b = 0; b < 3; b++) B[a * 3 + b] = P[(row + a) * ld + row + b];
            e[a] = dx[row + a];
        }
        double f[3] = {e[0], e[1], e[2]};
        if (lu_solve(B, 3, f, 1)) {
            release_all(&bufs);
            return PyFloat_FromDouble(-1.0);
        }
        double q = e[0] * f[0] + e[1] * f[1] + e[2] * f[2];
        if (isnan(q)) qnan = 1;
        else if (q > qmax) qmax = q;
    }
    if (k > 0) {
        if (qnan) qmax = NAN;
        if (qmax > size) size = qmax;
    }
    release_all(&bufs);
    if (!(0.0 > size) && !(size >= 0.0)) return PyFloat_FromDouble(NAN); /* NaN */
    return PyFloat_FromDouble(sqrt(0.0 > size ? 0.0 : size));
}

/* ------------------------------------------------------------------ drift test */

/* SlamFilter._drift_test's sums: w_i = Lt_i^-1 (r_i - Ht_i eps); for accepted ones
 * drift_sum[row] += w, drift_n[row] += 1; moving = ok & drift_n >= 2 &
 * |drift_sum|^2 / max(drift_n, 1) > gate.
 * drift(Lt, Ht, r, eps, ok, rows, drift_sum, drift_n, gate, moving) -> number moving */
static PyObject *py_drift(PyObject *self, PyObject *args) {
    PyObject *oLt, *oHt, *or, *oeps, *ook, *orows, *osum, *ocnt, *omov;
    double gate;
    if (!PyArg_ParseTuple(args, "OOOOOOOOdO", &oLt, &oHt, &or, &oeps, &ook, &orows, &osum, &ocnt, &gate, &omov))
        return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    Py_ssize_t k = items_of(orows, 8);
    if (k < 0) return NULL;
    Py_ssize_t R = items_of(ocnt, 8);
    if (R < 0) return NULL;
    const double *Lt = D(oLt, 16 * k, "Lt");
    const double *Ht = D(oHt, 24 * k, "Ht");
    const double *r = D(or, 4 * k, "r");
    const double *eps = D(oeps, 6, "eps");
    const unsigned char *ok = U8(ook, k, "ok");
    const long long *rows = I64(orows, k, "rows");
    double *dsum = DW(osum, 4 * R, "drift_sum");
    double *dn = DW(ocnt, R, "drift_n");
    unsigned char *mov = U8W(omov, k, "moving");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    long count = 0;
    if (check_indices(rows, k, R, "drift: row") < 0) {
        release_all(&bufs);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < k; i++) {
        long long row = rows[i];
        const double *ht = Ht + 24 * i;
        double e[4], w[4];
        for (int a = 0; a < 4; a++) {
            double s = 0.0;
            for (int b = 0; b < 6; b++) s += ht[a * 6 + b] * eps[b];
            e[a] = r[4 * i + a] - s;
        }
        forward_subst(Lt + 16 * i, 4, 4, e, w);
        double *ds = dsum + 4 * row;
        if (ok[i]) {
            for (int a = 0; a < 4; a++) ds[a] += w[a];
            dn[row] += 1.0;
        }
        double den = (isnan(dn[row]) || dn[row] > 1.0) ? dn[row] : 1.0;
        double stat = (ds[0] * ds[0] + ds[1] * ds[1] + ds[2] * ds[2] + ds[3] * ds[3]) / den;
        mov[i] = (unsigned char)(ok[i] && dn[row] >= 2.0 && stat > gate);
        count += mov[i];
    }
    release_all(&bufs);
    return PyLong_FromLong(count);
}

/* ------------------------------------------------------------------ state bookkeeping */

/* SlamState.remove_slots' Sigma' = Sigma[keep, keep] in place (keep increasing: each
 * entry moves up and left, so every source is read before it is overwritten).
 * compact(P, n, ld, keep) */
static PyObject *py_compact(PyObject *self, PyObject *args) {
    PyObject *oP, *okeep;
    Py_ssize_t n, ld;
    if (!PyArg_ParseTuple(args, "OnnO", &oP, &n, &ld, &okeep)) return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    Py_ssize_t m = items_of(okeep, 8);
    if (m < 0) return NULL;
    double *P = DW(oP, COV_ITEMS(n, ld), "P");
    const long long *keep = I64(okeep, m, "keep");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < m; i++)
        if (keep[i] < i || keep[i] >= n || (i && keep[i] <= keep[i - 1])) {
            release_all(&bufs);
            PyErr_SetString(PyExc_ValueError, "_ekf.compact: keep must be increasing indices below n");
            return NULL;
        }
    for (Py_ssize_t i = 0; i < m; i++) {
        const double *src = P + keep[i] * ld;
        double *dst = P + i * ld;
        for (Py_ssize_t j = 0; j < m; j++) dst[j] = src[keep[j]];
    }
    release_all(&bufs);
    Py_RETURN_NONE;
}

/* Whether the n doubles at x are all finite: an exponent field of all ones is inf or
 * NaN (integer tests, which the compiler vectorizes). */
static int all_finite(const double *x, Py_ssize_t n) {
    unsigned long long bad = 0;
    for (Py_ssize_t j = 0; j < n; j++) {
        unsigned long long b;
        memcpy(&b, x + j, sizeof b);
        bad |= (unsigned long long)((b & 0x7ff0000000000000ULL) == 0x7ff0000000000000ULL);
    }
    return bad == 0;
}

/* SlamFilter._check_health's tests: 1 when the pose, a landmark mean or Sigma is not
 * finite, 2 when a diagonal entry of Sigma is below -1e-9, else 0.
 * health(T, lm_mean, P, n, ld) */
static PyObject *py_health(PyObject *self, PyObject *args) {
    PyObject *oT, *olm, *oP;
    Py_ssize_t n, ld;
    if (!PyArg_ParseTuple(args, "OOOnn", &oT, &olm, &oP, &n, &ld)) return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    Py_ssize_t nl = items_of(olm, 8);
    if (nl < 0) return NULL;
    const double *T = D(oT, 16, "T");
    const double *lm = D(olm, nl, "lm_mean");
    const double *P = D(oP, COV_ITEMS(n, ld), "P");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    int status = 0;
    if (!all_finite(T, 16) || !all_finite(lm, nl)) status = 1;
    for (Py_ssize_t i = 0; i < n && !status; i++)
        if (!all_finite(P + i * ld, n)) status = 1;
    if (!status)
        for (Py_ssize_t i = 0; i < n; i++)
            if (P[i * ld + i] < -1e-9) {
                status = 2;
                break;
            }
    release_all(&bufs);
    return PyLong_FromLong(status);
}

/* SlamState.landmark_marginals: (k, 3) world points and (k, 3, 3) marginal covariances
 * of the landmarks in `slots`; inverse depth (anchors given): p = R_wa (a, b, 1)/rho + t_wa
 * and J Sigma_lambda J^T with J = dp/dlambda, rho at least 1e-6 (state.MIN_INVERSE_DEPTH).
 * marginals(lm_mean, anchors|None, P, n, ld, core, slots, p_out, cov_out) */
static PyObject *py_marginals(PyObject *self, PyObject *args) {
    PyObject *olm, *oanc, *oP, *oslots, *op, *ocov;
    Py_ssize_t n, ld, core;
    if (!PyArg_ParseTuple(args, "OOOnnnOOO", &olm, &oanc, &oP, &n, &ld, &core, &oslots, &op, &ocov)) return NULL;
    Bufs bufs = {.n = 0};
    int err = 0;
    Py_ssize_t k = items_of(oslots, 8);
    if (k < 0) return NULL;
    Py_ssize_t L = items_of(olm, 24);
    if (L < 0) return NULL;
    const double *lm = D(olm, 3 * L, "lm_mean");
    const double *anc = DOPT(oanc, 16 * L, "anchors");
    const double *P = D(oP, COV_ITEMS(n, ld), "P");
    const long long *slots = I64(oslots, k, "slots");
    double *pout = DW(op, 3 * k, "p_out");
    double *cout = DW(ocov, 9 * k, "cov_out");
    if (err) {
        release_all(&bufs);
        return NULL;
    }
    if (check_indices(slots, k, L < (n - core) / 3 ? L : (n - core) / 3, "marginals: slot") < 0) {
        release_all(&bufs);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < k; i++) {
        long long s = slots[i];
        Py_ssize_t row = core + 3 * s;
        double C[9];
        for (int a = 0; a < 3; a++)
            for (int b = 0; b < 3; b++) C[a * 3 + b] = P[(row + a) * ld + row + b];
        const double *l = lm + 3 * s;
        double *po = pout + 3 * i, *co = cout + 9 * i;
        if (!anc) {
            po[0] = l[0], po[1] = l[1], po[2] = l[2];
            memcpy(co, C, sizeof C);
            continue;
        }
        const double *A = anc + 16 * s;
        double rho = l[2] > 1e-6 ? l[2] : 1e-6;
        double bear[3] = {l[0], l[1], 1.0};
        double J[9];
        for (int a = 0; a < 3; a++) {
            double rb = A[a * 4] * bear[0] + A[a * 4 + 1] * bear[1] + A[a * 4 + 2] * bear[2];
            po[a] = rb / rho + A[a * 4 + 3];
            J[a * 3] = A[a * 4] / rho;
            J[a * 3 + 1] = A[a * 4 + 1] / rho;
            J[a * 3 + 2] = -rb / (rho * rho);
        }
        double JC[9];
        matmul(J, C, JC, 3, 3, 3);
        matmul_bt(JC, J, co, 3, 3, 3);
    }
    release_all(&bufs);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------ module */

#ifdef EKF_TIMING
static PyObject *py_timings(PyObject *self, PyObject *args) {
    PyObject *out = PyList_New(16);
    for (int i = 0; i < 16; i++) { PyList_SET_ITEM(out, i, PyFloat_FromDouble(tacc[i])); tacc[i] = 0.0; }
    return out;
}
#endif

static PyObject *py_counters(PyObject *self, PyObject *args) {
    return Py_BuildValue("{s:L}", "solve_fallbacks", solve_fallbacks);
}

static PyMethodDef methods[] = {
    {"counters", py_counters, METH_NOARGS, "how often the update took its fallbacks (for tests)"},
#ifdef EKF_TIMING
    {"timings", py_timings, METH_NOARGS, "accumulated stage times (profiling builds)"},
#endif
    {"set_lapack", py_set_lapack, METH_VARARGS, "set_lapack(dsyrk, dtrsm, dgemm, dpotrf, dgemv): scipy's BLAS/LAPACK capsules"},
    {"predict", py_predict, METH_VARARGS, "the pose prediction of the SLAM state (propagation.predict_state)"},
    {"linearize", py_linearize, METH_VARARGS, "residuals and OC Jacobians of stereo observations (updaters._linearize)"},
    {"innovation", py_innovation, METH_VARARGS, "blocks, NIS and drift model (updaters.slam_predict_nis)"},
    {"update", py_update, METH_VARARGS, "the joint EKF update (updaters.slam_update)"},
    {"restore", py_restore, METH_VARARGS, "Sigma + Bt Bt^T in place (updaters._restore_prior)"},
    {"gain_times", py_gain_times, METH_VARARGS, "K dr (updaters.gain_times)"},
    {"step_size", py_step_size, METH_VARARGS, "step size in sigma (updaters._step_size)"},
    {"drift", py_drift, METH_VARARGS, "the drift test's sums (SlamFilter._drift_test)"},
    {"compact", py_compact, METH_VARARGS, "Sigma[keep, keep] in place (SlamState.remove_slots)"},
    {"health", py_health, METH_VARARGS, "finite state and diagonal (SlamFilter._check_health)"},
    {"marginals", py_marginals, METH_VARARGS, "landmark positions and covariances (SlamState.landmark_marginals)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef moduledef = {PyModuleDef_HEAD_INIT, "_ekf",
                                       "Compiled kernels of the SLAM EKF (see vislam.core.kernels).", -1, methods};

/* The interface version vislam.core.kernels expects: raised with every change of a
 * function's arguments, so that a build older than its sources (an editable install
 * whose _ekf.c changed since `pip install -e .`) is refused instead of misread. */
#define EKF_ABI_VERSION 1

PyMODINIT_FUNC PyInit__ekf(void) {
    PyObject *m = PyModule_Create(&moduledef);
    if (m && PyModule_AddIntConstant(m, "ABI_VERSION", EKF_ABI_VERSION) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
