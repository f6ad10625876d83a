"""``vislam run DATA --mode MODE --out DIR``: run one of the report's estimators on a dataset.

Options: defaults of :class:`~vislam.core.options.FilterOptions` < ``--config FILE``
(YAML/TOML) < ``--robust`` < the other flags (:func:`vislam.tools.config.resolve_options`).
The estimator is :func:`vislam.core.estimators.run`; the files are written, all or
nothing, by :func:`vislam.tools.outputs.write_run_outputs`. This module parses, calls
and prints.

Shared with ``vislam compare`` (one definition each): the filter options
(:func:`add_filter_arguments`, :func:`options_from_args`), the noise injected into the
data after loading (``--add-*``, :func:`add_noise_injection_arguments`,
:func:`noise_spec_from_args` -> :class:`~vislam.core.noise.NoiseSpec`, recorded in
summary.json under ``"injected_noise"``) and the evaluation against ground truth in the
same run (``--gt``, :func:`add_ground_truth_arguments`, :func:`ground_truth_from_args`;
metrics in summary.json under ``"evaluation"``, plus ``metrics.json`` and
``error_over_distance.png``).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import time
from pathlib import Path

from vislam.core.options import EKF_VARIANTS, MODES, ROBUST_PRESET
from vislam.errors import ConfigError, EstimationError
from vislam.tools.trajectory_io import GT_FORMATS, GT_FRAME_CHOICES

__all__ = ["register", "run", "format_summary", "format_evaluation_line", "make_progress", "finish",
           "interrupted_message", "FLAG_FIELDS", "NOISE_FLAGS", "add_filter_arguments", "add_noise_injection_arguments",
           "add_ground_truth_arguments", "add_rerun_arguments", "open_rerun_recorder", "options_from_args",
           "noise_spec_from_args", "ground_truth_from_args", "load_data"]

_COMMAND_START = time.time()

#: argparse dest -> (FilterOptions field, flag)
FLAG_FIELDS = {
    "velocity_noise": ("velocity_noise_mps", "--velocity-noise"),
    "angular_noise": ("angular_noise_radps", "--angular-noise"),
    "pixel_noise": ("pixel_noise_px", "--pixel-noise"),
    "gate": ("gating_probability", "--gate"),
    "ekf": ("ekf", "--ekf"),
    "keep_all_landmarks": ("keep_all_landmarks", "--keep-all-landmarks"),
    "refine": ("refine", "--refine"),
    "imu_bias_time_constant": ("imu_bias_time_constant_s", "--imu-bias-time-constant"),
}


def _comma_numbers(text: str) -> tuple[float, ...]:
    """The numbers of "A,B,...", or () when one is not a number."""
    try:
        return tuple(float(p) for p in str(text).split(","))
    except ValueError:
        return ()


def _bias_sigmas(text: str) -> tuple[float, float]:
    """``--imu-bias-sigma MPS,RADPS``: the two stationary σ of the IMU-error state."""
    values = _comma_numbers(text)
    if len(values) != 2 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected two numbers >= 0 MPS,RADPS (e.g. 0.3,0.003), got {text!r}")
    return values


def _probability_or_off(text: str):
    if text.strip().lower() in ("off", "none"):
        return "none"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a probability in (0, 1) or 'off', got {text!r}") from None


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "run", add_help=False,
        help="run IMU localization, landmark mapping, SLAM or the sliding-window smoother on a dataset",
        description="Run one of the report's estimators on a dataset (.npz) and write DIR/trajectory.tum, "
        "DIR/trajectory.kitti, DIR/trajectory.png, DIR/summary.json and, for mapping and SLAM, "
        "DIR/landmarks.ply and DIR/landmarks.npz (with --gt also DIR/metrics.json and "
        "DIR/error_over_distance.png). Outputs appear all together or not at all. Options: "
        "defaults < --config FILE < --robust < the other flags. The --add-* flags add noise to the data (seeded); "
        "the filter's own noise model is set by --velocity-noise etc.",
        epilog="Every filter option (docs/options.md) can be set in the --config file, by its flat name "
        "(velocity_noise_mps: 0.5) or by group (noise: {velocity_mps: 0.5}); the flags above override the file.",
    )
    # what most runs need first; the rest below, grouped by component
    common = parser.add_argument_group("common options")
    common.add_argument("-h", "--help", action="help", help="show this help message and exit")
    parser.add_argument("data", metavar="DATA", help="dataset file (.npz), or an image folder (KITTI raw drive, "
                        "EuRoC, plain; tracked first, the tracks cached as DIR/tracks.npz)")
    common.add_argument("--mode", choices=MODES, default="slam",
                        help="localization (IMU only), mapping (landmarks from known poses), slam (the report's EKF) "
                        "or smoother (fixed-lag smoother on GTSAM over the same measurements) (default: slam)")
    common.add_argument("--out", metavar="DIR", required=True, help="output directory (created if needed)")
    add_filter_arguments(parser, common)
    smoother = _component_group(parser, "smoother")
    smoother.add_argument("--refine", action="store_true", default=None,
                          help="smoother only: a batch Levenberg-Marquardt pass over the whole drive from the "
                          "smoother's result (the trajectory written is the refined one; the smoother's goes to "
                          "smoother.tum)")
    mapping = parser.add_argument_group("mapping")
    mapping.add_argument("--poses", metavar="FILE",
                         help="mapping only: known world_T_imu poses, TUM or KITTI, one per frame (default: the "
                         "localization trajectory)")
    add_ground_truth_arguments(parser, common)
    common.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_noise_injection_arguments(parser)
    add_rerun_arguments(parser)
    from vislam.cli.track import add_source_arguments

    add_source_arguments(parser)
    _note_option_names(parser)
    parser.set_defaults(func=run)


def _component_group(parser, component: str):
    """A new argument group for the flags of one component of FilterOptions (a key of
    :data:`~vislam.core.options.OPTION_GROUPS`), titled like the options' docs."""
    from vislam.core.options import OPTION_GROUPS

    return parser.add_argument_group(f"filter options: {OPTION_GROUPS[component].TITLE}",
                                     f"options file: {component}.* (FilterOptions.{component})")


def _note_option_names(parser) -> None:
    """Each filter flag's help ends with the option it sets, flat and nested
    (``[pixel_noise_px = noise.pixel_px]``): the same names as in an options file."""
    from vislam.core.options import FLAT_FIELDS

    fields_of = {dest: (field,) for dest, (field, _) in FLAG_FIELDS.items()}
    fields_of["imu_bias_sigma"] = ("imu_bias_sigma_mps", "imu_bias_sigma_radps")
    for action in parser._actions:
        if action.dest in fields_of and action.help:
            names = ", ".join(f"{f} = {'.'.join(FLAT_FIELDS[f])}" for f in fields_of[action.dest])
            if f"[{names}]" not in action.help:  # once, however often it is called
                action.help = f"{action.help} [{names}]"


def load_data(args, cache_dir):
    """(sequence, info) of DATA: a dataset npz, or an image folder tracked first (the tracks
    cached in ``cache_dir``; :func:`vislam.tools.frontend_io.load_recording`)."""
    from vislam.tools.dataset_io import load_sequence

    if not Path(args.data).is_dir():
        for flag, value in (("--velocities", getattr(args, "velocities", None)),
                            ("--tracker-config", getattr(args, "tracker_config", None))):
            if value is not None:
                raise ConfigError(f"{flag} is only used when DATA is an image folder (got {args.data})")
        return load_sequence(args.data), None
    from vislam.cli.track import tracker_options_from_args
    from vislam.errors import OutputError
    from vislam.tools.frontend_io import load_recording

    if cache_dir is not None and Path(cache_dir).exists() and not Path(cache_dir).is_dir():  # before the tracking
        raise OutputError(f"{cache_dir}: exists and is not a directory (an output directory is expected)")

    options = tracker_options_from_args(getattr(args, "tracker_config", None))
    return load_recording(args.data, cache_dir, pair=getattr(args, "pair", "grey"),
                          velocities=getattr(args, "velocities", None), tracker_options=options,
                          progress_factory=lambda total, desc: make_progress(total, desc, args.quiet))


def add_rerun_arguments(parser) -> None:
    """``--rerun FILE.rrd`` and ``--rerun-spawn``: a 3D view of the run (vislam.tools.rerun_view)."""
    group = parser.add_argument_group(
        "3D viewer", "Record the run frame by frame for the Rerun viewer (needs rerun-sdk: "
        "pip install 'vislam[viewer]'): pose, covariance, camera frustum, landmarks, map, per-frame statistics.")
    group.add_argument("--rerun", metavar="FILE.rrd",
                       help="write a Rerun recording (open it with `rerun FILE.rrd`); written, atomically, after "
                       "the other outputs")
    group.add_argument("--rerun-spawn", action="store_true",
                       help="also stream the recording to a live Rerun viewer (skipped with a warning when no "
                       "viewer or display is available)")


def record_frame(recorder, sequence):
    """The ``on_frame`` callback that records, live, each frame a stepwise filter
    finishes: its pose and covariance, the landmarks in the state now, those frozen in
    the step, the frame's statistics (or None without a recorder)."""
    if recorder is None:
        return None
    timestamps = sequence.timestamps_s
    from vislam.core.lie import se3_inverse

    def on_frame(f, processed) -> None:
        for i, (t, imu_T_world, cov, fs) in enumerate(processed):
            last = i == len(processed) - 1
            stats = fs.to_dict()
            stats.pop("frame", None)
            frozen = f.last_frozen if last else (None, None, None)
            recorder.log_frame(t, float(timestamps[t]), se3_inverse(imu_T_world), cov, f.live_landmark_ids,
                               f.live_p_lm_in_world, *frozen, stats=stats)

    return on_frame


def open_rerun_recorder(args, sequence):
    """The :class:`~vislam.tools.rerun_view.RerunRecorder` of ``--rerun``/``--rerun-spawn``, or
    None. Opened before the run, so a missing rerun-sdk or an unwritable path fails first."""
    if not (getattr(args, "rerun", None) or getattr(args, "rerun_spawn", False)):
        return None
    from vislam.tools.rerun_view import RerunRecorder

    return RerunRecorder(sequence.camera, sequence.cam_T_imu, path=args.rerun or None, spawn=args.rerun_spawn,
                         recording_name=f"{sequence.name} ({args.mode})")


def add_filter_arguments(parser, common=None) -> None:
    """``--config``, ``--auto``, ``--robust`` and the filter's own options (shared by run
    and compare). The most used (--config, --velocity-noise, --angular-noise, --auto) go
    to ``common`` (default: the parser itself), the others to one argument group per
    component of FilterOptions (noise model, gating and rejection, ...)."""
    common = parser if common is None else common
    common.add_argument("--config", metavar="FILE",
                        help="filter options file (.yaml/.yml/.toml): a mapping of FilterOptions names (flat, or "
                        "nested by group) to values")
    common.add_argument("--velocity-noise", type=float, metavar="MPS",
                        help="the filter's 1-sigma error of one linear-velocity sample per axis, m/s (default 0.02; "
                        "the dense datasets need about 0.5)")
    common.add_argument("--angular-noise", type=float, metavar="RADPS",
                        help="the filter's 1-sigma error of one angular-velocity sample per axis, rad/s (default "
                        "0.0003; the dense datasets need about 0.05)")
    common.add_argument("--auto", action="store_true",
                        help="run `vislam check` on the data first and use its suggestions (noise per axis, gyro "
                        "bias, IMU-camera rotation, velocity association, time offset) as the base of the options, "
                        "below --config and the flags; recorded in summary.json under \"auto\"")
    noise = _component_group(parser, "noise")
    noise.add_argument("--pixel-noise", type=float, metavar="PX",
                       help="1-sigma error of one pixel coordinate of a stereo observation (default 2.0)")
    gating = _component_group(parser, "gating")
    gating.add_argument("--gate", type=_probability_or_off, metavar="PROB",
                        help="chi-square gate probability of the stereo innovation, or 'off' (default 0.95)")
    gating.add_argument("--robust", action="store_true",
                        help="preset for scenes with moving traffic: "
                        + ", ".join(f"{k}={v}" for k, v in ROBUST_PRESET.items()))
    update = _component_group(parser, "update")
    update.add_argument("--ekf", choices=EKF_VARIANTS,
                        help="oc: observability-constrained EKF (default); standard: the report's equations")
    landmarks = _component_group(parser, "landmarks")
    landmarks.add_argument("--keep-all-landmarks", action="store_true", default=None,
                           help="keep every landmark in the SLAM state (the report's variant; slower)")
    imu_error = _component_group(parser, "imu_error")
    imu_error.add_argument("--imu-bias-sigma", type=_bias_sigmas, metavar="MPS,RADPS",
                           help="SLAM: estimate a slowly varying error of the velocity samples (IMU-error state, a "
                           "Gauss-Markov process) with these stationary 1-sigma values, m/s and rad/s (default 0,0: "
                           "off)")
    imu_error.add_argument("--imu-bias-time-constant", type=float, metavar="S",
                           help="correlation time of the IMU-error state, s (default 5)")
    _note_option_names(parser)


def add_noise_injection_arguments(parser) -> None:
    """The ``--add-*`` flags: noise injected into the data after loading (shared by run and compare)."""
    group = parser.add_argument_group(
        "noise injection", "The report's 'artificially increased noise': added to the data after loading, seeded, "
        "recorded in summary.json under \"injected_noise\". The filter's noise model is a separate setting "
        "(--velocity-noise etc.).")
    group.add_argument("--add-velocity-noise", type=float, metavar="MPS",
                       help="add white Gaussian noise to every linear-velocity sample, 1-sigma per axis, m/s")
    group.add_argument("--add-angular-noise", type=float, metavar="RADPS",
                       help="add white Gaussian noise to every angular-velocity sample, 1-sigma per axis, rad/s")
    group.add_argument("--add-velocity-bias", metavar="X,Y,Z",
                       help="add a constant bias to every linear-velocity sample, m/s in the IMU frame")
    group.add_argument("--add-angular-bias", metavar="X,Y,Z",
                       help="add a constant bias to every angular-velocity sample, rad/s in the IMU frame")
    group.add_argument("--add-pixel-noise", type=float, metavar="PX",
                       help="add white Gaussian noise to every pixel coordinate of every observation, 1-sigma, px")
    group.add_argument("--add-outliers", type=float, metavar="FRACTION",
                       help="replace this share of the observations, in [0, 1), by gross outliers")
    group.add_argument("--noise-seed", type=int, metavar="N", help="seed of the injected noise (default 0)")


def add_ground_truth_arguments(parser, common=None) -> None:
    """``--gt``, ``--gt-format``, ``--gt-frame``: evaluate in the same run (shared by run and
    compare); ``--gt`` goes to ``common`` when given (run's first group)."""
    group = parser.add_argument_group(
        "evaluation against ground truth", "Evaluate in the same run: writes metrics.json and "
        "error_over_distance.png next to the other outputs and the metrics into summary.json under \"evaluation\".")
    (group if common is None else common).add_argument(
        "--gt", metavar="FILE", help="ground-truth trajectory file: evaluate in the same run (metrics.json, "
        "error_over_distance.png)")
    group.add_argument("--gt-format", choices=GT_FORMATS, default="kitti",
                       help="kitti: line i = frame i; tum: timestamped, matched by time (default: kitti)")
    group.add_argument("--gt-frame", choices=GT_FRAME_CHOICES, default="auto",
                       help="body frame of the ground-truth poses: cam (left camera, converted to the IMU with the "
                       "dataset's cam_T_imu) or imu. auto (default): the format's convention: kitti -> cam (KITTI "
                       "ground truth holds left-camera poses, as groundtruth/*.txt of the shared data and "
                       "groundtruth.kitti of vislam simulate), tum -> imu (TUM has no body-frame convention; "
                       "vislam's TUM files hold IMU poses)")


#: argparse dest of the noise-injection flags -> (NoiseSpec field, flag)
NOISE_FLAGS = {
    "add_velocity_noise": ("velocity_noise_mps", "--add-velocity-noise"),
    "add_angular_noise": ("angular_noise_radps", "--add-angular-noise"),
    "add_velocity_bias": ("velocity_bias_mps", "--add-velocity-bias"),
    "add_angular_bias": ("angular_bias_radps", "--add-angular-bias"),
    "add_pixel_noise": ("pixel_noise_px", "--add-pixel-noise"),
    "add_outliers": ("outlier_fraction", "--add-outliers"),
    "noise_seed": ("seed", "--noise-seed"),
}


def _vector3(text: str, flag: str) -> tuple[float, float, float]:
    values = _comma_numbers(text)
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{flag}: expected three finite numbers X,Y,Z (e.g. 0.1,0,0), got {text!r}")
    return values


def noise_spec_from_args(args):
    """The :class:`~vislam.core.noise.NoiseSpec` of the ``--add-*`` flags, or None when
    none is given (``--noise-seed`` alone adds nothing). A ConfigError names the flag."""
    from vislam.core.noise import NoiseSpec

    given = {dest: getattr(args, dest, None) for dest in NOISE_FLAGS}
    if all(value is None for dest, value in given.items() if dest != "noise_seed"):
        return None
    values = {}
    for dest, value in given.items():
        if value is not None:
            field, flag = NOISE_FLAGS[dest]
            values[field] = _vector3(value, flag) if dest.endswith("_bias") else value
    try:
        return NoiseSpec(**values)
    except ConfigError as exc:
        message = str(exc)
        for field, flag in NOISE_FLAGS.values():
            message = re.sub(rf"\b{re.escape(field)}\b", flag, message)
        raise ConfigError(message) from None


def ground_truth_from_args(args, sequence):
    """``(TrajectoryFile, info)`` of ``--gt`` checked against ``sequence``, or ``(None, None)``.

    ``--gt-frame auto`` follows the format's convention (KITTI: left camera, TUM: IMU);
    camera poses are checked against the dataset now and converted, after the run, with
    the ``cam_T_imu`` the filter used (:func:`vislam.tools.comparison.evaluate_run`).
    ``info`` (summary.json's ``evaluation.ground_truth``) records the frame used, what was
    asked for and where ``cam_T_imu`` comes from.
    """
    if not getattr(args, "gt", None):
        return None, None
    from vislam.tools.comparison import load_run_ground_truth
    from vislam.tools.evaluation import resolve_ground_truth_frame

    conversion = resolve_ground_truth_frame(args.gt_format, args.gt_frame, cam_T_imu=sequence.cam_T_imu,
                                            cam_T_imu_source=f"dataset {sequence.source or sequence.name}",
                                            ground_truth_path=args.gt)
    gt = load_run_ground_truth(args.gt, sequence, args.gt_format, conversion.frame)
    source = ("calibration.cam_T_imu of this run (the transform the filter used)" if conversion.frame == "cam"
              else None)
    info = {"path": str(Path(args.gt).resolve()), "format": args.gt_format, "frame": conversion.frame,
            "frame_requested": args.gt_frame, "cam_T_imu_source": source}
    return gt, info


def options_from_args(args, suggestions=None):
    """FilterOptions of defaults < ``suggestions`` (``--auto``) < --config < --robust < flags."""
    from vislam.tools.config import resolve_options

    overrides = dict(ROBUST_PRESET) if getattr(args, "robust", False) else {}
    flag_names = {field: "--robust" for field in overrides}
    for dest, (field, flag) in FLAG_FIELDS.items():
        value = getattr(args, dest, None)
        if value is not None:
            overrides[field] = value
            flag_names[field] = flag
    sigmas = getattr(args, "imu_bias_sigma", None)
    if sigmas is not None:
        for field, value in zip(("imu_bias_sigma_mps", "imu_bias_sigma_radps"), sigmas):
            overrides[field] = value
            flag_names[field] = "--imu-bias-sigma"
    return resolve_options(args.config, overrides, flag_names, base=suggestions)


def auto_options(args, sequence, quiet: bool):
    """``--auto``: (options, summary entry) from ``vislam check``'s suggestions on ``sequence``
    (:func:`vislam.tools.auto.auto_check`; the findings that are not OK on stderr)."""
    from vislam.tools.auto import auto_check, findings_to_print

    from vislam.cli import say_phase

    say_phase(f"--auto: checking {sequence.name} (noise, biases, conventions, calibration; vislam check)", quiet)
    record = auto_check(sequence)
    options = options_from_args(args, record["suggested"])
    if not quiet:
        for line in findings_to_print(record):
            print(line, file=sys.stderr)
    return options, record


def make_progress(total: int, desc: str, quiet: bool):
    """(callback, close) of a tqdm bar on stderr — only on a terminal and not quiet."""
    if quiet or not sys.stderr.isatty():
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True, leave=False)

    def progress(done: int) -> None:
        bar.update(done - bar.n)

    def phase(text: str) -> None:
        """A phase after the frames (e.g. the smoother's refinement): the bar says it."""
        bar.set_description_str(f"{desc}: {text}")
        bar.refresh()

    progress.phase = phase
    return progress, bar.close


def _seconds(x) -> str:
    return "n/a" if x is None else f"{x:.2f} s"


def format_summary(s: dict, out_dir) -> str:
    """The short human summary printed at the end of ``vislam run`` / ``vislam demo``."""
    from vislam.tools.outputs import MODE_TITLES

    ds = s["dataset"]
    frames = f"{s['frames_processed']}" + (f" of {s['frames']}" if s["frames_processed"] != s["frames"] else "")
    title = MODE_TITLES.get(s["mode"], s["mode"])
    if s["mode"] == "smoother" and (s.get("options") or {}).get("refine"):
        title += " + batch refinement"  # the method actually run
    lines = [f"{ds.get('name')}: {title}" + (" (PARTIAL)" if s["partial"] else ""),
             f"frames:        {frames} ({s['duration_s']:.1f} s of recording)"]
    if s["mode"] != "localization":
        lines.append(f"landmarks:     {s['landmarks_in_map']} in the map ({s['landmarks_rejected']} rejected), "
                     f"{s['landmarks_initialized']} initialized")
        lines.append(f"observations:  {s['observations_used']} used, {s['observations_gated']} gated, "
                     f"{s['observations_repeated']} repeated")
    rtf = s.get("real_time_factor")
    speed = f"real-time factor {rtf:.3g}, {1 / rtf:.0f}x faster than real time" if rtf else "real-time factor n/a"
    per_frame = ""
    if s.get("frame_ms_median") is not None:
        per_frame = f"; per frame median {s['frame_ms_median']:.2f} ms, p95 {s['frame_ms_p95']:.2f} ms"
    lines.append(f"filter time:   {_seconds(s['filter_seconds'])} ({speed}{per_frame})")
    lines.append(f"total time:    {_seconds(s.get('total_seconds'))}")
    gt = s.get("ground_truth")
    if gt:
        ate = gt["ate_m"]

        def m(x):
            return "n/a" if x is None else f"{x:.2f} m"

        lines.append(f"ATE:           SLAM {m(ate['slam'])}, localization {m(ate['localization'])} "
                     "(SE(3)-aligned RMSE vs ground truth)")
    ev = s.get("evaluation")
    if ev:
        lines.append(format_evaluation_line(ev))
    lines.append(f"outputs:       {out_dir}/ ({', '.join(s['outputs'])})")
    return "\n".join(lines)


def format_evaluation_line(ev: dict) -> str:
    """The ATE line of a summary's "evaluation" entry."""

    def num(x, spec, unit=""):
        return "n/a" if x is None or not math.isfinite(x) else f"{x:{spec}}{unit}"

    if ev.get("cam_ape_rmse_m") is None and ev.get("cam_kitti_t_pct") is None:  # IMU ground truth
        return (f"ATE:           {num(ev.get('ape_rmse_m'), '.3f', ' m')} (SE(3)-aligned RMSE vs ground truth, "
                f"{ev.get('n_frames_compared')} frames); KITTI {num(ev.get('kitti_t_pct'), '.2f', ' %')}, "
                f"{num(ev.get('kitti_r_deg_per_100m'), '.3f', ' deg/100 m')}")
    return (f"ATE:           camera {num(ev.get('cam_ape_rmse_m'), '.3f', ' m')}, IMU "
            f"{num(ev.get('ape_rmse_m'), '.3f', ' m')} (SE(3)-aligned RMSE vs ground truth, "
            f"{ev.get('n_frames_compared')} frames; camera: the left-camera poses with the calibration used vs the "
            f"ground truth as it is; IMU: vs the ground truth converted with that calibration)\n"
            f"KITTI:         camera {num(ev.get('cam_kitti_t_pct'), '.2f', ' %')}, "
            f"{num(ev.get('cam_kitti_r_deg_per_100m'), '.3f', ' deg/100 m')}; IMU "
            f"{num(ev.get('kitti_t_pct'), '.2f', ' %')}, {num(ev.get('kitti_r_deg_per_100m'), '.3f', ' deg/100 m')}")


def _print(text: str) -> None:
    try:
        print(text, flush=True)
    except BrokenPipeError:  # e.g. `vislam run ... | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def interrupted_message(command: str, stage) -> str:
    if stage.committed:
        return f"vislam {command}: interrupted; all outputs had been written to {stage.out_dir}"
    return f"vislam {command}: interrupted; no output written (nothing changed in {stage.out_dir})"


def run(args) -> int:
    from vislam.core.estimators import run as run_estimator
    from vislam.core.results import run_warnings
    from vislam.tools.comparison import evaluate_run, injected_noise_record, stage_evaluation
    from vislam.tools.config import load_known_poses
    from vislam.tools.outputs import OutputStage, display_name, method_title, process_start_time, write_run_outputs

    start_time = process_start_time() or _COMMAND_START
    for flag, given, needs in (("--poses", bool(args.poses), "mapping"), ("--refine", bool(args.refine), "smoother"),
                               ("--imu-bias-sigma", args.imu_bias_sigma is not None, "slam"),
                               ("--imu-bias-time-constant", args.imu_bias_time_constant is not None, "slam")):
        if given and args.mode != needs:
            raise ConfigError(f"{flag} is only used by --mode {needs} (got --mode {args.mode})")
    options = options_from_args(args)
    noise = noise_spec_from_args(args)
    sequence, tracking = load_data(args, args.out)
    poses = load_known_poses(args.poses, sequence) if args.poses else None
    gt, gt_info = ground_truth_from_args(args, sequence)  # checked before any work
    dataset = {"name": sequence.name, "path": str(Path(args.data).resolve()), "frames": sequence.n_frames,
               "landmarks": sequence.n_landmarks, "duration_s": sequence.duration_s,
               "cam_T_imu": sequence.cam_T_imu.tolist()}
    if tracking is not None:
        dataset["tracking"] = {k: tracking[k] for k in ("source", "layout", "cache", "cache_reused")}
    if args.mode == "mapping":
        dataset["poses"] = str(Path(args.poses).resolve()) if args.poses else "localization"
    extra = {}
    if noise is not None:
        from vislam.core.noise import inject_noise
        from vislam.tools.comparison import describe_noise

        sequence, info = inject_noise(sequence, noise)
        # ASCII: the label also goes into the PLY header
        dataset["label"] = f"{sequence.name} + noise ({describe_noise(noise, seed=False, ascii=True)})"
        extra["injected_noise"] = injected_noise_record(noise, info)
    if getattr(args, "auto", False):  # check what the filter will see (with any injected noise)
        options, extra["auto"] = auto_options(args, sequence, args.quiet)
    if options.has_data_corrections:
        from vislam.core.corrections import apply_corrections

        sequence = apply_corrections(sequence, options)  # a no-op if the estimators apply them again

    stage = OutputStage(args.out)
    close, recorder = (lambda: None), None
    try:
        with stage:
            recorder = open_rerun_recorder(args, sequence)
            progress, close = make_progress(sequence.n_frames, args.mode, args.quiet)
            try:
                result = run_estimator(sequence, args.mode, options, progress=progress, world_T_imu=poses,
                                       on_frame=record_frame(recorder, sequence))
            finally:
                close()
            extra["warnings"] = run_warnings(result)
            if "timing" in result.extra:  # smoother: its own timings and those of refine
                extra["timing"] = result.extra["timing"]
            gt_poses = None
            if gt is not None:
                evaluation = evaluate_run(result, gt, sequence)
                gt_poses = evaluation.gt_world_T_imu  # drawn in the figure
                extra["evaluation"] = stage_evaluation(
                    stage.staging, evaluation, f"{display_name(dataset)} — {method_title(result)} vs ground truth",
                    ground_truth=gt_info)
            summary = write_run_outputs(stage, result, dataset=dataset, duration_s=sequence.duration_s,
                                        start_time=start_time, extra=extra, ground_truth=gt_poses)
        if recorder is not None:
            recorder.close()  # the .rrd appears only after the other outputs
    except BaseException as exc:
        if recorder is not None:
            recorder.abort()
        if not isinstance(exc, KeyboardInterrupt):
            raise
        close()
        print(interrupted_message("run", stage), file=sys.stderr)
        return 130
    try:
        return finish(summary, result, stage, args.quiet)
    finally:
        if recorder is not None and recorder.path is not None and not args.quiet:
            _print(f"rerun:         {recorder.path} (open it with: rerun {recorder.path})")


def finish(summary: dict, result, stage, quiet: bool) -> int:
    """Print the human summary (unless quiet); a partial run is an error (one line)."""
    if not quiet:
        _print(format_summary(summary, stage.out_dir))
        for warning in summary.get("warnings") or ():
            print(f"vislam: warning: {warning}", file=sys.stderr)
    if result.partial:
        raise EstimationError(f"{result.error}; stopped after {result.stats.frames_processed} of "
                              f"{result.stats.frames} frames; partial outputs written to {stage.out_dir} "
                              f"(summary.json: \"partial\": true)")
    return 0
