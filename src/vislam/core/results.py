"""Result objects returned by the estimators (no I/O here; see vislam.tools.outputs)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vislam.core.lie import se3_inverse
from vislam.core.options import FilterOptions
from vislam.core.sequence import CAMERA_FRAME_INTERVAL_S, frame_times_not_seconds, true_runs

__all__ = ["CalibrationUsed", "LandmarkMap", "RunStats", "RunResult", "LANDMARK_OK", "LANDMARK_REJECTED",
           "model_fit_warnings", "FIT_LIMITS", "run_warnings", "JOB_LIMITS", "longest_run",
           "frozen_stretch"]

#: Landmark status codes in :attr:`LandmarkMap.status`.
LANDMARK_OK = 0
LANDMARK_REJECTED = 1


@dataclass(frozen=True, eq=False)
class CalibrationUsed:
    """The IMU-camera calibration a run used (see
    :func:`vislam.core.corrections.calibration_used`).

    Attributes:
        cam_T_imu: (4, 4) the transform the filter used, after every correction (maps IMU
            coordinates into the left camera frame).
        recorded_cam_T_imu: (4, 4) the recording's own (the data file's) transform.
        corrections: what turned the one into the other, in order: ``{"field", "value",
            "effect"}`` per FilterOptions field (``cam_T_imu``,
            ``imu_camera_rotation_correction_deg``); empty when the file's is used.
    """

    cam_T_imu: np.ndarray
    recorded_cam_T_imu: np.ndarray
    corrections: tuple = ()

    @property
    def corrected(self) -> bool:
        """Whether the transform used differs from the recording's."""
        return not np.array_equal(self.cam_T_imu, self.recorded_cam_T_imu)

    @property
    def imu_T_cam(self) -> np.ndarray:
        return se3_inverse(self.cam_T_imu)

    def to_dict(self) -> dict[str, Any]:
        """summary.json's ``calibration`` entry."""
        return {"cam_T_imu": np.asarray(self.cam_T_imu).tolist(),
                "cam_T_imu_meaning": "the transform the filter used (maps IMU coordinates into the left camera "
                                     "frame), after the corrections listed",
                "file_cam_T_imu": np.asarray(self.recorded_cam_T_imu).tolist(),
                "corrected": self.corrected,
                "corrections": [dict(c) for c in self.corrections]}


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
    #: Observations of stalled tracks lagging more than ``stall_max_delay_frames`` (dropped).
    observations_lag_dropped: int = 0
    landmarks_initialized: int = 0
    landmarks_rejected: int = 0
    landmarks_moving: int = 0
    max_state_landmarks: int = 0
    #: Observations of new landmarks left out because the SLAM state was full
    #: (``max_landmarks_in_state``), and the frames where that happened.
    observations_state_full: int = 0
    frames_state_full: int = 0
    #: Sum and count of the normalized innovations squared (4-D stereo) that passed the gate.
    nis_sum: float = 0.0
    nis_count: int = 0
    #: Per-frame filter time (s), estimation only.
    frame_seconds: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def filter_seconds(self) -> float:
        return float(np.sum(self.frame_seconds))

    @property
    def nis_mean(self) -> float | None:
        """Mean NIS of the accepted stereo innovations (4 for a consistent filter before
        gating; the 95 % gate cuts it to about 3.6), or None without updates."""
        return self.nis_sum / self.nis_count if self.nis_count else None

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
            "observations_lag_dropped": self.observations_lag_dropped,
            "landmarks_initialized": self.landmarks_initialized,
            "landmarks_rejected": self.landmarks_rejected,
            "landmarks_moving": self.landmarks_moving,
            "max_state_landmarks": self.max_state_landmarks,
            "observations_state_full": self.observations_state_full,
            "frames_state_full": self.frames_state_full,
            "nis_mean": self.nis_mean,
            "nis_count": self.nis_count,
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
        extra: more results of some runs, e.g. ``"imu_bias"``: (T, 6) estimate b̂ =
            (b_v, b_ω) of the SLAM filter's IMU-error state after each frame (m/s,
            rad/s), when it is on (FilterOptions.imu_bias_sigma_*); ``"arithmetic"``
            (SLAM): "compiled" or "numpy", which path of :mod:`vislam.core.kernels` ran.
        calibration: the ``cam_T_imu`` the run used and the corrections that made it
            (:class:`CalibrationUsed`), or None for a result built by hand; every
            consumer converting camera ground truth takes the transform from here.
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
    calibration: CalibrationUsed | None = None

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


#: When a run's own statistics say its noise model does not fit the data (see
#: :func:`model_fit_warnings`). Measured on the shared files: with fitting noise settings
#: the gate refuses 5-21 % of the observations, rejects 14-52 % of the landmarks (the
#: real drives' outliers and moving cars) and the accepted NIS averages 1.2-2.0; with the
#: clean-IMU defaults on the noisy dense files, 51 % are gated and 79 % rejected.
FIT_LIMITS = {"gated_share": 0.30, "rejected_share": 0.60, "nis_mean": 5.4}


def model_fit_warnings(result: "RunResult") -> list[str]:
    """Warnings (one line each) when the run's statistics say the filter's noise model
    does not fit the recording: too many observations gated, too many landmarks
    rejected, or the accepted innovations far larger than the model predicts (a
    consistent filter's NIS averages 4 before the gate, about 3.6 after a 95 % gate)."""
    if result.mode != "slam":
        return []
    s, out = result.stats, []
    tested = s.observations_used + s.observations_gated
    hint = ("the filter's noise model may not fit this recording (IMU noise or bias, or a calibration or "
            "convention mismatch): run `vislam check DATA` and use its suggested options (or `--auto`)")
    if tested >= 50 and s.observations_gated / tested > FIT_LIMITS["gated_share"]:
        out.append(f"{s.observations_gated / tested:.0%} of the tested observations failed the gate "
                   f"({s.observations_gated} of {tested}; expected below {FIT_LIMITS['gated_share']:.0%}); {hint}")
    n = len(result.landmarks) if result.landmarks is not None else 0
    if n >= 20:
        rejected = int(np.count_nonzero(result.landmarks.rejected))
        if rejected / n > FIT_LIMITS["rejected_share"]:
            out.append(f"{rejected / n:.0%} of the landmarks were rejected ({rejected} of {n}; expected below "
                       f"{FIT_LIMITS['rejected_share']:.0%}); {hint}")
    if s.nis_count >= 50 and s.nis_mean > FIT_LIMITS["nis_mean"]:
        out.append(f"the accepted stereo innovations average a NIS of {s.nis_mean:.1f} (a consistent filter: about "
                   f"3.6 after the gate); {hint}")
    return out


#: When a run's own statistics say it did not do its job (:func:`run_warnings`).
#: ``no_update_s``: longest stretch without a used observation; on the shared files with
#: fitting settings SLAM's longest is 3.8 s (sparse 0020; 0 s on the dense files), the
#: smoother's 4.0 s. ``gap_factor``/``gap_min_s``: a frame interval beyond both is a gap
#: the motion model does not cover (it holds one velocity sample over the interval; the
#: shared files' intervals are 0.09-0.11 s). The smoother's own limits on the shared
#: files' statistics: gated 8-24 %, landmarks rejected 31-61 % (61 %: sparse 0027).
#: Mapping on the dead-reckoned poses of the noisy dense files warns, truthfully: 53-61 %
#: of its observations are gated, 84-86 % of its landmarks rejected (sparse: 13-16 %, 34-49 %).
#: ``frozen_share``/``frozen_s``: frames whose observations (at least that share) repeat
#: the previous frame's pixels exactly, for longer than that: the shared files' tracker
#: repeats them in single frames (at most 0.1 s in a row, SLAM and smoother).
JOB_LIMITS = {"no_update_s": 6.0, "gap_factor": 5.0, "gap_min_s": 0.5,
              "smoother_gated_share": 0.5, "smoother_rejected_share": 0.8, "frozen_share": 0.9, "frozen_s": 1.0}

_VISUAL_MODES = ("mapping", "slam", "smoother")


def _frames(t: np.ndarray, indices) -> str:
    return ", ".join(f"{int(k) - 1} -> {int(k)} ({t[k] - t[k - 1]:.3g} s)" for k in indices)


def _timestamp_warnings(result: "RunResult") -> list[str]:
    """A median frame interval outside a camera's (time stamps not in seconds?)."""
    t = np.asarray(result.timestamps_s, dtype=np.float64)
    odd = frame_times_not_seconds(t) if t.size >= 3 else None
    if odd is None or not odd[0] > 0:  # (a NaN interval too)
        return []
    dt, guess = odd
    lo, hi = CAMERA_FRAME_INTERVAL_S
    cause = (f"if the time stamps are in {guess[1]}, run with --auto or with timestamp_scale {guess[0]:g} in a "
             f"--config file (`vislam check DATA` measures it)" if guess else
             "the time stamps are not a frame clock in seconds, nor in ms, µs or ns (`vislam check DATA`)")
    return [f"the frames are {dt:.4g} s apart (median), outside a camera's {lo:g}-{hi:g} s: {cause}; the motion "
            f"model held each velocity sample over {dt:.4g} s"]


def _gap_warnings(result: "RunResult") -> list[str]:
    t = np.asarray(result.timestamps_s, dtype=np.float64)
    if t.size < 2:
        return []
    dt = np.diff(t)
    out = []
    limit = max(JOB_LIMITS["gap_factor"] * float(np.median(dt)), JOB_LIMITS["gap_min_s"])
    window = float(result.options.smoother_window_s) if result.mode == "smoother" else None
    if window is not None:
        over = np.flatnonzero(dt > window) + 1
        if over.size:
            out.append(f"{over.size} time gap(s) longer than the smoother's window ({window:g} s), between frames "
                       f"{_frames(t, over[:3])}{', ...' if over.size > 3 else ''}: everything before a gap left the "
                       f"window, the tracks across it restart as new landmarks, the motion over it is one "
                       f"velocity sample held (dead reckoning), and the smoother starts again from that pose, "
                       f"held fixed as the first one is")
        dt = np.where(dt > window, 0.0, dt)  # named above
    over = np.flatnonzero(dt > limit) + 1
    if over.size:
        out.append(f"{over.size} time gap(s) beyond the motion model (frame intervals above {limit:.3g} s, "
                   f"{JOB_LIMITS['gap_factor']:g}x the median {float(np.median(np.diff(t))):.3g} s), between frames "
                   f"{_frames(t, over[:3])}{', ...' if over.size > 3 else ''}: the filter holds one velocity sample "
                   f"over each; the trajectory there is a guess")
    return out


def longest_run(mask: np.ndarray, t: np.ndarray) -> tuple[float, int, int]:
    """(seconds from the frame before it to its last, first frame, last frame) of the
    longest run of frames (after frame 0) where ``mask`` holds; (0, -1, -1) when none."""
    runs = true_runs(np.r_[False, np.asarray(mask[1:], dtype=bool)])
    if not runs:
        return 0.0, -1, -1
    starts, ends = np.array(runs).T
    seconds = t[ends] - t[starts - 1]
    i = int(np.argmax(seconds))
    return float(seconds[i]), int(starts[i]), int(ends[i])


def frozen_stretch(observations: np.ndarray, repeats: np.ndarray, t: np.ndarray) -> tuple[float, int, int]:
    """:func:`longest_run` of the frames whose observations (``observations`` per frame,
    at least one) repeat the previous frame's pixels (``repeats`` per frame) in at least
    the share ``JOB_LIMITS["frozen_share"]``: frozen images or tracker when it lasts
    longer than ``JOB_LIMITS["frozen_s"]`` (the run's warning and check's finding)."""
    observations, repeats = np.asarray(observations), np.asarray(repeats)
    frozen = (observations > 0) & (repeats >= JOB_LIMITS["frozen_share"] * observations)
    return longest_run(frozen, np.asarray(t, dtype=np.float64))


def run_warnings(result: "RunResult") -> list[str]:
    """Every warning of a run (one line each): :func:`model_fit_warnings` (SLAM) and
    those that say the estimator did not do its job — no observation ever used, a long
    stretch without a visual update, most observations refused (mapping, smoother), new
    landmarks left out of a full SLAM state, a time gap beyond its model (:data:`JOB_LIMITS`)."""
    out = model_fit_warnings(result)
    s = result.stats
    visual = result.mode in _VISUAL_MODES
    refused = (f"{s.observations_gated} gated, {s.observations_not_initialized} not initialized "
               f"(disparity, depth or row guards), {s.observations_repeated} repeated")
    what = "the map is empty" if result.mode == "mapping" else "the trajectory is dead reckoning and the map is empty"
    if visual and s.observations_used == 0 and s.frames_processed > 0:
        out.append(f"no observation was used in {s.frames_processed} frames (of {s.observations_total}: {refused}); "
                   f"{what}: run `vislam check DATA`")
    elif visual and result.frame_stats is not None and "used" in result.frame_stats:
        t = np.asarray(result.timestamps_s, dtype=np.float64)
        seconds, first, last = longest_run(np.asarray(result.frame_stats["used"]) == 0, t)
        if seconds > JOB_LIMITS["no_update_s"]:
            seen = int(np.sum(result.frame_stats["observations"][first:last + 1]))
            cause = (f"the recording has no observations there" if seen == 0 else
                     f"all {seen} observations there were refused")
            out.append(f"no visual update for {seconds:.1f} s (frames {first}-{last}; expected at most "
                       f"{JOB_LIMITS['no_update_s']:g} s): {cause}; the "
                       f"{'map' if result.mode == 'mapping' else 'trajectory'} there is "
                       f"{'from the given poses only' if result.mode == 'mapping' else 'dead reckoning'}")
    if visual and result.frame_stats is not None and "repeated" in result.frame_stats:
        obs = np.asarray(result.frame_stats["observations"])
        repeats = np.asarray(result.frame_stats["repeated"])
        seconds, first, last = frozen_stretch(obs, repeats, result.timestamps_s)
        if seconds > JOB_LIMITS["frozen_s"]:
            out.append(f"frames {first}-{last} ({seconds:.1f} s): {int(repeats[first:last + 1].sum())} of "
                       f"{int(obs[first:last + 1].sum())} observations repeat the previous frame's pixels exactly "
                       f"while the IMU moves (expected single frames, at most {JOB_LIMITS['frozen_s']:g} s): did the "
                       f"images or the tracker freeze? Those frames give no visual update; `vislam check DATA` counts "
                       f"the repeats")
    if result.mode in ("mapping", "smoother") and s.observations_used > 0:
        tested = s.observations_used + s.observations_gated
        limit = FIT_LIMITS["gated_share"] if result.mode == "mapping" else JOB_LIMITS["smoother_gated_share"]
        hint = ("the poses it maps from (dead reckoning by default) drift from what the camera sees" if
                result.mode == "mapping" else "its noise model may not fit this recording: run `vislam check DATA`")
        if tested >= 50 and s.observations_gated / tested > limit:
            out.append(f"{s.observations_gated / tested:.0%} of the tested observations were refused "
                       f"({s.observations_gated} of {tested}; expected below {limit:.0%}); {hint}")
        n = len(result.landmarks) if result.landmarks is not None else 0
        limit = FIT_LIMITS["rejected_share"] if result.mode == "mapping" else JOB_LIMITS["smoother_rejected_share"]
        if n >= 20:
            rejected = int(np.count_nonzero(result.landmarks.rejected))
            if rejected / n > limit:
                out.append(f"{rejected / n:.0%} of the landmarks were rejected ({rejected} of {n}; expected below "
                           f"{limit:.0%}); {hint}")
    if s.observations_state_full:
        holder = "the smoother's window" if result.mode == "smoother" else "the SLAM state"
        out.append(f"{holder} was full (max_landmarks_in_state {result.options.max_landmarks_in_state}) in "
                   f"{s.frames_state_full} of {s.frames_processed} frames: {s.observations_state_full} observations "
                   f"of new landmarks waited and were not used; raise max_landmarks_in_state in an options file "
                   f"(--config; a frame's update costs the cube of its landmarks) or give fewer features per frame")
    out.extend(_timestamp_warnings(result))
    out.extend(_gap_warnings(result))
    return out
