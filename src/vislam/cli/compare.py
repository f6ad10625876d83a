"""``vislam compare DATA --out DIR``: localization + mapping ("separately") against SLAM.

Runs both on the same data — with the noise of the ``--add-*`` flags injected once,
seeded — and writes, all or nothing, ``DIR/separate/`` and ``DIR/slam/`` (the files of
``vislam run``), ``DIR/comparison.png`` (both trajectories and landmark sets on one xy
figure, the report's Figs 7–9) and ``DIR/comparison.json``. The work is
:func:`vislam.tools.comparison.run_comparison` and
:func:`vislam.tools.comparison.write_comparison`; this module parses, calls and prints.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from vislam.cli.run import (
    _print,
    add_filter_arguments,
    add_ground_truth_arguments,
    add_noise_injection_arguments,
    ground_truth_from_args,
    interrupted_message,
    make_progress,
    noise_spec_from_args,
    options_from_args,
)
from vislam.errors import ConfigError, EstimationError

__all__ = ["register", "run", "format_comparison"]

_COMMAND_START = time.time()


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "compare",
        help="localization + mapping (separately) vs SLAM on the same data, one comparison figure",
        description="Run IMU localization + landmark mapping on its trajectory (the report's 'separately') and "
        "visual-inertial SLAM on the same data, with the noise of the --add-* flags injected once (seeded), and "
        "write DIR/separate/ and DIR/slam/ (the files of 'vislam run'), DIR/comparison.png (both trajectories and "
        "both landmark sets in the xy plane, the report's Figs 7-9) and DIR/comparison.json (frames, landmarks, "
        "filter time and, with --gt, the ATE and KITTI errors of each method). Outputs appear all together or not "
        "at all.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example (the report's Fig. 7 with numbers):\n"
        "  vislam compare ../shared/data/sparse/0027.npz --out cmp27 \\\n"
        "      --add-velocity-noise 0.3 --add-angular-noise 0.006 --velocity-noise 0.3 --angular-noise 0.006 \\\n"
        "      --gt ../shared/data/groundtruth/0027.txt   # KITTI ground truth: left-camera poses (the default)",
    )
    parser.add_argument("data", metavar="DATA", help="dataset file (.npz)")
    parser.add_argument("--out", metavar="DIR", required=True, help="output directory (created if needed)")
    add_filter_arguments(parser)
    add_noise_injection_arguments(parser)
    add_ground_truth_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    parser.set_defaults(func=run)


def _num(x, spec: str, unit: str = "") -> str:
    return "n/a" if x is None else f"{x:{spec}}{unit}"


def format_comparison(comparison, content: dict, out_dir) -> str:
    """The human summary printed by ``vislam compare`` (``content``: comparison.json's)."""
    from vislam.tools.comparison import describe_filter_noise, describe_noise

    lines = [f"{comparison.label}: localization + mapping (separately) vs SLAM",
             f"added noise:   {describe_noise(comparison.noise)}",
             f"filter noise:  {describe_filter_noise(comparison.options)}"]
    header = f"{'method':<38}{'frames':>8}{'landmarks':>11}{'filter s':>10}"
    has_gt = comparison.ground_truth is not None
    if has_gt:
        header += f"{'ATE (m)':>10}{'KITTI %':>9}{'deg/100m':>10}"
    lines.append(header)
    for key, m in content["methods"].items():
        frames = f"{m['frames_processed']}" + ("" if m["frames_processed"] == m["frames"] else f"/{m['frames']}")
        row = f"{m['label']:<38}{frames:>8}{m['landmarks_in_map']:>11}{m['filter_seconds']:>10.2f}"
        ev = m.get("evaluation")
        if has_gt and ev:
            row += (f"{_num(ev['ape_rmse_m'], '.3f'):>10}{_num(ev['kitti_t_pct'], '.2f'):>9}"
                    f"{_num(ev['kitti_r_deg_per_100m'], '.3f'):>10}")
        lines.append(row)
    lines.append(f"outputs:       {out_dir}/ (separate/, slam/, comparison.png, comparison.json)")
    return "\n".join(lines)


def run(args) -> int:
    from vislam.tools.comparison import dataset_record, run_comparison, write_comparison
    from vislam.tools.dataset_io import load_sequence
    from vislam.tools.outputs import OutputStage, process_start_time

    start_time = process_start_time() or _COMMAND_START
    # every input is checked before any work or output
    if getattr(args, "auto", False):
        raise ConfigError("--auto is supported by vislam run only (for now); run `vislam check DATA --out DIR` and "
                          "pass DIR/suggested.yaml with --config")
    options = options_from_args(args)
    noise = noise_spec_from_args(args)
    data = Path(args.data)
    sequence = load_sequence(data)
    gt, gt_info = ground_truth_from_args(args, sequence)
    if options.has_data_corrections:  # e.g. from vislam check's suggested.yaml
        from vislam.core.corrections import apply_corrections

        sequence = apply_corrections(sequence, options)
        if gt is not None and args.gt_frame == "cam":  # camera poses -> IMU with the corrected cam_T_imu
            gt, gt_info = ground_truth_from_args(args, sequence)
    dataset = dataset_record(sequence, data)

    stage = OutputStage(args.out)
    close = lambda: None  # noqa: E731
    try:
        with stage:
            bar, close = make_progress(2 * sequence.n_frames, "compare", args.quiet)
            offsets = {"separate": 0, "slam": sequence.n_frames}
            progress = (lambda method, done: bar(offsets[method] + done)) if bar else None
            try:
                comparison = run_comparison(sequence, options, noise=noise, ground_truth=gt,
                                            ground_truth_info=gt_info, dataset=dataset, progress=progress)
            finally:
                close()
            content = write_comparison(stage.staging, comparison, start_time=start_time)
            stage.commit(order=("separate", "slam", "comparison.png", "comparison.json"), replace_directories=True)
    except KeyboardInterrupt:
        close()
        print(interrupted_message("compare", stage), file=sys.stderr)
        return 130
    if not args.quiet:
        _print(format_comparison(comparison, content, stage.out_dir))
    partial = [m.result for m in comparison.methods.values() if m.result.partial]
    if partial:
        r = partial[0]
        raise EstimationError(f"{r.mode}: {r.error}; stopped after {r.stats.frames_processed} of {r.stats.frames} "
                              f"frames; partial outputs written to {stage.out_dir} (comparison.json: "
                              f"\"partial\": true)")
    return 0
