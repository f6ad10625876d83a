"""EKF updaters: the stereo observation model, gating, the joint SLAM update, landmark
initialization, and the per-landmark mapping update.

Observation model (the report's), with ``T = imu_T_world`` and a landmark ``m`` (world)::

    z = h(T, m) + v = M π(cam_T_imu T m) + v,        v ~ N(0, V)

Jacobians at the mean (left perturbation of T, additive on m)::

    H_pose = M dπ/dq(q) cam_T_imu (μ m)^⊙              (4x6)
    H_lm   = M dπ/dq(q) cam_T_imu μ Pᵀ                 (4x3),  q = cam_T_imu μ m

Each observation touches the pose block and one landmark block only, so the products
with the stacked Jacobian H are formed from those blocks (never a dense 4N x n H).
With the IMU-error state (``state.core_dim`` 12, rows 6:12 of Σ) H has zero columns for
b: S only involves the pose and landmark blocks, the gain Σ Hᵀ S⁻¹ has rows for b
(through Σ_b,pose and Σ_b,lm), and the correction applies b̂ ← b̂ + δ_b; the landmarks
start at ``core_dim``. The OC projection leaves b out (b is not moved by the global
gauge: its block of the nullspace is zero).
"""

from __future__ import annotations

import logging
import math

import numpy as np
from scipy.linalg import solve_triangular

from vislam.core import dense
from vislam.core.camera import StereoCamera, dpi_dq
from vislam.core.lie import se3_exp, se3_inverse, se3_log, se3_odot
from vislam.core.state import POSE_DIM, SlamState

logger = logging.getLogger(__name__)

__all__ = [
    "StereoModel",
    "innovation_nis",
    "initialization_guard",
    "oc_project",
    "slam_predict_nis",
    "conditional_residual_model",
    "compress_stereo",
    "slam_update",
    "slam_update_iterated",
    "gain_times",
    "innovation_covariances",
    "slam_update_reference",
    "slam_initialize_landmarks",
    "mapping_update",
    "mapping_initialize",
    "static_consistency_nis",
]


class StereoModel:
    """The stereo observation model for a fixed camera and cam_T_imu."""

    def __init__(self, camera: StereoCamera, cam_T_imu: np.ndarray):
        self.camera = camera
        self.M = np.ascontiguousarray(camera.M, dtype=np.float64)
        self.cam_T_imu = np.ascontiguousarray(cam_T_imu, dtype=np.float64)  # C order: the compiled kernels read it
        # the exact matrix inverse: a recorded cam_T_imu is rigid only to ~1e-7, and the
        # initialization must invert exactly what the observation model applies
        self.imu_T_cam = np.linalg.inv(self.cam_T_imu)

    def predict(self, imu_T_world: np.ndarray, p_lm_in_world: np.ndarray, with_pose_jacobian: bool = True,
                world_T_anchor: np.ndarray | None = None):
        """Predicted observations and Jacobians for k landmarks.

        ``world_T_anchor`` (k, 4, 4): the landmarks are anchored inverse-depth parameters
        λ = (α, β, ρ) (see :mod:`vislam.core.state`), whose homogeneous world point is
        ``m_h = world_T_anchor (α, β, 1, ρ)`` (the Cartesian point scaled by ρ, which the
        projection ignores); then ``H_lm = M dπ/dq(q) cam_T_imu μ world_T_anchor E`` with
        E the columns of α, β and ρ, and H_pose the same formula with the scaled m_h.

        Returns:
            z_hat: (k, 4) predicted pixels (rows with ``in_front`` False are garbage).
            H_pose: (k, 4, 6) or None.
            H_lm: (k, 4, 3).
            in_front: (k,) bool, q_z > 0 (only those can be linearized; inverse depth:
                also ρ > 0).
        """
        k = p_lm_in_world.shape[0]
        if world_T_anchor is None:
            m_h = np.empty((k, 4))
            m_h[:, :3] = p_lm_in_world
            m_h[:, 3] = 1.0
        else:
            lam_h = np.empty((k, 4))
            lam_h[:, :2] = p_lm_in_world[:, :2]
            lam_h[:, 2] = 1.0
            lam_h[:, 3] = p_lm_in_world[:, 2]
            m_h = np.einsum("kij,kj->ki", world_T_anchor, lam_h)  # world_T_anchor (α, β, 1, ρ)
        cam_T_world = self.cam_T_imu @ imu_T_world
        q = m_h @ cam_T_world.T  # q = cam_T_imu μ m
        in_front = q[:, 2] > 1e-6
        if world_T_anchor is not None:
            in_front &= m_h[:, 3] > 0
        q_safe = q
        if not in_front.all():
            q_safe = q.copy()
            q_safe[~in_front, 2] = 1.0
        J = self.M @ _dpi_dq_in_front(q_safe)  # M dπ/dq(q)   (k, 4, 4)
        z_hat = (q_safe / q_safe[:, 2:3]) @ self.M.T  # M π(q)
        if world_T_anchor is None:
            H_lm = J[:, :, :3] @ cam_T_world[:3, :3]  # M dπ/dq cam_T_imu μ Pᵀ
        else:
            A = cam_T_world @ world_T_anchor  # cam_T_anchor of each landmark
            H_lm = J @ A[:, :, _COLS_ALPHA_BETA_RHO]  # M dπ/dq cam_T_imu μ world_T_anchor [e1 e2 e4]
        H_pose = None
        if with_pose_jacobian:
            q_imu = m_h @ imu_T_world.T  # μ m
            H_pose = (J @ self.cam_T_imu) @ se3_odot(q_imu)  # M dπ/dq cam_T_imu (μ m)^⊙
        return z_hat, H_pose, H_lm, in_front


_COLS_ALPHA_BETA_RHO = np.array([0, 1, 3])
_XYW = np.array([0, 1, 3])  # the rows of dπ/dq with entries


def _dpi_dq_in_front(q: np.ndarray) -> np.ndarray:
    """:func:`~vislam.core.camera.dpi_dq` of (k, 4) float64 points all with q_z > 0 (the
    caller made sure): the same arithmetic without the argument checks (the filter calls
    it per frame); non-finite entries still raise GeometryError."""
    out = np.zeros(q.shape[:-1] + (4, 4))
    with np.errstate(over="ignore", invalid="ignore"):
        inv_z = (1.0 / q[:, 2])[:, None]
        out[:, _XYW, _XYW] = inv_z  # (0, 0), (1, 1), (3, 3)
        out[:, _XYW, 2] = -q[:, _XYW] * inv_z * inv_z  # (0, 2), (1, 2), (3, 2): −q_i / q_z²
    if not np.isfinite(out).all():
        return dpi_dq(q)  # raises the GeometryError of a non-finite Jacobian
    return out


def innovation_nis(r: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Normalized innovation squared rᵀ S⁻¹ r for (k, 4) residuals and (k, 4, 4) covariances.
    An S that is singular in floating point (a prior so wide — e.g. after a time gap of
    an hour — that the pixel noise is lost in rounding) gives NIS = inf: the gate refuses
    that observation instead of the frame failing."""
    if r.shape[0] == 0:
        return np.zeros(0)
    try:
        x = dense.solve(S, r[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        return np.array([_nis_or_inf(r[i], S[i]) for i in range(r.shape[0])])
    return np.einsum("ki,ki->k", r, x)


def _nis_or_inf(r: np.ndarray, S: np.ndarray) -> float:
    try:
        return float(r @ dense.solve(S, r))
    except np.linalg.LinAlgError:
        return math.inf


def initialization_guard(camera: StereoCamera, pixels: np.ndarray, options) -> np.ndarray:
    """(k,) True where an observation may be triangulated (the initialization rule).

    A landmark is initialized from its first observation that has a finite disparity of
    at least ``min_disparity_px``, rows that agree within ``max_row_difference_px``,
    and a triangulated depth within [``min_depth_m``, ``max_depth_m``].
    """
    pixels = np.asarray(pixels, dtype=np.float64)
    finite = np.all(np.isfinite(pixels), axis=1)
    d = np.where(finite, pixels[:, 0] - pixels[:, 2], -1.0)
    ok = finite & (d >= max(options.min_disparity_px, 1e-9))
    depth = np.divide(camera.fsu * camera.baseline_m, d, out=np.full_like(d, np.inf), where=d > 0)
    ok &= (depth >= options.min_depth_m) & (depth <= options.max_depth_m)
    ok &= np.abs(pixels[:, 1] - pixels[:, 3]) <= options.max_row_difference_px
    return ok


def _gather_blocks(state: SlamState, slots: np.ndarray):
    """Σ_pp (6,6), Σ_p,s (k,6,3) and Σ_s,s (k,3,3) for landmark slots."""
    P = state.cov
    rows = state.landmark_rows(slots)  # (k, 3)
    P_pl = P[:POSE_DIM][:, rows]  # (6, k, 3)
    P_ll = P[rows[:, :, None], rows[:, None, :]]  # (k, 3, 3)
    return P[:POSE_DIM, :POSE_DIM], np.transpose(P_pl, (1, 0, 2)), P_ll


def _linearize(state: SlamState, model: StereoModel, slots: np.ndarray, z: np.ndarray, N_pose: np.ndarray | None):
    """(r, H_pose, H_lm, in_front) of observations ``z`` of landmark ``slots`` at the
    current estimate (OC-projected with ``N_pose`` when given)."""
    anchors = state.world_T_anchor[slots] if state.inverse_depth else None
    z_hat, Hp, Hl, in_front = model.predict(state.imu_T_world, state.lm_mean[slots], world_T_anchor=anchors)
    if state.lm_dim == 6:  # the observation does not depend on the velocity
        Hl = np.concatenate([Hl, np.zeros_like(Hl)], axis=2)
    if N_pose is not None:
        Hp, Hl = oc_project(Hp, Hl, N_pose, state.lm_null[slots])
    return z - z_hat, Hp, Hl, in_front


def slam_predict_nis(state: SlamState, model: StereoModel, slots: np.ndarray, z: np.ndarray, V: np.ndarray,
                     N_pose: np.ndarray | None = None):
    """Linearize every observation and compute its own innovation covariance and NIS.

    Per observation i (landmark slot s)::

        S_i = H_p Σ_pp H_pᵀ + H_p Σ_ps H_lᵀ + H_l Σ_sp H_pᵀ + H_l Σ_ss H_lᵀ + V
        NIS_i = r_iᵀ S_i⁻¹ r_i,   r_i = z_i − ẑ_i

    Returns (r, H_pose, H_lm, in_front, nis, blocks); NIS is +inf where the landmark
    is behind the camera; blocks = (Σ_pp, Σ_ps, Σ_ss) of the prior.
    """
    r, Hp, Hl, in_front = _linearize(state, model, slots, z, N_pose)
    blocks = _gather_blocks(state, slots)
    S = innovation_covariances(Hp, Hl, blocks, V)
    if in_front.all():
        nis = innovation_nis(r, S)
    else:
        nis = np.full(len(slots), np.inf)
        if in_front.any():
            nis[in_front] = innovation_nis(r[in_front], S[in_front])
    return r, Hp, Hl, in_front, nis, blocks


def innovation_covariances(Hp: np.ndarray, Hl: np.ndarray, blocks, V: np.ndarray) -> np.ndarray:
    """(k, 4, 4) innovation covariance of each observation on its own, from its
    Jacobians and the prior blocks (Σ_pp, Σ_ps, Σ_ss) of :func:`slam_predict_nis`::

        S_i = H_p Σ_pp H_pᵀ + H_p Σ_ps H_lᵀ + H_l Σ_sp H_pᵀ + H_l Σ_ss H_lᵀ + V
    """
    P_pp, P_ps, P_ss = blocks
    cross = (Hp @ P_ps) @ np.swapaxes(Hl, 1, 2)  # H_p Σ_ps H_lᵀ (k, 4, 4)
    return Hp @ P_pp @ np.swapaxes(Hp, 1, 2) + cross + np.swapaxes(cross, 1, 2) + Hl @ P_ss @ np.swapaxes(Hl, 1, 2) + V


def conditional_residual_model(blocks, Hp: np.ndarray, Hl: np.ndarray, V: np.ndarray):
    """How each observation depends on the pose correction, and what is left.

    Conditioning the joint prior on the pose correction ε splits each landmark into
    E[δm | ε] = Σ_sp Σ_pp⁻¹ ε and a remainder of covariance Σ_ss − Σ_sp Σ_pp⁻¹ Σ_ps::

        r_i = H̃_i ε + e_i,   H̃_i = H_p + H_l Σ_sp Σ_pp⁻¹,
        e_i ~ N(0, S̃_i),     S̃_i = H_l (Σ_ss − Σ_sp Σ_pp⁻¹ Σ_ps) H_lᵀ + V

    Returns (H̃ (k, 4, 6), L̃ (k, 4, 4)) with S̃ = L̃ L̃ᵀ: after an update that corrected
    the pose by ε, L̃⁻¹ (r − H̃ ε) is what the landmark's own observation says beyond the
    consensus of the frame, whitened — N(0, I₄) for a static landmark.
    """
    P_pp, P_ps, P_ss = blocks
    k, _, d = P_ps.shape
    # Σ_pp⁻¹ Σ_ps of every landmark as one solve with 6 x dk right-hand sides (LAPACK solves
    # column by column: the same numbers as k broadcast solves of one matrix, 2.5x faster)
    X = dense.solve(P_pp + _EPS_EYE6, np.swapaxes(P_ps, 0, 1).reshape(POSE_DIM, k * d))
    G = X.reshape(POSE_DIM, k, d).transpose(1, 2, 0)  # Σ_sp Σ_pp⁻¹ (k, d, 6)
    Ht = Hp + Hl @ G
    C = P_ss - G @ P_ps  # Σ_ss − Σ_sp Σ_pp⁻¹ Σ_ps
    St = Hl @ C @ np.swapaxes(Hl, 1, 2) + V
    return Ht, dense.cholesky(0.5 * (St + np.swapaxes(St, 1, 2)))


_EPS_EYE6 = 1e-12 * np.eye(POSE_DIM)


def oc_project(Hp: np.ndarray, Hl: np.ndarray, N_pose: np.ndarray, N_lm: np.ndarray):
    """Observability-constrained Jacobians (Huang et al. 2010; Hesch et al. 2014).

    The global pose of the map is unobservable: moving world and landmarks together by
    exp(ε) changes no observation. With the pose error δ = −Ad(μ) ε and landmark error
    N_j ε, every observation's Jacobian H = [H_p, H_l] must satisfy H N = 0,
    N = [N_pose; N_j]. Linearizing at estimates that change from frame to frame breaks
    this and gives the filter spurious information along those directions (the classic
    EKF-SLAM inconsistency). The constrained Jacobian is the closest one (Frobenius) that
    keeps the nullspace::

        H* = H − H N (Nᵀ N)⁻¹ Nᵀ
    """
    N_lmT = np.swapaxes(N_lm, 1, 2)  # (k, 6, d)
    HN = Hp @ N_pose + Hl @ N_lm  # H N  (k, 4, 6)
    NtN = N_pose.T @ N_pose + N_lmT @ N_lm  # Nᵀ N  (k, 6, 6), symmetric
    Z = np.swapaxes(dense.solve(NtN, np.swapaxes(HN, 1, 2)), 1, 2)  # H N (Nᵀ N)⁻¹  (k, 4, 6)
    return Hp - Z @ N_pose.T, Hl - Z @ N_lmT  # H* = H − H N (Nᵀ N)⁻¹ Nᵀ, split by blocks


def _apply_correction(state: SlamState, dx: np.ndarray) -> None:
    """μ_pose ← exp(δ_p^) μ_pose;  b̂ ← b̂ + δ_b (IMU-error state);  m ← m + δ_m  (the
    report's split of K (z − ẑ))."""
    state.imu_T_world = se3_exp(dx[:POSE_DIM]) @ state.imu_T_world
    c = state.core_dim
    if state.has_bias:
        state.imu_bias = state.imu_bias + dx[POSE_DIM:c]
    if state.n_landmarks:
        d_lm = dx[c:].reshape(state.n_landmarks, state.lm_dim)
        state.lm_mean = state.lm_mean + d_lm[:, :3]
        if state.lm_dim == 6:
            state.v_lm_in_world = state.v_lm_in_world + d_lm[:, 3:]


def _innovation_terms(P: np.ndarray, rows: np.ndarray, Hp: np.ndarray, Hl: np.ndarray, var: np.ndarray):
    """Σ Hᵀ (n x mk) and the Cholesky factor L of S = H Σ Hᵀ + R, from the blocks.

    ``Hp`` (k, m, 6), ``Hl`` (k, m, 3); ``var`` (m,) is the diagonal of each
    observation's noise covariance (R = I ⊗ diag(var)).
    """
    k, m = Hp.shape[:2]
    n = P.shape[0]
    # Σ Hᵀ, column block i: Σ[:, :6] H_p,iᵀ + Σ[:, rows_i] H_l,iᵀ
    PHt = P[:, :POSE_DIM] @ Hp.reshape(k * m, POSE_DIM).T  # (n, mk)
    d = rows.shape[1]
    P_rows = P[:, rows.ravel()].reshape(n, k, d)  # Σ[:, s_i] for every i, one gather
    # (an einsum over the small block dimensions: 5x faster than a stacked matmul here)
    PHt += np.einsum("nkj,kmj->nkm", P_rows, Hl).reshape(n, k * m)
    # S = H (Σ Hᵀ) + R: the rows of Σ Hᵀ at the pose and at each observed landmark
    S = Hp.reshape(k * m, POSE_DIM) @ PHt[:POSE_DIM]  # (mk, mk)
    S += (Hl @ PHt[rows]).reshape(k * m, k * m)
    S.reshape(-1)[::k * m + 1] += np.tile(var, k)  # + I ⊗ R_i (the diagonal, as a strided view)
    return PHt, dense.cholesky(S)  # S = L Lᵀ (reads the lower triangle)


def compress_stereo(r: np.ndarray, Hp: np.ndarray, Hl: np.ndarray, V: np.ndarray):
    """Exact 3-row form of k stereo observations for the update.

    The rows of vL and vR in the model are identical (M's rows 2 and 4 are equal), so
    with independent noise of equal variance σ_v² the pair carries exactly the
    information of its mean, (vL + vR)/2 with variance σ_v²/2: the same Gaussian
    likelihood up to a constant, hence the same EKF update, with 3k instead of 4k rows.
    Returns (r3, Hp3, Hl3, var3).
    """
    compressed, var = stereo_row_variances(V)
    if not compressed:
        return r, Hp, Hl, var  # not applicable: keep the four rows
    r3 = r[:, :3].copy()
    r3[:, 1] = 0.5 * (r[:, 1] + r[:, 3])
    Hp3 = Hp[:, :3].copy()
    Hp3[:, 1] = 0.5 * (Hp[:, 1] + Hp[:, 3])
    Hl3 = Hl[:, :3].copy()
    Hl3[:, 1] = 0.5 * (Hl[:, 1] + Hl[:, 3])
    return r3, Hp3, Hl3, var


def stereo_row_variances(V: np.ndarray) -> tuple[bool, np.ndarray]:
    """(whether :func:`compress_stereo` folds the vL/vR rows for the noise V — diagonal,
    with equal row variances — and the noise variance of each row of the update: uL,
    (vL + vR)/2, uR when folded, else V's diagonal, the four rows)."""
    var = V.diagonal()  # (a read-only view, as np.diag(V) gives, without its dispatch)
    if V[1, 1] != V[3, 3] or np.count_nonzero(V - np.diag(var)):
        return False, var
    return True, np.array([var[0], 0.5 * var[1], var[2]])


def slam_update(state: SlamState, slots: np.ndarray, r: np.ndarray, Hp: np.ndarray, Hl: np.ndarray,
                V: np.ndarray, factors: dict | None = None) -> np.ndarray:
    """Joint EKF update of pose and landmarks with k accepted observations (in place).

    Block-sparse form of the report's update (after :func:`compress_stereo`)::

        Σ Hᵀ = Σ[:, pose] H_pᵀ + Σ[:, s_i] H_lᵀ          (n x 3k), from the blocks
        S    = H Σ Hᵀ + I ⊗ V                              (3k x 3k)
        S    = L Lᵀ                                        (Cholesky)
        B    = L⁻¹ (Σ Hᵀ)ᵀ                                 (so K S Kᵀ = Bᵀ B)
        δ    = K r = Bᵀ (L⁻¹ r)
        Σ   ← Σ − Bᵀ B = Σ − K S Kᵀ                        (symmetric rank-3k form)

    Returns the pose correction δ_p (μ ← exp(δ_p^) μ). Raises numpy.linalg.LinAlgError
    when S is not positive definite. ``factors``: a dict that receives the gain's factors
    (``L``, ``B`` and whether the rows were compressed), for :func:`gain_times`.
    """
    k = len(slots)
    if k == 0:
        return np.zeros(POSE_DIM)
    r, Hp, Hl, var = compress_stereo(r, Hp, Hl, V)
    P = state.cov
    rows = state.landmark_rows(slots)  # (k, 3)
    PHt, L = _innovation_terms(P, rows, Hp, Hl, var)
    B = dense.solve_lower(L, PHt.T)  # B = L⁻¹ H Σ
    y = dense.solve_lower(L, r.reshape(-1))  # y = L⁻¹ r
    dx = B.T @ y  # δ = K r = Σ Hᵀ S⁻¹ r
    if factors is not None:  # dx: K r, what gain_times(factors, r) computes (the same operations)
        factors.update(L=L, B=B, compressed=r.shape[1] == 3, dx=dx)
    P -= B.T @ B  # Σ ← Σ − K S Kᵀ (a full GEMM beats SYRK + symmetrizing at these sizes)
    _apply_correction(state, dx)
    return dx[:POSE_DIM]


def gain_times(factors: dict, dr: np.ndarray) -> np.ndarray:
    """K dr for (k, 4) residuals with the gain of the update that filled ``factors``
    (K = Σ Hᵀ S⁻¹ = Bᵀ L⁻¹, the rows compressed as that update did)."""
    if factors["compressed"]:  # the rows of compress_stereo: uL, (vL + vR)/2, uR
        dr = np.stack([dr[:, 0], 0.5 * (dr[:, 1] + dr[:, 3]), dr[:, 2]], axis=1)
    y = dense.solve_lower(factors["L"], dr.reshape(-1))
    return factors["B"].T @ y


def _step_size(state: SlamState, slots: np.ndarray, dx: np.ndarray) -> float:
    """Size of a state step in standard deviations of the current covariance: the largest
    of the pose's and of each observed landmark's Mahalanobis norm (marginal blocks)."""
    P = state.cov
    pose = dx[:POSE_DIM]
    try:
        size = float(pose @ dense.solve(P[:POSE_DIM, :POSE_DIM], pose))
    except np.linalg.LinAlgError:  # a singular block (zero IMU noise): the step lies in its range
        size = float(pose @ np.linalg.lstsq(P[:POSE_DIM, :POSE_DIM], pose, rcond=None)[0])
    if len(slots):
        rows = state.landmark_rows(slots)
        if rows.shape[1] != 3:
            rows = rows[:, :3]  # (k, 3) position rows
        P_ll = P[rows[:, :, None], rows[:, None, :]]
        e = dx[rows]
        try:
            q = np.einsum("ki,ki->k", e, dense.solve(P_ll, e[:, :, None])[:, :, 0])
        except np.linalg.LinAlgError:
            q = np.array([float(ek @ np.linalg.lstsq(Pk, ek, rcond=None)[0]) for Pk, ek in zip(P_ll, e)])
        size = max(size, q.max().item())  # (the method: np.max's dispatch costs more than the reduction)
    return math.sqrt(max(size, 0.0))


class FirstStepTest:
    """Whether to test the first step before re-linearizing (slam_update_iterated). Both
    orders take the same decisions; the test first saves a linearization when it settles
    the frame and costs one step-size evaluation when it does not. It is kept while it
    settles at least a fifth of the recent frames, and tried again every 32nd frame. One
    per filter (its frames' history); without one, the test always runs."""

    def __init__(self):
        self.rate = 1.0  # running share of the frames the test settled
        self.skipped = 0

    def worth_it(self) -> bool:
        if self.rate >= 0.2 or self.skipped >= 31:
            self.skipped = 0
            return True
        self.skipped += 1
        return False

    def record(self, settled: bool) -> None:
        self.rate += 0.1 * (float(settled) - self.rate)



def _relinearized_residual(state: SlamState, slots: np.ndarray, r: np.ndarray, Hp: np.ndarray, Hl: np.ndarray,
                           mu0: np.ndarray, lm0: np.ndarray, v0: np.ndarray) -> np.ndarray:
    """The iterated update's residual at x_i, z − h(x_i) − H_i (x₀ ⊟ x_i), from ``r`` = z − h(x_i)."""
    d = lm0[slots] - state.lm_mean[slots]  # m₀ − m_i (and v₀ − v_i with velocities)
    if Hl.shape[2] == 6:
        d = np.concatenate([d, v0[slots] - state.v_lm_in_world[slots]], axis=1)
    return r - Hp @ se3_log(mu0 @ se3_inverse(state.imu_T_world)) - np.einsum("kij,kj->ki", Hl, d)


def _restore_means(state: SlamState, mu0, b0, lm0, v0) -> None:
    """The prior's means x₀ back into the state (copies: the update replaces or moves them)."""
    state.imu_T_world = mu0.copy()
    state.imu_bias = b0.copy()
    state.lm_mean = lm0.copy()
    state.v_lm_in_world = v0.copy()


def _restore_prior(state: SlamState, mu0, b0, lm0, v0, P0, factors) -> None:
    """Back to the prior x₀, Σ₀ before a re-linearized update (Σ₀ kept in ``P0``, or
    restored from the last gain's factors when ``P0`` is None)."""
    _restore_means(state, mu0, b0, lm0, v0)
    if P0 is None:
        P, B = state.cov, factors["B"]
        P += B.T @ B  # Σ₀ = Σ + K S Kᵀ (in place)
    else:
        state.cov[...] = P0


def _next_step_size(state: SlamState, slots: np.ndarray, factors: dict, r: np.ndarray, r_prev: np.ndarray,
                    prev_step: float | None, tolerance: float, ops) -> float | None:
    """The adaptive iterated update's step x_{i+1} − x_i ≈ K_{i−1} (r̃_i − r̃_{i−1}) in σ,
    or None when the iteration stops: converged (below ``tolerance``) or not contracting
    (larger than ``prev_step``, the step before; the first, x_1 − x_0 = K_0 r_0, when None).
    ``ops``: the arithmetic of :func:`slam_update_iterated`."""
    step = ops.step_size(state, slots, ops.gain_times(factors, r - r_prev))
    if step < tolerance:
        return None  # converged: the re-linearization would move the estimate by a negligible step
    if prev_step is None:  # the size of the step already taken, x_1 − x_0 = K_0 r_0 (the update's own K r)
        prev_step = ops.step_size(state, slots, factors["dx"] if "dx" in factors else ops.gain_times(factors, r_prev))
    if step > prev_step:
        return None  # not contracting: Gauss-Newton would move away; keep the last iterate
    return step


def slam_update_iterated(state: SlamState, model: StereoModel, slots: np.ndarray, z: np.ndarray, V: np.ndarray,
                         N_pose: np.ndarray | None, iterations: int, update=None, tolerance: float = 0.0,
                         counts: list | None = None, first: tuple | None = None,
                         first_step_test: FirstStepTest | None = None, ops=None) -> np.ndarray:
    """Iterated EKF update (Gauss-Newton on the frame's observations) in place.

    Re-linearizes at the updated estimate x_i and redoes the update from the prior x₀, Σ₀::

        x_{i+1} = x₀ ⊞ K_i (z − h(x_i) − H_i (x₀ ⊟ x_i)),   Σ = Σ₀ − K_i S_i K_iᵀ

    (x₀ ⊟ x_i: log(μ₀ μ_i⁻¹) for the pose — the left perturbation at μ_i — and m₀ − m_i
    for the landmarks; the IMU-error state has zero columns in H, so b̂₀ − b̂_i adds
    nothing; H_i OC-projected with ``N_pose`` when given). ``iterations`` = 1 is the EKF
    update. ``update``: the update function (default :func:`slam_update`).

    ``tolerance`` > 0 makes ``iterations`` a maximum (adaptive iterated update): before each
    re-linearized update, the step it would take is predicted to first order with the last
    gain, ``x_{i+1} − x_i ≈ K_{i−1} (r̃_i − r̃_{i−1})`` (r̃_i the residual z − h(x_i) − H_i
    (x₀ ⊟ x_i) the update would use: a linear model leaves it unchanged), and the iterations
    stop when that step is below ``tolerance`` standard deviations (of the pose and of every
    observed landmark, marginally, under the current covariance) — the linearization at x_i
    then gives nothing new. A frame whose prior is narrow against the pixel noise costs one
    update and one prediction. They also stop when that step is larger than the step before
    (the first: x₁ − x₀ = K₀ r₀, in the same metric): Gauss-Newton that does not contract is
    moving away, so the last iterate is kept. The iteration therefore goes on only if
    tolerance ≤ step ≤ the step already taken, and a first step below the tolerance ends it
    before any re-linearization (the same decision, cheaper). ``counts``: a list that
    receives the number of updates done. ``first``: (r, H_pose, H_lm) of these observations
    at the prior, when the caller has them already. ``first_step_test``: the caller's
    :class:`FirstStepTest` (whether that first-step test pays). ``ops``: the arithmetic
    (:class:`vislam.core.kernels.NumpyOps`, the default, or the compiled
    :class:`~vislam.core.kernels.KernelOps`); ``update`` defaults to its ``update``.
    Returns the total pose correction ε, μ = exp(ε) μ₀.
    """
    ops = ops or _numpy_ops()
    update = update or ops.update
    first_step_test = first_step_test or FirstStepTest()  # without one: always test
    # the prior's means (the IMU-error state b̂₀ too: observations do not depend on it)
    prior = mu0, b0, lm0, v0 = (state.imu_T_world.copy(), state.imu_bias.copy(), state.lm_mean.copy(),
                                state.v_lm_in_world.copy())
    factors = {} if tolerance > 0 else None
    # the prior covariance: kept, or (adaptive) restored from the gain's factors only when
    # iterating, Σ₀ = Σ + Bᵀ B, so that a frame that needs one update copies nothing
    P0 = state.cov.copy() if factors is None else None
    r_prev = None
    prev_step = None
    done = 0
    for i in range(max(int(iterations), 1)):
        if i == 0 and first is not None:
            (r, Hp, Hl), in_front = first, None
        elif i == 1 and factors and first_step_test.worth_it():
            # The iteration goes on only if tolerance <= step <= prev_step (the two tests
            # below), so a first step x_1 − x_0 = K_0 r_0 already below the tolerance ends
            # it whatever the re-linearization says: decide that before paying for it (the
            # same decision and the same state; on the sparse files most frames stop here,
            # on the dense ones almost none, where the test is skipped: FirstStepTest).
            first_dx = factors["dx"] if "dx" in factors else ops.gain_times(factors, r_prev)
            prev_step = ops.step_size(state, slots, first_dx)
            first_step_test.record(prev_step < tolerance)
            if prev_step < tolerance:
                break
            r, Hp, Hl, in_front = ops.linearize(state, model, slots, z, N_pose, prior)
        else:  # (from the second iteration on, r is the residual z − h(x_i) − H_i (x₀ ⊟ x_i))
            r, Hp, Hl, in_front = ops.linearize(state, model, slots, z, N_pose, prior if i else None)
        if i and not in_front.all():
            break  # keep the last iterate: the next linearization point has a point behind the camera
        if i:
            if factors:
                prev_step = _next_step_size(state, slots, factors, r, r_prev, prev_step, tolerance, ops)
                if prev_step is None:
                    break
            ops.restore_prior(state, mu0, b0, lm0, v0, P0, factors)
        update(state, slots, r, Hp, Hl, V, factors=factors)
        r_prev = r
        done += 1
    if counts is not None:
        counts.append(done)
    return se3_log(state.imu_T_world @ se3_inverse(mu0))


def _numpy_ops():
    """The numpy arithmetic (:class:`vislam.core.kernels.NumpyOps`; imported here: that
    module builds on this one)."""
    from vislam.core.kernels import NumpyOps

    return NumpyOps()


def schmidt_update(state: SlamState, slots: np.ndarray, r: np.ndarray, Hp: np.ndarray, Hl: np.ndarray,
                   V: np.ndarray) -> None:
    """Update only the landmarks in ``slots``; the pose and every other landmark are
    *considered* (Schmidt-Kalman filter): their means and covariances are unchanged.

    With A the rows of the updated landmarks and K_A = (Σ Hᵀ)_A S⁻¹ (the other rows of
    the gain set to zero), the Joseph form reduces to::

        x_A ← x_A + K_A r
        Σ_A,: ← Σ_A,: − K_A (H Σ)          (and Σ_:,A = Σ_A,:ᵀ)

    This is the exact covariance of that (suboptimal, conservative) update, so Σ stays
    consistent. Used for young landmarks, which should not move the pose before their
    own position is well determined.
    """
    k = len(slots)
    if k == 0:
        return
    r, Hp, Hl, var = compress_stereo(r, Hp, Hl, V)
    P = state.cov
    rows = state.landmark_rows(slots)  # (k, d)
    PHt, L = _innovation_terms(P, rows, Hp, Hl, var)  # Σ Hᵀ (n x mk)
    A = rows.ravel()
    # K_A = (Σ Hᵀ)_A S⁻¹, via the Cholesky factor
    KA = solve_triangular(L.T, solve_triangular(L, PHt[A].T, lower=True, check_finite=False), lower=False,
                          check_finite=False).T  # (dk, mk)
    dxA = KA @ r.reshape(-1)
    update_rows = KA @ PHt.T  # K_A (H Σ)   (dk, n)
    P[A, :] -= update_rows
    P[:, A] = P[A, :].T
    d = state.lm_dim
    dx = dxA.reshape(k, d)
    state.lm_mean[slots] += dx[:, :3]
    if d == 6:
        state.v_lm_in_world[slots] += dx[:, 3:]


def slam_update_reference(state: SlamState, slots: np.ndarray, r: np.ndarray, Hp: np.ndarray, Hl: np.ndarray,
                          V: np.ndarray, factors: dict | None = None) -> None:
    """The plain (dense) formulation of :func:`slam_update`, for tests: builds the full
    4k x n Jacobian and applies the Joseph form ``(I − K H) Σ (I − K H)ᵀ + K (I ⊗ V) Kᵀ``."""
    k = len(slots)
    if k == 0:
        return np.zeros(POSE_DIM)
    n = state.dim
    H = np.zeros((4 * k, n))
    rows = state.landmark_rows(slots)
    for i in range(k):
        H[4 * i:4 * i + 4, :POSE_DIM] = Hp[i]
        H[4 * i:4 * i + 4, rows[i]] = Hl[i]
    P = state.cov.copy()
    R = np.kron(np.eye(k), V)  # I ⊗ V
    S = H @ P @ H.T + R  # S = H Σ Hᵀ + I ⊗ V
    K = P @ H.T @ np.linalg.inv(S)  # K = Σ Hᵀ S⁻¹
    dx = K @ r.reshape(-1)  # δ = K (z − ẑ)
    if factors is not None:  # K = Bᵀ L⁻¹ with S = L Lᵀ, B = L⁻¹ H Σ (for gain_times)
        L = np.linalg.cholesky(S)
        factors.update(L=L, B=np.linalg.solve(L, H @ P), compressed=False)
    IKH = np.eye(n) - K @ H
    state.cov[...] = IKH @ P @ IKH.T + K @ R @ K.T  # Joseph form
    _apply_correction(state, dx)
    return dx[:POSE_DIM]


def _init_geometry(model: StereoModel, imu_T_world: np.ndarray, pixels: np.ndarray):
    """Triangulate observations into the world and return (p_lm_in_world, G_pose, G_pix).

    m = (μ⁻¹ imu_T_cam tri(z)), so with T = exp(δ^) μ:
        dm/dδ = −[μ⁻¹ (imu_T_cam p_c)^⊙]_{0:3}              (k, 3, 6)
        dm/dz = R_wi R_ic dtri/dz                             (k, 3, 4)
    """
    cam = model.camera
    p_c = cam.triangulate(pixels)  # (k, 3) in the left camera
    p_i = p_c @ model.imu_T_cam[:3, :3].T + model.imu_T_cam[:3, 3]  # imu_T_cam p_c
    world_T_imu = se3_inverse(imu_T_world)
    p_w = p_i @ world_T_imu[:3, :3].T + world_T_imu[:3, 3]
    G_pose = -(world_T_imu @ se3_odot(p_i))[:, :3, :]
    G_pix = (world_T_imu[:3, :3] @ model.imu_T_cam[:3, :3]) @ cam.triangulation_jacobian(pixels)
    return p_w, G_pose, G_pix


def _init_geometry_inverse_depth(model: StereoModel, imu_T_world: np.ndarray, pixels: np.ndarray):
    """Anchored inverse-depth initialization: (λ (k, 3), G_pose (k, 3, 6), G_pix (k, 3, 4),
    world_T_anchor (k, 4, 4)).

    The anchor is the left camera at the current estimate, ``world_T_anchor = μ⁻¹
    imu_T_cam`` (a constant of the landmark), so λ = (x/z, y/z, 1/z) of the stereo point
    p_c in the left camera — linear in the pixels::

        α = (uL − cu)/fsu,   β = (vL − cv)/fsv,   ρ = (uL − uR)/(fsu b)

    With the true pose T = exp(δ^) μ the point in the anchor frame is
    q_A = cam_T_imu exp(−δ^) imu_T_cam p_c, so dλ/dδ = −dg/dq(p_c) [cam_T_imu (imu_T_cam p_c)^⊙]_{0:3}
    with g(q) = (q_x/q_z, q_y/q_z, 1/q_z).
    """
    cam = model.camera
    pixels = np.asarray(pixels, dtype=np.float64)
    k = pixels.shape[0]
    fsu, fsv, cu, cv, b = cam.fsu, cam.fsv, cam.cu, cam.cv, cam.baseline_m
    lam = np.stack([(pixels[:, 0] - cu) / fsu, (pixels[:, 1] - cv) / fsv,
                    (pixels[:, 0] - pixels[:, 2]) / (fsu * b)], axis=1)
    G_pix = np.zeros((k, 3, 4))
    G_pix[:, 0, 0] = 1.0 / fsu
    G_pix[:, 1, 1] = 1.0 / fsv
    G_pix[:, 2, 0] = 1.0 / (fsu * b)
    G_pix[:, 2, 2] = -1.0 / (fsu * b)
    p_c = cam.triangulate(pixels)
    p_i = p_c @ model.imu_T_cam[:3, :3].T + model.imu_T_cam[:3, 3]  # imu_T_cam p_c
    dq = -(model.cam_T_imu @ se3_odot(p_i))[:, :3, :]  # dq_A/dδ  (k, 3, 6)
    z = p_c[:, 2]
    dg = np.zeros((k, 3, 3))  # dg/dq at p_c
    dg[:, 0, 0] = 1.0 / z
    dg[:, 0, 2] = -p_c[:, 0] / z**2
    dg[:, 1, 1] = 1.0 / z
    dg[:, 1, 2] = -p_c[:, 1] / z**2
    dg[:, 2, 2] = -1.0 / z**2
    world_T_anchor = se3_inverse(imu_T_world) @ model.imu_T_cam
    return lam, dg @ dq, G_pix, np.broadcast_to(world_T_anchor, (k, 4, 4)).copy()


def slam_initialize_landmarks(state: SlamState, model: StereoModel, ids: np.ndarray, pixels: np.ndarray,
                              V: np.ndarray, N_pose: np.ndarray | None = None,
                              velocity_var: float = 0.0) -> np.ndarray:
    """Add landmarks to the joint state from one stereo observation each (guards already applied).

    With G_p = dm/dδ and G_z = dm/dz (see :func:`_init_geometry`)::

        Σ_mm = G_p Σ_pp G_pᵀ + G_z V G_zᵀ,   Σ_m,x = G_p Σ_p,x   for every x in the state

    (new landmarks of the same frame are correlated through the pose: Σ_ab = G_a Σ_pp G_bᵀ).
    Returns their slots.
    """
    k = len(ids)
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    anchors = None
    if state.inverse_depth:
        p_w, G_pose, G_pix, anchors = _init_geometry_inverse_depth(model, state.imu_T_world, pixels)
    else:
        p_w, G_pose, G_pix = _init_geometry(model, state.imu_T_world, pixels)
    d = state.lm_dim
    if d == 6:  # velocity rows: prior N(0, velocity_var I), independent of the rest
        G_pose = np.concatenate([G_pose, np.zeros_like(G_pose)], axis=1)
    Gp = G_pose.reshape(d * k, POSE_DIM)
    n = state.dim
    cross = Gp @ state.cov[:POSE_DIM, :n]  # Σ_m,x = G_p Σ_p,x (x: pose, IMU-error state, landmarks)
    new = Gp @ state.pose_cov @ Gp.T  # G_p Σ_pp G_pᵀ
    pix_cov = G_pix @ V @ np.swapaxes(G_pix, 1, 2)  # G_z V G_zᵀ per landmark
    blocks = new.reshape(k, d, k, d)  # blocks[i, :, j, :]: landmark i's rows, landmark j's columns (a view)
    each = np.arange(k)
    blocks[each, :3, each, :3] += pix_cov  # + G_z V G_zᵀ on each landmark's own block
    if d == 6:
        blocks[each, 3:, each, 3:] += velocity_var * np.eye(3)
    null = G_pose @ N_pose if N_pose is not None else None  # N_m = G_p N_pose (velocity: 0)
    return state.add_landmarks(ids, p_w, cross, new, null, anchors)


def static_consistency_nis(model: StereoModel, imu_T_world_now: np.ndarray, z_now: np.ndarray,
                           imu_T_world_then: np.ndarray, z_then: np.ndarray, V: np.ndarray,
                           Q_rel: np.ndarray) -> np.ndarray:
    """NIS of a landmark's earlier observation under the hypothesis that it is static.

    The landmark is triangulated from ``z_now`` at the current pose and projected at the
    earlier pose; the residual's covariance holds the triangulation (G_z V G_zᵀ), the
    earlier observation's noise V and the relative pose uncertainty ``Q_rel`` (6x6, the
    IMU noise accumulated in between)::

        r = z_then − h(μ_then, m(μ_now, z_now))
        S = H_l G_z V G_zᵀ H_lᵀ + H_p Q_rel H_pᵀ + V

    A point on a moving vehicle or a mismatched track gives a large NIS. Returns (k,)
    NIS values (+inf where the point is behind the earlier camera).
    """
    p_w, _, G_pix = _init_geometry(model, imu_T_world_now, z_now)
    z_hat, Hp, Hl, in_front = model.predict(imu_T_world_then, p_w)
    r = z_then - z_hat
    HG = Hl @ G_pix
    S = HG @ V @ np.swapaxes(HG, 1, 2) + Hp @ Q_rel @ np.swapaxes(Hp, 1, 2) + V
    nis = np.full(len(z_now), np.inf)
    if np.any(in_front):
        nis[in_front] = innovation_nis(r[in_front], S[in_front])
    return nis


# ------------------------------------------------------------------ mapping (known poses)


def mapping_initialize(model: StereoModel, imu_T_world: np.ndarray, pixels: np.ndarray, V: np.ndarray):
    """(p_lm_in_world (k, 3), covariance (k, 3, 3)) of landmarks triangulated at a known pose:
    Σ = G_z V G_zᵀ."""
    p_w, _, G_pix = _init_geometry(model, imu_T_world, pixels)
    return p_w, G_pix @ V @ np.swapaxes(G_pix, 1, 2)


def mapping_update(model: StereoModel, imu_T_world: np.ndarray, mean: np.ndarray, cov: np.ndarray,
                   z: np.ndarray, V: np.ndarray, gate: float):
    """EKF update of independent landmarks at a known pose (batched over k landmarks).

    Given the poses, landmarks are independent and H is block diagonal, so the report's
    3M x 3M update splits exactly into 3x3 blocks::

        S = H Σ Hᵀ + V,  K = Σ Hᵀ S⁻¹,  m ← m + K (z − ẑ),  Σ ← Σ − K S Kᵀ

    Returns (new mean, new cov, accepted mask, nis). Rejected rows are left unchanged.
    """
    k = mean.shape[0]
    if k == 0:
        return mean, cov, np.zeros(0, dtype=bool), np.zeros(0)
    z_hat, _, H, in_front = model.predict(imu_T_world, mean, with_pose_jacobian=False)
    r = z - z_hat
    PHt = cov @ np.swapaxes(H, 1, 2)  # Σ Hᵀ  (k, 3, 4)
    S = H @ PHt + V  # H Σ Hᵀ + V
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
    nis = np.full(k, np.inf)
    if np.any(in_front):
        nis[in_front] = innovation_nis(r[in_front], S[in_front])
    ok = in_front & (nis <= gate)
    new_mean = mean.copy()
    new_cov = cov.copy()
    if np.any(ok):
        K = np.swapaxes(dense.solve(S[ok], np.swapaxes(PHt[ok], 1, 2)), 1, 2)  # K = Σ Hᵀ S⁻¹ (S symmetric)
        new_mean[ok] = mean[ok] + np.einsum("kij,kj->ki", K, r[ok])  # m + K r
        c = cov[ok] - K @ S[ok] @ np.swapaxes(K, 1, 2)  # Σ − K S Kᵀ
        new_cov[ok] = 0.5 * (c + np.swapaxes(c, 1, 2))
    return new_mean, new_cov, ok, nis
