"""Evaluation of an estimated trajectory against ground truth.

* :func:`load_ground_truth` reads a KITTI or TUM ground-truth file and, for left-camera
  ground truth (``frame="cam"``, what ``groundtruth/*.txt`` of the shared data holds),
  converts it to the IMU: ``world_T_imu(i) = imu_T_cam @ world_T_cam(i) @ cam_T_imu``.
* :func:`resolve_ground_truth_frame` decides the ground truth's body frame and where
  ``cam_T_imu`` comes from. The default, ``"auto"``, follows the file format's
  convention: KITTI ground truth holds left-camera poses (``"cam"``), TUM ground truth
  IMU poses (``"imu"``; TUM has no body convention, vislam's TUM files hold the IMU).
  ``cam_T_imu`` is the one the filter used, recorded as ``calibration.cam_T_imu`` in the
  ``summary.json`` of the run folder the estimate sits in (:func:`cam_T_imu_from_run_summary`;
  with a dataset given, when that summary belongs to the same data file), else the
  dataset's, else the summary's ``dataset.cam_T_imu`` (the data file's, of summaries
  written before the calibration was recorded); with none, a camera-frame ground truth
  is refused with one line (never silently read as IMU poses). Which one was used is
  said in the result (``cam_T_imu_source``).
* :func:`load_estimate` reads an estimate, KITTI or TUM (detected from the number of
  values per line).
* :func:`associate` pairs estimate and ground-truth poses: KITTI ground truth by frame
  index (both truncated to the shorter length), TUM ground truth by timestamp (evo's
  ``sync.associate_trajectories``).
* :func:`evaluate` computes, with evo, the APE (translation part) with SE(3) Umeyama
  alignment and without alignment, the RPE (translation in m and rotation in deg) over 1
  frame and over 100 m of ground-truth path, and the KITTI odometry metric of
  :mod:`vislam.core.metrics` — of the IMU poses. Where the ground truth holds camera
  poses it also evaluates the **camera frame** (``EvaluationResult.camera``, keys
  ``cam_*``): the estimate turned into left-camera poses with the calibration used,
  ``world_T_cam = world_T_imu @ imu_T_cam``, against the ground truth as it is (SE(3)
  Umeyama alignment, KITTI segments). The camera-frame numbers do not depend on
  ``cam_T_imu`` entering the ground truth; the IMU-frame numbers do (a wrong lever arm
  turns every rotation error of the camera into a position error of the IMU).
* :func:`plot_error_over_distance`, :func:`write_metrics_json` and :func:`format_table`
  present an :class:`EvaluationResult`.

Every user mistake (missing or malformed file, ground truth that cannot be matched,
missing calibration) raises a :class:`~vislam.errors.VislamError` subclass with a
one-line message.
"""

from __future__ import annotations

import copy
import json
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vislam.core.lie import is_rigid_transform, se3_inverse, so3_log
from vislam.core.metrics import KittiOdometryErrors, kitti_odometry_errors, trajectory_distances
from vislam.errors import ConfigError, GroundTruthError, OutputError
from vislam.tools.atomic import atomic_path, write_text_atomic
from vislam.tools.jsonio import dumps
from vislam.tools.trajectory_io import (
    DEFAULT_MAX_DIFF_S,
    GT_FORMATS,
    GT_FORMAT_CHOICES,
    GT_FRAME_CHOICES,
    GT_FRAMES,
    TrajectoryFile,
    camera_to_imu_trajectory,
    default_gt_frame,
    imu_to_camera_trajectory,
    read_trajectory,
    resolve_gt_format,
)

__all__ = [
    "GT_FORMATS",
    "GT_FORMAT_CHOICES",
    "GT_FRAMES",
    "GT_FRAME_CHOICES",
    "DEFAULT_MAX_DIFF_S",
    "RUN_SUMMARY_FILE",
    "RPE_DISTANCE_M",
    "ErrorStats",
    "Association",
    "EvaluationResult",
    "ErrorFigureData",
    "camera_to_imu_trajectory",
    "imu_to_camera_trajectory",
    "GroundTruthFrame",
    "GroundTruthTrajectory",
    "RunCalibration",
    "default_gt_frame",
    "cam_T_imu_from_run_summary",
    "resolve_ground_truth_frame",
    "load_ground_truth",
    "load_estimate",
    "associate",
    "evaluate",
    "evaluate_associated",
    "evaluate_files",
    "METRICS_FRAMES",
    "plot_error_over_distance",
    "write_metrics_json",
    "format_table",
]



class _LazyModule:
    """A module imported on first attribute access (evo costs ~0.5 s of imports, which
    a run without ground truth does not need)."""

    def __init__(self, name: str):
        self._name = name

    def __getattr__(self, attr: str):
        import importlib

        return getattr(importlib.import_module(self._name), attr)


evo_metrics = _LazyModule("evo.core.metrics")
evo_sync = _LazyModule("evo.core.sync")
logger = logging.getLogger(__name__)

#: Ground-truth path length (m) between the poses of the distance-based RPE.
RPE_DISTANCE_M = 100.0

#: The estimate's path length over the compared frames, as a multiple of the ground truth's,
#: outside these bounds is named in the evaluation's notes: a ground truth of another drive,
#: speeds in the wrong unit, or a run that diverged. (The filters' estimates of the shared
#: drives are within 2 % of the ground truth's length, dead reckoning through their noise too.)
PATH_LENGTH_RATIO_BOUNDS = (0.8, 1.25)
#: ... checked on ground-truth paths at least this long (m): below it a vehicle standing still
#: with noisy velocities makes any ratio.
PATH_LENGTH_CHECK_MIN_M = 20.0
#: Fewer compared pose pairs than this share of the estimate's poses is named in the notes.
MIN_COVERAGE = 0.9
#: The file of a run folder (``vislam run``, ``vislam demo``) that records the
#: ``cam_T_imu`` the filter used under ``calibration.cam_T_imu`` (and the data file's under
#: ``dataset.cam_T_imu``).
RUN_SUMMARY_FILE = "summary.json"
#: Prefix of the camera-frame metrics in :meth:`EvaluationResult.to_dict`.
CAMERA_PREFIX = "cam_"


@dataclass(frozen=True, eq=False)
class GroundTruthTrajectory(TrajectoryFile):
    """A ground truth as ``world_T_imu`` (``world_T_body``) and, when the file holds
    left-camera poses, those poses as they are.

    Attributes (besides :class:`TrajectoryFile`'s):
        frame: ``"imu"`` or ``"cam"`` (the file's body frame).
        world_T_cam: (N, 4, 4) the file's camera poses (``frame="cam"``), else None.
        cam_T_imu: (4, 4) the transform ``world_T_body`` was converted with, else None.
        cam_T_imu_source: where that transform came from, else None.
    """

    frame: str = "imu"
    world_T_cam: np.ndarray | None = None
    cam_T_imu: np.ndarray | None = None
    cam_T_imu_source: str | None = None

    def camera_file(self) -> TrajectoryFile:
        """The file's camera poses as a TrajectoryFile (``frame="cam"`` only)."""
        if self.world_T_cam is None:
            raise ValueError("this ground truth holds IMU poses")
        return TrajectoryFile(self.world_T_cam, self.timestamps_s, self.fmt, self.path)


# ----------------------------------------------------------------------------- loading


@dataclass(frozen=True, eq=False)
class GroundTruthFrame:
    """The body frame of a ground truth and how it is brought to the IMU.

    Attributes:
        frame: ``"imu"`` or ``"cam"`` (left-camera poses, converted with ``cam_T_imu``).
        requested: what was asked for: ``"auto"`` (the format's convention), ``"imu"`` or
            ``"cam"``.
        fmt: the ground truth's file format, ``"kitti"`` or ``"tum"``.
        cam_T_imu: (4, 4) for ``frame="cam"``, else None.
        cam_T_imu_source: where ``cam_T_imu`` came from (``"dataset PATH"`` or
            ``"PATH/summary.json (dataset.cam_T_imu)"``), else None.
    """

    frame: str
    requested: str
    fmt: str
    cam_T_imu: np.ndarray | None = None
    cam_T_imu_source: str | None = None

    def describe(self) -> str:
        """One line for tables: which frame, why, and where cam_T_imu came from."""
        why = f"default for {self.fmt.upper()} ground truth" if self.requested == "auto" else "as requested"
        if self.frame == "imu":
            return f"IMU poses ({why})"
        return f"left-camera poses ({why}), converted to the IMU with cam_T_imu from {self.cam_T_imu_source}"

    def to_info(self) -> dict[str, Any]:
        """The entries recorded in metrics.json."""
        return {
            "ground_truth_frame": self.frame,
            "ground_truth_frame_requested": self.requested,
            "cam_T_imu_source": self.cam_T_imu_source,
            "cam_T_imu": self.cam_T_imu.tolist() if self.cam_T_imu is not None else None,
        }

    def apply(self, traj: TrajectoryFile) -> GroundTruthTrajectory:
        """``traj`` (poses of this frame) as world_T_imu (camera poses kept beside)."""
        if self.frame == "imu":
            return GroundTruthTrajectory(traj.world_T_body, traj.timestamps_s, traj.fmt, traj.path)
        poses = camera_to_imu_trajectory(traj.world_T_body, self.cam_T_imu)
        logger.info("%s: converted %d left-camera poses to the IMU frame (cam_T_imu from %s)",
                    traj.path, len(traj), self.cam_T_imu_source)
        return GroundTruthTrajectory(poses, traj.timestamps_s, traj.fmt, traj.path, "cam", traj.world_T_body,
                                     self.cam_T_imu, self.cam_T_imu_source)


def _check_format_and_frame(fmt: str, frame: str) -> None:
    if fmt not in GT_FORMAT_CHOICES:
        raise ConfigError(f"unknown ground-truth format {fmt!r}; expected one of {', '.join(GT_FORMAT_CHOICES)}")
    if frame not in GT_FRAME_CHOICES:
        raise ConfigError(f"unknown ground-truth frame {frame!r}; expected one of {', '.join(GT_FRAME_CHOICES)}")


@dataclass(frozen=True, eq=False)
class RunCalibration:
    """The ``cam_T_imu`` a run folder's summary.json records.

    Attributes:
        cam_T_imu: (4, 4) the transform the filter used (``calibration.cam_T_imu``) or,
            in a summary without it, the data file's (``dataset.cam_T_imu``).
        source: where it came from, for messages (``"PATH (calibration.cam_T_imu, ...)"``).
        used_by_filter: True when ``cam_T_imu`` is the filter's (``calibration``).
        file_cam_T_imu: (4, 4) the data file's transform (``dataset.cam_T_imu``), or None.
    """

    cam_T_imu: np.ndarray
    source: str
    used_by_filter: bool
    file_cam_T_imu: np.ndarray | None = None


def _summary_matrix(path: Path, value, key: str) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or not is_rigid_transform(a):
        raise ConfigError(f"{path}: {key} is not a 4x4 rigid transform (a list of 4 rows of 4 numbers)")
    return a


def cam_T_imu_from_run_summary(directory) -> RunCalibration | None:
    """The ``cam_T_imu`` recorded in ``directory/summary.json`` (a ``vislam run``,
    ``compare`` or ``demo`` folder): ``calibration.cam_T_imu``, the transform the filter
    used, or in a summary written before it was recorded ``dataset.cam_T_imu``, the data
    file's; None when there is no such file.

    Raises:
        ConfigError: the file exists but is not readable JSON, has neither key, or one
            is not a 4x4 rigid transform (the message names the file and the key).
    """
    path = Path(directory) / RUN_SUMMARY_FILE
    if not path.is_file():
        return None
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else "not valid JSON"
        raise ConfigError(f"{path}: cannot be read ({reason}); a vislam run summary was expected") from None
    dataset = content.get("dataset") if isinstance(content, dict) else None
    calibration = content.get("calibration") if isinstance(content, dict) else None
    raw_file = dataset.get("cam_T_imu") if isinstance(dataset, dict) else None
    file_cam_T_imu = _summary_matrix(path, raw_file, "dataset.cam_T_imu") if raw_file is not None else None
    if isinstance(calibration, dict) and calibration.get("cam_T_imu") is not None:
        used = _summary_matrix(path, calibration["cam_T_imu"], "calibration.cam_T_imu")
        corrected = file_cam_T_imu is None or not np.allclose(used, file_cam_T_imu, rtol=0, atol=1e-12)
        what = "the transform the filter used" + (", corrected from the data file's" if corrected and
                                                   file_cam_T_imu is not None else "")
        return RunCalibration(used, f"{path} (calibration.cam_T_imu, {what})", True, file_cam_T_imu)
    if file_cam_T_imu is None:
        recorded = dataset.get("path") if isinstance(dataset, dict) else None
        hint = f"--dataset {recorded}" if recorded else "--dataset DATA"
        raise ConfigError(
            f"{path}: no key calibration.cam_T_imu or dataset.cam_T_imu (written by an older vislam?); pass {hint} "
            "to convert the camera ground truth, or --gt-frame imu if it holds IMU poses"
        )
    logger.warning("%s records no calibration.cam_T_imu (written by an older vislam): converting the camera ground "
                   "truth with dataset.cam_T_imu, the data file's transform, which the filter used only if no "
                   "correction changed it", path)
    return RunCalibration(file_cam_T_imu, f"{path} (dataset.cam_T_imu, the data file's transform; this summary "
                          "records no calibration.cam_T_imu)", False, file_cam_T_imu)


def resolve_ground_truth_frame(
    fmt: str,
    frame: str = "auto",
    *,
    cam_T_imu=None,
    cam_T_imu_source: str | None = None,
    estimate_path=None,
    ground_truth_path=None,
) -> GroundTruthFrame:
    """Decide the body frame of a ground truth and, for the camera, find ``cam_T_imu``.

    ``frame="auto"`` takes the format's convention (:func:`default_gt_frame`: KITTI ->
    ``"cam"``, TUM -> ``"imu"``). For ``"cam"``, ``cam_T_imu`` is, in this order: the one
    the filter used, recorded in the ``summary.json`` next to ``estimate_path``
    (:func:`cam_T_imu_from_run_summary`) — with ``cam_T_imu`` given (the dataset's), only
    when that summary's data-file transform is the same (the run is of this dataset);
    else the one given; else the summary's data-file transform (older summaries).

    Raises:
        ConfigError: unknown format or frame; a camera ground truth without any
            ``cam_T_imu`` (one line saying how to give it); an invalid ``cam_T_imu``.
    """
    _check_format_and_frame(fmt, frame)
    if fmt == "auto":
        if ground_truth_path is None:
            raise ConfigError('ground-truth format "auto" needs the ground-truth file to detect it from')
        fmt = resolve_gt_format(ground_truth_path, fmt)
    resolved = default_gt_frame(fmt) if frame == "auto" else frame
    if resolved == "imu":
        return GroundTruthFrame("imu", frame, fmt)
    if cam_T_imu is not None:
        if not is_rigid_transform(cam_T_imu):
            raise ConfigError(f"cam_T_imu{f' of {cam_T_imu_source}' if cam_T_imu_source else ''} is not a 4x4 rigid "
                              "transform")
        given = np.array(cam_T_imu, dtype=np.float64)
        source = cam_T_imu_source or "the caller"
        run = _run_calibration_quiet(estimate_path)
        if run is not None and run.used_by_filter:
            if run.file_cam_T_imu is not None and np.allclose(run.file_cam_T_imu, given, rtol=0, atol=1e-9):
                return GroundTruthFrame("cam", frame, fmt, run.cam_T_imu, run.source)
            logger.warning("%s records another data-file cam_T_imu than %s; using %s's", run.source, source, source)
        elif run is not None and not np.allclose(run.cam_T_imu, given, rtol=0, atol=1e-9):
            logger.warning("%s records another cam_T_imu than %s; using %s's", run.source, source, source)
        return GroundTruthFrame("cam", frame, fmt, given, source)
    what = f"{ground_truth_path}: " if ground_truth_path is not None else ""
    why = ("KITTI ground truth holds left-camera poses by the format's convention" if frame == "auto"
           else "camera-frame ground truth")
    if estimate_path is None:
        raise ConfigError(f"{what}{why}; converting it to the IMU needs the dataset's cam_T_imu")
    directory = Path(estimate_path).resolve().parent
    found = cam_T_imu_from_run_summary(directory)
    if found is None:
        raise ConfigError(
            f"{what}{why} and needs cam_T_imu, but no dataset was given and {directory / RUN_SUMMARY_FILE} does not "
            "exist; pass --dataset DATA (the estimate's dataset), or --gt-frame imu if the file holds IMU poses"
        )
    return GroundTruthFrame("cam", frame, fmt, found.cam_T_imu, found.source)


def _run_calibration_quiet(estimate_path) -> RunCalibration | None:
    """The run summary's calibration next to ``estimate_path``, or None (no estimate, no
    summary, or an unreadable one: a dataset was given, so the summary is not needed)."""
    if estimate_path is None:
        return None
    try:
        return cam_T_imu_from_run_summary(Path(estimate_path).resolve().parent)
    except ConfigError:
        return None


def load_ground_truth(path, fmt: str = "auto", frame: str = "auto", cam_T_imu=None,
                      cam_T_imu_source: str | None = None) -> TrajectoryFile:
    """Read a ground-truth trajectory and return it as ``world_T_imu``.

    Args:
        path: KITTI or TUM file.
        fmt: ``"kitti"`` (12 values per line, matched to the estimate by frame index),
            ``"tum"`` (timestamped, matched by time) or ``"auto"`` (the default): the
            one the file's values per line say (:func:`resolve_gt_format`).
        frame: ``"imu"`` when the file holds ``world_T_imu``; ``"cam"`` when it holds the
            left camera ``world_T_cam`` (converted with ``cam_T_imu``); ``"auto"`` (the
            default): the format's convention, ``"cam"`` for KITTI, ``"imu"`` for TUM.
        cam_T_imu: (4, 4) the dataset's transform, required for the camera frame.
        cam_T_imu_source: where ``cam_T_imu`` comes from, for messages.

    Raises:
        GroundTruthError: missing, unreadable or malformed file (message names it).
        ConfigError: unknown ``fmt``/``frame``, or a camera frame without a valid
            ``cam_T_imu``.
    """
    _check_format_and_frame(fmt, frame)
    traj = read_trajectory(path, None if fmt == "auto" else fmt)  # None: detected from the values per line
    conversion = resolve_ground_truth_frame(traj.fmt, frame, cam_T_imu=cam_T_imu, cam_T_imu_source=cam_T_imu_source,
                                            ground_truth_path=path)
    return conversion.apply(traj)


def load_estimate(path) -> TrajectoryFile:
    """Read an estimated ``world_T_imu`` trajectory, KITTI (12 values per line) or TUM (8)."""
    traj = read_trajectory(path)
    logger.info("%s: %d poses (%s)", path, len(traj), traj.fmt.upper())
    return traj


# ----------------------------------------------------------------------------- association


@dataclass(frozen=True, eq=False)
class Association:
    """Estimate and ground-truth poses paired one to one.

    Attributes:
        est_world_T_imu: (n, 4, 4) estimated poses.
        gt_world_T_imu: (n, 4, 4) ground-truth poses of the same frames.
        timestamps_s: (n,) times of the pairs (the estimate's), or None when unknown.
        method: ``"index"`` or ``"timestamp"``.
        n_estimate: poses in the estimate before association.
        n_ground_truth: poses in the ground truth before association.
        max_diff_s: largest time difference allowed (timestamp association only).
    """

    est_world_T_imu: np.ndarray
    gt_world_T_imu: np.ndarray
    timestamps_s: np.ndarray | None
    method: str
    n_estimate: int
    n_ground_truth: int
    max_diff_s: float | None = None

    @property
    def n_pairs(self) -> int:
        return int(self.est_world_T_imu.shape[0])

    def describe(self) -> str:
        how = "by frame index" if self.method == "index" else f"by timestamp (max. difference {self.max_diff_s:g} s)"
        return (
            f"{self.n_pairs} frames compared, matched {how}; "
            f"estimate has {self.n_estimate} poses, ground truth {self.n_ground_truth}"
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "n_pairs": self.n_pairs,
            "n_estimate": self.n_estimate,
            "n_ground_truth": self.n_ground_truth,
            "max_diff_s": self.max_diff_s,
        }


def _frame_timestamps(traj: TrajectoryFile, dataset_timestamps, what: str) -> np.ndarray | None:
    """The trajectory's timestamps, or for a KITTI file the dataset's (line i = frame i)."""
    if traj.timestamps_s is not None:
        return traj.timestamps_s
    if dataset_timestamps is None:
        return None
    ts = np.asarray(dataset_timestamps, dtype=np.float64).ravel()
    if len(traj) > ts.shape[0]:
        raise GroundTruthError(
            f"{traj.path}: {len(traj)} poses but the dataset has only {ts.shape[0]} frames; "
            f"this {what} does not belong to the dataset"
        )
    return ts[: len(traj)]


def _time(x: float) -> str:
    """A time stamp for a message: 6 decimals, or 7 significant digits when that is noise."""
    return f"{x:.6f}" if abs(x) < 1e11 else f"{x:.10g}"


def _no_time_match(est: TrajectoryFile, gt: TrajectoryFile, est_ts, gt_ts, max_diff_s: float) -> GroundTruthError:
    """The error of :func:`associate` when no time stamps match: both ranges, and why if it can tell."""
    return GroundTruthError(
        f"{est.path} and {gt.path}: no timestamps match within {max_diff_s:g} s (estimate "
        f"{_time(est_ts[0])}..{_time(est_ts[-1])} s, ground truth {_time(gt_ts[0])}..{_time(gt_ts[-1])} s)"
        f"{_time_mismatch_hint(est_ts, gt_ts, est.path, gt.path)}")


def _time_mismatch_hint(est_ts: np.ndarray, gt_ts: np.ndarray, est_name, gt_name) -> str:
    """Why no time stamps match: one side in ms, µs or ns (its frame interval 1e3, 1e6 or
    1e9 times the other's), or the two ranges apart; "" when neither is evident."""
    from vislam.core.sequence import TIMESTAMP_UNITS

    def interval(ts):
        return float(np.median(np.diff(ts))) if ts.size > 1 else float("nan")

    de, dg = interval(est_ts), interval(gt_ts)
    if de > 0 and dg > 0:
        for factor, unit in TIMESTAMP_UNITS:
            for name, mine, other in ((gt_name, dg, de), (est_name, de, dg)):
                if 0.5 <= mine * factor / other <= 2.0:
                    return (f"; the frame interval of {name} is {mine / other:.3g} times the other's: are its time "
                            f"stamps in {unit}? Both must be in seconds")
    if est_ts[-1] < gt_ts[0] or gt_ts[-1] < est_ts[0]:
        gap = gt_ts[0] - est_ts[-1] if est_ts[-1] < gt_ts[0] else est_ts[0] - gt_ts[-1]
        return (f"; the two time ranges do not overlap ({gap:.6g} s apart): is {gt_name} the ground truth of this "
                f"recording, with time stamps on the same clock?")
    return ""


def associate(
    est: TrajectoryFile,
    gt: TrajectoryFile,
    dataset_timestamps=None,
    max_diff_s: float = DEFAULT_MAX_DIFF_S,
) -> Association:
    """Pair the poses of an estimate with those of the ground truth.

    * KITTI ground truth: line i is frame i. A KITTI estimate is matched by index, both
      truncated to the shorter length (the shared ground truth covers the first 1101
      frames of 1104-1106-frame datasets). A TUM estimate is matched by timestamp when
      ``dataset_timestamps`` give the ground truth its times, by index otherwise.
    * TUM ground truth: matched by timestamp (evo's ``sync.associate_trajectories``,
      nearest time within ``max_diff_s``). A KITTI estimate gets its times from
      ``dataset_timestamps`` (line i = frame i); without them it cannot be matched.

    Raises:
        GroundTruthError: nothing matches, or fewer than 2 pairs.
        ConfigError: a KITTI estimate against TUM ground truth without dataset timestamps.
    """
    from evo import EvoException
    from evo.core.trajectory import PoseTrajectory3D

    if not (max_diff_s > 0 and math.isfinite(max_diff_s)):
        raise ConfigError(f"max. time difference must be a positive number of seconds, got {max_diff_s!r}")
    est_ts = _frame_timestamps(est, dataset_timestamps, "estimate")
    gt_ts = _frame_timestamps(gt, dataset_timestamps, "ground truth")
    if gt.fmt == "tum" and est_ts is None:
        raise ConfigError(
            f"{est.path}: a KITTI estimate has no timestamps, and the TUM ground truth {gt.path} is matched by "
            "time; give the dataset (--dataset) to supply the frame times, or a TUM estimate"
        )
    by_time = gt.fmt == "tum" or (est.fmt == "tum" and gt_ts is not None)
    if not by_time:
        if est.fmt == "tum":
            logger.warning(
                "%s: TUM estimate matched to the KITTI ground truth %s by line index (no dataset timestamps "
                "given); this is right only if the estimate has one pose per dataset frame from frame 0",
                est.path, gt.path,
            )
        n = min(len(est), len(gt))
        assoc = Association(
            est.world_T_body[:n].copy(),
            gt.world_T_body[:n].copy(),
            est_ts[:n].copy() if est_ts is not None else None,
            "index",
            len(est),
            len(gt),
        )
    else:
        traj_est = PoseTrajectory3D(poses_se3=list(est.world_T_body), timestamps=est_ts, name=str(est.path))
        traj_gt = PoseTrajectory3D(poses_se3=list(gt.world_T_body), timestamps=gt_ts, name=str(gt.path))
        try:
            traj_est, traj_gt = evo_sync.associate_trajectories(traj_est, traj_gt, max_diff=max_diff_s)
        except EvoException:
            raise _no_time_match(est, gt, est_ts, gt_ts, max_diff_s) from None
        for traj in (traj_est, traj_gt):
            if np.any(np.diff(traj.timestamps) <= 0):
                raise GroundTruthError(
                    f"{est.path} and {gt.path}: a pose matches two others within {max_diff_s:g} s; "
                    "use a smaller max. time difference"
                )
        assoc = Association(
            np.array(traj_est.poses_se3),
            np.array(traj_gt.poses_se3),
            np.array(traj_est.timestamps, dtype=np.float64),
            "timestamp",
            len(est),
            len(gt),
            float(max_diff_s),
        )
    if assoc.n_pairs < 2:
        raise GroundTruthError(
            f"{est.path} and {gt.path}: only {assoc.n_pairs} pose pair(s) in common; at least 2 are needed"
        )
    logger.info("%s", assoc.describe())
    return assoc


# ----------------------------------------------------------------------------- evaluation


@dataclass(frozen=True)
class ErrorStats:
    """Statistics of an error array (evo's): rmse, mean, median, std, min, max; NaN when
    the metric could not be computed (``n == 0``)."""

    rmse: float = float("nan")
    mean: float = float("nan")
    median: float = float("nan")
    std: float = float("nan")
    min: float = float("nan")
    max: float = float("nan")
    n: int = 0

    @classmethod
    def from_metric(cls, metric: evo_metrics.PE) -> "ErrorStats":
        s = metric.get_all_statistics()
        return cls(
            rmse=float(s["rmse"]),
            mean=float(s["mean"]),
            median=float(s["median"]),
            std=float(s["std"]),
            min=float(s["min"]),
            max=float(s["max"]),
            n=int(np.size(metric.error)),
        )

    @classmethod
    def from_errors(cls, error: np.ndarray) -> "ErrorStats":
        """The statistics of an error array, by evo's formulas (``PE.get_statistic``)."""
        e = np.asarray(error, dtype=np.float64)
        return cls(
            rmse=math.sqrt(np.mean(np.power(e, 2))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            n=int(e.size),
        )

    def to_dict(self) -> dict[str, float]:
        return {"rmse": self.rmse, "mean": self.mean, "median": self.median, "std": self.std,
                "min": self.min, "max": self.max, "n": self.n}


@dataclass(frozen=True, eq=False)
class EvaluationResult:
    """Errors of an estimate against ground truth (see :func:`evaluate`).

    Attributes:
        n_frames_compared: number of associated pose pairs.
        path_length_m: length of the ground-truth path over the compared frames (m).
        ape: APE translation (m) after SE(3) Umeyama alignment (evo, ``align=True,
            correct_scale=False``).
        ape_unaligned: APE translation (m) without alignment.
        rpe_trans: RPE translation (m) between consecutive frames (delta = 1 frame).
        rpe_rot: RPE rotation angle (deg), delta = 1 frame.
        rpe_trans_100m: RPE translation (m) between poses 100 m apart along the ground
            truth (evo, delta = 100 m, consecutive pairs chosen on the ground truth); NaN
            when the path is shorter.
        rpe_rot_100m: RPE rotation angle (deg), delta = 100 m.
        kitti: the KITTI odometry errors (:class:`~vislam.core.metrics.KittiOdometryErrors`).
        aligned_position_error_m: (n,) position error of each frame after alignment (m).
        unaligned_position_error_m: (n,) position error of each frame without alignment (m).
        distance_along_gt_m: (n,) distance travelled along the ground truth (m).
        est_world_T_imu: (n, 4, 4) the estimate as given.
        est_world_T_imu_aligned: (n, 4, 4) the estimate after alignment (``alignment @ est``).
        gt_world_T_imu: (n, 4, 4) the ground truth.
        alignment: (4, 4) SE(3) transform from the estimate's world frame into the
            ground truth's (identity, with a note, when alignment is impossible).
        timestamps_s: (n,) times of the pairs, or None.
        notes: warnings about the evaluation (e.g. a metric that could not be computed).
        info: provenance (files, association), copied into :meth:`to_dict`.
        camera: where the ground truth holds left-camera poses, the same evaluation of the
            camera frame (the estimate as ``world_T_imu @ imu_T_cam`` with the calibration
            used, against the ground truth's camera poses as they are; its ``*_world_T_imu``
            arrays hold camera poses), else None.
        cam_T_imu: (4, 4) the calibration the camera frame was evaluated with, else None.
    """

    n_frames_compared: int
    path_length_m: float
    ape: ErrorStats
    ape_unaligned: ErrorStats
    rpe_trans: ErrorStats
    rpe_rot: ErrorStats
    rpe_trans_100m: ErrorStats
    rpe_rot_100m: ErrorStats
    kitti: KittiOdometryErrors
    aligned_position_error_m: np.ndarray
    unaligned_position_error_m: np.ndarray
    distance_along_gt_m: np.ndarray
    est_world_T_imu: np.ndarray
    est_world_T_imu_aligned: np.ndarray
    gt_world_T_imu: np.ndarray
    alignment: np.ndarray
    timestamps_s: np.ndarray | None = None
    notes: tuple[str, ...] = ()
    info: Mapping[str, Any] = field(default_factory=dict)
    camera: "EvaluationResult | None" = None
    cam_T_imu: np.ndarray | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (NaN becomes None, see :func:`write_metrics_json`).

        Flat keys ``ape_rmse_m``, ``ape_mean_m``, ``ape_median_m``, ``ape_max_m``,
        ``ape_std_m`` (likewise ``ape_unaligned_*_m``, ``rpe_trans_*_m``,
        ``rpe_rot_*_deg``, ``rpe_trans_100m_*_m``, ``rpe_rot_100m_*_deg``),
        ``kitti_t_pct``, ``kitti_r_deg_per_100m``, ``kitti_segments``,
        ``kitti_by_length`` (length in m -> t_pct, r_deg_per_100m, segments),
        ``n_frames_compared``, ``path_length_m``, ``notes`` and the ``info`` entries —
        all of the IMU frame. The camera frame (:attr:`camera`; None without camera
        ground truth): ``cam_ape_rmse_m``, ``cam_ape_mean_m``, ``cam_ape_median_m``,
        ``cam_ape_max_m``, ``cam_ape_std_m``, ``cam_ape_unaligned_rmse_m``,
        ``cam_kitti_t_pct``, ``cam_kitti_r_deg_per_100m``, ``cam_kitti_segments``,
        ``cam_T_imu_evaluated`` and ``metrics_frames`` (what the two sets mean).
        """
        out: dict[str, Any] = {
            "n_frames_compared": int(self.n_frames_compared),
            "path_length_m": float(self.path_length_m),
        }
        for prefix, stats, unit in (
            ("ape", self.ape, "m"),
            ("ape_unaligned", self.ape_unaligned, "m"),
            ("rpe_trans", self.rpe_trans, "m"),
            ("rpe_rot", self.rpe_rot, "deg"),
            ("rpe_trans_100m", self.rpe_trans_100m, "m"),
            ("rpe_rot_100m", self.rpe_rot_100m, "deg"),
        ):
            for stat in ("rmse", "mean", "median", "max", "std"):
                out[f"{prefix}_{stat}_{unit}"] = float(getattr(stats, stat))
        k = self.kitti
        out["kitti_t_pct"] = float(k.t_pct)
        out["kitti_r_deg_per_100m"] = float(k.r_deg_per_100m)
        out["kitti_segments"] = int(k.n_segments)
        out["kitti_by_length"] = {
            f"{length:g}": {
                "t_pct": float(t),
                "r_deg_per_100m": float(r),
                "segments": int(n),
            }
            for length, t, r, n in zip(k.lengths_m, k.t_pct_by_length, k.r_deg_per_100m_by_length,
                                       k.n_segments_by_length)
        }
        out["alignment_gt_world_T_est_world"] = self.alignment.tolist()
        c = self.camera
        for stat in ("rmse", "mean", "median", "max", "std"):
            out[f"{CAMERA_PREFIX}ape_{stat}_m"] = float(getattr(c.ape, stat)) if c is not None else None
        out[f"{CAMERA_PREFIX}ape_unaligned_rmse_m"] = float(c.ape_unaligned.rmse) if c is not None else None
        out[f"{CAMERA_PREFIX}kitti_t_pct"] = float(c.kitti.t_pct) if c is not None else None
        out[f"{CAMERA_PREFIX}kitti_r_deg_per_100m"] = float(c.kitti.r_deg_per_100m) if c is not None else None
        out[f"{CAMERA_PREFIX}kitti_segments"] = int(c.kitti.n_segments) if c is not None else None
        out["cam_T_imu_evaluated"] = self.cam_T_imu.tolist() if self.cam_T_imu is not None else None
        out["metrics_frames"] = METRICS_FRAMES if c is not None else METRICS_FRAMES_IMU_ONLY
        out["notes"] = list(self.notes) + [f"camera frame: {n}" for n in (c.notes if c is not None else ())]
        for key, value in self.info.items():
            out.setdefault(key, value)
        return out


#: What the two metric sets of :meth:`EvaluationResult.to_dict` mean (camera ground truth).
METRICS_FRAMES = ("ape_*, rpe_*, kitti_*: IMU frame (the ground truth's camera poses converted to the IMU with "
                  "cam_T_imu_evaluated: they depend on that lever arm); cam_ape_*, cam_kitti_*: left-camera frame "
                  "(the estimate as world_T_imu @ imu_T_cam with cam_T_imu_evaluated, against the ground truth as it "
                  "is)")
METRICS_FRAMES_IMU_ONLY = "ape_*, rpe_*, kitti_*: IMU frame (the ground truth holds IMU poses; no camera-frame metrics)"


def _check_poses(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (N, 4, 4), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise GroundTruthError(f"{name} contains non-finite poses")
    return a


def _project_rotations(poses: np.ndarray) -> np.ndarray:
    """Replace each rotation block by the nearest rotation (SVD), so that files printed
    with few digits pass evo's strict SO(3) checks; positions are untouched."""
    out = poses.copy()
    U, _, Vt = np.linalg.svd(poses[:, :3, :3])
    D = np.ones((poses.shape[0], 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    out[:, :3, :3] = (U * D[:, None, :]) @ Vt
    out[:, 3, :] = (0.0, 0.0, 0.0, 1.0)
    return out


def _rpe(ref, est, relation, delta, unit) -> evo_metrics.RPE:
    metric = evo_metrics.RPE(relation, delta=delta, delta_unit=unit, all_pairs=False, pairs_from_reference=True)
    metric.process_data((ref, est))
    return metric


def evaluate(
    est_world_T_imu,
    gt_world_T_imu,
    timestamps=None,
    *,
    info: Mapping[str, Any] | None = None,
    gt_world_T_cam=None,
    cam_T_imu=None,
) -> EvaluationResult:
    """Errors of associated estimate / ground-truth poses (same length, frame i with i).

    APE and RPE are computed by evo (``evo.core.metrics``); the KITTI metric by
    :func:`vislam.core.metrics.kitti_odometry_errors`. Rotation blocks are projected onto
    SO(3) first (a no-op up to rounding for proper rotations). A metric that cannot be
    computed (a straight-line path cannot be aligned; a path shorter than 100 m has no
    100 m RPE or KITTI segment) is NaN, with a note in ``notes``.

    ``gt_world_T_cam`` (n, 4, 4) — the ground truth's own left-camera poses, of which
    ``gt_world_T_imu`` is the conversion with ``cam_T_imu`` — adds the camera-frame
    evaluation (:attr:`EvaluationResult.camera`): ``est_world_T_imu @ imu_T_cam``
    against ``gt_world_T_cam``.
    """
    # Positions so far off that their squares overflow (1e308 m) give NaN metrics with a
    # note ("alignment impossible", "the path is inf m"), not floating-point warnings.
    with np.errstate(over="ignore", invalid="ignore"):
        return _evaluate(est_world_T_imu, gt_world_T_imu, timestamps, info, gt_world_T_cam, cam_T_imu)


def _evaluate(est_world_T_imu, gt_world_T_imu, timestamps, info, gt_world_T_cam, cam_T_imu) -> EvaluationResult:
    from evo.core.trajectory import PosePath3D

    camera = None
    if gt_world_T_cam is not None:
        camera, cam_T_imu = _camera_evaluation(est_world_T_imu, gt_world_T_cam, cam_T_imu, timestamps)
    elif cam_T_imu is not None:
        cam_T_imu = np.array(cam_T_imu, dtype=np.float64)
    est, gt, ts = _checked_pairs(est_world_T_imu, gt_world_T_imu, timestamps)
    n = est.shape[0]
    notes: list[str] = []

    ref = PosePath3D(poses_se3=list(gt.copy()))
    est_path = PosePath3D(poses_se3=list(est.copy()))

    # APE, not aligned.
    ape_unaligned = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape_unaligned.process_data((ref, est_path))
    alignment, ape_stats, aligned_err, est_aligned = _aligned_ape(ref, est_path, est, notes)
    rpe_trans, rpe_rot, rpe_trans_100, rpe_rot_100 = _rpe_stats(ref, est_path, notes)

    kitti = kitti_odometry_errors(est, gt)
    if not kitti.has_segments:
        notes.append(f"ground truth shorter than {kitti.lengths_m.min():g} m: no KITTI odometry segments")
    distances = trajectory_distances(gt)
    result = EvaluationResult(
        n_frames_compared=n,
        path_length_m=float(distances[-1]),
        ape=ape_stats,
        ape_unaligned=ErrorStats.from_metric(ape_unaligned),
        rpe_trans=rpe_trans,
        rpe_rot=rpe_rot,
        rpe_trans_100m=rpe_trans_100,
        rpe_rot_100m=rpe_rot_100,
        kitti=kitti,
        aligned_position_error_m=aligned_err,
        unaligned_position_error_m=np.asarray(ape_unaligned.error, dtype=np.float64),
        distance_along_gt_m=distances,
        est_world_T_imu=est,
        est_world_T_imu_aligned=est_aligned,
        gt_world_T_imu=gt,
        alignment=alignment,
        timestamps_s=ts,
        notes=tuple(notes),
        info=dict(info or {}),
        camera=camera,
        cam_T_imu=cam_T_imu,
    )
    logger.info(
        "APE %.4f m (aligned), KITTI %.3f %% / %.4f deg/100 m over %d frames",
        ape_stats.rmse, kitti.t_pct, kitti.r_deg_per_100m, n,
    )
    return result


def _camera_evaluation(est_world_T_imu, gt_world_T_cam, cam_T_imu, timestamps):
    """(the camera-frame :class:`EvaluationResult`, cam_T_imu as floats) of
    :func:`evaluate` with the ground truth's own left-camera poses."""
    if cam_T_imu is None or not is_rigid_transform(cam_T_imu):
        raise ValueError("camera-frame evaluation needs the 4x4 rigid cam_T_imu used")
    cam_T_imu = np.array(cam_T_imu, dtype=np.float64)
    # world_T_cam = world_T_imu @ imu_T_cam, expressed in the first camera's world frame (as KITTI ground
    # truth is, when the estimate starts at the identity) by a left factor: the aligned metrics do not
    # depend on that world frame, the unaligned APE does. The factor is cam_T_imu with its rotation
    # projected onto SO(3) (the shared files' is orthonormal to 1e-7 only), so that it is exactly rigid
    # and the aligned metrics are those of world_T_imu @ imu_T_cam to rounding.
    world_change = _project_rotations(cam_T_imu[None])[0]
    est_cam = world_change @ _check_poses(est_world_T_imu, "estimate") @ se3_inverse(cam_T_imu)
    return evaluate(est_cam, gt_world_T_cam, timestamps, info={"frame": "left camera"}), cam_T_imu


def _checked_pairs(est_world_T_imu, gt_world_T_imu, timestamps):
    """(estimate, ground truth with rotations projected onto SO(3), timestamps or None)
    of :func:`evaluate`, checked: the same number of poses, at least 2."""
    est = _check_poses(est_world_T_imu, "estimate")
    gt = _check_poses(gt_world_T_imu, "ground truth")
    if est.shape[0] != gt.shape[0]:
        raise ValueError(f"estimate has {est.shape[0]} poses, ground truth {gt.shape[0]}; associate them first")
    n = est.shape[0]
    if n < 2:
        raise GroundTruthError(f"only {n} pose pair(s) to compare; at least 2 are needed")
    ts = None
    if timestamps is not None:
        ts = np.asarray(timestamps, dtype=np.float64).ravel()
        if ts.shape[0] != n:
            raise ValueError(f"{ts.shape[0]} timestamps for {n} poses")
    return _project_rotations(est), _project_rotations(gt), ts


def _aligned_ape(ref, est_path, est: np.ndarray, notes: list):
    """APE with SE(3) Umeyama alignment (as evo_ape -a): (alignment 4x4, its ErrorStats,
    the aligned position error per pose, the aligned estimate); NaN with a note when the
    path cannot be aligned."""
    from evo import EvoException

    aligned = copy.deepcopy(est_path)
    try:
        r_a, t_a, _ = aligned.align(ref, correct_scale=False)
        alignment = np.eye(4)
        alignment[:3, :3] = r_a
        alignment[:3, 3] = t_a
        ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        ape.process_data((ref, aligned))
        return alignment, ErrorStats.from_metric(ape), np.asarray(ape.error, dtype=np.float64), \
            np.array(aligned.poses_se3)
    except (EvoException, np.linalg.LinAlgError) as exc:  # LinAlgError: positions that overflow (1e308 m)
        notes.append(f"SE(3) alignment impossible ({exc}); aligned APE not computed")
        logger.warning("%s", notes[-1])
        return np.eye(4), ErrorStats(), np.full(est.shape[0], np.nan), est.copy()


def _rpe_translation_rotation(ref, est_path, delta, unit) -> tuple[ErrorStats, ErrorStats]:
    """(translation, rotation angle in degrees) of evo's RPE over ``delta``. One evo RPE
    (``translation_part``) pairs the poses and forms the relative error poses E_i (its
    ``E``); their angles |Log(R(E_i))| come from :func:`vislam.core.lie.so3_log` in one
    batch — what evo's ``rotation_angle_deg`` computes one matrix at a time through scipy
    (two thirds of an evaluation's time), for the same pairs a second time."""
    metric = _rpe(ref, est_path, evo_metrics.PoseRelation.translation_part, delta, unit)
    E = np.asarray(metric.E, dtype=np.float64).reshape(-1, 4, 4)
    if E.shape[0] == 0:
        return ErrorStats.from_metric(metric), ErrorStats()
    angles_deg = np.rad2deg(np.linalg.norm(so3_log(E[:, :3, :3]), axis=-1))
    return ErrorStats.from_metric(metric), ErrorStats.from_errors(angles_deg)


def _rpe_stats(ref, est_path, notes: list):
    """RPE over one frame and over 100 m of ground-truth path: (translation, rotation,
    translation 100 m, rotation 100 m); the 100 m ones empty with a note on a shorter path."""
    from evo import EvoException

    rpe_trans, rpe_rot = _rpe_translation_rotation(ref, est_path, 1, evo_metrics.Unit.frames)
    try:
        rpe_trans_100, rpe_rot_100 = _rpe_translation_rotation(ref, est_path, RPE_DISTANCE_M,
                                                               evo_metrics.Unit.meters)
    except EvoException:
        notes.append(f"ground truth shorter than {RPE_DISTANCE_M:g} m: no {RPE_DISTANCE_M:g} m RPE")
        rpe_trans_100 = rpe_rot_100 = ErrorStats()
    return rpe_trans, rpe_rot, rpe_trans_100, rpe_rot_100


def evaluate_associated(est: TrajectoryFile, gt: TrajectoryFile, dataset_timestamps=None,
                        max_diff_s: float = DEFAULT_MAX_DIFF_S, *, cam_T_imu=None,
                        info: Mapping[str, Any] | None = None) -> EvaluationResult:
    """Associate ``est`` (world_T_imu) with ``gt`` and evaluate.

    ``gt``: IMU poses, or — with ``cam_T_imu`` (the calibration the estimate used) — the
    ground truth's left-camera poses as they are, converted to the IMU with it for the
    IMU-frame metrics and compared as they are for the camera-frame ones. The
    association's info is added to ``info``.
    """
    assoc = associate(est, gt, dataset_timestamps, max_diff_s)
    info = {**(info or {}), "association": assoc.to_dict()}
    if cam_T_imu is None:
        result = evaluate(assoc.est_world_T_imu, assoc.gt_world_T_imu, assoc.timestamps_s, info=info)
    else:
        gt_cam = assoc.gt_world_T_imu  # camera poses here
        result = evaluate(assoc.est_world_T_imu, camera_to_imu_trajectory(gt_cam, cam_T_imu), assoc.timestamps_s,
                          info=info, gt_world_T_cam=gt_cam, cam_T_imu=cam_T_imu)
    with np.errstate(over="ignore", invalid="ignore"):  # a path of inf m is said in a note
        notes = _pairing_notes(assoc, result, gt)
    for note in notes:
        logger.warning("%s", note)
    return replace(result, notes=(*notes, *result.notes)) if notes else result


def _pairing_notes(assoc: Association, result: EvaluationResult, gt: TrajectoryFile) -> list[str]:
    """What makes an evaluation doubtful although it could be computed: a ground truth that
    covers few of the estimate's poses, or paths whose lengths disagree (see
    :data:`PATH_LENGTH_RATIO_BOUNDS`)."""
    notes = []
    if assoc.n_pairs < MIN_COVERAGE * assoc.n_estimate:
        notes.append(f"only {assoc.n_pairs} of the estimate's {assoc.n_estimate} poses have a ground-truth pose "
                     f"({gt.path}: {assoc.n_ground_truth}); the others are not evaluated")
    gt_m = result.path_length_m  # the ground truth's path over the compared frames
    if gt_m >= PATH_LENGTH_CHECK_MIN_M:
        est_m = float(trajectory_distances(result.est_world_T_imu)[-1])
        ratio = est_m / gt_m
        low, high = PATH_LENGTH_RATIO_BOUNDS
        if not low <= ratio <= high:
            notes.append(f"the estimate's path over the compared frames is {est_m:.1f} m, {ratio:.2f}x the ground "
                         f"truth's {gt_m:.1f} m: is {gt.path} the ground truth of this drive, are the speeds in "
                         f"m/s, or did the run diverge?")
    return notes


def evaluate_files(
    est_path,
    gt_path,
    gt_format: str = "auto",
    gt_frame: str = "auto",
    sequence=None,
    max_diff_s: float = DEFAULT_MAX_DIFF_S,
) -> EvaluationResult:
    """Load, associate and evaluate: the whole of ``vislam eval``.

    ``sequence`` (a :class:`~vislam.core.sequence.Sequence`, optional) supplies the frame
    times of KITTI files and ``cam_T_imu`` for a camera-frame ground truth; without it,
    ``cam_T_imu`` comes from the ``summary.json`` of the estimate's run folder (see
    :func:`resolve_ground_truth_frame`). ``gt_frame="auto"`` follows the format's
    convention (KITTI: left camera; TUM: IMU); ``gt_format="auto"`` reads the format from
    the file's values per line. The frame used and the source of
    ``cam_T_imu`` are recorded in the result's ``info``.
    """
    _check_format_and_frame(gt_format, gt_frame)
    raw_gt = read_trajectory(gt_path, None if gt_format == "auto" else gt_format)  # None: from the values per line
    gt_format = raw_gt.fmt
    est = load_estimate(est_path)
    source = f"dataset {getattr(sequence, 'source', None) or getattr(sequence, 'name', '')}".strip() \
        if sequence is not None else None
    conversion = resolve_ground_truth_frame(
        gt_format, gt_frame,
        cam_T_imu=sequence.cam_T_imu if sequence is not None else None,
        cam_T_imu_source=source,
        estimate_path=est_path,
        ground_truth_path=gt_path,
    )
    if conversion.frame == "cam":
        logger.info("%s: left-camera poses, converted to the IMU with cam_T_imu from %s", gt_path,
                    conversion.cam_T_imu_source)
    info = {
        "estimate": str(est_path),
        "estimate_format": est.fmt,
        "ground_truth": str(gt_path),
        "ground_truth_format": raw_gt.fmt,
        **conversion.to_info(),
        "ground_truth_description": conversion.describe(),
        "dataset": getattr(sequence, "source", None) if sequence is not None else None,
    }
    return evaluate_associated(est, raw_gt, sequence.timestamps_s if sequence is not None else None, max_diff_s,
                               cam_T_imu=conversion.cam_T_imu if conversion.frame == "cam" else None, info=info)


# ----------------------------------------------------------------------------- output


def write_metrics_json(result: EvaluationResult, path) -> None:
    """Write ``result.to_dict()`` as strict JSON (NaN -> null), atomically."""
    text = dumps(result.to_dict()) + "\n"
    try:
        write_text_atomic(path, text)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write: {exc.strerror or exc}") from None


def _fmt(x: float, spec: str = ".4f") -> str:
    return "n/a" if x is None or not math.isfinite(x) else format(x, spec)


def format_table(result: EvaluationResult) -> str:
    """A readable text table of the result."""
    r = result
    lines = []
    assoc = r.info.get("association") if r.info else None
    header = f"frames compared: {r.n_frames_compared}"
    if assoc:
        how = "by frame index" if assoc["method"] == "index" else "by timestamp"
        header += (f" (matched {how}; estimate {assoc['n_estimate']} poses, "
                   f"ground truth {assoc['n_ground_truth']})")
    lines.append(header)
    description = r.info.get("ground_truth_description") if r.info else None
    if description:
        lines.append(f"ground truth: {description}")
    lines.append(f"ground-truth path length: {r.path_length_m:.2f} m")
    lines.append("")
    c = r.camera
    w = 50 if c is not None else 38
    if c is not None:
        lines.append("IMU frame: the estimate against the ground truth converted to the IMU with cam_T_imu (depends "
                     "on its lever arm); camera frame: the estimate as left-camera poses (world_T_imu @ imu_T_cam) "
                     "against the ground truth as it is")
    lines.append(f"{'metric':<{w}}{'rmse':>10}{'mean':>10}{'median':>10}{'max':>10}{'std':>10}")
    imu = "IMU frame: " if c is not None else ""
    rows = ((("camera frame: APE translation, SE(3)-aligned (m)", c.ape),
             ("camera frame: APE translation, not aligned (m)", c.ape_unaligned)) if c is not None else ()) + (
        (f"{imu}APE translation, SE(3)-aligned (m)", r.ape),
        (f"{imu}APE translation, not aligned (m)", r.ape_unaligned),
        (f"{imu}RPE translation, 1 frame (m)", r.rpe_trans),
        (f"{imu}RPE rotation, 1 frame (deg)", r.rpe_rot),
        (f"{imu}RPE translation, {RPE_DISTANCE_M:g} m (m)", r.rpe_trans_100m),
        (f"{imu}RPE rotation, {RPE_DISTANCE_M:g} m (deg)", r.rpe_rot_100m),
    )
    for label, s in rows:
        lines.append(f"{label:<{w}}" + "".join(f"{_fmt(getattr(s, k)):>10}"
                                              for k in ("rmse", "mean", "median", "max", "std")))
    k = r.kitti
    lines.append("")
    if c is not None and c.kitti.has_segments:
        lines.append(
            f"KITTI odometry, camera frame ({c.kitti.n_segments} segments): translation "
            f"{_fmt(c.kitti.t_pct, '.3f')} %, rotation {_fmt(c.kitti.r_deg_per_100m, '.4f')} deg/100 m"
        )
    if k.has_segments:
        lines.append(
            f"KITTI odometry{', IMU frame' if c is not None else ''} ({k.n_segments} segments): translation "
            f"{_fmt(k.t_pct, '.3f')} %, rotation {_fmt(k.r_deg_per_100m, '.4f')} deg/100 m"
        )
        lines.append(f"{'length (m)':>12}{'segments':>10}{'t (%)':>10}{'r (deg/100 m)':>16}")
        for length, n, t, rot in zip(k.lengths_m, k.n_segments_by_length, k.t_pct_by_length,
                                     k.r_deg_per_100m_by_length):
            lines.append(f"{length:>12g}{n:>10d}{_fmt(t, '.3f'):>10}{_fmt(rot, '.4f'):>16}")
    else:
        lines.append(f"KITTI odometry: n/a (ground truth shorter than {k.lengths_m.min():g} m)")
    for note in r.notes:
        lines.append(f"note: {note}")
    return "\n".join(lines)


@dataclass(frozen=True, eq=False)
class ErrorFigureData:
    """What :func:`plot_error_over_distance` draws of an :class:`EvaluationResult`: plain
    arrays and numbers (so that the figure can be drawn by another process,
    :mod:`vislam.tools.figure_process`). The attributes are those of the result
    (``ape_rmse_m``: ``ape.rmse``); ``camera`` the same of the camera-frame evaluation."""

    distance_along_gt_m: np.ndarray
    aligned_position_error_m: np.ndarray
    unaligned_position_error_m: np.ndarray
    ape_rmse_m: float
    n_frames_compared: int
    kitti: KittiOdometryErrors
    camera: "ErrorFigureData | None" = None

    @classmethod
    def from_result(cls, result: EvaluationResult) -> "ErrorFigureData":
        camera = cls.from_result(result.camera) if result.camera is not None else None
        return cls(result.distance_along_gt_m, result.aligned_position_error_m, result.unaligned_position_error_m,
                   float(result.ape.rmse), int(result.n_frames_compared), result.kitti, camera)


def plot_error_over_distance(result: EvaluationResult | ErrorFigureData, path, title: str | None = None) -> None:
    """PNG figure (9.5x6 in, 120 dpi), written atomically: aligned APE translation error vs
    distance travelled along the ground truth (top) and the KITTI translational error per
    segment length (bottom); the legends sit right of the axes, off the curves."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from vislam.tools.plotting import layout_once

    r = result if isinstance(result, ErrorFigureData) else ErrorFigureData.from_result(result)
    fig = Figure(figsize=(9.5, 6), dpi=120)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(2, 1)
    fig.suptitle(title or "Trajectory error against ground truth", fontsize=13)

    d = r.distance_along_gt_m
    if np.all(np.isnan(r.aligned_position_error_m)):
        ax1.plot(d, r.unaligned_position_error_m, color="tab:blue", lw=1.2, label="not aligned")
        ax1.set_title("APE translation, not aligned (alignment impossible)", fontsize=10, loc="left")
        ax1.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)
    elif r.camera is not None:  # camera ground truth: both frames
        c = r.camera
        ax1.plot(c.distance_along_gt_m, c.aligned_position_error_m, color="tab:green", lw=1.2,
                 label=f"left camera (RMSE {c.ape_rmse_m:.3f} m)")
        ax1.plot(d, r.aligned_position_error_m, color="tab:blue", lw=1.0, alpha=0.8,
                 label=f"IMU, ground truth converted with cam_T_imu (RMSE {r.ape_rmse_m:.3f} m)")
        ax1.set_title(f"APE translation after SE(3) alignment ({r.n_frames_compared} frames)", fontsize=10,
                      loc="left")
        ax1.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)
    else:
        ax1.plot(d, r.aligned_position_error_m, color="tab:blue", lw=1.2, label="per frame")
        ax1.axhline(r.ape_rmse_m, color="tab:red", ls="--", lw=1.0, label=f"RMSE {r.ape_rmse_m:.3f} m")
        ax1.set_title(f"APE translation after SE(3) alignment ({r.n_frames_compared} frames)", fontsize=10,
                      loc="left")
        ax1.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)
    ax1.set_xlabel("distance travelled along ground truth (m)")
    ax1.set_ylabel("position error (m)")
    finite_d = d[np.isfinite(d)]  # (positions that overflow give an infinite distance)
    ax1.set_xlim(0, max(float(finite_d.max()) if finite_d.size else 0.0, 1e-9))
    ax1.set_ylim(bottom=0)
    ax1.grid(True, alpha=0.3)

    k = r.kitti
    lengths = k.lengths_m
    if k.has_segments:
        jitter = (np.random.default_rng(0).random(k.n_segments) - 0.5) * 0.25 * np.min(np.diff(lengths)) \
            if lengths.size > 1 else np.zeros(k.n_segments)
        ax2.scatter(k.segment_length_m + jitter, k.t_pct_segments, s=8, color="0.6", alpha=0.6,
                    label="each segment", zorder=2)
        has = k.n_segments_by_length > 0
        ax2.plot(lengths[has], k.t_pct_by_length[has], "o-", color="tab:orange", lw=1.5, ms=5,
                 label="mean per length", zorder=3)
        frame = "IMU" if r.camera is not None else ""
        cam = (f"; camera {r.camera.kitti.t_pct:.2f} %" if r.camera is not None and r.camera.kitti.has_segments
               else "")
        ax2.set_title(
            f"KITTI odometry error{f' ({frame})' if frame else ''}: {k.t_pct:.2f} % translation, "
            f"{k.r_deg_per_100m:.3f} deg/100 m rotation ({k.n_segments} segments){cam}", fontsize=10, loc="left")
        ax2.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)
        ax2.set_ylim(bottom=0)
    else:
        ax2.text(0.5, 0.5, f"ground truth shorter than {lengths.min():g} m:\nno KITTI segments",
                 ha="center", va="center", transform=ax2.transAxes, fontsize=11, color="0.3")
        ax2.set_title("KITTI odometry error", fontsize=10, loc="left")
    ax2.set_xticks(lengths)
    ax2.set_xlim(lengths.min() - 50, lengths.max() + 50)
    ax2.set_xlabel("segment length (m)")
    ax2.set_ylabel("translational error (%)")
    ax2.grid(True, alpha=0.3)

    layout_once(fig, h_pad=1.5)  # one pass (constrained layout costs several draws)
    try:
        with atomic_path(path, suffix=".png") as tmp:
            fig.savefig(tmp, format="png", dpi=120)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write: {exc.strerror or exc}") from None
