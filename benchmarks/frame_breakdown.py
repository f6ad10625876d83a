"""Where a SLAM frame's time goes: the EKF's steps timed one by one (inclusive CPU time).

Usage (from the repository root)::

    PYTHONPATH=src python benchmarks/frame_breakdown.py ../shared/data/sparse/0027.npz [--repeat 3]

Each step of :class:`vislam.core.filters.SlamFilter` (and the updater functions it calls)
is wrapped in a timer (``time.process_time``: CPU time of the process, so that other
work on a shared machine adds little; a fraction of a microsecond per call) and
the drive is run ``--repeat`` times; the best run's per-frame mean of every step is
printed with its share of the run (nested steps are included in their parents; the
line "every linearization" adds up the linearizations of "linearize + NIS" and those
of the iterated update).
Dense files are run with the filter told their IMU noise (0.5 m/s, 0.05 rad/s).
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

from vislam.core import filters, updaters
from vislam.core.estimators import run
from vislam.core.options import FilterOptions
from vislam.core.stalls import StallRemapBuffer
from vislam.tools.dataset_io import load_sequence

TOTALS: dict[str, float] = defaultdict(float)

#: (label, owner, attribute): the steps timed, in the order printed (indented: inside the one above)
STEPS = [
    ("stall buffer (push/release)", StallRemapBuffer, "push"),
    ("prediction", filters.SlamFilter, "predict"),
    ("update (steps 2-7)", filters.SlamFilter, "_update_frame"),
    ("  select (repeats, rejected)", filters.SlamFilter, "_select"),
    ("  update of live landmarks", filters.SlamFilter, "_update_live"),
    ("    linearize + NIS (Jacobians, gating)", filters, "slam_predict_nis"),
    ("    (every linearization: here and iterating)", updaters, "_linearize"),
    ("    drift-test model", filters, "conditional_residual_model"),
    ("    iterated update", filters, "slam_update_iterated"),
    ("      EKF update (gain, covariance)", filters, "slam_update"),
    ("      iteration decision (step size)", updaters, "_step_size"),
    ("    drift test", filters.SlamFilter, "_drift_test"),
    ("    Schmidt update (young landmarks)", filters, "schmidt_update"),
    ("  reject", filters.SlamFilter, "_reject"),
    ("  marginalize ended", filters.SlamFilter, "_marginalize_ended"),
    ("  initialize new", filters.SlamFilter, "_initialize_new"),
    ("  health check", filters.SlamFilter, "_check_health"),
    ("history record", filters.SlamFilter, "_record"),
]


def _timed(label, fn):
    def wrapper(*args, **kwargs):
        t0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            TOTALS[label] += time.process_time() - t0
    return wrapper


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    seq = load_sequence(args.data)
    kw = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05) if "/dense/" in args.data else {}
    for label, owner, attr in STEPS:
        setattr(owner, attr, _timed(label, getattr(owner, attr)))
    best = None
    for _ in range(args.repeat):
        TOTALS.clear()
        c0 = time.process_time()
        run(seq, "slam", FilterOptions(**kw))
        cpu = time.process_time() - c0
        if best is None or cpu < best[0]:
            best = (cpu, dict(TOTALS))
    seconds, totals = best
    n = seq.n_frames
    print(f"{args.data}: {n} frames, SLAM run {seconds:.3f} s CPU ({1e3 * seconds / n:.3f} ms/frame, timers "
          f"included; best of {args.repeat})")
    for label, _, _ in STEPS:
        t = totals.get(label, 0.0)
        print(f"  {label:44s} {1e6 * t / n:8.1f} us/frame  {100 * t / seconds:5.1f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
