"""``vislam eval EST GT --out DIR``: evaluate an estimated trajectory against ground truth.

Prints a table of APE / RPE / KITTI errors and writes ``DIR/metrics.json`` and
``DIR/error_over_distance.png``. The numbers come from
:func:`vislam.tools.evaluation.evaluate_files`; this module only parses, prints and saves.

The ground truth's body frame defaults to the format's convention (``--gt-frame auto``:
KITTI files hold left-camera poses, TUM files IMU poses). Camera poses are converted
with ``cam_T_imu`` from ``--dataset``, else from the ``summary.json`` of the run folder
the estimate sits in; with neither the command refuses (one line) rather than compare
camera poses with IMU poses.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from vislam.errors import OutputError
from vislam.tools.trajectory_io import DEFAULT_MAX_DIFF_S, GT_FORMAT_CHOICES, GT_FRAME_CHOICES

__all__ = ["register", "run"]

METRICS_FILE = "metrics.json"
FIGURE_FILE = "error_over_distance.png"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "eval",
        help="evaluate an estimated trajectory against ground truth",
        description="Evaluate an estimated world_T_imu trajectory (KITTI or TUM file, detected from the number "
        "of values per line) against ground truth: APE (SE(3)-aligned and not aligned), RPE over 1 frame and "
        "100 m, and the KITTI odometry metric. Prints a table and writes DIR/metrics.json and "
        "DIR/error_over_distance.png.",
    )
    parser.add_argument("est", metavar="EST", help="estimated trajectory (KITTI: 12 values per line; TUM: 8)")
    parser.add_argument("gt", metavar="GT", help="ground-truth trajectory")
    parser.add_argument("--out", metavar="DIR", required=True, help="output directory (created if needed)")
    parser.add_argument("--gt-format", choices=GT_FORMAT_CHOICES, default="auto",
                        help="ground-truth file format: kitti (line i = frame i, matched by index), tum "
                        "(timestamped, matched by time) or auto (default): the one the file's values per line "
                        "say (12: kitti, 8: tum)")
    parser.add_argument("--gt-frame", choices=GT_FRAME_CHOICES, default="auto",
                        help="body frame of the ground-truth poses: cam (left camera, converted to the IMU with "
                        "cam_T_imu) or imu. auto (default): the format's convention: kitti -> cam (KITTI ground "
                        "truth holds left-camera poses, as groundtruth/*.txt of the shared data), tum -> imu (TUM "
                        "has no body-frame convention; vislam's TUM files hold IMU poses). cam_T_imu comes from "
                        "--dataset, else from summary.json in the estimate's folder (a vislam run folder); with "
                        "neither, a camera ground truth is refused")
    parser.add_argument("--dataset", metavar="DATA",
                        help="the dataset (.npz) the estimate was computed from: supplies cam_T_imu and the "
                        "frame timestamps (default: cam_T_imu from the run folder's summary.json)")
    parser.add_argument("--max-diff", type=float, default=DEFAULT_MAX_DIFF_S, metavar="SECONDS",
                        help=f"largest time difference of matched poses, for timestamp association "
                        f"(default: {DEFAULT_MAX_DIFF_S:g})")
    parser.add_argument("--title", help="figure title (default: the two file names)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from vislam.tools.evaluation import evaluate_files, format_table, plot_error_over_distance, write_metrics_json

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a directory (--out expects a directory)")
    sequence = None
    if args.dataset:
        from vislam.tools.dataset_io import load_sequence

        sequence = load_sequence(args.dataset)
    result = evaluate_files(
        args.est,
        args.gt,
        gt_format=args.gt_format,
        gt_frame=args.gt_frame,
        sequence=sequence,
        max_diff_s=args.max_diff,
    )
    from vislam.tools.outputs import OutputStage

    title = args.title or f"{Path(args.est).name} vs ground truth {Path(args.gt).name}"
    # both files appear together or not at all (a failed figure leaves no new metrics.json beside an old figure);
    # the other entries of DIR (e.g. the run folder the estimate comes from) stay as they are
    with OutputStage(out) as stage:
        write_metrics_json(result, stage.path(METRICS_FILE))
        plot_error_over_distance(result, stage.path(FIGURE_FILE), title=title)
        stage.commit(order=(METRICS_FILE, FIGURE_FILE), remove_stale=())
    metrics_path = out / METRICS_FILE
    figure_path = out / FIGURE_FILE
    text = format_table(result) + f"\n\nwrote {metrics_path}\nwrote {figure_path}"
    try:
        print(text, flush=True)
    except BrokenPipeError:  # e.g. `vislam eval ... | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0
