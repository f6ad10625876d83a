"""``vislam info DATA``: validate a dataset file and print a summary of it.

The numbers come from :func:`vislam.tools.dataset_io.summarize_sequence`; this module
only formats them (as text, or as JSON with ``--json``).
"""

from __future__ import annotations

import os
import sys

import numpy as np

from vislam.tools.dataset_io import load_dataset, summarize_sequence
from vislam.tools.jsonio import dumps

__all__ = ["register", "run", "format_summary"]


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "info",
        help="validate a dataset file and summarize it",
        description="Load and validate a dataset (.npz, report or later key convention) and print a summary: "
        "frames, duration, landmarks, observations, track lengths, disparities, speeds and calibration.",
    )
    parser.add_argument("data", metavar="DATA", help="dataset file (.npz)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.set_defaults(func=run)


def _num(value, fmt: str = ".3f") -> str:
    """Format a number; ``fmt="count"`` prints whole numbers without decimals (means keep one)."""
    if value is None:
        return "n/a"
    if fmt == "count":
        return str(int(value)) if float(value).is_integer() else format(value, ".1f")
    return format(value, fmt)


def _range(stats: dict, fmt: str = ".3f") -> str:
    parts = []
    for key in ("min", "median", "mean", "max"):
        if key in stats:
            parts.append(f"{key} {_num(stats[key], fmt)}")
    return " / ".join(parts)


def _matrix(rows, indent: str = "    ") -> list[str]:
    a = np.asarray(rows, dtype=np.float64)
    text = np.array2string(a, precision=6, suppress_small=True, max_line_width=200, floatmode="maxprec")
    return [indent + line for line in text.splitlines()]


def format_summary(summary: dict) -> str:
    from vislam.core.check import describe_repeat_evidence

    """The human-readable text of ``vislam info``."""
    s = summary
    cal = s["calibration"]
    obs = s["observations"]
    disp = s["disparity_px"]
    keys = s.get("keys", {})
    ts_key, av_key, tr_key = keys.get("timestamps"), keys.get("angular_velocity"), keys.get("transform")
    convention = s.get("convention", "?")
    if ts_key:
        convention += f" ({ts_key}, {av_key}, {tr_key})"
    rate = s["mean_frame_rate_hz"]
    lines = [
        f"file:            {s.get('file', s['source'])}",
        f"key convention:  {convention}",
    ]
    if s.get("extra_keys"):
        lines.append(f"ignored keys:    {', '.join(s['extra_keys'])}")
    lines += [
        f"frames:          {s['frames']}",
        f"duration:        {s['duration_s']:.3f} s (mean frame rate {_num(rate, '.3f')} Hz; "
        f"frame interval {_range(s['frame_interval_s'], '.4f')} s)",
        f"landmarks:       {s['landmarks']['total']} ({s['landmarks']['observed']} observed at least once)",
        f"observations:    {obs['total']} (per frame {_range(obs['per_frame'], 'count')}; "
        f"{obs['frames_without']} frames without any)",
        *([f"repeats:         {obs['repeated']} observations repeat the previous frame's pixels "
           f"({describe_repeat_evidence(obs['repeat_evidence'])})"] if "repeated" in obs else []),
        f"track length:    frames {_range(s['track_length_frames'], 'count')}",
        f"disparity:       px {_range(disp, '.3f')} ({disp['non_positive']} non-positive)",
        f"|vL - vR|:       px max {_num(s['row_mismatch_px']['max'], '.3f')}",
        f"speed:           m/s {_range(s['speed_mps'], '.3f')}",
        f"angular rate:    rad/s {_range(s['angular_rate_radps'], '.4f')}",
        f"calibration:     fsu {cal['fsu']:.4f}  fsv {cal['fsv']:.4f}  cu {cal['cu']:.4f}  cv {cal['cv']:.4f}  "
        f"baseline {cal['baseline_m']:.6f} m",
        "stereo matrix M:",
        *_matrix(cal["M"]),
        "cam_T_imu:",
        *_matrix(s["cam_T_imu"]),
    ]
    return "\n".join(lines)


def run(args) -> int:
    dataset = load_dataset(args.data)
    summary = {
        "file": dataset.path,
        "convention": dataset.convention,
        "keys": dict(dataset.keys),
        "extra_keys": list(dataset.extra_keys),
        "features_dtype": dataset.features_dtype,
        "features_fortran_order": dataset.features_fortran_order,
        **summarize_sequence(dataset.sequence),
    }
    text = dumps(summary) if args.json else format_summary(summary)
    try:
        print(text, flush=True)
    except BrokenPipeError:  # e.g. `vislam info DATA | head`: the reader left, not an error of ours
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0
