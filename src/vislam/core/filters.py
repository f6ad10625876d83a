"""The report's three estimators as stepwise filters: objects that own their state and
bookkeeping and advance one frame at a time, as a robot (or a ROS node) delivers data.

* :class:`LocalizationFilter` — EKF prediction of the IMU pose (the report's III-A);
* :class:`MappingFilter` — EKF update of landmarks with the poses known (III-B);
* :class:`SlamFilter` — the joint EKF over pose and landmarks (III-C).

Each implements the stepwise filter contract (:class:`vislam.core.contract.StepwiseFilter`,
whose module docstring is the written contract): ``predict(dt_s, linear_velocity,
angular_velocity)`` (the IMU sample of the interval ending at the new frame),
``update(ids, pixels)`` (the stereo observations of the new frame) and ``step(frame)``
(both; the first frame has no prediction), ``drain()`` after the last frame, and read
access to the current estimate: ``world_T_imu`` (4x4), ``pose_covariance`` (6x6, left
perturbation of ``imu_T_world`` in (v, ω) order), the landmarks in the state and the
frozen map, the statistics of the last frame (:class:`FrameStats`) and of the run
(:class:`~vislam.core.results.RunStats`). ``finish()`` freezes what is still live and
returns the :class:`~vislam.core.results.LandmarkMap`.

The batch drivers of :mod:`vislam.core.estimators` are loops over these objects, so the
online and offline paths are one code.

SLAM processing order at frame t (:meth:`SlamFilter.update`; each step is a method):

1. :meth:`SlamFilter.predict` with the velocity sample of frame t over [t−1, t];
2. :meth:`SlamFilter._select` — skip exact repeats and observations of rejected landmarks;
3. :meth:`SlamFilter._update_live` — gate, joint EKF update of pose and landmarks in the
   state, innovation drift test, Schmidt probation of young landmarks;
4. :meth:`SlamFilter._reject` — landmarks gated too often in a row leave the state;
5. :meth:`SlamFilter._marginalize_ended` — landmarks not observed leave Σ, frozen into the map;
6. :meth:`SlamFilter._initialize_new` — new landmarks from the stereo model's inverse;
7. :meth:`SlamFilter._check_health` — non-finite state or a lost PSD diagonal raise
   :class:`~vislam.errors.EstimationError` naming the frame.

A failure leaves the filter unusable for further frames; the batch driver stops there and
returns a partial result.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager

import numpy as np

from vislam.core.contract import (
    EMPTY_FROZEN,
    FRAME_STAT_FIELDS,
    FrameStats,
    FrameStatsCounter,
    LandmarkEstimates,
    StepwiseFilter,
)
from vislam.core.contract import checked_dt as _check_dt
from vislam.core.contract import checked_observations as _observations
from vislam.core.contract import checked_frame as _frame
from vislam.core.contract import checked_world_T_imu as _known_pose
from vislam.core.contract import twist as _twist
from vislam.core import kernels
from vislam.core.bookkeeping import IdTable, MapBuilder, RepeatDetector, TrackTable, admitted_count, in_sorted
from vislam.core.lie import se3_adjoint, se3_exp, se3_inverse
from vislam.core.options import FilterOptions
from vislam.core.propagation import (ImuBias, bias_twist_jacobian, body_twist, predict_pose, predict_state,
                                     prediction_twist)
from vislam.core.results import LANDMARK_OK, LANDMARK_REJECTED, LandmarkMap, RunStats
from vislam.core.sequence import Calibration, Frame
from vislam.core.stalls import StallRemapBuffer
from vislam.core.state import SlamState
from vislam.core.updaters import (
    FirstStepTest,
    StereoModel,
    initialization_guard,
    mapping_initialize,
    mapping_update,
    schmidt_update,
    slam_initialize_landmarks,
    slam_predict_nis,
    slam_update_iterated,
    static_consistency_nis,
)
from vislam.errors import ConfigError, EstimationError, GeometryError

logger = logging.getLogger(__name__)

__all__ = ["FrameStats", "FinalPoses", "LocalizationFilter", "MappingFilter", "SlamFilter", "FRAME_STAT_FIELDS",
           "final_poses"]


class _FrozenLog:
    """``last_frozen``: (ids, p_lm_in_world, rejected) of the landmarks frozen into the
    map during the last update (for live views such as the Rerun recording)."""

    _EMPTY = EMPTY_FROZEN

    def _init_frozen_log(self) -> None:
        self.last_frozen = self._EMPTY
        self._frozen_parts: list = []

    def _log_frozen(self, ids: np.ndarray, p: np.ndarray, rejected: bool) -> None:
        self._frozen_parts.append((np.asarray(ids), np.asarray(p).reshape(-1, 3), np.full(np.size(ids), rejected)))

    def _collect_frozen(self) -> None:
        parts = self._frozen_parts
        self.last_frozen = tuple(np.concatenate([p[i] for p in parts]) for i in range(3)) if parts else self._EMPTY
        self._frozen_parts = []


_BLAS_CONTROLLER = None
_BLAS_DEPTH = 0  # how many single_thread_blas contexts are open (the outermost one limits)


@contextmanager
def single_thread_blas():
    """A context that runs BLAS on one thread (``threadpoolctl``). The filter's matrices
    are small (a few hundred rows): more threads only add synchronization (measured 4x
    slower on 2 cores, and 30x on a busy machine), so each update runs single-threaded
    also when a user steps the filter by hand. The controller is made once (entering
    the context then costs ~30 µs instead of ~0.6 ms), and a context opened inside
    another one (every frame of a batch run, see :func:`vislam.core.estimators.run`)
    costs nothing: only the outermost one sets and restores the limit."""
    global _BLAS_CONTROLLER, _BLAS_DEPTH
    if _BLAS_DEPTH:
        _BLAS_DEPTH += 1
        try:
            yield
        finally:
            _BLAS_DEPTH -= 1
        return
    if _BLAS_CONTROLLER is None:
        from threadpoolctl import ThreadpoolController

        _BLAS_CONTROLLER = ThreadpoolController()
    with _BLAS_CONTROLLER.limit(limits=1, user_api="blas"):
        _BLAS_DEPTH += 1
        try:
            yield
        finally:
            _BLAS_DEPTH -= 1


# ============================================================================= localization


class LocalizationFilter(StepwiseFilter):
    """EKF prediction of the IMU pose only (the report's III-A)::

        μ ← exp(−τ û) μ,     Σ ← F Σ Fᵀ + τ² W,     F = exp(−τ ad(u))

    Starts at the world frame (the first IMU pose) with ``options.initial_pose_covariance``.
    Observations are ignored (``update`` only counts the frame).
    """

    mode = "localization"

    def __init__(self, calibration: Calibration | None = None, options: FilterOptions | None = None):
        self.calibration = calibration
        self.options = options or FilterOptions()
        self._W = self.options.W
        self._attitude_jacobian = self.options.level_velocity_jacobian
        self.imu_T_world = np.eye(4)
        self._pose_cov = np.array(self.options.initial_pose_covariance, dtype=np.float64)
        self.stats = RunStats()
        self.frame_index = -1  # the last frame updated
        self.last_frame_stats = FrameStats(frame=-1)
        self._init_history()

    @property
    def world_T_imu(self) -> np.ndarray:
        """(4, 4) current IMU pose in the world frame."""
        return se3_inverse(self.imu_T_world)

    @property
    def pose_covariance(self) -> np.ndarray:
        """(6, 6) covariance of the left perturbation of imu_T_world, (v, ω) order."""
        return self._pose_cov

    def predict(self, dt_s: float, linear_velocity, angular_velocity) -> None:
        """μ ← exp(−τ û) μ,  Σ ← F Σ Fᵀ + τ² W  (the report's eq. for the IMU prediction)."""
        tau = _check_dt(dt_s)
        u, du = prediction_twist(_twist(linear_velocity, angular_velocity), self.imu_T_world,
                                 self.options.velocity_frame, self._attitude_jacobian)
        self.imu_T_world, self._pose_cov, _ = predict_pose(self.imu_T_world, self._pose_cov, tau, u, self._W, du=du)

    def update(self, ids=None, pixels=None) -> FrameStats:
        """Count the frame (IMU localization uses no observations; given ones are checked
        as every filter checks them, then counted)."""
        n = 0 if ids is None and pixels is None else int(_observations(ids, pixels)[0].size)
        self.frame_index += 1
        self.stats.frames += 1
        self.stats.frames_processed += 1
        self.stats.observations_total += n
        self.last_frame_stats = FrameStats(frame=self.frame_index, observations=n)
        self._record(self.last_frame_stats)
        return self.last_frame_stats

    def step(self, frame: Frame) -> FrameStats:
        """Predict over ``frame.dt_s`` (not for the first frame), then count the frame."""
        _frame(frame)
        if self.frame_index >= 0:
            self.predict(frame.dt_s, frame.linear_velocity_mps, frame.angular_velocity_radps)
        return self.update(frame.landmark_ids, frame.pixels)

    def finish(self) -> None:
        """Nothing to freeze (no landmarks)."""
        return None


# ============================================================================= mapping


class MappingFilter(_FrozenLog, StepwiseFilter):
    """Landmark mapping with the poses known (the report's III-B).

    Landmarks are independent given the poses, so each keeps its own 3x3 covariance —
    the exact block-diagonal equivalent of the report's 3M x 3M Σ::

        K = Σ Hᵀ (H Σ Hᵀ + V)⁻¹,   m ← m + K (z − ẑ),   Σ ← (I − K H) Σ

    The pose of each frame is given to :meth:`update` (``world_T_imu``), or else comes
    from IMU dead reckoning (an internal :class:`LocalizationFilter`, fed by
    :meth:`predict`). A landmark's track ends when it is not observed in a frame; its
    estimate then enters the map (seen again, it starts a new track), so memory follows
    the landmarks in view.
    """

    mode = "mapping"

    def __init__(self, calibration: Calibration, options: FilterOptions | None = None):
        self.calibration = calibration
        self.options = options or FilterOptions()
        self._model = StereoModel(calibration.camera, calibration.cam_T_imu)
        self._V = self.options.V
        self._gate = self.options.gate_threshold
        self._odometry = LocalizationFilter(calibration, self.options)
        self._pose_given = None  # world_T_imu given for the current frame, if any
        # one row per track in progress, with its estimate
        self._tracks = TrackTable({"mean": ((3,), np.float64, 0.0), "cov": ((3, 3), np.float64, 0.0)})
        self._builder = MapBuilder()
        self.stats = RunStats()
        self._delta = FrameStatsCounter(self.stats)
        repeated = self.options.repeated_policy("mapping")
        self._repeated = RepeatDetector(repeated != "use", self.stats, calibration.camera)
        self._split = repeated == "split"
        self.frame_index = -1
        self.last_frame_stats = FrameStats(frame=-1)
        self._init_frozen_log()
        self._init_history()

    # --- read access ----------------------------------------------------------------
    @property
    def imu_T_world(self) -> np.ndarray:
        return se3_inverse(self._pose_given) if self._pose_given is not None else self._odometry.imu_T_world

    @property
    def world_T_imu(self) -> np.ndarray:
        """(4, 4) pose of the current frame (given, or dead-reckoned)."""
        return self._pose_given.copy() if self._pose_given is not None else self._odometry.world_T_imu

    @property
    def pose_covariance(self) -> np.ndarray | None:
        """Dead-reckoning covariance, or None when the poses are given."""
        return None if self._pose_given is not None else self._odometry.pose_covariance

    @property
    def live_landmark_ids(self) -> np.ndarray:
        """Ids of the landmarks with a track in progress (rejected ones excluded)."""
        rows = self._tracks.live_rows
        return self._tracks.ids[~self._tracks["rejected"][rows]]

    def landmark_estimates(self) -> LandmarkEstimates:
        """The tracks in progress (rejected ones excluded): world points and their 3x3 covariances."""
        ids = self.live_landmark_ids
        rows = self._tracks.rows(ids)
        return LandmarkEstimates(ids, self._tracks["mean"][rows], self._tracks["cov"][rows])

    @property
    def live_p_lm_in_world(self) -> np.ndarray:
        rows = self._tracks.live_rows
        return self._tracks["mean"][rows[~self._tracks["rejected"][rows]]].copy()

    # --- steps ----------------------------------------------------------------------
    def predict(self, dt_s: float, linear_velocity, angular_velocity) -> None:
        """Dead-reckon the pose: μ ← exp(−τ û) μ (used when no pose is given to update)."""
        self._odometry.predict(dt_s, linear_velocity, angular_velocity)
        self._repeated.set_motion(dt_s, linear_velocity, angular_velocity)

    def step(self, frame: Frame, world_T_imu: np.ndarray | None = None) -> FrameStats:
        """Predict (dead reckoning; not for the first frame), then update with the frame's observations."""
        _frame(frame)
        if self.frame_index >= 0:
            self.predict(frame.dt_s, frame.linear_velocity_mps, frame.angular_velocity_radps)
        return self.update(frame.landmark_ids, frame.pixels, world_T_imu=world_T_imu)

    def update(self, ids, pixels, world_T_imu: np.ndarray | None = None) -> FrameStats:
        """Update the tracks of the landmarks observed in this frame, end the others,
        start new ones. ``world_T_imu``: the known pose of this frame (else dead reckoning)."""
        ids_seen, z = _observations(ids, pixels)
        if world_T_imu is not None:
            world_T_imu = _known_pose(world_T_imu)  # finite and rigid (checked before the frame counts)
        self.frame_index += 1
        t = self.frame_index
        self._delta.begin()
        self._pose_given = world_T_imu
        self._frozen_parts = []
        imu_T_world = self.imu_T_world
        self.stats.frames += 1
        self.stats.observations_total += ids_seen.size
        ids, z, rows, act = self._select(t, ids_seen, z)
        if np.any(act):
            self._update_tracks(t, imu_T_world, ids[act], rows[act], z[act])
        self._end_unseen(ids_seen)
        if np.any(~act):
            self._start_tracks(t, imu_T_world, ids[~act], z[~act])
        self.stats.frames_processed += 1
        self.last_frame_stats = self._delta.end(t, ids_seen.size, int((~self._tracks["rejected"][
            self._tracks.live_rows]).sum()), 0.0, 0)
        self._collect_frozen()
        self._record(self.last_frame_stats)
        return self.last_frame_stats

    def _freeze(self, ids: np.ndarray, status: int) -> None:
        """Enter the tracks of ``ids`` into the map; a rejected track stays (flagged)
        while its landmark is in view, so that its observations keep being ignored."""
        if ids.size:
            rows = self._tracks.rows(ids)
            self._builder.add(ids, self._tracks["mean"][rows], self._tracks["cov"][rows],
                              *self._tracks.entry(ids, rows), status)
            self._log_frozen(ids, self._tracks["mean"][rows], status == LANDMARK_REJECTED)
            if status != LANDMARK_REJECTED:
                self._tracks.remove(ids)

    def _select(self, t: int, ids_seen: np.ndarray, z: np.ndarray):
        """Drop exact repeats ("skip"; "split" ends the track instead) and observations of
        rejected landmarks. Returns (ids, pixels, track rows, has-an-estimate mask)."""
        rep = self._repeated(t, ids_seen, z)
        rows, rejected = self._tracks.lookup(ids_seen)
        act = (rows >= 0) & ~rejected  # has a current estimate
        if self._split and np.any(rep & act):
            self._freeze(ids_seen[rep & act], LANDMARK_OK)  # the track ends; the repeat starts a new one
            rep = np.zeros_like(rep)
            rows, rejected = self._tracks.lookup(ids_seen)
            act = (rows >= 0) & ~rejected
        keep = ~rep & ~rejected  # rejected landmarks stay ignored while in view
        return ids_seen[keep], z[keep], rows[keep], act[keep]

    def _update_tracks(self, t: int, imu_T_world: np.ndarray, ids: np.ndarray, rows: np.ndarray,
                       z: np.ndarray) -> None:
        """Gated EKF update of each landmark (K = Σ Hᵀ S⁻¹, m ← m + K r, Σ ← (I − K H) Σ);
        tracks gated ``max_consecutive_gated`` frames in a row are rejected."""
        tr = self._tracks
        tr["mean"][rows], tr["cov"][rows], ok, _ = mapping_update(
            self._model, imu_T_world, tr["mean"][rows], tr["cov"][rows], z, self._V, self._gate)
        bad = tr.updated(ids, ok, t, self.stats, self.options.max_consecutive_gated, rows=rows)
        self._freeze(bad, LANDMARK_REJECTED)

    def _end_unseen(self, ids_seen: np.ndarray) -> None:
        """Tracks whose landmark is out of view end (a skipped repeat keeps its track alive)."""
        tr = self._tracks
        ended = ~in_sorted(tr.ids, ids_seen) & ~tr["rejected"][tr.live_rows]
        self._freeze(tr.ids[ended], LANDMARK_OK)
        tr.end_unseen_rejections(ids_seen)

    def _start_tracks(self, t: int, imu_T_world: np.ndarray, ids: np.ndarray, z: np.ndarray) -> None:
        """Initialize new landmarks by inverting the stereo model (the guards first)."""
        good = initialization_guard(self.calibration.camera, z, self.options)
        self.stats.observations_not_initialized += int((~good).sum())
        if np.any(good):
            g_ids = ids[good]
            rows = self._tracks.started(g_ids, t)
            self._tracks["mean"][rows], self._tracks["cov"][rows] = mapping_initialize(self._model, imu_T_world,
                                                                                     z[good], self._V)
            self.stats.landmarks_initialized += int(g_ids.size)
            self.stats.observations_used += int(g_ids.size)

    def frozen_map(self) -> LandmarkMap:
        """The map of the tracks ended so far (a copy; the run goes on)."""
        return self._builder.snapshot()

    def finish(self) -> LandmarkMap:
        """Freeze the tracks in progress and return the whole map (the filter is done)."""
        tr = self._tracks
        self._freeze(tr.ids[~tr["rejected"][tr.live_rows]], LANDMARK_OK)
        return self._builder.build()


# ============================================================================= SLAM


class _PendingLandmarks:
    """Delayed SLAM initialization (``options.init_frames``): a landmark waits until it
    has been seen in that many consecutive frames, then its first and latest
    observations must agree with a static point (:func:`static_consistency_nis`).
    Memory: one row per landmark waiting in view (with the pose and the accumulated
    Σ τ² of the frame its window started)."""

    def __init__(self, options: FilterOptions, model: StereoModel, tracks: TrackTable, freeze_rejected):
        self.n = options.init_frames
        self.options = options
        self._model = model
        self._tracks = tracks
        self.freeze_rejected = freeze_rejected
        # start: first frame of the waiting window; last: last frame seen while waiting
        self.waiting = IdTable({"start": ((), np.int64, -1), "last": ((), np.int64, -2),
                                "pixels": ((4,), np.float64, 0.0), "failures": ((), np.int64, 0),
                                "pose": ((4, 4), np.float64, 0.0), "tau2": ((), np.float64, 0.0)}, capacity=16)

    def forget_unseen(self, ids_seen: np.ndarray) -> None:
        """Landmarks out of view stop waiting (seen again, they start over)."""
        if self.n > 1 and len(self.waiting):
            ids = self.waiting.ids
            self.waiting.remove(ids[~in_sorted(ids, ids_seen)])

    def admit(self, ids: np.ndarray, z: np.ndarray, t: int, imu_T_world: np.ndarray, tau2_sum: float,
              stats: RunStats, room: int | None = None):
        """Return the (ids, pixels) to initialize now among candidates observed at t: at
        most ``room`` of them, lowest ids first; the others that passed keep waiting (their
        window goes on) and are counted in ``stats.observations_state_full``.

        ``tau2_sum``: Σ τ² of the prediction steps so far (the IMU noise between two
        frames is (Σ τ²)(t) − (Σ τ²)(t₀) times W)."""
        if self.n <= 1:
            k = admitted_count(ids.size, room, stats)
            return ids[:k], z[:k]
        w = self.waiting
        rows = w.rows(ids)
        w.add(ids[rows < 0])
        rows = w.rows(ids)
        start, last, pixels, failures = w["start"], w["last"], w["pixels"], w["failures"]
        restart = last[rows] != t - 1
        self._open(rows[restart], t, z[restart], imu_T_world, tau2_sum)
        last[rows] = t
        ready = ~restart & (t - start[rows] + 1 >= self.n)
        if not np.any(ready):
            return ids[:0], z[:0]
        r_ids, r_z, r_rows = ids[ready], z[ready], rows[ready]
        t0 = start[r_rows]
        opts = self.options
        nis = np.empty(r_ids.size)
        for f0 in np.unique(t0):  # usually one start frame per batch
            sel = t0 == f0
            first = r_rows[sel][0]
            Q = (tau2_sum - w["tau2"][first]) * opts.W  # Σ τ² W between the two frames
            nis[sel] = static_consistency_nis(self._model, imu_T_world, r_z[sel], w["pose"][first],
                                              pixels[r_rows[sel]], opts.V, Q)
        ok = nis <= opts.gate_threshold
        bad_rows = r_rows[~ok]
        if bad_rows.size:
            failures[bad_rows] += 1
            stats.observations_gated += int(bad_rows.size)
            # try again from the latest observation; a second failure rejects the landmark
            self._open(bad_rows, t, r_z[~ok], imu_T_world, tau2_sum)
            out_sel = ~ok & (failures[r_rows] >= 2)
            if np.any(out_sel):
                out = r_ids[out_sel]
                w.remove(out)
                rows_out = self._tracks.started(out, t)
                self._tracks["rejected"][rows_out] = True
                stats.landmarks_rejected += int(out.size)
                p_w, cov = mapping_initialize(self._model, imu_T_world, r_z[out_sel], opts.V)
                self.freeze_rejected(out, p_w, cov)
        k = admitted_count(int(ok.sum()), room, stats)
        a_ids, a_z = r_ids[ok][:k], r_z[ok][:k]
        w.remove(a_ids)
        return a_ids, a_z

    def _open(self, rows: np.ndarray, t: int, z: np.ndarray, imu_T_world: np.ndarray, tau2_sum: float) -> None:
        """(Re)start the waiting window of ``rows`` at frame t with pixels ``z``."""
        w = self.waiting
        w["start"][rows] = t
        w["pixels"][rows] = z
        w["pose"][rows] = imu_T_world
        w["tau2"][rows] = tau2_sum


class SlamFilter(_FrozenLog, StepwiseFilter):
    """The joint EKF over the IMU pose and the landmarks (the report's III-C).

    State: the inverse IMU pose ``imu_T_world`` (left perturbation) and the positions of
    the landmarks with a live track (see :class:`~vislam.core.state.SlamState`).

    ``reference=True`` uses the plain dense Joseph-form update
    (:func:`~vislam.core.updaters.slam_update_reference`) — slow, for tests.
    """

    mode = "slam"

    def __init__(self, calibration: Calibration, options: FilterOptions | None = None, reference: bool = False):
        self.calibration = calibration
        self.options = opts = options or FilterOptions()
        self._model = StereoModel(calibration.camera, calibration.cam_T_imu)
        self._V, self._W = opts.V, opts.W
        self._attitude_jacobian = opts.level_velocity_jacobian
        self._gate = opts.gate_threshold
        self._drift_gate = opts.drift_threshold
        self._oc = opts.ekf == "oc"
        self._motion = opts.landmark_motion
        # the landmark motion model keeps Cartesian (p, v) landmarks, where iterating
        # converges on the linearized triangulation's error: one update (see update_iterations)
        self._iterations = 1 if self._motion else opts.update_iterations
        self._first_step_test = FirstStepTest()  # whether the iterated update's first-step test pays
        self._velocity_var = opts.landmark_velocity_std_mps**2
        self._accel_var = opts.landmark_acceleration_std_mps2**2
        #: The IMU-error state's model (FilterOptions.imu_bias_sigma_*), or None (off).
        self._imu_bias_model = ImuBias(opts.imu_bias_sigma, opts.imu_bias_time_constant_s) \
            if opts.imu_bias_enabled else None
        self._state = SlamState(np.eye(4), opts.initial_pose_covariance, lm_dim=6 if self._motion else 3,
                               inverse_depth=opts.landmark_parametrization == "inverse_depth" and not self._motion,
                               bias_covariance=None if self._imu_bias_model is None
                               else np.diag(self._imu_bias_model.variance))
        # one row per track in progress; the drift test's per-landmark sums live there too
        self._tracks = TrackTable({"drift_sum": ((4,), np.float64, 0.0), "drift_n": ((), np.float64, 0.0)})
        self._builder = MapBuilder()
        self.stats = RunStats()
        self._delta = FrameStatsCounter(self.stats)
        repeated = opts.repeated_policy("slam")
        self._repeated = RepeatDetector(repeated != "use", self.stats, calibration.camera)
        self._split = repeated == "split"
        self._last_correction = np.zeros(6)  # pose correction of the last update (OC transition)
        self._tau2_sum = 0.0  # Σ τ² of the predictions so far (delayed initialization)
        self._pending = _PendingLandmarks(opts, self._model, self._tracks, self._freeze_rejected_new)
        self._t = -1  # the last frame updated
        self.last_frame_stats = FrameStats(frame=-1)
        self._init_frozen_log()
        # diagnostics: failed, innovation_hook, observations_of_rejected, update_counts and,
        # with the IMU-error state, imu_bias_log (see vislam.core.contract.FilterDiagnostics)
        self._init_history(bias_log=self._imu_bias_model is not None)
        #: The per-frame arithmetic: compiled kernels or the numpy reference (vislam.core.kernels).
        self._ops = kernels.ops_for(self._state, reference, drift=self._drift_gate < np.inf)
        #: The stalled-track remap of :meth:`step` (None with ``stalled_tracks: keep``).
        self._stall_buffer = StallRemapBuffer(opts.stall_max_delay_frames, calibration.camera) \
            if opts.remaps_stalled_tracks else None

    # --- read access ----------------------------------------------------------------
    @property
    def arithmetic(self) -> str:
        """"compiled" when the per-frame arithmetic runs in the compiled kernels
        (:mod:`vislam.core.kernels`), else "numpy"."""
        return "compiled" if self._ops.compiled else "numpy"

    @property
    def frame_index(self) -> int:
        """Index of the newest frame received (−1 before the first)."""
        return self._t + (self._stall_buffer.n_pending if self._stall_buffer is not None else 0)

    @property
    def imu_T_world(self) -> np.ndarray:
        """(4, 4) the filter's pose variable μ (the report's inverse IMU pose) at its
        last updated frame (with the stalled-track remap, ``stall_max_delay_frames``
        behind the newest frame; :attr:`world_T_imu` is predicted up to the newest)."""
        return self._state.imu_T_world

    @property
    def world_T_imu(self) -> np.ndarray:
        """(4, 4) the IMU pose in the world frame at the newest frame: with the
        stalled-track remap, the last updated pose predicted with the IMU samples
        received since (μ ← exp(−τ û) μ per frame)."""
        mean = self._state.imu_T_world
        if self._stall_buffer is not None and self._stall_buffer.n_pending:
            frames = self._stall_buffer.pending_frames()
            bias = self._state.imu_bias if self._imu_bias_model is not None else None
            for frame in frames[1:] if self._t < 0 else frames:  # the first frame has no prediction
                u = _twist(frame.linear_velocity_mps, frame.angular_velocity_radps)
                if bias is not None:
                    u = u - bias  # the IMU-error estimate, predicted: b̂ ← a b̂ per step
                    bias = self._imu_bias_model.decay(frame.dt_s) * bias
                u = body_twist(u, mean, self.options.velocity_frame)
                mean = se3_exp(-frame.dt_s * u) @ mean
        return se3_inverse(mean)

    @property
    def pose_covariance(self) -> np.ndarray:
        """(6, 6) covariance of the left perturbation of imu_T_world, (v, ω) order, at
        the frame of :attr:`imu_T_world` (a copy)."""
        return self._state.pose_cov.copy()

    @property
    def imu_bias(self) -> np.ndarray | None:
        """(6,) estimate b̂ = (b_v, b_ω) of the IMU-error state at the frame of
        :attr:`imu_T_world` (m/s, rad/s; a copy), or None when it is off."""
        return self._state.imu_bias.copy() if self._imu_bias_model is not None else None

    @property
    def imu_bias_covariance(self) -> np.ndarray | None:
        """(6, 6) covariance of :attr:`imu_bias` (a copy), or None when it is off."""
        return self._state.bias_cov.copy() if self._imu_bias_model is not None else None

    @property
    def live_landmark_ids(self) -> np.ndarray:
        """(L,) ids of the landmarks in the state."""
        return self._state.landmark_ids.copy()

    @property
    def live_p_lm_in_world(self) -> np.ndarray:
        """(L, 3) positions of the landmarks in the state (m)."""
        return self._state.p_lm_in_world.copy()

    @property
    def state(self):
        """The :class:`~vislam.core.state.SlamState` (read only; for tests and inspection)."""
        return self._state

    def landmark_estimates(self) -> LandmarkEstimates:
        """The landmarks in the state in its own chart (world points, or inverse depth
        with the anchor poses) and their marginal covariances in that chart."""
        state = self._state
        ids = state.landmark_ids.copy()
        cov = state.param_cov(np.arange(state.n_landmarks))
        return LandmarkEstimates(ids, state.lm_mean, cov, state.world_T_anchor if state.inverse_depth else None)

    @property
    def live_landmark_covariance(self) -> np.ndarray:
        """(L, 3, 3) marginal covariances of the landmarks in the state (m²)."""
        return self._state.landmark_cov(np.arange(self._state.n_landmarks))

    def frozen_map(self) -> LandmarkMap:
        """The map of the landmarks frozen so far (marginalized or rejected; a copy)."""
        return self._builder.snapshot()

    # --- the frame --------------------------------------------------------------------
    def step(self, frame: Frame) -> FrameStats:
        """:meth:`predict` over ``frame.dt_s`` with the frame's IMU sample (not for the
        first frame), then :meth:`update` with its observations.

        With ``stalled_tracks: remap`` the frame first goes through the stall buffer
        (:class:`~vislam.core.stalls.StallRemapBuffer`): the filter then updates the
        frames that are complete, ``stall_max_delay_frames`` behind this one, and
        :attr:`world_T_imu` predicts the pose up to this frame. Returns the statistics
        of the last frame updated."""
        _frame(frame)
        if self._stall_buffer is None:
            return self._step_now(frame)
        buf = self._stall_buffer
        repeats, dropped = buf.repeats, buf.dropped
        ready = buf.push(frame)
        self.stats.observations_repeated += buf.repeats - repeats
        self.stats.observations_lag_dropped += buf.dropped - dropped
        for f in ready:
            self._step_now(f)
        return self.last_frame_stats

    def drain(self) -> None:
        """The recording ended: update the frames still held by the stall buffer."""
        if self._stall_buffer is not None:
            for ready in self._stall_buffer.flush():
                self._step_now(ready)

    def _step_now(self, frame: Frame) -> FrameStats:
        if self._t >= 0:
            self.predict(frame.dt_s, frame.linear_velocity_mps, frame.angular_velocity_radps)
        return self.update(frame.landmark_ids, frame.pixels, _trusted=True)

    def predict(self, dt_s: float, linear_velocity, angular_velocity) -> None:
        """Step 1, the report's prediction::

            μ ← exp(−τ û) μ,   Σ_pp ← F Σ_pp Fᵀ + τ² W,   Σ_pl ← F Σ_pl,   F = exp(−τ ad(u))

        (OC-EKF: F* = F Ad(exp(ε)) with ε the last update's correction; with the landmark
        motion model, m ← m + τ v for every landmark; with the IMU-error state the sample
        is corrected by b̂ and the core block (pose, b) is propagated, see
        :mod:`vislam.core.propagation`.)"""
        self._require_healthy()
        tau = _check_dt(dt_s)
        u = _twist(linear_velocity, angular_velocity)
        self._repeated.set_motion(tau, linear_velocity, angular_velocity)
        bias, D = self._imu_bias_model, None
        if bias is not None:
            u = u - self._state.imu_bias  # u_meas − b̂
            D = bias_twist_jacobian(self._state.imu_T_world, self.options.velocity_frame)
        eps = self._last_correction if self._oc else None
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            if bias is None and not self._motion:
                self._ops.predict(self._state, tau, u, self._W, eps, self.options.velocity_frame,
                                  self._attitude_jacobian)
            else:
                u, du = prediction_twist(u, self._state.imu_T_world, self.options.velocity_frame,
                                         self._attitude_jacobian)
                predict_state(self._state, tau, u, self._W, eps, du, bias, D)
                if self._motion:
                    self._state.predict_landmarks(tau, self._accel_var)
        self._last_correction = np.zeros(6)  # used once: the next correction comes with the next update
        self._tau2_sum += tau * tau

    def update(self, ids, pixels, _trusted: bool = False) -> FrameStats:
        """Steps 2–7 with the stereo observations of a new frame: ``ids`` (n,) strictly
        increasing, ``pixels`` (n, 4) ``[uL, vL, uR, vR]``. Raises EstimationError (and
        the filter stops) on a numerical failure."""
        with single_thread_blas():
            return self._update_frame(ids, pixels, _trusted)

    def _update_frame(self, ids, pixels, _trusted: bool) -> FrameStats:
        self._require_healthy()
        ids_seen, z = _observations(ids, pixels, _trusted)
        self._t += 1
        t = self._t
        self.stats.frames += 1
        self.stats.observations_total += ids_seen.size
        self._delta.begin()
        self._frozen_parts = []
        nis_sum, nis_count = 0.0, 0
        try:
            # overflow/NaN is detected by the health check and reported as an error
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                # unobservable directions of the pose at the prior (OC variant)
                N_pose = -se3_adjoint(self._state.imu_T_world) if self._oc else None
                ids, z, rows = self._select(t, ids_seen, z)
                slots = self._state.slots_of(ids)
                live = slots >= 0
                correction = np.zeros(6)
                if live.any():
                    correction, ok, nis = self._update_live(slots[live], ids[live], rows[live], z[live], N_pose)
                    nis_sum, nis_count = float(nis[ok].sum()), int(ok.sum())
                    self.stats.nis_sum += nis_sum
                    self.stats.nis_count += nis_count
                    self._reject(t, ids[live], rows[live], ok)
                self._marginalize_ended(ids_seen)
                if (~live).any():
                    self._initialize_new(t, ids[~live], z[~live], N_pose)
                if self._oc:
                    self._last_correction = correction
                self.stats.max_state_landmarks = max(self.stats.max_state_landmarks, self._state.n_landmarks)
                self._check_health(t)
        except (EstimationError, GeometryError, np.linalg.LinAlgError) as exc:
            self.diagnostics.failed = str(exc) if isinstance(exc, EstimationError) \
                else f"numerical failure at frame {t}: {exc}"
            raise EstimationError(self.diagnostics.failed, frame=t) from exc
        self.stats.frames_processed += 1
        self.last_frame_stats = self._delta.end(t, ids_seen.size, self._state.n_landmarks, nis_sum, nis_count)
        self._collect_frozen()
        self._record(self.last_frame_stats)
        return self.last_frame_stats

    # --- steps 2-7 ----------------------------------------------------------------------
    def _select(self, t: int, ids_seen: np.ndarray, z: np.ndarray):
        """Step 2: drop exact repeats of the previous frame's pixels ("skip"; "split" ends
        the track and starts a new one) and observations of rejected landmarks.
        Returns (ids, pixels, track rows)."""
        rep = self._repeated(t, ids_seen, z)
        if self._split and rep.any():
            slots_rep = self._state.slots_of(ids_seen[rep])
            self._freeze(slots_rep[slots_rep >= 0], LANDMARK_OK)  # the track ends; the repeat starts a new one
            rep = np.zeros_like(rep)
        track_rows, rejected = self._tracks.lookup(ids_seen)
        usable = ~rep & ~rejected
        self.diagnostics.observations_of_rejected += int(np.count_nonzero(rejected & ~rep))
        return ids_seen[usable], z[usable], track_rows[usable]

    def _update_live(self, slots: np.ndarray, ids: np.ndarray, rows: np.ndarray, z: np.ndarray, N_pose):
        """Step 3, the report's update of pose and landmarks in the state::

            r = z − M π(cam_T_imu μ m),   S = H Σ Hᵀ + V,   gate: rᵀ S⁻¹ r ≤ χ²₄(p)
            K = Σ Hᵀ S⁻¹,   μ ← exp((K r)_pose^) μ,   m ← m + (K r)_lm,   Σ ← Σ − K S Kᵀ

        then the innovation drift test and the Schmidt-Kalman probation of young
        landmarks. Returns (pose correction ε, accepted mask, NIS per observation)."""
        opts, state, tracks, ops = self.options, self._state, self._tracks, self._ops
        V = self._V
        drift = self._drift_gate < np.inf
        r, Hp, Hl, in_front, nis, blocks = ops.predict_nis(state, self._model, slots, z, V, N_pose)
        if self.diagnostics.innovation_hook is not None:
            self.diagnostics.innovation_hook(r, Hp, Hl, blocks, V, in_front, nis)
        ok = in_front & (nis <= self._gate)
        young = tracks["nobs"][rows] <= opts.probation_frames  # init counts as 1
        joint = ok & ~young
        if drift and ok.any():
            Ht, Lt = ops.residual_model(blocks, Hp, Hl, V)
        if self._iterations > 1 and joint.any():
            correction = slam_update_iterated(state, self._model, slots[joint], z[joint], V, N_pose,
                                              self._iterations, ops.update, opts.update_iteration_tolerance,
                                              self.diagnostics.update_counts, (r[joint], Hp[joint], Hl[joint]),
                                              self._first_step_test, ops)
        else:
            correction = ops.update(state, slots[joint], r[joint], Hp[joint], Hl[joint], V)
        if drift and ok.any():
            ok = self._drift_test(rows, ok, r, Ht, Lt, correction)
        probe = ok & young
        if probe.any():
            # slots are unchanged by the joint update; re-linearize at the new pose
            r2, Hp2, Hl2, _, _, _ = slam_predict_nis(state, self._model, slots[probe], z[probe], V, N_pose)
            schmidt_update(state, slots[probe], r2, Hp2, Hl2, V)  # K_lm only: the pose is "considered"
        return correction, ok, nis

    def _drift_test(self, rows, ok, r, Ht, Lt, correction) -> np.ndarray:
        """Innovation drift test: beyond the frame's consensus pose correction ε, a static
        landmark's whitened residuals w = L⁻¹ (r − H̃ ε) are white, so Σ w / √k ~ N(0, I₄);
        a point on a moving vehicle drifts one way. Returns ``ok`` without the movers
        (they are rejected at once by :meth:`_reject`)."""
        tracks = self._tracks
        # drift_sum[row] += w for the accepted ones (drift_n[row] += 1); moving: accepted,
        # seen twice and |drift_sum|² / drift_n beyond the gate
        moving = self._ops.drift_sums(Lt, Ht, r, correction, ok, rows, tracks["drift_sum"], tracks["drift_n"],
                                      self._drift_gate)
        if moving.any():
            self.stats.landmarks_moving += int(moving.sum())
            ok = ok & ~moving
            tracks["consecutive"][rows[moving]] = max(self.options.max_consecutive_gated, 1) - 1
        return ok

    def _reject(self, t: int, ids: np.ndarray, rows: np.ndarray, ok: np.ndarray) -> None:
        """Step 4: a landmark whose observations failed the gate ``max_consecutive_gated``
        frames in a row leaves the state and enters the map flagged as rejected."""
        bad = self._tracks.updated(ids, ok, t, self.stats, self.options.max_consecutive_gated, rows=rows)
        if bad.size:
            self._freeze(self._state.slots_of(bad), LANDMARK_REJECTED)

    def _marginalize_ended(self, ids_seen: np.ndarray) -> None:
        """Step 5: landmarks not observed in this frame leave the state — dropping their
        rows and columns of Σ is the exact marginal of a Gaussian — and their mean and
        marginal covariance are frozen into the map (``keep_all_landmarks`` keeps them)."""
        state = self._state
        if not self.options.keep_all_landmarks and state.n_landmarks:
            # a skipped repeat keeps its track alive
            self._freeze(np.flatnonzero(~in_sorted(state.landmark_ids, ids_seen)), LANDMARK_OK)
        self._tracks.end_unseen_rejections(ids_seen)
        self._pending.forget_unseen(ids_seen)

    def _initialize_new(self, t: int, ids: np.ndarray, z: np.ndarray, N_pose) -> None:
        """Step 6: new landmarks, from the first observation that passes the guards, by
        inverting the stereo model — m = μ⁻¹ cam_T_imu⁻¹ π⁻¹(M⁻¹ z) — with the covariance
        propagated from the pixel noise and the pose (and its correlation with the pose)."""
        good = initialization_guard(self.calibration.camera, z, self.options)
        self.stats.observations_not_initialized += int((~good).sum())
        if good.any():
            # at most max_landmarks_in_state in the state: when it is full, the others wait
            room = max(self.options.max_landmarks_in_state - self._state.n_landmarks, 0)
            g_ids, g_z = self._pending.admit(ids[good], z[good], t, self._state.imu_T_world, self._tau2_sum, self.stats,
                                             room)
            if g_ids.size:
                slam_initialize_landmarks(self._state, self._model, g_ids, g_z, self._V, N_pose, self._velocity_var)
                self._tracks.started(g_ids, t)
                self.stats.landmarks_initialized += int(g_ids.size)
                self.stats.observations_used += int(g_ids.size)

    def _check_health(self, t: int) -> None:
        """Step 7: the state and Σ must stay finite and Σ's diagonal non-negative."""
        status = self._ops.health(self._state)
        if status == 1:
            raise EstimationError(f"non-finite state or covariance at frame {t}", frame=t)
        if status == 2:
            raise EstimationError(f"covariance lost positive semi-definiteness at frame {t}", frame=t)

    def _record(self, stats: FrameStats) -> None:
        super()._record(stats)
        if self._imu_bias_model is not None:
            self.diagnostics.imu_bias_log.append((stats.frame, self._state.imu_bias.copy()))

    def _require_healthy(self) -> None:
        if self.diagnostics.failed is not None:
            raise EstimationError(f"the filter stopped earlier ({self.diagnostics.failed}); start a new one")

    # --- the map ------------------------------------------------------------------------
    def _freeze(self, slots: np.ndarray, status: int) -> None:
        """Move the landmarks in ``slots`` from the state into the map."""
        if slots.size == 0:
            return
        state = self._state
        ids = state.landmark_ids[slots]
        p, cov = state.landmark_marginals(slots)
        self._builder.add(ids, p, cov, *self._tracks.entry(ids), status, state.v_lm_in_world[slots])
        self._log_frozen(ids, p, status == LANDMARK_REJECTED)
        state.remove_slots(slots)
        if status != LANDMARK_REJECTED:  # a rejected track stays (flagged) while in view
            self._tracks.remove(ids)

    def _freeze_rejected_new(self, ids: np.ndarray, p: np.ndarray, cov: np.ndarray) -> None:
        """A landmark rejected by the static check of delayed initialization (never in the state)."""
        self._builder.add(ids, p, cov, *self._tracks.entry(ids), LANDMARK_REJECTED)
        self._log_frozen(ids, p, True)

    def finish(self) -> LandmarkMap:
        """Freeze the landmarks still in the state (after a failure, only those whose mean
        and covariance are finite) and return the whole map. The filter is done."""
        state = self._state
        if state.n_landmarks:
            slots = np.arange(state.n_landmarks)
            if self.diagnostics.failed is not None:
                finite = np.all(np.isfinite(state.p_lm_in_world), axis=1)
                finite &= np.all(np.isfinite(state.landmark_cov(slots)), axis=(1, 2))
                slots = slots[finite]
            self._freeze(slots, LANDMARK_OK)
        self._frozen_parts = []
        return self._builder.build()


# ============================================================================= final poses


class FinalPoses:
    """Iterator over ``(t, world_T_imu)``: each frame's final pose, in frame order, from a
    stepwise filter fed ``frames`` (see :func:`final_poses`). After the last frame it
    drains the filter (frames held by the stalled-track remap), calls ``finish()`` and
    keeps its map in :attr:`landmarks` (None for localization)."""

    def __init__(self, filt, frames):
        self.filter = filt
        self._frames = frames
        #: The map returned by the filter's ``finish()``, once the iteration is over.
        self.landmarks: LandmarkMap | None = None

    def __iter__(self):
        filt = self.filter
        for frame in self._frames:
            filt.step(frame)
            yield from filt.pop_final_poses()
        filt.drain()  # the EKF with the stalled-track remap holds frames
        yield from filt.pop_final_poses()
        self.landmarks = filt.finish()  # the smoother's window is final only now
        yield from filt.pop_final_poses()


def final_poses(filt, frames) -> FinalPoses:
    """Step ``filt`` (a :class:`SlamFilter`, :class:`LocalizationFilter` or
    :class:`~vislam.core.smoother.SmootherFilter`) through ``frames`` and yield
    ``(t, world_T_imu)`` for every frame as soon as its estimate is final — the same poses
    as the batch :func:`vislam.run` returns::

        f = vislam.SlamFilter(seq.calibration, options)
        poses = vislam.final_poses(f, seq.frames())
        for t, world_T_imu in poses:
            ...
        landmark_map = poses.landmarks   # after the loop: the filter's finish()
    """
    return FinalPoses(filt, frames)
