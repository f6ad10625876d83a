"""``vislam run DATA --mode MODE --out DIR``: run one of the report's estimators on a dataset.

Options: defaults of :class:`~vislam.core.options.FilterOptions` < ``--config FILE``
(YAML/TOML) < ``--robust`` < the other flags (:func:`vislam.tools.config.resolve_options`).
The estimator is :func:`vislam.core.estimators.run`; the files are written, all or
nothing, by :func:`vislam.tools.outputs.write_run_outputs`. This module parses, calls
and prints.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from vislam.core.options import EKF_VARIANTS, MODES, ROBUST_PRESET
from vislam.errors import ConfigError, EstimationError

__all__ = ["register", "run", "format_summary", "make_progress", "finish", "interrupted_message", "FLAG_FIELDS"]

_COMMAND_START = time.time()

#: argparse dest -> (FilterOptions field, flag)
FLAG_FIELDS = {
    "velocity_noise": ("velocity_noise_mps", "--velocity-noise"),
    "angular_noise": ("angular_noise_radps", "--angular-noise"),
    "pixel_noise": ("pixel_noise_px", "--pixel-noise"),
    "gate": ("gating_probability", "--gate"),
    "ekf": ("ekf", "--ekf"),
    "keep_all_landmarks": ("keep_all_landmarks", "--keep-all-landmarks"),
}


def _probability_or_off(text: str):
    if text.strip().lower() in ("off", "none"):
        return "none"
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a probability in (0, 1) or 'off', got {text!r}") from None


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run IMU localization, landmark mapping or SLAM on a dataset",
        description="Run one of the report's estimators on a dataset (.npz) and write DIR/trajectory.tum, "
        "DIR/trajectory.kitti, DIR/trajectory.png, DIR/summary.json and, for mapping and SLAM, "
        "DIR/landmarks.ply and DIR/landmarks.npz. Outputs appear all together or not at all. Options: "
        "defaults < --config FILE < --robust < the other flags.",
    )
    parser.add_argument("data", metavar="DATA", help="dataset file (.npz)")
    parser.add_argument("--mode", choices=MODES, default="slam",
                        help="localization (IMU only), mapping (landmarks from known poses) or slam (default: slam)")
    parser.add_argument("--out", metavar="DIR", required=True, help="output directory (created if needed)")
    parser.add_argument("--config", metavar="FILE",
                        help="filter options file (.yaml/.yml/.toml): a mapping of FilterOptions field names")
    noise = parser.add_argument_group("filter options (override --config)")
    noise.add_argument("--velocity-noise", type=float, metavar="MPS",
                       help="1-sigma error of one linear-velocity sample per axis, m/s (default 0.02; the dense "
                       "datasets need about 0.5)")
    noise.add_argument("--angular-noise", type=float, metavar="RADPS",
                       help="1-sigma error of one angular-velocity sample per axis, rad/s (default 0.0003; the "
                       "dense datasets need about 0.05)")
    noise.add_argument("--pixel-noise", type=float, metavar="PX",
                       help="1-sigma error of one pixel coordinate of a stereo observation (default 2.0)")
    noise.add_argument("--gate", type=_probability_or_off, metavar="PROB",
                       help="chi-square gate probability of the stereo innovation, or 'off' (default 0.95)")
    noise.add_argument("--ekf", choices=EKF_VARIANTS,
                       help="oc: observability-constrained EKF (default); standard: the report's equations")
    noise.add_argument("--keep-all-landmarks", action="store_true", default=None,
                       help="keep every landmark in the SLAM state (the report's variant; slower)")
    noise.add_argument("--robust", action="store_true",
                       help="preset for scenes with moving traffic: "
                       + ", ".join(f"{k}={v}" for k, v in ROBUST_PRESET.items()))
    parser.add_argument("--poses", metavar="FILE",
                        help="mapping only: known world_T_imu poses, TUM or KITTI, one per frame (default: the "
                        "localization trajectory)")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    parser.set_defaults(func=run)


def options_from_args(args):
    from vislam.tools.config import resolve_options

    overrides = dict(ROBUST_PRESET) if getattr(args, "robust", False) else {}
    flag_names = {field: "--robust" for field in overrides}
    for dest, (field, flag) in FLAG_FIELDS.items():
        value = getattr(args, dest, None)
        if value is not None:
            overrides[field] = value
            flag_names[field] = flag
    return resolve_options(args.config, overrides, flag_names)


def make_progress(total: int, desc: str, quiet: bool):
    """(callback, close) of a tqdm bar on stderr — only on a terminal and not quiet."""
    if quiet or not sys.stderr.isatty():
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True, leave=False)

    def progress(done: int) -> None:
        bar.update(done - bar.n)

    return progress, bar.close


def _seconds(x) -> str:
    return "n/a" if x is None else f"{x:.2f} s"


def format_summary(s: dict, out_dir) -> str:
    """The short human summary printed at the end of ``vislam run`` / ``vislam demo``."""
    from vislam.tools.outputs import MODE_TITLES

    ds = s["dataset"]
    frames = f"{s['frames_processed']}" + (f" of {s['frames']}" if s["frames_processed"] != s["frames"] else "")
    lines = [f"{ds.get('name')}: {MODE_TITLES.get(s['mode'], s['mode'])}" + (" (PARTIAL)" if s["partial"] else ""),
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
    lines.append(f"outputs:       {out_dir}/ ({', '.join(s['outputs'])})")
    return "\n".join(lines)


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
    from vislam.tools.config import load_known_poses
    from vislam.tools.dataset_io import load_sequence
    from vislam.tools.outputs import OutputStage, process_start_time, write_run_outputs

    start_time = process_start_time() or _COMMAND_START
    if args.poses and args.mode != "mapping":
        raise ConfigError(f"--poses is only used by --mode mapping (got --mode {args.mode})")
    options = options_from_args(args)
    data = Path(args.data)
    sequence = load_sequence(data)
    poses = load_known_poses(args.poses, sequence) if args.poses else None
    dataset = {"name": sequence.name, "path": str(data.resolve()), "frames": sequence.n_frames,
               "landmarks": sequence.n_landmarks, "duration_s": sequence.duration_s}
    if args.mode == "mapping":
        dataset["poses"] = str(Path(args.poses).resolve()) if args.poses else "localization"

    stage = OutputStage(args.out)
    progress, close = None, lambda: None
    try:
        with stage:
            progress, close = make_progress(sequence.n_frames, args.mode, args.quiet)
            try:
                result = run_estimator(sequence, args.mode, options, progress=progress, world_T_imu=poses)
            finally:
                close()
            summary = write_run_outputs(stage, result, dataset=dataset, duration_s=sequence.duration_s,
                                        start_time=start_time)
    except KeyboardInterrupt:
        close()
        print(interrupted_message("run", stage), file=sys.stderr)
        return 130
    return finish(summary, result, stage, args.quiet)


def finish(summary: dict, result, stage, quiet: bool) -> int:
    """Print the human summary (unless quiet); a partial run is an error (one line)."""
    if not quiet:
        _print(format_summary(summary, stage.out_dir))
    if result.partial:
        raise EstimationError(f"{result.error}; stopped after {result.stats.frames_processed} of "
                              f"{result.stats.frames} frames; partial outputs written to {stage.out_dir} "
                              f"(summary.json: \"partial\": true)")
    return 0
