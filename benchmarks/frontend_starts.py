#!/usr/bin/env python
"""Where the tracker's new corners are lost, by image row (issue 21).

Usage::

    PYTHONPATH=src python benchmarks/frontend_starts.py DRIVE_FOLDER [--frames 150] [--config FILE.yaml]
                                                       [--rows 0,125,190,250,300,375]

Tracks the first frames of a stereo folder (any layout ``vislam track`` reads) and counts, in
bands of image rows, the corners at each stage of :meth:`StereoTracker._new_tracks`: detected
(Shi-Tomasi), matched into the right image (NCC search), expected to stay in view for
``min_expected_frames`` (the last motion carried forward), started as tracks. On a forward-moving
car the rows below the horizon are the road: near points that pass the stereo match but leave
the view within a few frames.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

STAGES = ("detected", "stereo_matched", "expected_to_stay", "started")


def count_starts(source, options, frames: int, rows) -> dict:
    """Per stage, the corners in each band of ``rows`` over the first ``frames`` frames."""
    from vislam.core.tracking import StereoTracker

    tracker = StereoTracker(source.K, source.baseline_m, options)
    counts = {stage: np.zeros(len(rows) - 1, np.int64) for stage in STAGES}

    def add(stage, pixels):
        if pixels.size:
            counts[stage] += np.histogram(pixels[:, 1], rows)[0]

    detect, search, expected, new = (tracker._detect, tracker._stereo_search, tracker._expected_frames,
                                     tracker._new_tracks)

    def _detect(*args):
        corners = detect(*args)
        add("detected", corners)
        return corners

    def _stereo_search(frame, left):
        stereo, ok = search(frame, left)
        add("stereo_matched", left[ok])
        return stereo, ok

    def _expected_frames(stereo, horizon):
        n = expected(stereo, horizon)
        add("expected_to_stay", stereo[n >= horizon])
        return n

    def _new_tracks(frame, tracks):
        started = new(frame, tracks)
        add("started", started.pixels)
        return started

    tracker._detect, tracker._stereo_search = _detect, _stereo_search
    tracker._expected_frames, tracker._new_tracks = _expected_frames, _new_tracks
    for t in range(min(frames, source.n_frames)):
        tracker.process(*source.read_pair(t))
    return {stage: v.tolist() for stage, v in counts.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", help="stereo folder (e.g. DIR/sim_drive_0000_sync)")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--config", help="tracker options (YAML/TOML)")
    parser.add_argument("--rows", default="0,125,190,250,300,375", help="band edges (image rows, px)")
    args = parser.parse_args()
    from vislam.cli.common import tracker_options_from_args
    from vislam.tools.frontend_io import open_stereo_source

    rows = [float(r) for r in args.rows.split(",")]
    counts = count_starts(open_stereo_source(args.source), tracker_options_from_args(args.config), args.frames, rows)
    bands = [f"{rows[k]:g}-{rows[k + 1]:g}" for k in range(len(rows) - 1)]
    print(f"rows (px)          {' '.join(f'{b:>8s}' for b in bands)}")
    for stage in STAGES:
        print(f"{stage:18s} {' '.join(f'{c:8d}' for c in counts[stage])}")
    print(json.dumps({"rows": rows, "frames": args.frames, "counts": counts}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
