"""``vislam track SOURCE --out FILE.npz``: stereo images -> the recording format.

SOURCE is a folder in one of the layouts of :mod:`vislam.tools.frontend_io` (KITTI raw
drive, EuRoC/ASL, plain ``left/`` + ``right/``); the tracker is
:class:`vislam.core.tracking.StereoTracker` with :class:`~vislam.core.tracking.TrackerOptions`
from ``--config FILE`` (YAML/TOML, a flat mapping of option names) and the flags. Writes
FILE.npz (atomically) and the tracker's statistics as FILE.tracking.json beside it.
"""

from __future__ import annotations

import sys
from pathlib import Path

from vislam.cli.common import TRACKER_FLAGS, add_source_arguments, tracker_options_from_args  # noqa: F401
from vislam.errors import ConfigError, OutputError

__all__ = ["register", "run", "tracker_options_from_args", "format_stats"]


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "track",
        help="track stereo features in an image folder (KITTI raw, EuRoC, plain) into a dataset .npz",
        description="Track stereo features through the rectified image pairs of SOURCE (a KITTI raw drive folder, "
        "an EuRoC/ASL folder, or a folder with left/, right/, calibration.yaml and velocities.csv; see "
        "docs/frontend.md) and write FILE.npz in the dataset format every vislam command reads, plus the tracker's "
        "statistics as FILE.tracking.json. Nothing is written unless the whole recording was tracked.",
    )
    parser.add_argument("source", metavar="SOURCE", help="image folder")
    parser.add_argument("--out", metavar="FILE.npz", required=True, help="output recording (.npz)")
    parser.add_argument("--config", metavar="FILE", help="tracker options (YAML/TOML): TrackerOptions fields")
    add_source_arguments(parser)
    parser.add_argument("--features", type=int, metavar="N", help="target number of live tracks (default 300)")
    parser.add_argument("--min-track-length", type=int, metavar="N",
                        help="leave out tracks seen in fewer frames (default 3)")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    parser.set_defaults(func=run)


def format_stats(stats: dict, paths) -> str:
    tpf = stats["tracks_per_frame_output"]
    tl = stats["track_length"]
    rej = stats["rejections"]
    lines = [
        f"layout:        {stats['layout']} ({stats['source']})",
        f"frames:        {stats['frames']}",
        f"tracks:        {stats['tracks']} (length median {tl['median']:g}, mean {tl['mean']:.1f}, max {tl['max']})",
        f"per frame:     mean {tpf['mean']:.1f}, min {tpf['min']}, max {tpf['max']}",
        f"rejected:      forward-backward {rej['forward_backward']}, left image {rej['left_image']}, stereo "
        f"{rej['stereo_tracked']} tracked + {rej['stereo_new']} new, geometric {rej['geometric']}",
        "tracks ended:  " + (", ".join(f"{k.replace('_', ' ')} {v['count']} (median {v['median_length']} frames)"
                                       for k, v in stats.get("track_ends", {}).items()) or "none"),
        f"velocities:    {stats['velocities']}",
        "wrote:",
    ]
    lines += [f"  {p}" for p in paths]
    return "\n".join(lines)


def run(args) -> int:
    from vislam.cli.common import make_progress
    from vislam.tools.frontend_io import open_stereo_source, track_source, write_tracks

    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise ConfigError(f"--out {out}: expected a file name ending in .npz")
    if out.is_dir():
        raise ConfigError(f"--out {out}: is a directory; expected a file name ending in .npz")
    for folder in (out.parent, *out.parent.parents):  # before the tracking, not after it
        if folder.exists():
            if not folder.is_dir():
                raise OutputError(f"--out {out}: {folder} is a file; expected a directory to write {out.name} into")
            break
    config = args.config or getattr(args, "tracker_config", None)
    options = tracker_options_from_args(config, {f: getattr(args, d, None) for d, f in TRACKER_FLAGS.items()})
    source = open_stereo_source(args.source, pair=args.pair, velocities=args.velocities)
    progress, close = make_progress(source.n_frames, "track", args.quiet)
    try:
        sequence, stats = track_source(source, options, progress=progress)
    finally:
        close()
    paths = write_tracks(sequence, stats, out)
    if not args.quiet:
        print(format_stats(stats, paths), flush=True)
        for warning in stats["warnings"]:
            print(f"vislam track: warning: {warning}", file=sys.stderr)
        if source.velocities is None:
            print(f"vislam track: warning: {out}: no velocities (NaN): {source.velocity_note}; the filter commands "
                  f"will refuse this file", file=sys.stderr)
    return 0
