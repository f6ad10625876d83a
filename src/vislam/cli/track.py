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

from vislam.errors import ConfigError

__all__ = ["register", "run", "tracker_options_from_args", "format_stats"]

#: argparse dest -> TrackerOptions field
_FLAGS = {"features": "target_features", "min_track_length": "min_track_length"}


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
        for dest, field in _FLAGS.items():
            message = message.replace(field, "--" + dest.replace("_", "-"))
        raise ConfigError(message) from None


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
    from vislam.cli.run import make_progress
    from vislam.tools.frontend_io import open_stereo_source, track_source, write_tracks

    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise ConfigError(f"--out {out}: expected a file name ending in .npz")
    if out.is_dir():
        raise ConfigError(f"--out {out}: is a directory; expected a file name ending in .npz")
    config = args.config or getattr(args, "tracker_config", None)
    options = tracker_options_from_args(config, {f: getattr(args, d, None) for d, f in _FLAGS.items()})
    source = open_stereo_source(args.source, pair=args.pair, velocities=args.velocities)
    progress, close = make_progress(source.n_frames, "track", args.quiet)
    try:
        sequence, stats = track_source(source, options, progress=progress)
    finally:
        close()
    paths = write_tracks(sequence, stats, out)
    if not args.quiet:
        print(format_stats(stats, paths), flush=True)
        if source.velocities is None:
            print(f"vislam track: warning: {out}: no velocities (NaN): {source.velocity_note}; the filter commands "
                  f"will refuse this file", file=sys.stderr)
    return 0
