"""The joint EKF state of visual-inertial SLAM.

Variables (the report's):

* the **inverse IMU pose** ``imu_T_world`` (4x4 mean ``μ``), perturbed on the **left**:
  ``imu_T_world = exp(δ^) μ``, δ = (ρ, φ) in the (v, ω) order of :mod:`vislam.core.lie`;
* three parameters per landmark currently in the state (``lm_mean``, additive
  perturbation), in one of two charts:

  - **Cartesian** (the report's): the position ``p_lm_in_world`` itself;
  - **anchored inverse depth** (``inverse_depth=True``): λ = (α, β, ρ) = (x/z, y/z, 1/z)
    of the point in its *anchor* camera frame, a constant of the landmark
    (``world_T_anchor``: the left camera pose estimated when it was initialized), so
    ``p_lm_in_world = world_T_anchor · (α, β, 1)/ρ``. A stereo observation is linear
    in λ at initialization (α, β, ρ are pixel coordinates and disparity scaled), so its
    Gaussian is exact there, and points far away (ρ → 0) stay well described;
    :attr:`p_lm_in_world` and :meth:`landmark_cov` convert to Cartesian
    (the covariance to first order);

  and, with the landmark motion model (the report's proposed fix for moving
  landmarks; Cartesian only), their velocities ``v_lm_in_world`` (3 more each).

Optionally (``core_dim`` 12) the **IMU-error state** b = (b_v, b_ω) (``imu_bias``, additive;
see :mod:`vislam.core.propagation` for its Gauss-Markov model): slowly varying errors of
the recorded velocity samples, estimated with the rest.

Covariance layout: one symmetric matrix Σ of size ``n = c + d L`` for ``L`` landmarks of
``d = lm_dim`` (3, or 6 with velocities) dimensions. The *core* block comes first, rows
0:c with ``c = core_dim``: the pose (rows 0:6) and, with the IMU-error state, b (rows
6:12); then landmark *slot* ``s`` at rows ``c + d s : c + d (s + 1)`` (position first).
``POSE_DIM`` (6) is the pose itself; the landmarks start at ``core_dim``.
Σ lives in a preallocated buffer with slack (it grows by 25 % when more landmarks are in
view than ever before, and is compacted in place when landmarks leave), so steady-state
frames allocate no new covariance and its size follows the landmarks in view.
"""

from __future__ import annotations

import numpy as np

from vislam.core.bookkeeping import sorted_lookup

__all__ = ["SlamState", "POSE_DIM", "BIAS_DIM", "LM_DIM", "inverse_depth_to_world", "MIN_INVERSE_DEPTH"]

POSE_DIM = 6
#: Rows of the optional IMU-error state b = (b_v, b_ω).
BIAS_DIM = 6
LM_DIM = 3


#: Smallest inverse depth (1/m) used when converting to Cartesian (ρ ≤ 0 is a point at or
#: beyond infinity; such landmarks fail the gate and are rejected).
MIN_INVERSE_DEPTH = 1e-6


def inverse_depth_to_world(lam: np.ndarray, world_T_anchor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(k, 3) world points and (k, 3, 3) Jacobians dp/dλ of anchored inverse-depth
    parameters λ = (α, β, ρ): ``p = R_wa (α, β, 1)/ρ + t_wa``,
    dp/dα = R_wa e₁/ρ, dp/dβ = R_wa e₂/ρ, dp/dρ = −R_wa (α, β, 1)/ρ²."""
    lam = np.asarray(lam, dtype=np.float64).reshape(-1, 3)
    R = world_T_anchor[:, :3, :3]
    rho = np.maximum(lam[:, 2], MIN_INVERSE_DEPTH)
    bearing = np.stack([lam[:, 0], lam[:, 1], np.ones(lam.shape[0])], axis=1)
    p = np.einsum("kij,kj->ki", R, bearing) / rho[:, None] + world_T_anchor[:, :3, 3]
    J = np.empty((lam.shape[0], 3, 3))
    J[:, :, 0] = R[:, :, 0] / rho[:, None]
    J[:, :, 1] = R[:, :, 1] / rho[:, None]
    J[:, :, 2] = -np.einsum("kij,kj->ki", R, bearing) / (rho * rho)[:, None]
    return p, J


class SlamState:
    """Means, covariance and the index of each landmark block."""

    #: Factor by which the covariance buffer grows when it is full.
    GROWTH = 1.25

    #: Whether :meth:`remove_slots` and :meth:`landmark_marginals` call the compiled
    #: kernels (``vislam.core._ekf``; set by :func:`vislam.core.kernels.ops_for`), else
    #: numpy: the same numbers (the compaction moves entries, the marginals agree to rounding).
    compiled = False

    @property
    def kernels(self):
        """The compiled extension module when :attr:`compiled` and it is installed, else
        None (looked up, not stored: a state stays picklable)."""
        if not self.compiled:
            return None
        from vislam.core import kernels  # (that module builds on this one)

        return kernels._ekf

    def __init__(self, imu_T_world: np.ndarray, pose_covariance: np.ndarray, capacity_landmarks: int = 64,
                 lm_dim: int = LM_DIM, inverse_depth: bool = False, bias_covariance: np.ndarray | None = None):
        if lm_dim not in (3, 6):
            raise ValueError("lm_dim must be 3 (position) or 6 (position and velocity)")
        if inverse_depth and lm_dim != 3:
            raise ValueError("the inverse-depth chart has no landmark velocities (lm_dim 3 only)")
        self.lm_dim = lm_dim
        #: Landmarks in the anchored inverse-depth chart (else Cartesian).
        self.inverse_depth = bool(inverse_depth)
        self.imu_T_world = np.array(imu_T_world, dtype=np.float64)
        #: Rows of the core block (pose, and the IMU-error state when ``bias_covariance``
        #: is given): the landmarks start here.
        self.core_dim = POSE_DIM if bias_covariance is None else POSE_DIM + BIAS_DIM
        #: (6,) mean of the IMU-error state b = (b_v, b_ω) (zero and unused without it).
        self.imu_bias = np.zeros(BIAS_DIM)
        cap = self.core_dim + lm_dim * max(int(capacity_landmarks), 1)
        self._buffer = np.zeros((cap, cap))
        self._buffer[:POSE_DIM, :POSE_DIM] = pose_covariance
        if bias_covariance is not None:
            self._buffer[POSE_DIM:self.core_dim, POSE_DIM:self.core_dim] = bias_covariance  # Σ_bb
        self.n_landmarks = 0
        #: (L,) dataset id of the landmark in each slot.
        self.landmark_ids = np.zeros(0, dtype=np.int64)
        #: (L, 3) mean parameters of the landmark in each slot (the Cartesian position,
        #: or (α, β, ρ) in the inverse-depth chart).
        self.lm_mean = np.zeros((0, 3))
        #: (L, 4, 4) world_T_anchor of each landmark (inverse-depth chart; identity otherwise).
        self.world_T_anchor = np.zeros((0, 4, 4))
        #: (L, 3) mean velocity (zero and unused without the motion model).
        self.v_lm_in_world = np.zeros((0, 3))
        #: (L, d, 6) block of each landmark in the unobservable directions (the global
        #: gauge) of the linearized system, used by the observability-constrained update.
        self.lm_null = np.zeros((0, lm_dim, 6))
        # landmark_ids sorted, and the slot of each: the index behind slots_of()
        self._sorted_ids = np.zeros(0, dtype=np.int64)
        self._sorted_slots = np.zeros(0, dtype=np.int64)

    # --- sizes and views -------------------------------------------------------------
    @property
    def dim(self) -> int:
        return self.core_dim + self.lm_dim * self.n_landmarks

    @property
    def cov(self) -> np.ndarray:
        """View of the active covariance Σ (dim x dim). Writes go to the state."""
        n = self.dim
        return self._buffer[:n, :n]

    @property
    def pose_cov(self) -> np.ndarray:
        return self._buffer[:POSE_DIM, :POSE_DIM]

    @property
    def has_bias(self) -> bool:
        """Whether the state holds the IMU-error block (rows 6:12)."""
        return self.core_dim > POSE_DIM

    @property
    def bias_cov(self) -> np.ndarray | None:
        """View of Σ_bb (6x6), or None without the IMU-error state."""
        return self._buffer[POSE_DIM:self.core_dim, POSE_DIM:self.core_dim] if self.has_bias else None

    @property
    def capacity(self) -> int:
        return self._buffer.shape[0]

    def landmark_rows(self, slots: np.ndarray) -> np.ndarray:
        """(k, d) covariance row indices of the given slots (position rows first)."""
        return self.core_dim + self.lm_dim * np.asarray(slots, dtype=np.int64)[:, None] + np.arange(self.lm_dim)

    def slots_of(self, ids: np.ndarray) -> np.ndarray:
        """Slot of each dataset id, −1 for ids not in the state (a binary search in the
        live ids: no memory per dataset id)."""
        return sorted_lookup(ids, self._sorted_ids, self._sorted_slots)

    # --- structural changes ----------------------------------------------------------
    def _reindex(self) -> None:
        order = np.argsort(self.landmark_ids, kind="stable")
        self._sorted_ids = self.landmark_ids[order]
        self._sorted_slots = order

    def _ensure_capacity(self, dim: int) -> None:
        if dim <= self.capacity:
            return
        new_cap = max(dim, int(np.ceil(self.GROWTH * self.capacity)))
        n = self.dim
        buf = np.zeros((new_cap, new_cap))
        buf[:n, :n] = self._buffer[:n, :n]
        self._buffer = buf

    def add_landmarks(self, ids: np.ndarray, p_lm_in_world: np.ndarray, cross_cov: np.ndarray,
                      new_cov: np.ndarray, null_blocks: np.ndarray | None = None,
                      world_T_anchor: np.ndarray | None = None) -> np.ndarray:
        """Append k landmarks and return their slots.

        Args:
            ids: (k,) dataset ids (not already in the state).
            p_lm_in_world: (k, 3) means (in the state's chart: (α, β, ρ) with inverse depth).
            cross_cov: (dk, n) covariance between the new landmarks and the current state.
            new_cov: (dk, dk) covariance among the new landmarks.
            world_T_anchor: (k, 4, 4) anchor camera poses (inverse-depth chart only).
        """
        k = len(ids)
        if k == 0:
            return np.zeros(0, dtype=np.int64)
        n = self.dim
        m = n + self.lm_dim * k
        self._ensure_capacity(m)
        buf = self._buffer
        buf[n:m, :n] = cross_cov
        buf[:n, n:m] = cross_cov.T
        buf[n:m, n:m] = 0.5 * (new_cov + new_cov.T)
        slots = np.arange(self.n_landmarks, self.n_landmarks + k)
        self.landmark_ids = np.concatenate([self.landmark_ids, np.asarray(ids, dtype=np.int64)])
        self.lm_mean = np.concatenate([self.lm_mean, np.asarray(p_lm_in_world, dtype=np.float64)])
        if world_T_anchor is None:
            if self.inverse_depth:
                raise ValueError("inverse-depth landmarks need their world_T_anchor")
            world_T_anchor = np.broadcast_to(np.eye(4), (k, 4, 4))
        self.world_T_anchor = np.concatenate([self.world_T_anchor,
                                              np.asarray(world_T_anchor, dtype=np.float64).reshape(k, 4, 4)])
        self.v_lm_in_world = np.concatenate([self.v_lm_in_world, np.zeros((k, 3))])
        if null_blocks is None:
            null_blocks = np.zeros((k, self.lm_dim, 6))
        self.lm_null = np.concatenate([self.lm_null,
                                       np.asarray(null_blocks, dtype=np.float64).reshape(k, self.lm_dim, 6)])
        self.n_landmarks += k
        self._reindex()
        return slots

    def remove_slots(self, slots: np.ndarray) -> None:
        """Marginalize the landmarks in ``slots``: drop their rows and columns of Σ.

        For a Gaussian, dropping rows/columns is the exact marginal of the rest. The
        remaining slots keep their order and are renumbered contiguously.
        """
        slots = np.asarray(slots, dtype=np.int64)
        if slots.size == 0:
            return
        keep_slot = np.ones(self.n_landmarks, dtype=bool)
        keep_slot[slots] = False
        keep_rows = np.concatenate([np.arange(self.core_dim), self.landmark_rows(np.nonzero(keep_slot)[0]).ravel()])
        n = self.dim
        compiled = self.kernels
        if compiled is not None:
            compiled.compact(self._buffer, n, self.capacity, keep_rows)  # Σ' = Σ[keep, keep] in place
        else:
            self._compact(keep_rows, n)
        self.landmark_ids = self.landmark_ids[keep_slot]
        self.lm_mean = self.lm_mean[keep_slot]
        self.world_T_anchor = self.world_T_anchor[keep_slot]
        self.v_lm_in_world = self.v_lm_in_world[keep_slot]
        self.lm_null = self.lm_null[keep_slot]
        self.n_landmarks = int(keep_slot.sum())
        self._reindex()

    def _compact(self, keep_rows: np.ndarray, n: int) -> None:
        """Σ' = Σ[keep_rows, keep_rows] in place, with numpy."""
        m = keep_rows.size
        # Compact in place, Σ' = Σ[keep, keep]: the kept rows form a few runs of consecutive
        # rows (a frame removes a few landmarks), each moved up as one block, then the same
        # for the columns — a few block copies instead of an m² fancy-index gather (3x
        # faster at 300 rows). Blocks move towards the origin in increasing order, so a
        # source is never overwritten before it is read (numpy buffers overlapping copies).
        breaks = np.flatnonzero(np.diff(keep_rows) != 1) + 1
        runs = [(s, e, int(keep_rows[s])) for s, e in zip([0, *breaks.tolist()], [*breaks.tolist(), m])]
        buf = self._buffer
        for s, e, src in runs:
            if src != s:
                buf[s:e, :n] = buf[src:src + e - s, :n]
        for s, e, src in runs:
            if src != s:
                buf[:m, s:e] = buf[:m, src:src + e - s]

    @property
    def p_lm_in_world(self) -> np.ndarray:
        """(L, 3) mean positions of the landmarks in the world (m). Cartesian chart: the
        state's own array (writes go to the state); inverse depth: converted (a copy)."""
        if not self.inverse_depth:
            return self.lm_mean
        return inverse_depth_to_world(self.lm_mean, self.world_T_anchor)[0]

    def param_cov(self, slots: np.ndarray) -> np.ndarray:
        """(k, 3, 3) marginal covariances of the state's 3 parameters of each landmark in
        ``slots`` (the chart's own: position, or (α, β, ρ))."""
        rows = self.landmark_rows(slots)[:, :3]
        return self.cov[rows[:, :, None], rows[:, None, :]]

    def landmark_marginals(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((k, 3) positions, (k, 3, 3) marginal covariances, m²) of the landmarks in
        ``slots``: :attr:`p_lm_in_world` of those slots and, with inverse depth,
        J Σ_λ Jᵀ with J = dp/dλ at the mean — one conversion of those slots only."""
        slots = np.asarray(slots, dtype=np.int64)
        compiled = self.kernels
        if compiled is not None and self.lm_dim == 3:
            k = slots.size
            p, cov = np.empty((k, 3)), np.empty((k, 3, 3))
            compiled.marginals(self.lm_mean, self.world_T_anchor if self.inverse_depth else None, self._buffer,
                                   self.dim, self.capacity, self.core_dim, np.ascontiguousarray(slots), p, cov)
            return p, cov
        cov = self.param_cov(slots)
        if not self.inverse_depth:
            return self.lm_mean[slots], cov
        p, J = inverse_depth_to_world(self.lm_mean[slots], self.world_T_anchor[slots])
        return p, J @ cov @ np.swapaxes(J, 1, 2)

    def landmark_cov(self, slots: np.ndarray) -> np.ndarray:
        """(k, 3, 3) marginal covariances of the positions of the landmarks in ``slots``
        (m²; inverse depth: J Σ_λ Jᵀ with J = dp/dλ at the mean)."""
        return self.landmark_marginals(slots)[1]

    def predict_landmarks(self, tau: float, accel_var: float) -> None:
        """Constant-velocity prediction of every landmark (motion model, lm_dim 6)::

            m ← m + τ v,   v ← v + a,   a ~ N(0, σ_a² τ² I)
            Σ ← F Σ Fᵀ + Q,   F = I except F[m_j, v_j] = τ I,   Q[v_j, v_j] = σ_a² τ² I
        """
        if self.lm_dim != 6 or self.n_landmarks == 0:
            return
        self.lm_mean = self.lm_mean + tau * self.v_lm_in_world
        P = self.cov
        rows = self.landmark_rows(np.arange(self.n_landmarks))
        pos, vel = rows[:, :3].ravel(), rows[:, 3:].ravel()
        P[:, pos] += tau * P[:, vel]  # Σ Fᵀ: column m_j += τ column v_j
        P[pos, :] += tau * P[vel, :]  # F (Σ Fᵀ): row m_j += τ row v_j
        P[vel, vel] += accel_var * tau * tau  # + Q

    def is_finite(self) -> bool:
        n = self.dim
        return bool(
            np.isfinite(self.imu_T_world).all()
            and np.isfinite(self.lm_mean).all()
            and np.isfinite(self.imu_bias).all()
            and np.isfinite(self.v_lm_in_world).all()
            and np.isfinite(self._buffer[:n, :n]).all()
        )
