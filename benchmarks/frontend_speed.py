#!/usr/bin/env python
"""Speed and memory of the stereo tracker (`vislam track`, issue 21).

Usage::

    PYTHONPATH=src python benchmarks/frontend_speed.py [--source FOLDER] [--frames 200] [--out FILE.json]
                                                       [--config TRACKER.yaml]

On one core (the process pinned to one CPU with ``os.sched_setaffinity``, like ``taskset -c``;
``cv2.setNumThreads(1)``; BLAS/OpenMP limited to one thread) it tracks the
rectified 1242x375 grey pairs of a KITTI raw drive folder — by default one rendered by
``vislam simulate --images --frames 250 --seed 0`` into a temporary folder (the rendering
is not timed). It reports:

* frames per second of :meth:`StereoTracker.process` alone (images already in memory) and
  of the whole loop with PNG decoding (``StereoSource.read_pair``), per-frame median and
  p95 (ms), the CPU time per frame of each of the tracker's named steps and of the
  primitives inside them (a separate pass), and cProfile's top functions;
* memory: the peak of Python/numpy allocations (``tracemalloc``) while tracking the first
  ``N/4`` and all ``N`` frames, minus what the kept observations themselves take
  (``n_observations x 40`` bytes): the tracker's working memory, which must not grow
  with the number of frames.

Target (issue 21): >= 30 frames per second on one core; memory independent of the frames.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import numpy as np  # noqa: E402


def _source(folder: str | None, frames: int):
    from vislam.tools.frontend_io import open_stereo_source

    if folder:
        return open_stereo_source(folder), None
    tmp = tempfile.TemporaryDirectory(prefix="vislam-speed-")
    subprocess.run([sys.executable, "-m", "vislam", "simulate", "--images", "--frames", str(frames), "--seed", "0",
                    "--out", tmp.name], check=True, stdout=subprocess.DEVNULL)
    return open_stereo_source(next(Path(tmp.name).glob("sim_drive_*_sync"))), tmp


#: The tracker's named steps (StereoTracker.process calls them in this order) and the primitives
#: inside them, timed per frame by :func:`_step_times`.
STEPS = ("_frame", "_track_temporal", "_track_stereo", "_check_geometry", "_new_tracks", "_commit")
PRIMITIVES = ("_klt", "_affine", "_detect", "_templates", "_geometric_inliers", "_expected_frames")


def _step_times(source, n, pairs, options=None) -> dict:
    """CPU ms per frame in each step and primitive (time.process_time around each call)."""
    from vislam.core.tracking import StereoTracker

    tracker = StereoTracker(source.K, source.baseline_m, options)
    spent = {name: 0.0 for name in STEPS + PRIMITIVES}

    def timed(name, method):
        def call(*args, **kwargs):
            t0 = time.process_time()
            try:
                return method(*args, **kwargs)
            finally:
                spent[name] += time.process_time() - t0
        return call

    for name in STEPS + PRIMITIVES:
        setattr(tracker, name, timed(name, getattr(tracker, name)))
    t0 = time.process_time()
    for t in range(n):
        tracker.process(*pairs[t])
    total = time.process_time() - t0
    out = {name: 1e3 * v / n for name, v in spent.items()}
    out["process_total"] = 1e3 * total / n
    return out


def _track(source, n, pairs=None, options=None):
    from vislam.core.tracking import StereoTracker

    tracker = StereoTracker(source.K, source.baseline_m, options)
    times, kept = [], 0
    for t in range(n):
        t0 = time.perf_counter()
        left, right = pairs[t] if pairs is not None else source.read_pair(t)
        ids, _ = tracker.process(left, right)
        times.append(time.perf_counter() - t0)
        kept += ids.size
    return np.array(times), kept, tracker


def main() -> int:
    import cv2

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", help="KITTI raw drive / EuRoC / plain folder (default: render one)")
    parser.add_argument("--frames", type=int, default=200, help="frames to track (default 200)")
    parser.add_argument("--out", default="benchmarks/results/frontend_speed.json")
    parser.add_argument("--config", help="tracker options (YAML/TOML; default: TrackerOptions())")
    args = parser.parse_args()
    from vislam.cli.common import tracker_options_from_args

    options = tracker_options_from_args(args.config)
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):  # one core: like taskset -c N
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover
        pass
    source, tmp = _source(args.source, args.frames + 10)
    n = min(args.frames, source.n_frames)
    pairs = [source.read_pair(t) for t in range(n)]
    cpu0 = time.process_time()
    t_proc, kept, tracker = _track(source, n, pairs, options)
    cpu_proc = time.process_time() - cpu0
    t_all, _, _ = _track(source, n, options=options)
    # memory: working memory after N/4 and N frames
    memory = {}
    for m in (max(2, n // 4), n):
        tracemalloc.start()
        _, kept_m, _ = _track(source, m, pairs, options)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        memory[m] = {"peak_mib": peak / 2**20, "observations_mib": kept_m * 40 / 2**20,
                     "working_mib": (peak - kept_m * 40) / 2**20}
    # where the time goes
    import cProfile
    import pstats

    prof = cProfile.Profile()
    prof.enable()
    _track(source, min(n, 60), pairs, options)
    prof.disable()
    stats = pstats.Stats(prof)
    steps = _step_times(source, n, pairs, options)
    result = {
        "machine": {"nproc": os.cpu_count(), "python": platform.python_version(), "opencv": cv2.__version__,
                    "loadavg": os.getloadavg(), "cpu": platform.processor()},
        "source": str(source.root), "frames": n, "image_size_px": list(source.image_size_px),
        "tracks_per_frame_mean": kept / n,
        "process_only": {"fps": n / t_proc.sum(), "median_ms": 1e3 * float(np.median(t_proc)),
                         "p95_ms": 1e3 * float(np.percentile(t_proc, 95)), "cpu_fps": n / cpu_proc},
        "with_png_decoding": {"fps": n / t_all.sum(), "median_ms": 1e3 * float(np.median(t_all))},
        "memory": {str(k): v for k, v in memory.items()},
        "profile_top_tottime_s": [(name, round(t, 3)) for t, name in
                                  sorted(((v[2], f"{k[2]} ({Path(k[0]).name}:{k[1]})")
                                          for k, v in stats.stats.items()), reverse=True)[:10]],
        "step_cpu_ms_per_frame": {k: round(v, 2) for k, v in steps.items()},
        "target_fps": 30.0,
    }
    proc, png = result["process_only"], result["with_png_decoding"]
    print(f"tracking {n} frames of {source.image_size_px[0]}x{source.image_size_px[1]} on one core: "
          f"{proc['fps']:.1f} fps (median {proc['median_ms']:.1f} ms, p95 {proc['p95_ms']:.1f} ms; "
          f"CPU {proc['cpu_fps']:.1f} fps), with PNG decoding {png['fps']:.1f} fps; "
          f"{result['tracks_per_frame_mean']:.0f} tracks/frame")
    for m, v in memory.items():
        print(f"memory after {m} frames: peak {v['peak_mib']:.1f} MiB = observations {v['observations_mib']:.2f} "
              f"MiB + working {v['working_mib']:.1f} MiB")
    print(f"target >= 30 fps: {'HOLDS' if proc['fps'] >= 30 else 'MISSED'}")
    print("CPU ms per frame: " + ", ".join(f"{k.strip('_')} {v:.1f}" for k, v in steps.items()))
    for name, t in result["profile_top_tottime_s"][:6]:
        print(f"  {t:7.3f} s  {name}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
