"""Where a smoother frame's time goes: the steps of SmootherFilter timed one by one (CPU time).

Usage (from the repository root)::

    PYTHONPATH=src python benchmarks/smoother_breakdown.py ../shared/data/dense/0034.npz [--repeat 3]

Each step of :class:`vislam.core.smoother.SmootherFilter` is wrapped in a timer
(``time.process_time``: CPU time of the process, so that other work on a shared machine
adds little) and the drive is run ``--repeat`` times with the smoother's defaults; the
best run's per-frame mean of every step is printed with its share of the run (nested
steps are included in their parents). "levelled odometry factor" is the Python code
GTSAM calls back from inside the iSAM2 update to linearize the levelled motion model
(``level_odometry_error``; the number of calls per frame is printed too). Dense files
are run with the filter told their IMU noise (0.5 m/s, 0.05 rad/s), as benchmarks do.
The steps timed are those the tree under ``PYTHONPATH`` has (a step it lacks is
printed as "-"), so the script also runs on older trees.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

from vislam.core import smoother
from vislam.core.estimators import run
from vislam.core.options import FilterOptions
from vislam.tools.dataset_io import load_sequence

TOTALS: dict[str, float] = defaultdict(float)
CALLS: dict[str, int] = defaultdict(int)

#: (label, owner, attribute or attributes): the steps timed, in the order printed (indented: inside the one above)
STEPS = [
    ("frame (step)", smoother.SmootherFilter, "step"),
    ("  pose and motion factor", smoother.SmootherFilter, "_predict_pose"),
    ("  select (repeats, stall counts)", smoother.SmootherFilter, "_select"),
    ("  stereo factors of known landmarks", smoother.SmootherFilter, "_add_observations"),
    ("  new landmarks", smoother.SmootherFilter, "_initialize_new"),
    ("  marginalize (final values, covariances)", smoother.SmootherFilter, "_marginalize"),
    ("  iSAM2 update (window)", smoother.SmootherFilter, "_update_window"),
    ("    levelled odometry factor (callbacks)", smoother, ("_level_odometry", "level_odometry_error")),
    ("  outlier check", smoother.SmootherFilter, "_check_outliers"),
    ("    drift test", smoother.SmootherFilter, "_drift_test"),
    ("  history record", smoother.SmootherFilter, "_record"),
]


def _timed(label, fn):
    def wrapper(*args, **kwargs):
        t0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            TOTALS[label] += time.process_time() - t0
            CALLS[label] += 1
    return wrapper


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    seq = load_sequence(args.data)
    kw = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05) if "/dense/" in args.data else {}
    present = []
    for label, owner, attrs in STEPS:
        # the first of the names the tree has (the factor's code was renamed)
        attr = next((a for a in ((attrs,) if isinstance(attrs, str) else attrs) if hasattr(owner, a)), None)
        if attr is not None:
            setattr(owner, attr, _timed(label, getattr(owner, attr)))
            present.append(label)
    best = None
    for _ in range(args.repeat):
        TOTALS.clear()
        CALLS.clear()
        c0 = time.process_time()
        run(seq, "smoother", FilterOptions(**kw))
        cpu = time.process_time() - c0
        if best is None or cpu < best[0]:
            best = (cpu, dict(TOTALS), dict(CALLS))
    seconds, totals, calls = best
    n = seq.n_frames
    print(f"{args.data}: {n} frames, smoother run {seconds:.3f} s CPU ({1e3 * seconds / n:.3f} ms/frame, timers "
          f"included; best of {args.repeat})")
    for label, _, _ in STEPS:
        if label not in present:
            print(f"  {label:44s} {'-':>8s}")
            continue
        t = totals.get(label, 0.0)
        extra = f"  ({calls.get(label, 0) / n:.1f} calls/frame)" if "callbacks" in label else ""
        print(f"  {label:44s} {1e6 * t / n:8.1f} us/frame  {100 * t / seconds:5.1f} %{extra}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
