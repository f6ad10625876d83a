"""Comparing estimators on the same data: the report's Part A ("separately") against SLAM,
and both against the sliding-window smoother and its batch refinement.

* :func:`run_comparison` injects the requested noise (:func:`vislam.core.noise.inject_noise`)
  once and runs the requested :data:`METHODS` on the same noisy sequence: IMU
  localization + landmark mapping on the localization trajectory ("separately", the
  report's Figs 1–3), SLAM (Figs 4–6), the fixed-lag smoother (:mod:`vislam.core.smoother`)
  and the smoother followed by its batch refinement ("refine"; one smoother run serves
  both). It evaluates each against a ground truth when one is given and returns a
  :class:`Comparison` — no I/O.
* :func:`write_comparison` writes a comparison into a directory: one folder per method
  (``separate/``, ``slam/``, ``smoother/``, ``refine/``: the files of ``vislam run``, plus
  ``metrics.json`` and ``error_over_distance.png`` with a ground truth),
  ``comparison.png`` (every trajectory and landmark set on one xy figure with a side view,
  the report's Figs 7–9) and ``comparison.json``.
* Ground truth of a run: :func:`load_run_ground_truth` (checked against the dataset
  before any work), :func:`evaluate_run`, :func:`stage_evaluation` (``metrics.json``,
  ``error_over_distance.png``) and :func:`evaluation_summary` (the compact dict stored
  under ``"evaluation"`` in summary.json).
* :meth:`vislam.tools.outputs.OutputStage.commit` with ``replace_directories`` commits a stage
  whose staged entries include directories (``separate/``, ``slam/``, ``runs/``):
  existing directories of the same name are replaced as a whole, so the output directory
  holds one command's outputs, all of them or (on failure or Ctrl-C) the previous ones.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Collection, Mapping

import numpy as np

from vislam.core.estimators import run as run_estimator
from vislam.core.noise import NoiseSpec, inject_noise
from vislam.core.options import FilterOptions
from vislam.core.results import RunResult
from vislam.core.sequence import Sequence
from vislam.core.suggest import did_you_mean
from vislam.tools.evaluation import EvaluationResult, associate, evaluate_associated, load_ground_truth, \
    plot_error_over_distance, write_metrics_json
from vislam.tools.jsonio import write_json
from vislam.tools.outputs import FIGURE, OutputStage, display_name, write_run_outputs
from vislam.tools.trajectory_io import DEFAULT_MAX_DIFF_S, TrajectoryFile

__all__ = [
    "METHODS",
    "DEFAULT_METHODS",
    "EKF_METHODS",
    "parse_methods",
    "METHOD_LABELS",
    "METHOD_COLORS",
    "METRICS_FILE",
    "ERROR_FIGURE_FILE",
    "COMPARISON_FIGURE",
    "COMPARISON_JSON",
    "MethodResult",
    "Comparison",
    "load_run_ground_truth",
    "evaluate_run",
    "evaluation_summary",
    "ground_truth_from_start",
    "start_anchor",
    "stage_evaluation",
    "describe_noise",
    "injected_noise_record",
    "run_comparison",
    "write_comparison",
]

logger = logging.getLogger(__name__)

#: The methods a comparison can run, in drawing order, and how figures and tables name them.
METHODS = ("separate", "slam", "smoother", "refine")
#: What ``vislam compare`` runs by default: all of them. The smoother costs 2-4x SLAM per
#: frame on the dense files and refine a few seconds more per drive: on dense 0027 the
#: estimation takes 2.6 s (separately) + 9.7 s (SLAM) + 31 s (smoother and refine), the
#: whole command 61 s on the loaded 2-core machine (see README); ``--methods
#: separate,slam`` for the EKF alone.
DEFAULT_METHODS = METHODS
#: The report's two EKF methods (the noise comparison runs only these).
EKF_METHODS = ("separate", "slam")
METHOD_LABELS = {"separate": "localization + mapping (separately)", "slam": "visual-inertial SLAM",
                 "smoother": "sliding-window smoother", "refine": "smoother + batch refinement"}
METHOD_SHORT = {"separate": "separately", "slam": "SLAM", "smoother": "smoother", "refine": "refined"}
METHOD_COLORS = {"separate": "tab:orange", "slam": "tab:blue", "smoother": "tab:green", "refine": "tab:purple"}
#: Estimator mode of each method: "separately" is a mapping run on the localization poses;
#: "refine" is the smoother with ``refine=True``.
METHOD_MODES = {"separate": "mapping", "slam": "slam", "smoother": "smoother", "refine": "smoother"}
#: Accepted spellings of the methods in ``--methods`` besides their keys.
METHOD_ALIASES = {"separately": "separate", "localization+mapping": "separate", "ekf": "slam",
                  "refined": "refine"}


def parse_methods(text: str, flag: str = "--methods") -> tuple[str, ...]:
    """The methods of a comma-separated list (keys of :data:`METHODS` or aliases), in
    drawing order; ``"all"`` for every method. A ConfigError names ``flag``."""
    from vislam.errors import ConfigError

    items = [t.strip().lower() for t in str(text).split(",") if t.strip()]
    if items == ["all"]:
        return METHODS
    chosen = set()
    for item in items:
        key = METHOD_ALIASES.get(item, item)
        if key not in METHODS:
            hint = did_you_mean(item, [*METHODS, *METHOD_ALIASES, "all"])
            raise ConfigError(f"{flag}: unknown method {item!r}; {hint + ' ' if hint else ''}expected a "
                              f"comma-separated list of {', '.join(METHODS)} (or 'all')")
        chosen.add(key)
    if not chosen:
        raise ConfigError(f"{flag}: expected at least one of {', '.join(METHODS)}, got {text!r}")
    return tuple(k for k in METHODS if k in chosen)

METRICS_FILE = "metrics.json"
ERROR_FIGURE_FILE = "error_over_distance.png"
COMPARISON_FIGURE = "comparison.png"
COMPARISON_JSON = "comparison.json"

#: Metrics copied from :meth:`EvaluationResult.to_dict` into summary.json's "evaluation".
SUMMARY_METRICS = (
    "n_frames_compared", "path_length_m",
    "ape_rmse_m", "ape_mean_m", "ape_median_m", "ape_max_m", "ape_unaligned_rmse_m",
    "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "rpe_trans_100m_rmse_m", "rpe_rot_100m_rmse_deg",
    "kitti_t_pct", "kitti_r_deg_per_100m", "kitti_segments",
    "cam_ape_rmse_m", "cam_ape_mean_m", "cam_ape_median_m", "cam_ape_max_m", "cam_kitti_t_pct",
    "cam_kitti_r_deg_per_100m", "cam_kitti_segments", "metrics_frames",
)


# ----------------------------------------------------------------------------- ground truth


def load_run_ground_truth(path, sequence: Sequence, fmt: str = "auto", frame: str = "auto",
                          max_diff_s: float = DEFAULT_MAX_DIFF_S) -> TrajectoryFile:
    """Read the ground truth of ``sequence`` as world_T_imu and check that it matches the
    dataset's frames (at least 2 pairs), so a wrong file fails before any work.

    ``fmt="auto"`` reads the format from the file's values per line (12: KITTI, 8: TUM);
    ``frame="auto"`` follows the format's convention (KITTI: left camera, TUM: IMU);
    camera poses are converted with ``sequence.cam_T_imu`` and kept as they are beside
    (:class:`~vislam.tools.evaluation.GroundTruthTrajectory`): :func:`evaluate_run`
    converts them again with the transform the run used.

    Raises GroundTruthError / ConfigError with a one-line message naming the file.
    """
    gt = load_ground_truth(path, fmt, frame, sequence.cam_T_imu,
                           cam_T_imu_source=f"dataset {sequence.source or sequence.name}")
    ground_truth_pairs(gt, sequence, max_diff_s)
    return gt


def ground_truth_pairs(ground_truth: TrajectoryFile, sequence: Sequence, max_diff_s: float = DEFAULT_MAX_DIFF_S) -> int:
    """How many of the frames of ``sequence`` have a pose in ``ground_truth`` (GroundTruthError
    when fewer than 2 do)."""
    probe = TrajectoryFile(np.broadcast_to(np.eye(4), (sequence.n_frames, 4, 4)).copy(), sequence.timestamps_s.copy(),
                           "tum", f"{sequence.source or sequence.name} (frame times)")
    return associate(probe, ground_truth, sequence.timestamps_s, max_diff_s).n_pairs


def evaluate_run(result: RunResult, ground_truth: TrajectoryFile, sequence: Sequence,
                 max_diff_s: float = DEFAULT_MAX_DIFF_S) -> EvaluationResult:
    """Errors of a run's trajectory (the frames it processed) against ``ground_truth``.

    A ground truth of camera poses (a :class:`~vislam.tools.evaluation.GroundTruthTrajectory`
    with ``world_T_cam``, as :func:`load_run_ground_truth` returns) is converted to the IMU
    with the transform the run used (``result.calibration.cam_T_imu``; the sequence's for
    a result without one), whatever it was loaded with, and also evaluated in the camera
    frame (``EvaluationResult.camera``)."""
    est = TrajectoryFile(np.asarray(result.world_T_imu), np.asarray(result.timestamps_s), "tum",
                         f"{result.mode} estimate of {sequence.name}")
    info = {
        "estimate": f"{result.mode} run",
        "ground_truth": str(ground_truth.path),
        "ground_truth_format": ground_truth.fmt,
        "dataset": sequence.source or sequence.name,
    }
    world_T_cam = getattr(ground_truth, "world_T_cam", None)
    if world_T_cam is None:
        return evaluate_associated(est, ground_truth, sequence.timestamps_s, max_diff_s, info=info)
    if result.calibration is not None:
        cam_T_imu = result.calibration.cam_T_imu
        source = "the run's calibration.cam_T_imu (the transform the filter used)"
    else:
        cam_T_imu, source = sequence.cam_T_imu, f"dataset {sequence.source or sequence.name}"
    info.update(ground_truth_frame="cam", cam_T_imu_source=source, cam_T_imu=np.asarray(cam_T_imu).tolist())
    return evaluate_associated(est, ground_truth.camera_file(), sequence.timestamps_s, max_diff_s,
                               cam_T_imu=cam_T_imu, info=info)


def start_anchor(evaluation: EvaluationResult) -> np.ndarray:
    """(4, 4) the rigid transform ``est[0] gt[0]⁻¹`` of an evaluation's first pose pair: it
    takes the ground truth's world frame into the estimate's so that both start at the same
    pose (the identity when the ground truth already starts at the estimate's first pose,
    as KITTI's and the simulator's do)."""
    from vislam.core.lie import se3_inverse

    return evaluation.est_world_T_imu[0] @ se3_inverse(evaluation.gt_world_T_imu[0])


def ground_truth_from_start(evaluation: EvaluationResult, poses: np.ndarray | None = None) -> np.ndarray:
    """The ground truth drawn beside an estimate: ``poses`` (default: the evaluation's own
    ground-truth poses), world_T_imu in the ground truth's world frame, moved by
    :func:`start_anchor` into the estimate's world frame from the same start pose. A ground
    truth recorded in another world frame (a motion-capture room, a map's east-north-up
    frame) is then drawn where the estimate is; the figure does not align it in SE(3) as
    the ATE does (its side view says so)."""
    gt = evaluation.gt_world_T_imu if poses is None else np.asarray(poses, dtype=np.float64)
    if gt.shape[0] == 0 or evaluation.gt_world_T_imu.shape[0] == 0:
        return gt
    return start_anchor(evaluation) @ gt


def evaluation_summary(evaluation: EvaluationResult, **extra) -> dict[str, Any]:
    """The compact dict stored under ``"evaluation"`` in summary.json: the headline
    metrics (``ape_rmse_m``, ``kitti_t_pct``, ``kitti_r_deg_per_100m``, RPE …), the
    notes, the association and ``extra`` (e.g. the ground-truth file and frame)."""
    full = evaluation.to_dict()
    out = {key: full[key] for key in SUMMARY_METRICS}
    out["association"] = full.get("association")
    out["notes"] = full["notes"]
    out.update(extra)
    return out


#: Entries of a ground-truth info dict (``ground_truth=`` of :func:`stage_evaluation`)
#: recorded in metrics.json, under the names ``vislam eval`` uses.
_FRAME_INFO_KEYS = {"frame": "ground_truth_frame", "frame_requested": "ground_truth_frame_requested",
                    "cam_T_imu_source": "cam_T_imu_source"}


def stage_evaluation(directory, evaluation: EvaluationResult, title: str, plot=None, figure: bool = True,
                     **extra) -> dict[str, Any]:
    """Write ``metrics.json`` and ``error_over_distance.png`` into ``directory`` (a staging
    directory) and return :func:`evaluation_summary` with the file names. The frame of
    the ground truth (``extra["ground_truth"]``, see
    :func:`vislam.cli.run.ground_truth_from_args`) is recorded in metrics.json too.
    ``plot`` draws the figure (default :func:`~vislam.tools.evaluation.plot_error_over_distance`;
    ``vislam run`` passes a :class:`~vislam.tools.figure_process.FigureProcess`'s);
    ``figure=False`` writes metrics.json only (its summary's ``figure`` is then None)."""
    directory = Path(directory)
    gt_info = extra.get("ground_truth")
    if isinstance(gt_info, Mapping):
        frame_info = {name: gt_info[key] for key, name in _FRAME_INFO_KEYS.items() if key in gt_info}
        evaluation = replace(evaluation, info={**frame_info, **evaluation.info})  # the evaluation's own first
    write_metrics_json(evaluation, directory / METRICS_FILE)
    if figure:
        (plot or plot_error_over_distance)(evaluation, directory / ERROR_FIGURE_FILE, title=title)
    return evaluation_summary(evaluation, **extra, metrics_file=METRICS_FILE,
                              figure=ERROR_FIGURE_FILE if figure else None)


# ----------------------------------------------------------------------------- noise


def _g(x: float) -> str:
    return f"{x:.3g}"


def describe_noise(spec: NoiseSpec | None, seed: bool = True, ascii: bool = False) -> str:
    """A short human description of the injected noise ("none" when there is none);
    ``ascii`` spells σv, σω, σpx as "v", "w", "px" (for PLY headers)."""
    if spec is None or spec.is_zero:
        return "none"
    sv, sw, spx = ("v", "w", "pixels") if ascii else ("σv", "σω", "σpx")
    parts = []
    if spec.velocity_noise_mps:
        parts.append(f"{sv} {_g(spec.velocity_noise_mps)} m/s")
    if spec.angular_noise_radps:
        parts.append(f"{sw} {_g(spec.angular_noise_radps)} rad/s")
    if any(spec.velocity_bias_mps):
        parts.append("v bias (" + ", ".join(_g(b) for b in spec.velocity_bias_mps) + ") m/s")
    if any(spec.angular_bias_radps):
        parts.append(f"{'w' if ascii else 'ω'} bias (" + ", ".join(_g(b) for b in spec.angular_bias_radps) + ") rad/s")
    if spec.pixel_noise_px:
        parts.append(f"{spx} {_g(spec.pixel_noise_px)} px")
    if spec.outlier_fraction:
        parts.append(f"{_g(100 * spec.outlier_fraction)} % outliers")
    text = ", ".join(parts)
    return f"{text} (seed {spec.seed})" if seed else text


def injected_noise_record(spec: NoiseSpec | None, info: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """What summary.json records under ``"injected_noise"``: the NoiseSpec's fields and
    what :func:`inject_noise` reports (e.g. ``outliers_injected``); None without noise."""
    if spec is None:
        return None
    record = spec.to_dict()
    record.update({k: v for k, v in (info or {}).items() if k != "spec"})
    return record


def _g_axes(x) -> str:
    """A number, or three per-axis numbers as "(x, y, z)"."""
    if isinstance(x, (tuple, list)):
        return "(" + ", ".join(_g(v) for v in x) + ")"
    return _g(x)


def describe_filter_noise(options: FilterOptions) -> str:
    return f"σv {_g_axes(options.velocity_noise_mps)} m/s, σω {_g_axes(options.angular_noise_radps)} rad/s"


# ----------------------------------------------------------------------------- comparison


@dataclass
class MethodResult:
    """One method of a comparison: its run and, with a ground truth, its evaluation."""

    key: str
    result: RunResult
    evaluation: EvaluationResult | None = None

    @property
    def label(self) -> str:
        return METHOD_LABELS[self.key]

    @property
    def warnings(self) -> list[str]:
        """:func:`vislam.core.results.run_warnings` of the run (one line each)."""
        from vislam.core.results import run_warnings

        return run_warnings(self.result)

    @property
    def ate_m(self) -> float | None:
        if self.evaluation is None or not math.isfinite(self.evaluation.ape.rmse):
            return None
        return float(self.evaluation.ape.rmse)

    @property
    def cam_ate_m(self) -> float | None:
        """Camera-frame ATE (camera ground truth only), else None."""
        camera = self.evaluation.camera if self.evaluation is not None else None
        if camera is None or not math.isfinite(camera.ape.rmse):
            return None
        return float(camera.ape.rmse)

    @property
    def refine_seconds(self) -> float | None:
        """Time of the batch refinement (refine only), or None."""
        value = (self.result.extra.get("timing") or {}).get("refine_seconds")
        return float(value) if value is not None else None

    @property
    def estimation_seconds(self) -> float:
        """Estimation time of the method: the filter's (or smoother's) frames plus, for
        refine, the batch refinement."""
        return float(self.result.stats.filter_seconds) + (self.refine_seconds or 0.0)

    @property
    def frame_ms_median(self) -> float | None:
        fs = np.asarray(self.result.stats.frame_seconds)
        return float(np.median(fs) * 1e3) if fs.size else None

    def to_dict(self) -> dict[str, Any]:
        r = self.result
        st = r.stats
        lm = r.landmarks
        ts = np.asarray(r.timestamps_s)
        processed_s = float(ts[-1] - ts[0]) if ts.size > 1 else 0.0
        return {
            "label": self.label,
            "mode": r.mode,
            "directory": self.key,
            "frames": st.frames,
            "frames_processed": st.frames_processed,
            "landmarks_in_map": len(lm) if lm is not None else 0,
            "landmarks_rejected": int(np.count_nonzero(lm.status)) if lm is not None else 0,
            "filter_seconds": st.filter_seconds,
            "frame_ms_median": self.frame_ms_median,
            "refine_seconds": self.refine_seconds,
            "estimation_seconds": self.estimation_seconds,
            "real_time_factor": self.estimation_seconds / processed_s if processed_s > 0 else None,
            "partial": bool(r.partial),
            "error": r.error,
            "warnings": self.warnings,
            "evaluation": evaluation_summary(self.evaluation) if self.evaluation is not None else None,
        }


@dataclass
class Comparison:
    """Several estimators (:data:`METHODS`) on the same (noisy) sequence.

    Attributes:
        sequence: the sequence the filters ran on (with the injected noise).
        options: the filter options of every run (refine: with ``refine=True``).
        noise: the injected noise, or None.
        noise_info: what :func:`inject_noise` reported, or None.
        methods: ``{key: MethodResult}`` in :data:`METHODS` order.
        ground_truth: the ground truth (world_T_imu), or None.
        ground_truth_info: provenance of the ground truth (file, format, frame).
        dataset: name, path, frames, landmarks, duration and a display ``label``.
        auto: with ``--auto``, what :func:`vislam.tools.auto.auto_check` found and
            suggested (``{"suggested", "findings", "check_seconds"}``), or None.
    """

    sequence: Sequence
    options: FilterOptions
    noise: NoiseSpec | None
    noise_info: dict[str, Any] | None
    methods: dict[str, MethodResult]
    ground_truth: TrajectoryFile | None = None
    ground_truth_info: dict[str, Any] | None = None
    dataset: dict[str, Any] = field(default_factory=dict)
    auto: dict[str, Any] | None = None

    @property
    def label(self) -> str:
        return str(self.dataset.get("label") or self.sequence.name)

    @property
    def partial(self) -> bool:
        return any(m.result.partial for m in self.methods.values())

    @property
    def warnings(self) -> list[str]:
        """Warnings about the data every method ran on (one line each):
        :func:`vislam.core.sequence.imu_sample_warnings`."""
        from vislam.core.sequence import imu_sample_warnings

        seq = self.sequence
        return imu_sample_warnings(seq.linear_velocity_in_imu_mps, seq.angular_velocity_in_imu_radps)

    def ground_truth_poses(self) -> np.ndarray | None:
        """The ground-truth poses of the dataset's frames (for drawing), or None: in the
        estimates' world frame from their start pose (:func:`ground_truth_from_start` with
        the first method's evaluation; the methods share their start pose)."""
        if self.ground_truth is None:
            return None
        gt = self.ground_truth
        poses = gt.world_T_body
        if getattr(gt, "world_T_cam", None) is not None:  # camera poses: with the cam_T_imu the runs used
            from vislam.tools.trajectory_io import camera_to_imu_trajectory

            poses = camera_to_imu_trajectory(gt.world_T_cam, self.sequence.cam_T_imu)
        if gt.timestamps_s is None:
            poses = poses[: self.sequence.n_frames]
        else:
            keep = (gt.timestamps_s >= self.sequence.timestamps_s[0] - DEFAULT_MAX_DIFF_S) & \
                   (gt.timestamps_s <= self.sequence.timestamps_s[-1] + DEFAULT_MAX_DIFF_S)
            poses = poses[keep]
        evaluation = next((m.evaluation for m in self.methods.values() if m.evaluation is not None), None)
        return poses if evaluation is None else ground_truth_from_start(evaluation, poses)

    def to_dict(self) -> dict[str, Any]:
        from vislam import __version__

        return {
            "vislam_version": __version__,
            "dataset": dict(self.dataset),
            "options": self.options.to_dict(),
            "injected_noise": injected_noise_record(self.noise, self.noise_info),
            "ground_truth": self.ground_truth_info,
            "auto": self.auto,
            "methods": {key: m.to_dict() for key, m in self.methods.items()},
            "ate_m": {key: m.ate_m for key, m in self.methods.items()},
            "cam_ate_m": {key: m.cam_ate_m for key, m in self.methods.items()},
            "partial": self.partial,
            "warnings": self.warnings,
        }


def dataset_record(sequence: Sequence, path=None, label: str | None = None) -> dict[str, Any]:
    """The ``dataset`` entry of summary.json / comparison.json (``cam_T_imu``: the data
    file's, before any correction; the one the filter used is summary.json's
    ``calibration.cam_T_imu``)."""
    return {"name": sequence.name, "label": label or sequence.name,
            "path": str(Path(path).resolve()) if path is not None else (sequence.source or None),
            "frames": sequence.n_frames, "landmarks": sequence.n_landmarks, "duration_s": sequence.duration_s,
            "cam_T_imu": sequence.recorded_cam_T_imu.tolist()}


def runs_of(methods) -> tuple[str, ...]:
    """The estimator runs behind ``methods`` (progress keys): "separate", "slam" and one
    "smoother" run for both "smoother" and "refine"."""
    runs = [k for k in ("separate", "slam") if k in methods]
    if "smoother" in methods or "refine" in methods:
        runs.append("smoother")
    return tuple(runs)


def _smoother_before_refine(result: RunResult) -> RunResult:
    """The smoother's own result out of a refined run: its final trajectory, its timings."""
    extra = {k: v for k, v in result.extra.items() if k != "smoother_world_T_imu"}
    if "timing" in extra:
        extra["timing"] = {k: v for k, v in extra["timing"].items() if not k.startswith("refine_")}
    return replace(result, world_T_imu=np.asarray(result.extra["smoother_world_T_imu"]),
                   options=result.options.replace(refine=False), extra=extra)


def _run_smoother_methods(sequence: Sequence, options: FilterOptions, methods, progress) -> dict[str, RunResult]:
    """One smoother run for "smoother" and/or "refine" (refined only when asked for)."""
    want_refine = "refine" in methods
    result = run_estimator(sequence, "smoother", options.replace(refine=want_refine), progress=progress)
    out: dict[str, RunResult] = {}
    if want_refine and "smoother_world_T_imu" in result.extra:
        if "smoother" in methods:
            out["smoother"] = _smoother_before_refine(result)
        out["refine"] = result
    elif want_refine:  # the smoother stopped early: no refinement; both show the partial smoother
        if "smoother" in methods:
            out["smoother"] = replace(result, options=result.options.replace(refine=False))
        out["refine"] = replace(result, error=f"{result.error} (not refined)" if result.error else result.error)
    else:
        out["smoother"] = result
    return out


def run_comparison(sequence: Sequence, options: FilterOptions, *, noise: NoiseSpec | None = None,
                   ground_truth: TrajectoryFile | None = None, ground_truth_info: Mapping[str, Any] | None = None,
                   dataset: Mapping[str, Any] | None = None,
                   progress: Callable[[str, int], None] | None = None, methods=EKF_METHODS,
                   noise_info: Mapping[str, Any] | None = None, auto: Mapping[str, Any] | None = None) -> Comparison:
    """Inject ``noise`` (if any), run ``methods`` (keys of :data:`METHODS`; by default
    the report's "separately" — localization, then mapping on its trajectory — and SLAM)
    with the same ``options``, and evaluate each against ``ground_truth`` (world_T_imu,
    e.g. from :func:`load_run_ground_truth`) if given. "smoother" and "refine" share one
    smoother run (``refine`` set as needed).

    ``noise_info`` given: ``sequence`` already carries ``noise`` (injected by the caller,
    e.g. to check the noisy data first) and ``noise_info`` is what :func:`inject_noise`
    reported; it is not injected again. ``auto``: the record of
    :func:`vislam.tools.auto.auto_check` the options came from (kept in the comparison).

    ``progress(run, frames_done)`` is called during the runs (``run`` in
    :func:`runs_of`). A run that stops early gives a partial result
    (``Comparison.partial``), evaluated on its frames.
    """
    methods = tuple(k for k in METHODS if k in set(methods))
    if not methods:
        raise ValueError("run_comparison: no method")
    if noise is not None and noise_info is None:
        sequence, noise_info = inject_noise(sequence, noise)
    results: dict[str, RunResult] = {}
    for run_key in runs_of(methods):
        cb = None
        if progress:
            def cb(done, run_key=run_key):
                progress(run_key, done)
            if hasattr(progress, "phase"):  # a bar that can name a phase (the refinement)
                cb.phase = progress.phase
        if run_key == "smoother":
            results.update(_run_smoother_methods(sequence, options, methods, cb))
        else:
            results[run_key] = run_estimator(sequence, METHOD_MODES[run_key], options.replace(refine=False),
                                             progress=cb)
        logger.info("%s: %s done", sequence.name, run_key)
    out: dict[str, MethodResult] = {}
    for key in methods:
        result = results[key]
        evaluation = evaluate_run(result, ground_truth, sequence) if ground_truth is not None else None
        out[key] = MethodResult(key, result, evaluation)
    info = dict(ground_truth_info) if ground_truth_info else (
        {"path": str(ground_truth.path), "format": ground_truth.fmt} if ground_truth is not None else None)
    return Comparison(sequence, options, noise, dict(noise_info) if noise_info is not None else None, out,
                      ground_truth, info, dict(dataset) if dataset else dataset_record(sequence),
                      dict(auto) if auto is not None else None)


def _fmt_m(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f} m"


def comparison_title(comparison: Comparison) -> tuple[str, str]:
    """(title, subtitle) of the comparison figure."""
    title = f"{display_name(comparison.dataset, comparison.sequence.name)}: " + " vs ".join(
        METHOD_SHORT[k] for k in comparison.methods)
    lines = [f"added noise: {describe_noise(comparison.noise)} · filter noise: {describe_filter_noise(comparison.options)}"]
    if comparison.ground_truth is not None:
        if any(m.cam_ate_m is not None for m in comparison.methods.values()):
            lines.append("ATE (SE(3)-aligned RMSE), camera / IMU frame: " + ", ".join(
                f"{METHOD_SHORT[k]} {_fmt_m(m.cam_ate_m)} / {_fmt_m(m.ate_m)}" for k, m in comparison.methods.items()))
        else:
            lines.append("ATE (SE(3)-aligned RMSE): " + ", ".join(
                f"{METHOD_SHORT[k]} {_fmt_m(m.ate_m)}" for k, m in comparison.methods.items()))
    return title, "\n".join(lines)


def _method_layer_label(m: MethodResult) -> str:
    label = m.label
    r = m.result
    if r.partial:
        label += f" — stopped at frame {r.stats.frames_processed} of {r.stats.frames}"
    return label


def plot_comparison(comparison: Comparison, path) -> dict:
    """Draw the comparison figure (the report's Figs 7–9) at ``path``."""
    from vislam.tools.plotting import MapLayer, plot_comparison_map

    # "separately" drawn wider underneath, so that it shows where the trajectories coincide.
    # Maps: those of the EKF methods (the report's figures); the smoother's (which refine
    # shares) only without them — three overlapping landmark sets hide each other (each
    # run's own figure shows its map)
    ekf = any(k in comparison.methods for k in EKF_METHODS)
    shown = [k for k in comparison.methods if k in EKF_METHODS or not ekf][:2 if ekf else 1]
    layers = [MapLayer(m.result.world_T_imu, _method_layer_label(m), METHOD_COLORS[k],
                       m.result.landmarks if k in shown else None,
                       linewidth=2.8 if k == "separate" else 1.5, short=METHOD_SHORT[k],
                       # dashed: the smoother's line shows through where the refinement follows it
                       linestyle="--" if k == "refine" and "smoother" in comparison.methods else "-")
              for k, m in comparison.methods.items()]
    title, subtitle = comparison_title(comparison)
    return plot_comparison_map(path, layers, title, subtitle, ground_truth=comparison.ground_truth_poses())


def write_comparison(directory, comparison: Comparison, start_time: float | None = None,
                     run_figures: Collection[str] | None = None) -> dict[str, Any]:
    """Write one folder per method (``separate/``, ``slam/``, ``smoother/``, ``refine/``),
    ``comparison.png`` and ``comparison.json`` into ``directory`` — meant to be a staging directory (see :meth:`OutputStage.commit`);
    the run folders are themselves written all-or-nothing. ``run_figures``: the method
    folders' figures to draw, as paths in ``directory`` (``"slam/trajectory.png"``,
    ``"slam/error_over_distance.png"``); None (the default) draws all of them.
    ``comparison.png`` is always drawn. Returns comparison.json's content."""
    directory = Path(directory)
    label = comparison.label
    noise_record = injected_noise_record(comparison.noise, comparison.noise_info)
    if comparison.noise is not None and not comparison.noise.is_zero:
        label = f"{label} + noise"
    summaries = {}
    for key, m in comparison.methods.items():
        dataset = {**comparison.dataset, "label": label}
        if m.result.mode == "mapping":
            dataset["poses"] = "localization"
        extra: dict[str, Any] = {"injected_noise": noise_record, "comparison": {"method": key, "label": m.label},
                                 "warnings": comparison.warnings + m.warnings}
        if comparison.auto is not None:
            extra["auto"] = comparison.auto
        if "timing" in m.result.extra:  # smoother: its own timings and those of refine
            extra["timing"] = m.result.extra["timing"]
        with OutputStage(directory / key) as stage:
            if m.evaluation is not None:
                extra["evaluation"] = stage_evaluation(
                    stage.staging, m.evaluation, f"{display_name(dataset)} — {m.label} vs ground truth",
                    ground_truth=comparison.ground_truth_info,
                    figure=run_figures is None or f"{key}/{ERROR_FIGURE_FILE}" in run_figures)
            summaries[key] = write_run_outputs(stage, m.result, dataset=dataset,
                                               duration_s=comparison.sequence.duration_s, start_time=start_time,
                                               extra=extra, ground_truth=None if m.evaluation is None
                                               else ground_truth_from_start(m.evaluation),
                                               figure=run_figures is None or f"{key}/{FIGURE}" in run_figures)
    view = plot_comparison(comparison, directory / COMPARISON_FIGURE)
    content = comparison.to_dict()
    content["figure"] = COMPARISON_FIGURE
    content["landmarks_outside_figure"] = view["landmarks_outside_view"]
    content["total_seconds"] = (time.time() - start_time) if start_time is not None else None
    write_json(directory / COMPARISON_JSON, content)
    return content


# ----------------------------------------------------------------------------- committing


