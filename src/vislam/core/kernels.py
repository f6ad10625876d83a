"""The SLAM EKF's per-frame arithmetic, two ways: numpy (the reference) and compiled.

A sparse frame (3–4 observations, a state of a few dozen numbers) is a few hundred numpy
calls of a few microseconds each, most of it call overhead; a dense one adds a few large
BLAS products. :class:`KernelOps` does the same steps in a handful of calls into
``vislam.core._ekf`` (C, built by ``pip install``; its BLAS and LAPACK are scipy's), and
:class:`NumpyOps` calls the numpy functions of :mod:`vislam.core.updaters` and
:mod:`vislam.core.propagation`, which define what each step computes. Both expose one
interface, used by :class:`vislam.core.filters.SlamFilter` and
:func:`vislam.core.updaters.slam_update_iterated`:

* ``predict(state, tau, u, W, eps, velocity_frame, jacobian)`` — the prediction of the
  pose and its covariance blocks (:func:`~vislam.core.propagation.predict_state`);
* ``predict_nis`` — linearization, prior blocks, innovation covariances and NIS
  (:func:`~vislam.core.updaters.slam_predict_nis`); ``residual_model`` — the drift test's
  model (:func:`~vislam.core.updaters.conditional_residual_model`);
* ``linearize`` — residuals and Jacobians, with ``prior`` the iterated update's residual;
* ``update``, ``gain_times``, ``step_size``, ``restore_prior`` — the joint update and what
  the adaptive iterated update asks of its gain;
* ``drift_sums`` — the drift test's per-landmark sums and verdicts.

The two agree to rounding (the compiled kernels sum in another order): tests/test_kernels.py
checks each kernel against its numpy twin on random and near-degenerate inputs, and whole
runs of both on simulated drives. The compiled path covers the default state (pose and
3-parameter landmarks, either chart, with or without the OC projection); the IMU-error
state and the landmark motion model run on numpy. ``VISLAM_KERNELS=0`` in the
environment (read at import) or :func:`use_kernels` selects the numpy path for filters
made afterwards; :func:`kernels_available` tells whether the extension was built (where it
was not, or is older than its source, the first filter that would have used it logs a
warning, :data:`UNAVAILABLE`, and runs on numpy).
"""

from __future__ import annotations

import importlib
import logging
import os
from contextlib import contextmanager

import numpy as np

from vislam.core import dense, propagation, updaters
from vislam.core.state import POSE_DIM

logger = logging.getLogger(__name__)

__all__ = ["NumpyOps", "KernelOps", "kernels_available", "kernels_enabled", "use_kernels", "ops_for"]

#: The interface version of vislam.core._ekf this module calls (its ABI_VERSION).
ABI_VERSION = 1


def _load():
    """(the extension module or None, why it is not used)."""
    try:  # built by pip install (setup.py); optional
        module = importlib.import_module("vislam.core._ekf")
    except ImportError as exc:
        return None, (f"the compiled extension vislam.core._ekf is not built ({exc}; `pip install` needs a C "
                      f"compiler and Python's headers)")
    version = getattr(module, "ABI_VERSION", None)
    if version != ABI_VERSION:
        return None, (f"the compiled extension vislam.core._ekf is older than its source (interface "
                      f"{version}, expected {ABI_VERSION}): run `pip install -e .` again")
    return module, None


_ekf, UNAVAILABLE = _load()
_LAPACK_READY = False
_ENABLED = os.environ.get("VISLAM_KERNELS", "1").strip().lower() not in ("0", "false", "no", "off")
_WARNED = False


def _ready() -> bool:
    """Hand scipy's BLAS/LAPACK to the extension once; False without the extension."""
    global _LAPACK_READY
    if _ekf is None:
        return False
    if not _LAPACK_READY:
        from scipy.linalg import cython_blas, cython_lapack

        blas = cython_blas.__pyx_capi__
        _ekf.set_lapack(blas["dsyrk"], blas["dtrsm"], blas["dgemm"], cython_lapack.__pyx_capi__["dpotrf"],
                        blas["dgemv"])
        _LAPACK_READY = True
    return True


def kernels_available() -> bool:
    """Whether the compiled extension ``vislam.core._ekf`` is installed (and matches
    this source; :data:`UNAVAILABLE` says why not)."""
    return _ekf is not None


def kernels_enabled() -> bool:
    """Whether filters made now take the compiled path (available and not switched off)."""
    return _ENABLED and _ekf is not None


@contextmanager
def use_kernels(enabled: bool):
    """Filters made inside the context take the compiled path (``True``, where it is
    available) or the numpy reference (``False``)."""
    global _ENABLED
    before = _ENABLED
    _ENABLED = bool(enabled)
    try:
        yield
    finally:
        _ENABLED = before


def ops_for(state, reference: bool = False, drift: bool = True):
    """The arithmetic for a filter with this ``state``: :class:`KernelOps` where the
    compiled path covers it and is enabled, else :class:`NumpyOps` (``reference``: the
    filter's plain dense update, numpy only; ``drift``: whether the filter runs the drift
    test, whose model the compiled path forms with the NIS)."""
    covered = not reference and state.lm_dim == 3 and not state.has_bias and state.core_dim == POSE_DIM
    if covered and kernels_enabled() and _ready():
        state.compiled = True  # its compaction and marginals
        return KernelOps(drift)
    if covered and _ENABLED:
        _warn_once()
    return NumpyOps(reference)


def _warn_once() -> None:
    global _WARNED
    if not _WARNED:
        _WARNED = True
        logger.warning("%s; the SLAM filter runs its numpy path, 2-3x slower", UNAVAILABLE)


# ----------------------------------------------------------------------------- numpy


class NumpyOps:
    """The reference: the numpy functions of :mod:`vislam.core.updaters` and
    :mod:`vislam.core.propagation`, step for step."""

    compiled = False

    def __init__(self, reference: bool = False):
        self.update = updaters.slam_update_reference if reference else updaters.slam_update

    @staticmethod
    def predict(state, tau, u, W, eps, velocity_frame, jacobian) -> None:
        """:func:`~vislam.core.propagation.prediction_twist` and
        :func:`~vislam.core.propagation.predict_state` (no IMU-error state)."""
        u, du = propagation.prediction_twist(u, state.imu_T_world, velocity_frame, jacobian)
        propagation.predict_state(state, tau, u, W, eps, du)

    predict_nis = staticmethod(updaters.slam_predict_nis)
    gain_times = staticmethod(updaters.gain_times)
    step_size = staticmethod(updaters._step_size)
    restore_prior = staticmethod(updaters._restore_prior)

    @staticmethod
    def residual_model(blocks, Hp, Hl, V):
        return updaters.conditional_residual_model(blocks, Hp, Hl, V)

    @staticmethod
    def health(state) -> int:
        """0: healthy; 1: a non-finite mean or Σ; 2: a diagonal entry of Σ below −1e-9."""
        if not state.is_finite():
            return 1
        return 2 if (np.diagonal(state.cov) < -1e-9).any() else 0

    @staticmethod
    def linearize(state, model, slots, z, N_pose, prior=None):
        """(r, H_pose, H_lm, in_front); with ``prior`` = (μ₀, b̂₀, m₀, v₀) r is the
        iterated update's residual z − h(x_i) − H_i (x₀ ⊟ x_i)."""
        r, Hp, Hl, in_front = updaters._linearize(state, model, slots, z, N_pose)
        if prior is not None:
            mu0, _b0, lm0, v0 = prior
            r = updaters._relinearized_residual(state, slots, r, Hp, Hl, mu0, lm0, v0)
        return r, Hp, Hl, in_front

    @staticmethod
    def drift_sums(Lt, Ht, r, correction, ok, rows, drift_sum, drift_n, gate):
        """The drift test's sums (see :meth:`vislam.core.filters.SlamFilter._drift_test`):
        returns the (k,) mask of the landmarks that drift."""
        w = dense.solve(Lt, (r - Ht @ correction)[:, :, None])[:, :, 0]
        drift_sum[rows] += np.where(ok[:, None], w, 0.0)
        drift_n[rows] += ok
        stat = np.einsum("ki,ki->k", drift_sum[rows], drift_sum[rows]) / np.maximum(drift_n[rows], 1)
        return ok & (drift_n[rows] >= 2) & (stat > gate)


# ----------------------------------------------------------------------------- compiled


class KernelOps:
    """The same steps through ``vislam.core._ekf`` (one instance per filter: it keeps the
    drift model the last :meth:`predict_nis` formed with the NIS)."""

    compiled = True

    def __init__(self, drift: bool = True):
        self._drift = bool(drift)  # form the drift test's model with the NIS
        self._model_of = None  # the blocks tuple the stored drift model belongs to
        self._model = None

    def __reduce__(self):
        # a pickled filter unpickled where the extension is missing goes on in numpy
        return (_unpickled_ops, (self._drift,))

    # --- prediction -------------------------------------------------------------------
    @staticmethod
    def predict(state, tau, u, W, eps, velocity_frame, jacobian) -> None:
        T_out = np.empty((4, 4))
        _ekf.predict(state.imu_T_world, T_out, state._buffer, state.dim, state.capacity, float(tau),
                     np.ascontiguousarray(u, dtype=np.float64), W, eps, velocity_frame == "level", bool(jacobian),
                     propagation._PERTURB_ROTATIONS)
        state.imu_T_world = T_out

    # --- linearization ----------------------------------------------------------------
    @staticmethod
    def _inputs(state, model, slots, z):
        return (state.imu_T_world, model.cam_T_imu, model.M, state.lm_mean,
                state.world_T_anchor if state.inverse_depth else None,
                np.ascontiguousarray(slots, dtype=np.int64), np.ascontiguousarray(z, dtype=np.float64))

    def linearize(self, state, model, slots, z, N_pose, prior=None):
        k = len(slots)
        r, Hp, Hl = np.empty((k, 4)), np.empty((k, 4, 6)), np.empty((k, 4, 3))
        front = np.empty(k, dtype=bool)
        mu0 = lm0 = None
        if prior is not None:
            mu0, _b0, lm0, _v0 = prior
        status = _ekf.linearize(*self._inputs(state, model, slots, z), N_pose, state.lm_null, mu0, lm0,
                                r, Hp, Hl, front)
        if status:  # a non-finite Jacobian (numpy raises its error) or a rotation beyond 3 rad
            return NumpyOps.linearize(state, model, slots, z, N_pose, prior)
        return r, Hp, Hl, front

    def predict_nis(self, state, model, slots, z, V, N_pose=None):
        r, Hp, Hl, front = self.linearize(state, model, slots, z, N_pose)
        drift = self._drift
        k = len(slots)
        nis = np.empty(k)
        Ppp, Pps, Pss = np.empty((6, 6)), np.empty((k, 6, 3)), np.empty((k, 3, 3))
        Ht, Lt = (np.empty((k, 4, 6)), np.empty((k, 4, 4))) if drift else (None, None)
        status = _ekf.innovation(state._buffer, state.dim, state.capacity, state.core_dim,
                                 np.ascontiguousarray(slots, dtype=np.int64), r, Hp, Hl, front, V, nis, Ppp, Pps, Pss,
                                 bool(drift), Ht, Lt)
        blocks = (Ppp, Pps, Pss)
        self._model_of, self._model = blocks, ((Ht, Lt) if drift and not status else None)
        return r, Hp, Hl, front, nis, blocks

    def residual_model(self, blocks, Hp, Hl, V):
        if blocks is self._model_of and self._model is not None:
            return self._model
        return updaters.conditional_residual_model(blocks, Hp, Hl, V)  # raises its LinAlgError

    @staticmethod
    def health(state) -> int:
        return _ekf.health(state.imu_T_world, state.lm_mean, state._buffer, state.dim, state.capacity)

    # --- update -----------------------------------------------------------------------
    def update(self, state, slots, r, Hp, Hl, V, factors=None):
        k = len(slots)
        if k == 0:
            return np.zeros(POSE_DIM)
        compress, var = updaters.stereo_row_variances(V)  # the rows of compress_stereo
        var = np.ascontiguousarray(var)
        n = state.dim
        m = (3 if compress else 4) * k
        T_out, lm_out = np.empty((4, 4)), np.empty_like(state.lm_mean)
        L, Bt, dx = np.empty((m, m)), np.empty((n, m)), np.empty(n)
        status = _ekf.update(state._buffer, n, state.capacity, state.core_dim, np.ascontiguousarray(slots, dtype=np.int64),
                             np.ascontiguousarray(r), np.ascontiguousarray(Hp), np.ascontiguousarray(Hl), bool(compress),
                             var, state.imu_T_world, T_out, state.lm_mean, lm_out, L, Bt, dx)
        if status:
            raise np.linalg.LinAlgError("Matrix is not positive definite")
        if factors is not None:
            factors.update(L=L, Bt=Bt, compressed=bool(compress), dx=dx)
        state.imu_T_world = T_out
        state.lm_mean = lm_out
        return dx[:POSE_DIM]

    @staticmethod
    def gain_times(factors, dr):
        Bt = factors["Bt"]
        out = np.empty(Bt.shape[0])
        _ekf.gain_times(factors["L"], Bt, Bt.shape[0], np.ascontiguousarray(dr, dtype=np.float64),
                        factors["compressed"], out)
        return out

    @staticmethod
    def step_size(state, slots, dx):
        size = _ekf.step_size(state._buffer, state.dim, state.capacity, state.core_dim,
                              np.ascontiguousarray(slots, dtype=np.int64), np.ascontiguousarray(dx, dtype=np.float64))
        if size < 0.0:  # a singular block: numpy's least-squares path
            return updaters._step_size(state, slots, dx)
        return size

    @staticmethod
    def restore_prior(state, mu0, b0, lm0, v0, P0, factors) -> None:
        updaters._restore_means(state, mu0, b0, lm0, v0)
        if P0 is None:
            Bt = factors["Bt"]
            _ekf.restore(state._buffer, state.dim, state.capacity, Bt, Bt.shape[1])  # Σ₀ = Σ + K S Kᵀ
        else:
            state.cov[...] = P0

    @staticmethod
    def drift_sums(Lt, Ht, r, correction, ok, rows, drift_sum, drift_n, gate):
        moving = np.empty(len(rows), dtype=bool)
        _ekf.drift(Lt, Ht, np.ascontiguousarray(r), np.ascontiguousarray(correction, dtype=np.float64),
                   np.ascontiguousarray(ok), np.ascontiguousarray(rows, dtype=np.int64), drift_sum, drift_n,
                   float(gate), moving)
        return moving


def _unpickled_ops(drift: bool):
    """A filter's :class:`KernelOps` after pickling: itself where the extension is
    available here, else the numpy arithmetic (with the warning)."""
    if kernels_enabled() and _ready():
        return KernelOps(drift)
    _warn_once()
    return NumpyOps()
