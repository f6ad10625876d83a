"""``vislam check DATA [--out DIR] [--json]``: what the recording says about itself.

The analysis is :func:`vislam.core.check.check_sequence` (noise, biases, conventions,
reprojection consistency, no ground truth needed); this module prints its verdict (one
line per finding) or, with ``--json``, the whole result, and with ``--out`` writes
``DIR/check.json`` and ``DIR/suggested.yaml`` (:mod:`vislam.tools.check_io`). The exit
code is 0 whatever the findings: a finding is information, not a failure of the command.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from vislam.cli import say_phase
from vislam.core.check import check_sequence
from vislam.errors import OutputError
from vislam.tools.check_io import format_verdict, write_check_outputs
from vislam.tools.jsonio import dumps

__all__ = ["register", "run"]


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "check",
        help="learn the noise, biases and conventions of a recording (no ground truth)",
        description="Estimate from the recording alone: IMU white noise per axis, gyro bias, the velocity-sample "
        "association, the IMU-camera rotation (hand-eye through the images, incl. 180-degree axis mismatches), a "
        "camera-IMU time offset, the pixel noise and outliers of the tracks and their reprojection consistency "
        "under dead-reckoned poses. Prints one line per finding (OK / WARN / ERROR); with --out writes "
        "DIR/check.json and DIR/suggested.yaml, an options file for `vislam run --config`.",
    )
    parser.add_argument("data", metavar="DATA", help="dataset file (.npz), or an image folder (tracked first; with "
                        "--out the tracks are cached as DIR/tracks.npz)")
    parser.add_argument("--out", metavar="DIR", help="write check.json and suggested.yaml into DIR")
    parser.add_argument("--json", action="store_true", help="print the whole result as JSON instead of the verdict")
    from vislam.cli.common import add_source_arguments

    add_source_arguments(parser)
    parser.set_defaults(func=run)


def run(args) -> int:
    if args.out and Path(args.out).exists() and not Path(args.out).is_dir():  # before seconds of work
        raise OutputError(f"{args.out}: exists and is not a directory (an output directory is expected)")
    from vislam.cli.common import load_data, tracking_warnings

    args.quiet = getattr(args, "quiet", False) or args.json
    sequence, tracking = load_data(args, args.out)
    for warning in tracking_warnings(tracking):  # an image folder's tracks
        print(f"vislam check: warning: tracking: {warning}", file=sys.stderr)
    if not args.json:
        say_phase(f"checking {sequence.name}: timestamps, IMU noise and biases, speed units, IMU-camera rotation "
                  f"and translation, time offset, pixel noise, moving landmarks", quiet=False)
    result = check_sequence(sequence)
    paths = write_check_outputs(result, args.out) if args.out else []
    text = dumps(result.to_dict()) if args.json else format_verdict(result)
    if paths and not args.json:
        text += "\nwrote:\n" + "\n".join(f"  {p}" for p in paths)
    try:
        print(text, flush=True)
    except BrokenPipeError:  # e.g. `vislam check DATA | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0
