"""The joint EKF state of visual-inertial SLAM.

Variables (the report's):

* the **inverse IMU pose** ``imu_T_world`` (4x4 mean ``μ``), perturbed on the **left**:
  ``imu_T_world = exp(δ^) μ``, δ = (ρ, φ) in the (v, ω) order of :mod:`vislam.core.lie`;
* the positions ``p_lm_in_world`` (3 each, additive perturbation) of the landmarks
  currently in the state — and, with the landmark motion model (the report's proposed
  fix for moving landmarks), their velocities ``v_lm_in_world`` (3 more each).

Covariance layout: one symmetric matrix Σ of size ``n = 6 + d L`` for ``L`` landmarks of
``d = lm_dim`` (3, or 6 with velocities) dimensions, the pose block first (rows 0:6),
then landmark *slot* ``s`` at rows ``6 + d s : 6 + d (s + 1)`` (position first).
Σ lives in a preallocated buffer with slack (it grows by 25 % when more landmarks are in
view than ever before, and is compacted in place when landmarks leave), so steady-state
frames allocate no new covariance and its size follows the landmarks in view.
"""

from __future__ import annotations

import numpy as np

from vislam.core.bookkeeping import sorted_lookup

__all__ = ["SlamState", "POSE_DIM", "LM_DIM"]

POSE_DIM = 6
LM_DIM = 3


class SlamState:
    """Means, covariance and the index of each landmark block."""

    #: Factor by which the covariance buffer grows when it is full.
    GROWTH = 1.25

    def __init__(self, imu_T_world: np.ndarray, pose_covariance: np.ndarray, capacity_landmarks: int = 64,
                 lm_dim: int = LM_DIM):
        if lm_dim not in (3, 6):
            raise ValueError("lm_dim must be 3 (position) or 6 (position and velocity)")
        self.lm_dim = lm_dim
        self.imu_T_world = np.array(imu_T_world, dtype=np.float64)
        cap = POSE_DIM + lm_dim * max(int(capacity_landmarks), 1)
        self._buffer = np.zeros((cap, cap))
        self._buffer[:POSE_DIM, :POSE_DIM] = pose_covariance
        self.n_landmarks = 0
        #: (L,) dataset id of the landmark in each slot.
        self.landmark_ids = np.zeros(0, dtype=np.int64)
        #: (L, 3) mean position of the landmark in each slot.
        self.p_lm_in_world = np.zeros((0, 3))
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
        return POSE_DIM + self.lm_dim * self.n_landmarks

    @property
    def cov(self) -> np.ndarray:
        """View of the active covariance Σ (dim x dim). Writes go to the state."""
        n = self.dim
        return self._buffer[:n, :n]

    @property
    def pose_cov(self) -> np.ndarray:
        return self._buffer[:POSE_DIM, :POSE_DIM]

    @property
    def capacity(self) -> int:
        return self._buffer.shape[0]

    def landmark_rows(self, slots: np.ndarray) -> np.ndarray:
        """(k, d) covariance row indices of the given slots (position rows first)."""
        return POSE_DIM + self.lm_dim * np.asarray(slots, dtype=np.int64)[:, None] + np.arange(self.lm_dim)

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
                      new_cov: np.ndarray, null_blocks: np.ndarray | None = None) -> np.ndarray:
        """Append k landmarks and return their slots.

        Args:
            ids: (k,) dataset ids (not already in the state).
            p_lm_in_world: (k, 3) means.
            cross_cov: (dk, n) covariance between the new landmarks and the current state.
            new_cov: (dk, dk) covariance among the new landmarks.
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
        self.p_lm_in_world = np.concatenate([self.p_lm_in_world, np.asarray(p_lm_in_world, dtype=np.float64)])
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
        keep_rows = np.concatenate([np.arange(POSE_DIM), self.landmark_rows(np.nonzero(keep_slot)[0]).ravel()])
        m = keep_rows.size
        n = self.dim
        # Compact in place: Σ' = Σ[keep, keep] (the fancy index makes a copy first).
        self._buffer[:m, :m] = self._buffer[:n, :n][np.ix_(keep_rows, keep_rows)]
        self.landmark_ids = self.landmark_ids[keep_slot]
        self.p_lm_in_world = self.p_lm_in_world[keep_slot]
        self.v_lm_in_world = self.v_lm_in_world[keep_slot]
        self.lm_null = self.lm_null[keep_slot]
        self.n_landmarks = int(keep_slot.sum())
        self._reindex()

    def landmark_cov(self, slots: np.ndarray) -> np.ndarray:
        """(k, 3, 3) marginal covariances of the positions of the landmarks in ``slots``."""
        rows = self.landmark_rows(slots)[:, :3]
        return self.cov[rows[:, :, None], rows[:, None, :]]

    def predict_landmarks(self, tau: float, accel_var: float) -> None:
        """Constant-velocity prediction of every landmark (motion model, lm_dim 6)::

            m ← m + τ v,   v ← v + a,   a ~ N(0, σ_a² τ² I)
            Σ ← F Σ Fᵀ + Q,   F = I except F[m_j, v_j] = τ I,   Q[v_j, v_j] = σ_a² τ² I
        """
        if self.lm_dim != 6 or self.n_landmarks == 0:
            return
        self.p_lm_in_world = self.p_lm_in_world + tau * self.v_lm_in_world
        P = self.cov
        rows = self.landmark_rows(np.arange(self.n_landmarks))
        pos, vel = rows[:, :3].ravel(), rows[:, 3:].ravel()
        P[:, pos] += tau * P[:, vel]  # Σ Fᵀ: column m_j += τ column v_j
        P[pos, :] += tau * P[vel, :]  # F (Σ Fᵀ): row m_j += τ row v_j
        P[vel, vel] += accel_var * tau * tau  # + Q

    def is_finite(self) -> bool:
        n = self.dim
        return bool(
            np.all(np.isfinite(self.imu_T_world))
            and np.all(np.isfinite(self.p_lm_in_world))
            and np.all(np.isfinite(self.v_lm_in_world))
            and np.all(np.isfinite(self._buffer[:n, :n]))
        )
