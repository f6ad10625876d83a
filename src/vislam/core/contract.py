"""The stepwise filter contract: what every estimator of vislam offers, and nothing more.

:class:`~vislam.core.filters.LocalizationFilter`, :class:`~vislam.core.filters.MappingFilter`,
:class:`~vislam.core.filters.SlamFilter` and :class:`~vislam.core.smoother.SmootherFilter`
derive from :class:`StepwiseFilter`. The batch driver (:func:`vislam.core.estimators.drive`),
:func:`vislam.core.filters.final_poses`, the consistency runs
(:func:`vislam.core.consistency.filter_nees`) and the noise tuning
(:func:`vislam.core.tune.score_candidate`) use only what is written here.

Construction: ``Filter(calibration, options)`` (``sequence.calibration`` and a
:class:`~vislam.core.options.FilterOptions`); attributes ``mode`` (the mode name of
:data:`vislam.core.options.MODES`), ``calibration``, ``options``.

Input, one frame at a time:

* ``predict(dt_s, linear_velocity, angular_velocity)`` — the IMU sample of the interval
  ending at the next frame (s, m/s, rad/s, IMU frame); ``dt_s`` must be finite, >= 0 and
  at most :data:`~vislam.core.sequence.MAX_TIME_STEP_S` (:func:`checked_dt`), the two
  samples 3 finite numbers each within ±:data:`~vislam.core.sequence.MAX_IMU_SAMPLE`
  (:func:`twist`). Called before every ``update`` but the first.
* ``update(ids, pixels)`` — the stereo observations of the new frame: landmark ids
  (n,), strictly increasing integers (within int64), and pixels (n, 4) ``uL, vL, uR, vR``,
  real, finite and within ±:data:`~vislam.core.sequence.MAX_PIXEL_COORD` (:func:`checked_observations`). Returns the :class:`FrameStats` of the last frame
  finished. The mapping filter also takes the known pose, ``world_T_imu=`` (a finite rigid
  transform; :func:`checked_world_T_imu` is its check).
* ``step(frame)`` — both, from a :class:`~vislam.core.sequence.Frame` (no prediction for
  the first frame). Bad input raises :class:`~vislam.errors.ConfigError`; a numerical
  failure raises :class:`~vislam.errors.EstimationError` naming the frame, and the filter
  refuses further frames (``diagnostics.failed`` says why).

Output convention. The filters' state variable is the report's **imu_T_world** (the
inverse IMU pose, left perturbation). What they hand out for a user is **world_T_imu**
(the IMU pose in the world frame, the first IMU pose being the identity):

* ``world_T_imu`` (4, 4) — the current estimate at the newest frame received (with the
  stalled-track remap a prediction ahead of the frames already updated);
* ``pose_covariance`` (6, 6) or None — covariance of the left perturbation of
  ``imu_T_world``, (v, ω) order, at the last frame updated (a copy);
* ``live_landmark_ids`` (L,), ``live_p_lm_in_world`` (L, 3) — the landmarks being
  estimated; ``landmark_estimates()`` the same in the filter's own chart with their
  covariances (for NEES); ``frozen_map()`` the map so far; ``last_frozen`` the
  ``(ids, p_lm_in_world, rejected)`` frozen in the last step (for live views);
* ``frame_index`` — the newest frame received (−1 before the first), ``last_frame_stats``
  the :class:`FrameStats` of the last frame finished, ``stats`` the run's
  :class:`~vislam.core.results.RunStats` so far.

Finished frames, when they may be taken:

* ``pop_processed()`` — after any ``step``/``update``/``drain``: ``[(t, imu_T_world,
  pose_covariance or None, FrameStats), ...]`` of the frames finished since the last
  call, in order (filter convention, **imu_T_world**). Usually the frame just stepped; a
  filter that runs behind the newest frame returns its frames when they are final. At most
  :attr:`StepwiseFilter.HISTORY` are kept if nobody takes them.
* ``pop_final_poses()`` — the same frames as ``[(t, world_T_imu), ...]`` (output
  convention); use one or the other (the smoother's hands out its final poses instead,
  which leave the window later than ``pop_processed`` hands out its online estimates).
* ``drain()`` — once, after the last frame: finishes the frames a filter still holds (the
  EKF's stalled-track remap; a no-op for the others). Then ``pop_processed()`` again.
* ``finish()`` — last: freezes what is still live and returns the
  :class:`~vislam.core.results.LandmarkMap` (None for localization). The filter is done.
* ``final_trajectory()`` — after ``finish()``: None when the poses of ``pop_processed``
  are final (the EKFs), else ``((T, 4, 4) world_T_imu, (T, 6, 6) covariances or None)``
  that replace them (the smoother).

Everything else a filter can tell is in one :class:`FilterDiagnostics` object,
``diagnostics``: the failure message, the IMU-error estimate per finished frame (taken
and cleared by the batch driver), the innovation observer used by the noise tuning, and
counters and logs of single filters.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from vislam.core.lie import is_rigid_transform, se3_inverse
from vislam.core.results import LandmarkMap, RunStats
from vislam.core.sequence import MAX_IMU_SAMPLE, MAX_PIXEL_COORD, MAX_TIME_STEP_S, first_pixel_row_beyond
from vislam.errors import ConfigError

logger = logging.getLogger(__name__)

__all__ = ["StepwiseFilter", "FilterDiagnostics", "FrameStats", "FRAME_STAT_FIELDS", "FrameStatsCounter",
           "LandmarkEstimates", "checked_dt", "checked_observations", "checked_world_T_imu", "checked_frame", "twist"]

#: (ids, p_lm_in_world, rejected) of no landmark: ``last_frozen`` of a step that froze none.
EMPTY_FROZEN = (np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0, dtype=bool))


@dataclass
class FrameStats:
    """What happened in one frame's update.

    Attributes:
        frame: frame index t.
        observations: observations in the frame.
        used: observations used (updates of live landmarks accepted by the gate, plus
            initializations).
        gated: observations refused by the chi-square gate (or the static check of
            delayed initialization).
        repeated: exact repeats of the previous frame's pixels (skipped by default).
        initialized: landmarks that entered the state (or the mapping tracks started).
        rejected: landmarks rejected in this frame (gate or drift test).
        live_landmarks: landmarks in the state after the frame.
        nis_mean: mean normalized innovation squared ``rᵀS⁻¹r`` of the 4-D stereo
            innovations that passed the gate (expected 4 for a consistent filter before
            gating; NaN when none).
        nis_count: how many innovations ``nis_mean`` averages.
    """

    frame: int = 0
    observations: int = 0
    used: int = 0
    gated: int = 0
    repeated: int = 0
    initialized: int = 0
    rejected: int = 0
    live_landmarks: int = 0
    nis_mean: float = float("nan")
    nis_count: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    def values(self) -> tuple:
        """The fields' values in the order of :data:`FRAME_STAT_FIELDS`."""
        return tuple(self.__dict__[name] for name in FRAME_STAT_FIELDS)


#: Names of the per-frame statistics (the batch result keeps one array of each).
FRAME_STAT_FIELDS = tuple(FrameStats.__dataclass_fields__)


class FrameStatsCounter:
    """Per-frame statistics as differences of the cumulative :class:`RunStats` counters:
    :meth:`begin` before a frame's update, :meth:`end` after it."""

    def __init__(self, stats: RunStats):
        self.stats = stats
        self._start = (0, 0, 0, 0, 0)

    def _now(self):
        s = self.stats
        return (s.observations_used, s.observations_gated, s.observations_repeated, s.landmarks_initialized,
                s.landmarks_rejected)

    def begin(self) -> None:
        self._start = self._now()

    def end(self, frame: int, observations: int, live: int, nis_sum: float, nis_count: int) -> FrameStats:
        used, gated, repeated, initialized, rejected = (b - a for a, b in zip(self._start, self._now()))
        return FrameStats(frame, observations, used, gated, repeated, initialized, rejected, live,
                          nis_sum / nis_count if nis_count else float("nan"), nis_count)


class LandmarkEstimates(NamedTuple):
    """The landmarks being estimated, in the filter's own chart (what a NEES needs).

    ``ids`` (L,); ``mean`` (L, d) and ``cov`` (L, d, d) in the chart of the state
    (d = 3: world point, or inverse depth (α, β, ρ) with ``world_T_anchor`` (L, 4, 4) the
    anchor poses; None for world points); ``cov`` entries NaN where the filter keeps no
    covariance (the smoother's window)."""

    ids: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    world_T_anchor: np.ndarray | None = None


NO_LANDMARKS = LandmarkEstimates(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)))


@dataclass
class FilterDiagnostics:
    """What a filter tells beyond its estimate (``filter.diagnostics``); fields a filter
    does not have keep their defaults.

    Attributes:
        failed: why the filter stopped (the message of its EstimationError), or None.
        imu_bias_log: SLAM with the IMU-error state: ``(frame, b̂ (6,))`` of the frames
            finished, in order (taken and cleared by the batch driver; at most
            :attr:`StepwiseFilter.HISTORY` kept); None without an IMU-error state.
        innovation_hook: SLAM: observer of the innovations before gating (the noise
            tuning's likelihood, :mod:`vislam.core.tune`), called in every update as
            ``hook(r, H_pose, H_lm, blocks, V, in_front, nis)``; None: not called. Set it
            before the first frame.
        observations_of_rejected: SLAM: observations skipped because their landmark was
            rejected earlier (no innovation computed).
        update_counts: SLAM: updates done per frame by the iterated update, one entry per
            frame with a joint update.
        drift_log: smoother: None, or a list (set it to ``[]``) that receives ``(id, n,
            statistic / median, speed, frame)`` per drift test.
        timings: smoother: seconds spent in the window updates and the marginals.
        restarts: smoother: frames after a time gap longer than its window, where it
            started again from the dead-reckoned pose.
    """

    failed: str | None = None
    imu_bias_log: deque | None = None
    innovation_hook: Callable | None = None
    observations_of_rejected: int = 0
    update_counts: list = field(default_factory=list)
    drift_log: list | None = None
    timings: dict = field(default_factory=dict)
    restarts: list = field(default_factory=list)


class StepwiseFilter:
    """Base class of the stepwise filters: the contract of the module docstring.

    Subclasses implement ``predict``, ``update``, ``step``, ``finish``, ``world_T_imu``
    and ``pose_covariance``; this class keeps the finished frames (:meth:`pop_processed`,
    :meth:`pop_final_poses`) and gives the defaults of a filter that holds no frames back
    (:meth:`drain`), whose handed-out poses are final (:meth:`final_trajectory`) and that
    estimates no landmarks.
    """

    #: Mode name (one of :data:`vislam.core.options.MODES`).
    mode = ""
    #: Most finished frames kept for :meth:`pop_processed` if nobody takes them.
    HISTORY = 4096
    #: (ids, p_lm_in_world, rejected) of the landmarks frozen in the last step.
    last_frozen = EMPTY_FROZEN
    live_landmark_ids = np.zeros(0, dtype=np.int64)
    live_p_lm_in_world = np.zeros((0, 3))

    def _init_history(self, bias_log: bool = False) -> None:
        """Start the finished-frame queue and the :class:`FilterDiagnostics` (with an
        IMU-bias log when ``bias_log``)."""
        self._processed = deque(maxlen=self.HISTORY)
        self.diagnostics = FilterDiagnostics(imu_bias_log=deque(maxlen=self.HISTORY) if bias_log else None)

    # --- input (subclasses) -----------------------------------------------------------
    def predict(self, dt_s: float, linear_velocity, angular_velocity) -> None:
        raise NotImplementedError

    def update(self, ids, pixels) -> FrameStats:
        raise NotImplementedError

    def step(self, frame) -> FrameStats:
        raise NotImplementedError

    # --- estimate (subclasses) --------------------------------------------------------
    @property
    def world_T_imu(self) -> np.ndarray:
        raise NotImplementedError

    @property
    def pose_covariance(self) -> np.ndarray | None:
        raise NotImplementedError

    def landmark_estimates(self) -> LandmarkEstimates:
        """The landmarks being estimated in the filter's chart, with covariances."""
        return NO_LANDMARKS

    def frozen_map(self) -> LandmarkMap | None:
        """The map of the landmarks frozen so far (a copy; None without landmarks)."""
        return None

    # --- finished frames --------------------------------------------------------------
    def _record(self, stats: FrameStats) -> None:
        cov = self.pose_covariance  # a copy (or None)
        self._processed.append((stats.frame, np.array(self.imu_T_world), cov, stats))

    def pop_processed(self) -> list:
        """``[(t, imu_T_world (4, 4), pose_covariance (6, 6) or None, FrameStats), ...]`` of
        the frames finished since the last call, in order. Usually the frame just
        stepped; a filter that runs behind the newest frame (the stalled-track remap)
        returns its frames when they are final."""
        out = list(self._processed)
        self._processed.clear()
        return out

    def pop_final_poses(self) -> list:
        """``[(t, world_T_imu (4, 4)), ...]`` of the frames finished since the last call,
        in order: :meth:`pop_processed` in the output convention (the IMU pose in the
        world frame, the inverse of the filter's ``imu_T_world``). It takes the same
        frames as :meth:`pop_processed`: use one or the other. With the stalled-track
        remap these are the frames ``stall_max_delay_frames`` behind the newest one
        (:attr:`world_T_imu` is the newest frame's pose, predicted); after the last frame,
        ``drain()`` finishes the rest (or use :func:`~vislam.core.filters.final_poses`)."""
        return [(t, se3_inverse(imu_T_world)) for t, imu_T_world, _cov, _stats in self.pop_processed()]

    def drain(self) -> None:
        """The recording ended: finish the frames still held (none here)."""
        return None

    def finish(self) -> LandmarkMap | None:
        raise NotImplementedError

    def final_trajectory(self) -> tuple[np.ndarray, np.ndarray | None] | None:
        """None: the poses of :meth:`pop_processed` are final."""
        return None


# ----------------------------------------------------------------------------- input checks


def checked_dt(dt_s) -> float:
    """``predict``'s time step as a float: finite and >= 0 (s), else ConfigError."""
    try:
        dt = float(dt_s)
    except (TypeError, ValueError):
        raise ConfigError(f"predict: dt_s must be a finite time step >= 0 (s), at most {MAX_TIME_STEP_S:g}, "
                          f"got {dt_s!r}") from None
    if not 0 <= dt <= MAX_TIME_STEP_S:  # NaN fails too
        raise ConfigError(f"predict: dt_s must be a finite time step >= 0 (s), at most {MAX_TIME_STEP_S:g}, "
                          f"got {dt_s!r}")
    return dt


def checked_observations(ids, pixels, trusted: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Checked (ids (n,), pixels (n, 4)) of one frame (``trusted``: the arrays of a
    :class:`~vislam.core.sequence.Frame`, already validated by its sequence — only converted)."""
    if trusted and isinstance(ids, np.ndarray) and ids.dtype == np.int64 and isinstance(pixels, np.ndarray) \
            and pixels.dtype == np.float64:
        return ids, pixels
    try:
        ids = np.asarray(ids)
    except (TypeError, ValueError, OverflowError):  # e.g. ragged nested lists
        raise ConfigError(f"update: landmark ids must be integers, (n,); got {ids!r:.80}") from None
    if np.iscomplexobj(pixels):  # np.asarray(..., float64) would drop the imaginary part with a ComplexWarning
        raise ConfigError("update: pixels must be real numbers, (n, 4) [uL, vL, uR, vR]; got complex values")
    try:
        pixels = np.asarray(pixels, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"update: pixels must be numbers, (n, 4) [uL, vL, uR, vR]; got {pixels!r:.80}") from None
    if ids.ndim != 1 or pixels.shape != (ids.shape[0], 4):
        raise ConfigError(f"update: expected landmark ids (n,) and pixels (n, 4), got {ids.shape} and {pixels.shape}")
    if ids.size and not np.issubdtype(ids.dtype, np.integer):
        raise ConfigError(f"update: landmark ids must be integers, got dtype {ids.dtype}")
    if ids.size and ids.dtype.kind == "u" and int(ids.max()) > np.iinfo(np.int64).max:  # would wrap around
        raise ConfigError(f"update: landmark ids must be within the int64 range, got {int(ids.max())}")
    ids = ids.astype(np.int64, copy=False)
    if ids.size > 1 and np.any(np.diff(ids) <= 0):
        raise ConfigError("update: landmark ids must be strictly increasing within a frame")
    row = first_pixel_row_beyond(pixels)
    if row is not None:
        raise ConfigError(f"update: pixels must be finite and within ±{MAX_PIXEL_COORD:g}; landmark {ids[row]} has "
                          f"{pixels[row].tolist()} (leave an unobserved landmark out of the frame)")
    return ids, pixels


def checked_world_T_imu(world_T_imu) -> np.ndarray:
    """A known pose given to ``update`` (the mapping filter's ``world_T_imu=``) as a float
    (4, 4) array: finite and rigid (rotation block, last row ``[0, 0, 0, 1]``) to
    :data:`KNOWN_POSE_RIGID_TOL`, else ConfigError naming what was given (a NaN pose
    reached the camera model as "point coordinates must be finite"; a scaled one was used
    as it was). A rotation block that is rigid only to that tolerance (a pose file printed
    with four decimals) is replaced by the nearest rotation (SVD)."""
    try:
        T = np.asarray(world_T_imu, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"update: world_T_imu must be a 4x4 rigid transform, got {world_T_imu!r:.80}") from None
    if T.shape != (4, 4):
        raise ConfigError(f"update: world_T_imu must be 4x4, got {T.shape}")
    if is_rigid_transform(T, tol=1e-9):
        return T
    if not is_rigid_transform(T, tol=KNOWN_POSE_RIGID_TOL):
        raise ConfigError(f"update: world_T_imu must be a finite 4x4 rigid transform (rotation block, last row "
                          f"[0, 0, 0, 1], to {KNOWN_POSE_RIGID_TOL:g}), got {T.tolist()}")
    U, _, Vt = np.linalg.svd(T[:3, :3])  # det(U Vᵀ) = +1 here: det R is within the tolerance of 1
    out = T.copy()
    out[:3, :3] = U @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


#: How far from rigid a known pose may be (|RᵀR − I|, |det R − 1|, last row): the
#: rounding of a pose file printed with four decimals passes, a scaled or sheared matrix not.
KNOWN_POSE_RIGID_TOL = 1e-3


def checked_frame(frame):
    """``frame`` when it has what ``step`` reads of a :class:`~vislam.core.sequence.Frame`
    (dt_s, the two IMU samples, landmark_ids, pixels), else ConfigError (an
    AttributeError from inside the filter before)."""
    missing = [name for name in ("dt_s", "linear_velocity_mps", "angular_velocity_radps", "landmark_ids", "pixels")
               if not hasattr(frame, name)]
    if missing:
        raise ConfigError(f"step: expected a vislam Frame (sequence.frames(), vislam.iter_frames), got "
                          f"{type(frame).__name__} without {', '.join(missing)}")
    return frame


def twist(linear_velocity, angular_velocity) -> np.ndarray:
    """u = (v, ω), the report's twist order, from ``predict``'s two samples: 3 numbers
    each, finite and within ±:data:`~vislam.core.sequence.MAX_IMU_SAMPLE`, else ConfigError."""
    if isinstance(linear_velocity, np.ndarray) and isinstance(angular_velocity, np.ndarray) \
            and linear_velocity.shape == angular_velocity.shape == (3,):
        u = np.concatenate([linear_velocity, angular_velocity]).astype(np.float64, copy=False)
    else:
        parts = []
        for name, unit, value in (("linear_velocity", "m/s", linear_velocity),
                                  ("angular_velocity", "rad/s", angular_velocity)):
            try:
                a = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                raise ConfigError(f"predict: {name} must be 3 numbers ({unit}), got {value!r}") from None
            if a.size != 3:
                raise ConfigError(f"predict: {name} must be 3 numbers ({unit}), got shape {a.shape}")
            parts.append(a.reshape(3))
        u = np.concatenate(parts)
    if not all(-MAX_IMU_SAMPLE <= x <= MAX_IMU_SAMPLE for x in u.tolist()):  # NaN fails too
        raise ConfigError(f"predict: the IMU sample (v, ω) = {u.tolist()} must be finite and within "
                          f"±{MAX_IMU_SAMPLE:g} (m/s, rad/s)")
    return u
