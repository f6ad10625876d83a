"""``vislam compare DATA --out DIR``: localization + mapping ("separately"), SLAM, the
sliding-window smoother and its batch refinement, side by side.

Runs the ``--methods`` (default: all four) on the same data — with the noise of the
``--add-*`` flags injected once, seeded; with ``--auto`` after ``vislam check``'s
suggestions, as ``vislam run --auto`` — and writes, all or nothing, one folder per method
(``DIR/separate/``, ``DIR/slam/``, ``DIR/smoother/``, ``DIR/refine/``: the files of
``vislam run``), ``DIR/comparison.png`` (every trajectory and landmark set on one xy
figure with a side view, the report's Figs 7–9) and ``DIR/comparison.json``. The work is
:func:`vislam.tools.comparison.run_comparison` and
:func:`vislam.tools.comparison.write_comparison`; this module parses, calls and prints.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from vislam.cli.common import (
    _print,
    add_filter_arguments,
    auto_options,
    add_ground_truth_arguments,
    add_noise_injection_arguments,
    interrupted_message,
    make_progress,
    noise_spec_from_args,
    options_from_args,
    pair_ground_truth,
    reference_poses_from_args,
)
from vislam.errors import EstimationError

__all__ = ["register", "run", "format_comparison"]

#: The default of --methods (tools.comparison.DEFAULT_METHODS, without importing it here).
DEFAULT_METHODS = ("separate", "slam", "smoother", "refine")

_COMMAND_START = time.time()


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "compare",
        help="localization + mapping (separately), SLAM, the smoother and its refinement on the same data, "
        "one comparison figure",
        description="Run IMU localization + landmark mapping on its trajectory (the report's 'separately'), "
        "visual-inertial SLAM, the sliding-window smoother and the smoother with its batch refinement (--methods) "
        "on the same data, with the noise of the --add-* flags injected once (seeded), and write one folder per "
        "method (DIR/separate/, DIR/slam/, DIR/smoother/, DIR/refine/: the files of 'vislam run'), "
        "DIR/comparison.png (every trajectory and landmark set in the xy plane, with a side view; the report's "
        "Figs 7-9) and DIR/comparison.json (frames, landmarks, time per frame and, with --gt, the ATE and KITTI "
        "errors of each method). Outputs appear all together or not at all.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example (the report's Fig. 7 with numbers):\n"
        "  vislam compare ../shared/data/sparse/0027.npz --out cmp27 \\\n"
        "      --add-velocity-noise 0.3 --add-angular-noise 0.006 --velocity-noise 0.3 --angular-noise 0.006 \\\n"
        "      --gt ../shared/data/groundtruth/0027.txt   # KITTI ground truth: left-camera poses (the default)\n"
        "  vislam compare ../shared/data/dense/0027.npz --out cmp27d --auto \\\n"
        "      --gt ../shared/data/groundtruth/0027.txt   # noise and corrections from vislam check",
    )
    parser.add_argument("data", metavar="DATA", help="dataset file (.npz), or an image folder (tracked first, the "
                        "tracks cached as DIR/tracks.npz)")
    parser.add_argument("--out", metavar="DIR", required=True, help="output directory (created if needed)")
    parser.add_argument("--methods", metavar="LIST", default=",".join(DEFAULT_METHODS),
                        help="comma-separated methods to run: separate (localization + mapping), slam, smoother, "
                        "refine (smoother + batch refinement; one smoother run serves both), or all (default: "
                        "%(default)s; the smoother costs about 4x SLAM per frame, ~20 s on a dense drive, refine a "
                        "few s more: --methods separate,slam for the EKF alone)")
    add_filter_arguments(parser)
    add_noise_injection_arguments(parser)
    add_ground_truth_arguments(parser)
    from vislam.cli.common import add_source_arguments

    add_source_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    parser.set_defaults(func=run)


def _num(x, spec: str, unit: str = "") -> str:
    return "n/a" if x is None else f"{x:{spec}}{unit}"


def format_comparison(comparison, content: dict, out_dir) -> str:
    """The human summary printed by ``vislam compare`` (``content``: comparison.json's)."""
    from vislam.tools.comparison import describe_filter_noise, describe_noise

    from vislam.tools.auto import describe_suggestions
    from vislam.tools.comparison import METHOD_SHORT

    lines = [f"{comparison.label}: " + " vs ".join(METHOD_SHORT[k] for k in comparison.methods),
             f"added noise:   {describe_noise(comparison.noise)}",
             f"filter noise:  {describe_filter_noise(comparison.options)}"]
    if comparison.auto is not None:
        lines.append(f"auto (check): {describe_suggestions(comparison.auto)}")
    header = f"{'method':<38}{'frames':>8}{'landmarks':>11}{'time s':>9}{'ms/frame':>10}"
    has_gt = comparison.ground_truth is not None
    has_cam = has_gt and any((m.get("evaluation") or {}).get("cam_ape_rmse_m") is not None
                             for m in content["methods"].values())
    if has_cam:
        header += f"{'cam ATE m':>10}{'cam KITTI %':>12}"
    if has_gt:
        header += f"{'IMU ATE m' if has_cam else 'ATE (m)':>10}{'KITTI %':>9}{'deg/100m':>10}"
    lines.append(header)
    for key, m in content["methods"].items():
        frames = f"{m['frames_processed']}" + ("" if m["frames_processed"] == m["frames"] else f"/{m['frames']}")
        row = (f"{m['label']:<38}{frames:>8}{m['landmarks_in_map']:>11}{m['estimation_seconds']:>9.2f}"
               f"{_num(m['frame_ms_median'], '.2f'):>10}")
        ev = m.get("evaluation")
        if has_cam and ev:
            row += f"{_num(ev.get('cam_ape_rmse_m'), '.3f'):>10}{_num(ev.get('cam_kitti_t_pct'), '.2f'):>12}"
        if has_gt and ev:
            row += (f"{_num(ev['ape_rmse_m'], '.3f'):>10}{_num(ev['kitti_t_pct'], '.2f'):>9}"
                    f"{_num(ev['kitti_r_deg_per_100m'], '.3f'):>10}")
        lines.append(row)
    if has_cam:
        lines.append("cam: the estimate as left-camera poses (calibration used) vs the ground truth as it is; IMU: "
                     "vs the ground truth converted to the IMU with that calibration (KITTI %, deg/100m: IMU frame)")
    folders = ", ".join(f"{k}/" for k in content["methods"])
    lines.append(f"time s: estimation (refine: smoother + refinement); ms/frame: median per frame (refine: the "
                 f"smoother's)" if "refine" in content["methods"] else
                 "time s: estimation; ms/frame: median per frame")
    lines.append(f"outputs:       {out_dir}/ ({folders}, comparison.png, comparison.json)")
    return "\n".join(lines)


def run(args) -> int:
    from vislam.tools.comparison import dataset_record, parse_methods, run_comparison, runs_of, write_comparison
    from vislam.cli.common import load_data, tracking_warnings
    from vislam.tools.outputs import OutputStage, command_start_time

    start_time = command_start_time() or _COMMAND_START
    # every input is checked before any work or output
    methods = parse_methods(args.methods)
    options = options_from_args(args)
    noise = noise_spec_from_args(args)
    data = Path(args.data)
    sequence, tracking = load_data(args, args.out)
    # the ground truth, matched with the frames the filters will see (see vislam run)
    _, gt, gt_info, recheck = reference_poses_from_args(args, sequence, options, getattr(args, "auto", False))
    noise_info = auto = None
    if noise is not None:  # injected once, here, so that --auto checks what the methods will see
        from vislam.core.noise import inject_noise

        sequence, noise_info = inject_noise(sequence, noise)
    if getattr(args, "auto", False):  # as vislam run --auto: check first, its suggestions below --config/flags
        options, auto = auto_options(args, sequence, args.quiet)
    if options.has_data_corrections:  # from --auto or vislam check's suggested.yaml
        from vislam.core.corrections import apply_corrections

        sequence = apply_corrections(sequence, options)  # camera ground truth: converted with each run's calibration
    if recheck:  # against the frame times --auto's corrections give
        pair_ground_truth(gt, sequence, options)
    dataset = dataset_record(sequence, data)  # the file's cam_T_imu; the one used is in each summary's calibration

    stage = OutputStage(args.out)
    close = lambda: None  # noqa: E731
    try:
        with stage:
            runs = runs_of(methods)
            bar, close = make_progress(len(runs) * sequence.n_frames, "compare", args.quiet)
            offsets = {key: i * sequence.n_frames for i, key in enumerate(runs)}
            progress = None
            if bar:
                def progress(run_key, done):
                    bar(offsets[run_key] + done)
                progress.phase = bar.phase  # the refinement says so on the bar
            try:
                comparison = run_comparison(sequence, options, noise=noise, noise_info=noise_info, ground_truth=gt,
                                            ground_truth_info=gt_info, dataset=dataset, progress=progress,
                                            methods=methods, auto=auto)
            finally:
                close()
            content = write_comparison(stage.staging, comparison, start_time=start_time)
            stage.commit(order=(*methods, "comparison.png", "comparison.json"), replace_directories=True)
    except KeyboardInterrupt:
        close()
        print(interrupted_message("compare", stage), file=sys.stderr)
        return 130
    if not args.quiet:
        _print(format_comparison(comparison, content, stage.out_dir))
        for warning in tracking_warnings(tracking):  # an image folder's tracks
            print(f"vislam: warning: tracking: {warning}", file=sys.stderr)
        for warning in content.get("warnings") or ():  # about the data every method ran on
            print(f"vislam: warning: {warning}", file=sys.stderr)
        for key, method in content["methods"].items():
            for warning in method.get("warnings") or ():
                print(f"vislam: warning: {key}: {warning}", file=sys.stderr)
    partial = [m.result for m in comparison.methods.values() if m.result.partial]
    if partial:
        r = partial[0]
        raise EstimationError(f"{r.mode}: {r.error}; stopped after {r.stats.frames_processed} of {r.stats.frames} "
                              f"frames; partial outputs written to {stage.out_dir} (comparison.json: "
                              f"\"partial\": true)")
    return 0
