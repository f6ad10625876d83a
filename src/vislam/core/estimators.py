"""The three estimators of the report as batch drivers: short loops over the stepwise
filters of :mod:`vislam.core.filters`, so the online and the offline path are one code.

* :func:`run_localization` — EKF prediction of the IMU pose only (Section III-A);
* :func:`run_mapping` — EKF update of landmarks with the poses known (Section III-B);
* :func:`run_slam` — the joint EKF over pose and landmarks (Section III-C);
* :func:`run` — dispatch on a mode name, with single-threaded BLAS.

Each returns a :class:`vislam.core.results.RunResult`. ``progress`` (optional) is called
with the number of frames done, for a progress bar; ``on_frame`` (optional) with the
filter and the frames it finished in that step — ``[(t, imu_T_world, pose_covariance,
FrameStats), ...]``, usually the frame just stepped, later ones with the stalled-track
remap — e.g. to record a 3D view; the library prints nothing. A
numerical failure of the filter stops the loop: the result is then *partial*, with the
frames done so far and ``error`` saying why.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from vislam.core.corrections import apply_corrections, calibration_used
from vislam.core.contract import FRAME_STAT_FIELDS, StepwiseFilter
from vislam.core.filters import LocalizationFilter, MappingFilter, SlamFilter, single_thread_blas
from vislam.core.lie import se3_inverse
from vislam.core.options import MODES, FilterOptions
from vislam.core.results import RunResult
from vislam.core.sequence import Sequence
from vislam.errors import ConfigError, DatasetError, EstimationError

logger = logging.getLogger(__name__)

__all__ = ["run", "run_localization", "run_mapping", "run_slam", "drive"]

Progress = Callable[[int], None] | None
OnFrame = Callable[[object], None] | None


def run(sequence: Sequence, mode: str, options: FilterOptions | None = None, progress: Progress = None,
        world_T_imu: np.ndarray | None = None, on_frame: OnFrame = None) -> RunResult:
    """Run one of the report's estimators (``mode`` in :data:`vislam.core.options.MODES`).

    ``world_T_imu`` (mapping only): the known poses; by default the localization result.
    The options' data corrections (:func:`vislam.core.corrections.apply_corrections`)
    are applied to ``sequence`` first; a stepwise filter fed by hand gets frames of an
    already corrected sequence (``vislam.apply_corrections(seq, options).frames()``).
    """
    if not isinstance(sequence, Sequence):
        raise ConfigError(f"run: expected a vislam Sequence (vislam.load_sequence(path), or a simulated drive's "
                          f".sequence), got {type(sequence).__name__}")
    if options is not None and not isinstance(options, FilterOptions):
        raise ConfigError(f"run: options must be a FilterOptions (FilterOptions.from_dict for a dict), got "
                          f"{type(options).__name__}")
    options = options or FilterOptions()
    if not isinstance(mode, str) or mode not in MODES:
        raise ConfigError(f"unknown mode {mode!r}; expected one of {', '.join(MODES)}")
    # the options' data corrections (biases, conventions, calibration; see vislam check);
    # a no-op without any, or when the caller already applied them
    sequence = apply_corrections(sequence, options)
    _require_velocities(sequence)
    # The filter's matrices are small (a few hundred rows): multi-threaded BLAS only adds
    # synchronization cost there (measured 4x slower on 2 cores), so use one thread (a
    # controller made now sees every BLAS loaded so far; inside single_thread_blas the
    # filters' own per-frame contexts cost nothing).
    with threadpool_limits(limits=1, user_api="blas"), single_thread_blas():
        if mode == "localization":
            return run_localization(sequence, options, progress, on_frame=on_frame)
        if mode == "mapping":
            return run_mapping(sequence, options, world_T_imu=world_T_imu, progress=progress, on_frame=on_frame)
        if mode == "smoother":
            from vislam.core.smoother import run_smoother  # gtsam: imported only when used

            return run_smoother(sequence, options, progress, on_frame=on_frame)
        return run_slam(sequence, options, progress, on_frame=on_frame)


def _require_velocities(sequence: Sequence) -> None:
    """Every estimator integrates the IMU velocities: a non-finite one (a sequence tracked
    from images without velocities holds NaN) is a DatasetError before any frame."""
    for name, v in (("linear", sequence.linear_velocity_in_imu_mps), ("angular", sequence.angular_velocity_in_imu_radps)):
        bad = ~np.isfinite(v)
        if bad.any():
            k = int(np.argwhere(bad)[0, 0])
            raise DatasetError(f"{sequence.name}: the {name} velocity of frame {k} is {v[k].tolist()}; every "
                               f"estimator needs finite IMU velocities (tracked without velocities? give them: "
                               f"`vislam track SOURCE --velocities FILE.csv`)")


def run_localization(sequence: Sequence, options: FilterOptions | None = None, progress: Progress = None,
                     on_frame: OnFrame = None) -> RunResult:
    """EKF prediction only: μ ← exp(−τ û) μ, Σ ← F Σ Fᵀ + τ² W for every frame."""
    return drive(LocalizationFilter(sequence.calibration, options), sequence, progress, on_frame)


def run_mapping(sequence: Sequence, options: FilterOptions | None = None, world_T_imu: np.ndarray | None = None,
                progress: Progress = None, on_frame: OnFrame = None) -> RunResult:
    """Landmark mapping with known poses ``world_T_imu`` (T, 4, 4) — by default the
    localization (dead-reckoning) trajectory."""
    if world_T_imu is not None:
        world_T_imu = np.asarray(world_T_imu, dtype=np.float64)
        if world_T_imu.shape != (sequence.n_frames, 4, 4):
            raise ConfigError(f"mapping needs one pose per frame: expected ({sequence.n_frames}, 4, 4), "
                              f"got {world_T_imu.shape}")
    return drive(MappingFilter(sequence.calibration, options), sequence, progress, on_frame, poses=world_T_imu)


def run_slam(sequence: Sequence, options: FilterOptions | None = None, progress: Progress = None,
             reference: bool = False, on_frame: OnFrame = None) -> RunResult:
    """The joint EKF over the IMU pose and the landmarks (the report's Section III-C).

    ``reference=True`` uses the plain dense update — slow, for tests of the block form.
    """
    return drive(SlamFilter(sequence.calibration, options, reference=reference), sequence, progress, on_frame)


class _Collector:
    """What :func:`drive` keeps of the frames a filter finishes: poses, covariances,
    per-frame statistics and, with the IMU-error state, the bias estimate per frame."""

    def __init__(self, filt: StepwiseFilter, n_frames: int):
        self.filt = filt
        self.imu_T_world = np.zeros((n_frames, 4, 4))
        self.covs = np.zeros((n_frames, 6, 6))
        self.has_cov = True
        self.frame_seconds = np.zeros(n_frames)
        self.frame_stats = np.zeros((len(FRAME_STAT_FIELDS), n_frames))
        self.bias_log = filt.diagnostics.imu_bias_log  # SLAM with the IMU-error state: b̂ per frame
        self.imu_bias = np.zeros((n_frames, 6)) if self.bias_log is not None else None
        self.done = 0

    def collect(self) -> list:
        """Store the frames the filter has finished (usually the one just stepped)."""
        processed = self.filt.pop_processed()
        for t, pose, cov, fs in processed:
            self.imu_T_world[t] = pose
            if cov is None:
                self.has_cov = False
            else:
                self.covs[t] = cov
            self.frame_stats[:, t] = fs.values()
            self.done = t + 1
        if self.imu_bias is not None:
            for t, b in self.bias_log:
                self.imu_bias[t] = b
            self.bias_log.clear()
        return processed


def drive(filt: StepwiseFilter, sequence: Sequence, progress: Progress = None, on_frame: OnFrame = None,
          poses: np.ndarray | None = None) -> RunResult:
    """Feed every frame of ``sequence`` to the stepwise filter ``filt`` (the contract of
    :mod:`vislam.core.contract`) and collect the result (``poses``: known world_T_imu per
    frame, for a :class:`MappingFilter`)."""
    out = _Collector(filt, sequence.n_frames)
    error = None
    for frame in sequence.frames():
        t = frame.index
        tic = time.perf_counter()
        processed = []
        try:
            if poses is None:
                filt.step(frame)
            else:
                filt.step(frame, world_T_imu=poses[t])
        except EstimationError as exc:
            error = str(exc)
            break
        finally:
            out.frame_seconds[t] = time.perf_counter() - tic
            processed = out.collect()
        if on_frame is not None:
            on_frame(filt, processed)
        if progress:
            progress(t + 1)
    if error is None:  # frames a delayed filter still holds (a no-op for the others)
        tic = time.perf_counter()
        try:
            filt.drain()
        except EstimationError as exc:
            error = str(exc)
        out.frame_seconds[sequence.n_frames - 1] += time.perf_counter() - tic
        processed = out.collect()
        if on_frame is not None and processed:
            on_frame(filt, processed)
    if error is not None:
        logger.info("%s; stopping with a partial result", error)  # reported by the caller (result.error)
    return _result(filt, sequence, out, poses, error)


def _result(filt: StepwiseFilter, sequence: Sequence, out: _Collector, poses: np.ndarray | None,
            error: str | None) -> RunResult:
    """The :class:`RunResult` of a driven filter: ``finish()``, the statistics, and the
    final trajectory where the filter has one (the smoother's replaces the online poses)."""
    done = out.done
    landmarks = filt.finish()
    stats = filt.stats
    stats.frames = sequence.n_frames
    stats.observations_total = sequence.observations.n_observations
    stats.frames_processed = done
    stats.frame_seconds = out.frame_seconds[:done]
    if poses is not None:
        world_T_imu = poses[:done].copy()
    else:
        world_T_imu = se3_inverse(out.imu_T_world[:done]) if done else np.zeros((0, 4, 4))
    result = RunResult(filt.mode, sequence.name, sequence.timestamps_s[:done].copy(), world_T_imu,
                       out.covs[:done] if out.has_cov else None, landmarks, filt.options, stats,
                       partial=error is not None, error=error, calibration=calibration_used(sequence))
    arithmetic = getattr(filt, "arithmetic", None)  # the SLAM EKF: compiled kernels or numpy
    if arithmetic is not None:
        result.extra["arithmetic"] = arithmetic
    final = filt.final_trajectory()
    if final is not None:  # a smoother: its final poses (and marginals) replace the online ones
        result.extra["online_world_T_imu"] = result.world_T_imu
        result.extra["online_pose_covariance"] = result.pose_covariance
        final_poses, final_cov = final
        result.world_T_imu = final_poses[:done]
        result.pose_covariance = final_cov[:done] if final_cov is not None else None
    result.frame_stats = {name: out.frame_stats[i, :done].copy() for i, name in enumerate(FRAME_STAT_FIELDS)}
    if out.imu_bias is not None:
        result.extra["imu_bias"] = out.imu_bias[:done]
    return result
