"""Pieces of the command line shared by several commands: common flags (filter options,
noise injection, ground truth, image-folder sources, the Dask engine), reading DATA, the
progress bar, the end-of-run summary and the interrupt messages.

The commands import them from here, never from one another, so that running one command
imports only its own module and this one (see :data:`vislam.cli.COMMANDS`).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import signal
import sys
from pathlib import Path

from vislam.errors import ConfigError, EstimationError
from vislam.signals import replaced_handler

__all__ = [
    "FLAG_FIELDS", "load_data", "add_filter_arguments", "add_noise_injection_arguments",
    "add_ground_truth_arguments", "NOISE_FLAGS", "noise_spec_from_args", "ground_truth_from_args", "pair_ground_truth",
    "known_poses_from_args", "reference_poses_from_args",
    "options_from_args", "auto_options", "make_progress", "format_summary", "format_evaluation_line",
    "interrupted_message", "finish", "configure_dask_logging", "add_engine_arguments",
    "terminate_as_interrupt", "add_source_arguments", "tracker_options_from_args", "TRACKER_FLAGS",
]

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
    from vislam.errors import OutputError
    from vislam.tools.frontend_io import load_recording

    if cache_dir is not None and Path(cache_dir).exists() and not Path(cache_dir).is_dir():  # before the tracking
        raise OutputError(f"{cache_dir}: exists and is not a directory (an output directory is expected)")

    options = tracker_options_from_args(getattr(args, "tracker_config", None))
    return load_recording(args.data, cache_dir, pair=getattr(args, "pair", "grey"),
                          velocities=getattr(args, "velocities", None), tracker_options=options,
                          progress_factory=lambda total, desc: make_progress(total, desc, args.quiet))

def tracking_warnings(info) -> list[str]:
    """The tracker's warnings of what :func:`load_data` returned with the sequence (none for an npz)."""
    return list((info or {}).get("statistics", {}).get("warnings", []))


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


def add_filter_arguments(parser, common=None) -> None:
    """``--config``, ``--auto``, ``--robust`` and the filter's own options (shared by run
    and compare). The most used (--config, --velocity-noise, --angular-noise, --auto) go
    to ``common`` (default: the parser itself), the others to one argument group per
    component of FilterOptions (noise model, gating and rejection, ...)."""
    from vislam.core.options import EKF_VARIANTS, ROBUST_PRESET  # numpy: only for the commands with these flags

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
    from vislam.tools.trajectory_io import GT_FORMAT_CHOICES, GT_FRAME_CHOICES

    group = parser.add_argument_group(
        "evaluation against ground truth", "Evaluate in the same run: writes metrics.json and "
        "error_over_distance.png next to the other outputs and the metrics into summary.json under \"evaluation\".")
    (group if common is None else common).add_argument(
        "--gt", metavar="FILE", help="ground-truth trajectory file: evaluate in the same run (metrics.json, "
        "error_over_distance.png)")
    group.add_argument("--gt-format", choices=GT_FORMAT_CHOICES, default="auto",
                       help="kitti: line i = frame i; tum: timestamped, matched by time; auto (default): the one "
                       "the file's values per line say (12: kitti, 8: tum)")
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

def ground_truth_from_args(args, sequence, pair: bool = True):
    """``(TrajectoryFile, info)`` of ``--gt`` checked against ``sequence``, or ``(None, None)``.

    ``pair=False`` reads and checks the file only; :func:`pair_ground_truth` then checks
    that it covers the frames the filter will see (after the data corrections: a
    ``timestamp_scale`` changes the frame times a TUM ground truth is matched with).

    ``--gt-frame auto`` follows the format's convention (KITTI: left camera, TUM: IMU);
    camera poses are checked against the dataset now and converted, after the run, with
    the ``cam_T_imu`` the filter used (:func:`vislam.tools.comparison.evaluate_run`).
    ``info`` (summary.json's ``evaluation.ground_truth``) records the frame used, what was
    asked for and where ``cam_T_imu`` comes from.
    """
    if not getattr(args, "gt", None):
        return None, None
    from vislam.tools.comparison import ground_truth_pairs
    from vislam.tools.evaluation import load_ground_truth, resolve_ground_truth_frame
    from vislam.tools.trajectory_io import resolve_gt_format

    fmt = resolve_gt_format(args.gt, args.gt_format)
    source = f"dataset {sequence.source or sequence.name}"
    conversion = resolve_ground_truth_frame(fmt, args.gt_frame, cam_T_imu=sequence.cam_T_imu,
                                            cam_T_imu_source=source, ground_truth_path=args.gt)
    gt = load_ground_truth(args.gt, fmt, conversion.frame, sequence.cam_T_imu, cam_T_imu_source=source)
    if pair:
        ground_truth_pairs(gt, sequence)
    source = ("calibration.cam_T_imu of this run (the transform the filter used)" if conversion.frame == "cam"
              else None)
    info = {"path": str(Path(args.gt).resolve()), "format": fmt, "frame": conversion.frame,
            "frame_requested": args.gt_frame, "cam_T_imu_source": source}
    return gt, info


def _matched_to_frames(check, exc_types, sequence, options, auto_pending: bool):
    """``check(seen)`` of the frames the filter will see (``apply_corrections``: a
    ``timestamp_scale`` changes the frame times); a failure names the fix when the frame
    times are not in seconds — or, with ``auto_pending`` (``--auto``, whose check may
    scale them, has not run yet), returns ``(None, False)`` for the caller to check again
    after it. Else ``(check's value, True)``."""
    from vislam.core.corrections import apply_corrections

    seen = apply_corrections(sequence, options)  # (sequence itself without corrections)
    try:
        return check(seen), True
    except exc_types as exc:
        from vislam.core.sequence import frame_times_not_seconds

        odd = frame_times_not_seconds(seen.timestamps_s)
        if odd is None:
            raise
        if auto_pending:
            return None, False
        interval, unit = odd
        if unit is None:
            raise
        raise type(exc)(f"{exc}; the recording's frames are {interval:.4g} apart: with time stamps in {unit[1]}, "
                        f"run with --auto or with timestamp_scale {unit[0]:g} in a --config file") from None


def pair_ground_truth(gt, sequence, options, auto_pending: bool = False) -> bool:
    """Check that the ground truth ``gt`` (of :func:`ground_truth_from_args` with
    ``pair=False``; None: nothing to check) has a pose for at least 2 of the frames the
    filter will see (:func:`_matched_to_frames`: time stamps in ns with ``timestamp_scale:
    1e-9`` are matched in seconds); GroundTruthError otherwise. With ``auto_pending``
    see :func:`_matched_to_frames`: False means "check again after --auto's check"."""
    if gt is None:
        return True
    from vislam.errors import GroundTruthError
    from vislam.tools.comparison import ground_truth_pairs

    return _matched_to_frames(lambda seen: ground_truth_pairs(gt, seen), GroundTruthError, sequence, options,
                              auto_pending)[1]


def known_poses_from_args(args, sequence, options, auto_pending: bool = False):
    """``(poses, done)``: the (T, 4, 4) world_T_imu of ``--poses`` (None without it)
    matched with the frames the filter will see (:func:`_matched_to_frames`); ``done`` False with
    ``auto_pending`` when they may match only after --auto's check (see
    :func:`_matched_to_frames`)."""
    if not getattr(args, "poses", None):
        return None, True
    from vislam.tools.config import load_known_poses

    return _matched_to_frames(lambda seen: load_known_poses(args.poses, seen), ConfigError, sequence, options,
                              auto_pending)


def reference_poses_from_args(args, sequence, options, auto: bool):
    """``(poses, gt, gt_info, recheck)``: ``--poses`` and ``--gt``, read and matched with the
    frames the filter will see (after --config's ``timestamp_scale``) before any work;
    ``recheck``: match them again (:func:`pair_ground_truth`, :func:`known_poses_from_args`)
    after --auto's check, which may scale frame times that are not in seconds."""
    poses, poses_matched = known_poses_from_args(args, sequence, options, auto_pending=auto)
    gt, gt_info = ground_truth_from_args(args, sequence, pair=False)  # the file itself
    paired = pair_ground_truth(gt, sequence, options, auto_pending=auto)
    return poses, gt, gt_info, auto or not (paired and poses_matched)


def options_from_args(args, suggestions=None):
    """FilterOptions of defaults < ``suggestions`` (``--auto``) < --config < --robust < flags."""
    from vislam.core.options import ROBUST_PRESET
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

def _times_real_time(rtf: float) -> str:
    """``"34x faster than real time"`` for a real-time factor (filter time / recording
    duration) of 0.029, ``"19x slower than real time"`` for 19.4."""
    factor = 1 / rtf if rtf < 1 else rtf
    text = f"{factor:.0f}" if factor >= 10 else f"{factor:.1f}"
    return f"{text}x {'faster' if rtf < 1 else 'slower'} than real time"


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
    speed = f"real-time factor {rtf:.3g}, {_times_real_time(rtf)}" if rtf else "real-time factor n/a"
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

#: argparse dest of ``vislam track``'s flags -> TrackerOptions field
TRACKER_FLAGS = {"features": "target_features", "min_track_length": "min_track_length"}


def add_source_arguments(parser) -> None:
    """Flags of an image-folder SOURCE (shared with run/check/compare/report)."""
    group = parser.add_argument_group("image folders (SOURCE a folder instead of an .npz)")
    group.add_argument("--pair", choices=("grey", "colour"), default="grey",
                       help="KITTI raw: the grey (image_00/01, default) or colour (image_02/03) pair")
    group.add_argument("--velocities", metavar="CSV",
                       help="EuRoC: IMU velocities t,vx,vy,vz,wx,wy,wz (s, m/s, rad/s, IMU frame), interpolated at "
                       "the image times (EuRoC's IMU gives accelerations, which the filters cannot use)")
    group.add_argument("--tracker-config", metavar="FILE", dest="tracker_config",
                       help="tracker options (YAML/TOML) when SOURCE is a folder")

def tracker_options_from_args(config_path, overrides: dict | None = None):
    """TrackerOptions of defaults < options file < flags (None values ignored)."""
    from vislam.core.tracking import TrackerOptions
    from vislam.tools.config import load_options_file

    values = {}
    if config_path is not None:
        values = load_options_file(config_path)
        TrackerOptions.from_dict(values, source=str(config_path))
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    if not given:
        return TrackerOptions.from_dict(values, source=str(config_path) if config_path else "options")
    try:
        return TrackerOptions.from_dict({**values, **given}, source="command line")
    except ConfigError as exc:
        message = str(exc)
        for dest, field in TRACKER_FLAGS.items():
            message = message.replace(field, "--" + dest.replace("_", "-"))
        raise ConfigError(message) from None

def configure_dask_logging(verbosity: int) -> None:
    """Dask's own log output: none by default (Dask logs every worker start and stop at
    INFO, and a worker that loses its scheduler while a local cluster shuts down at ERROR;
    what matters reaches the command through its tasks' results), errors and warnings
    with -v, everything with -vv. Set through the environment so that the local
    cluster's worker processes inherit it."""
    import logging
    import os

    level = "critical" if verbosity <= 0 else "warning" if verbosity == 1 else "info"
    os.environ["DASK_LOGGING__DISTRIBUTED"] = level
    if "distributed" in sys.modules:  # already imported: its logger is configured
        logging.getLogger("distributed").setLevel(level.upper())

def add_engine_arguments(parser, sequential_help: str | None = None) -> None:
    """``--scheduler``, ``--workers`` (and ``--sequential``) — shared by sweep and report."""
    group = parser.add_argument_group(
        "engine", "Runs go to a Dask cluster: by default a local one started (and stopped) by this command; "
        "--scheduler uses a running one (dask scheduler/dask worker by hand, dask-jobqueue, Kubernetes). Workers "
        "must import the same vislam and see the data files under the same paths.")
    group.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                       help="address of a running Dask scheduler (default: start a local cluster)")
    group.add_argument("--workers", type=int, metavar="N",
                       help="worker processes of the local cluster, one thread each (default: 2; ignored with "
                       "--scheduler)")
    group.add_argument("--sequential", action="store_true",
                       help=sequential_help or "run everything in this process, one run after the other (no Dask)")

@contextlib.contextmanager
def terminate_as_interrupt():
    """Treat SIGTERM like Ctrl-C for the block, so a killed command still stops its
    cluster and leaves its outputs consistent."""

    def handler(signum, frame):
        raise KeyboardInterrupt

    with replaced_handler(signal.SIGTERM, handler):
        yield
