"""Result objects returned by the estimators (no I/O here; see vislam.tools.outputs)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vislam.core.lie import se3_inverse
from vislam.core.options import FilterOptions

__all__ = ["LandmarkMap", "RunStats", "RunResult", "LANDMARK_OK", "LANDMARK_REJECTED"]

#: Landmark status codes in :attr:`LandmarkMap.status`.
LANDMARK_OK = 0
LANDMARK_REJECTED = 1


@dataclass
class LandmarkMap:
    """Landmarks estimated by mapping or SLAM, one entry per track.

    Attributes:
        ids: (K,) dataset landmark id (column j of the features array).
        track: (K,) 0 for a landmark's first track; a landmark seen again after its
            track ended (a frame without it) starts track 1, 2, … in the order of their
            first frames (never happens with contiguous tracks).
        p_lm_in_world: (K, 3) position mean in the world frame (m).
        covariance: (K, 3, 3) marginal covariance of the position (m²).
        n_observations: (K,) observations used (initialization + accepted updates).
        n_gated: (K,) observations refused by the chi-square gate.
        first_frame, last_frame: (K,) frames of the first and last observation.
        status: (K,) :data:`LANDMARK_OK` or :data:`LANDMARK_REJECTED`.
        v_lm_in_world: (K, 3) velocity (m/s) with the landmark motion model, else zeros.
    """

    ids: np.ndarray
    track: np.ndarray
    p_lm_in_world: np.ndarray
    covariance: np.ndarray
    n_observations: np.ndarray
    n_gated: np.ndarray
    first_frame: np.ndarray
    last_frame: np.ndarray
    status: np.ndarray
    v_lm_in_world: np.ndarray | None = None

    def __post_init__(self):
        if self.v_lm_in_world is None:
            self.v_lm_in_world = np.zeros((len(self.ids), 3))

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    @property
    def rejected(self) -> np.ndarray:
        return self.status == LANDMARK_REJECTED

    @classmethod
    def empty(cls) -> "LandmarkMap":
        z = np.zeros(0, dtype=np.int64)
        return cls(z, z.copy(), np.zeros((0, 3)), np.zeros((0, 3, 3)), z.copy(), z.copy(), z.copy(), z.copy(),
                   np.zeros(0, dtype=np.uint8))


@dataclass
class RunStats:
    """Counts and timings of one run."""

    frames: int = 0
    frames_processed: int = 0
    observations_total: int = 0
    observations_used: int = 0
    observations_gated: int = 0
    observations_repeated: int = 0
    observations_not_initialized: int = 0
    landmarks_initialized: int = 0
    landmarks_rejected: int = 0
    landmarks_moving: int = 0
    max_state_landmarks: int = 0
    #: Per-frame filter time (s), estimation only.
    frame_seconds: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def filter_seconds(self) -> float:
        return float(np.sum(self.frame_seconds))

    def to_dict(self) -> dict[str, Any]:
        fs = self.frame_seconds
        return {
            "frames": self.frames,
            "frames_processed": self.frames_processed,
            "observations_total": self.observations_total,
            "observations_used": self.observations_used,
            "observations_gated": self.observations_gated,
            "observations_repeated": self.observations_repeated,
            "observations_not_initialized": self.observations_not_initialized,
            "landmarks_initialized": self.landmarks_initialized,
            "landmarks_rejected": self.landmarks_rejected,
            "landmarks_moving": self.landmarks_moving,
            "max_state_landmarks": self.max_state_landmarks,
            "filter_seconds": self.filter_seconds,
            "frame_ms_median": float(np.median(fs) * 1e3) if fs.size else None,
            "frame_ms_p95": float(np.percentile(fs, 95) * 1e3) if fs.size else None,
        }


@dataclass
class RunResult:
    """What an estimator returns.

    Attributes:
        mode: "localization", "mapping" or "slam".
        sequence_name: name of the input sequence.
        timestamps_s: (T,) frame timestamps.
        world_T_imu: (T, 4, 4) estimated (or given, for mapping) IMU poses.
        pose_covariance: (T, 6, 6) covariance of the left perturbation of imu_T_world in
            the (v, ω) order (the report's Σ), or None for mapping with given poses.
        landmarks: the map (mapping and SLAM) or None (localization).
        options: the filter options used.
        stats: counts and timings.
        partial: True when the run stopped early (``error`` says why); arrays then hold
            the frames processed so far (``stats.frames_processed``).
        frame_stats: per-frame statistics, one (T,) array per field of
            :class:`vislam.core.filters.FrameStats` (observations, used, gated, repeated,
            initialized, rejected, live_landmarks, nis_mean, nis_count), or None.
    """

    mode: str
    sequence_name: str
    timestamps_s: np.ndarray
    world_T_imu: np.ndarray
    pose_covariance: np.ndarray | None
    landmarks: LandmarkMap | None
    options: FilterOptions
    stats: RunStats
    partial: bool = False
    error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    frame_stats: dict[str, np.ndarray] | None = None

    @property
    def imu_T_world(self) -> np.ndarray:
        return se3_inverse(self.world_T_imu)

    def position_covariance_in_world(self) -> np.ndarray | None:
        """(T, 3, 3) covariance of the IMU position in the world frame (m²).

        With imu_T_world = exp(δ) μ and δ = (ρ, φ), to first order the world position
        error is −R_wi ρ, so its covariance is R_wi Σ_ρρ R_wiᵀ.
        """
        if self.pose_covariance is None:
            return None
        R = self.world_T_imu[:, :3, :3]
        return R @ self.pose_covariance[:, :3, :3] @ np.swapaxes(R, 1, 2)
