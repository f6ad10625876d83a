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
Dense files are run with the filter told their IMU noise (0.5 m/s, 0.05 rad/s). The
filter takes the compiled kernels where the tree has them (vislam.core.kernels), the
numpy reference with ``--numpy``.
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import time
from collections import defaultdict

from vislam.core import filters, updaters
from vislam.core.estimators import run
from vislam.core.options import FilterOptions
from vislam.core.stalls import StallRemapBuffer
from vislam.tools.dataset_io import load_sequence

try:  # the per-frame arithmetic's two paths (trees before vislam.core.kernels have neither)
    from vislam.core import kernels
except ImportError:  # pragma: no cover - older trees
    kernels = None

TOTALS: dict[str, float] = defaultdict(float)
CALLS: dict[str, int] = defaultdict(int)

#: Where each step of the arithmetic lives: in the compiled KernelOps and the numpy
#: NumpyOps (a run takes one; both are timed under the same label), or, in trees before
#: vislam.core.kernels, the updaters' functions as the filters module imported them.
if kernels is not None:
    _OPS = (kernels.KernelOps, kernels.NumpyOps)
    _LINEARIZE, _UPDATE = (kernels.KernelOps, updaters), (kernels.KernelOps, updaters)
else:  # pragma: no cover - older trees
    _OPS = _UPDATE = (filters,)
    _LINEARIZE = (updaters,)

#: (label, owner(s), attribute or attributes — the first one each owner has): the steps
#: timed, in the order printed (indented: inside the one above)
STEPS = [
    ("stall buffer (push/release)", StallRemapBuffer, "push"),
    ("prediction", filters.SlamFilter, "predict"),
    ("update (steps 2-7)", filters.SlamFilter, "_update_frame"),
    ("  select (repeats, rejected)", filters.SlamFilter, "_select"),
    ("  update of live landmarks", filters.SlamFilter, "_update_live"),
    ("    linearize + NIS (Jacobians, gating)", _OPS, ("predict_nis", "slam_predict_nis")),
    ("    (every linearization: here and iterating)", _LINEARIZE, ("linearize", "_linearize")),
    ("    drift-test model", _OPS, ("residual_model", "conditional_residual_model")),
    ("    iterated update", filters, "slam_update_iterated"),
    ("      EKF update (gain, covariance)", _UPDATE, ("update", "slam_update")),
    ("      iteration decision (step size)", _OPS if kernels is not None else (updaters,), ("step_size", "_step_size")),
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
            CALLS[label] += 1
    return wrapper


def breakdown(steps, mode: str, title: str, description: str, counted: tuple[str, ...] = (), argv=None) -> int:
    """The command line of this script for an estimator ``mode``: wrap every step of
    ``steps`` — (label, owner, attribute or attributes: the first one the tree has, so
    that the script also runs on older trees; a step it lacks is printed as "-") — in a
    timer, run DATA ``--repeat`` times and print the best run's per-frame means; labels
    containing one of ``counted`` also get their calls per frame."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("data")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--numpy", action="store_true", help="the numpy reference path instead of the compiled kernels "
                    "(vislam.core.kernels)")
    args = ap.parse_args(argv)
    seq = load_sequence(args.data)
    kw = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05) if "/dense/" in args.data else {}
    present = []
    for label, owners, attrs in steps:
        for owner in owners if isinstance(owners, tuple) else (owners,):
            attr = next((a for a in ((attrs,) if isinstance(attrs, str) else attrs) if hasattr(owner, a)), None)
            if attr is None:
                continue
            raw = inspect.getattr_static(owner, attr)
            timed = _timed(label, getattr(owner, attr))
            # a class's staticmethod stays one (an instance of NumpyOps or KernelOps calls it)
            setattr(owner, attr, staticmethod(timed) if isinstance(raw, staticmethod) else timed)
            if label not in present:
                present.append(label)
    best = None
    for _ in range(args.repeat):
        use = kernels.use_kernels(not args.numpy) if kernels is not None else contextlib.nullcontext()
        TOTALS.clear()
        CALLS.clear()
        c0 = time.process_time()
        with use:
            run(seq, mode, FilterOptions(**kw))
        cpu = time.process_time() - c0
        if best is None or cpu < best[0]:
            best = (cpu, dict(TOTALS), dict(CALLS))
    seconds, totals, calls = best
    n = seq.n_frames
    print(f"{args.data}: {n} frames, {title} run {seconds:.3f} s CPU ({1e3 * seconds / n:.3f} ms/frame, timers "
          f"included; best of {args.repeat})")
    for label, _, _ in steps:
        if label not in present:
            print(f"  {label:44s} {'-':>8s}")
            continue
        t = totals.get(label, 0.0)
        extra = f"  ({calls.get(label, 0) / n:.1f} calls/frame)" if any(c in label for c in counted) else ""
        print(f"  {label:44s} {1e6 * t / n:8.1f} us/frame  {100 * t / seconds:5.1f} %{extra}")
    return 0


def main() -> int:
    return breakdown(STEPS, "slam", "SLAM", __doc__.splitlines()[0])


if __name__ == "__main__":
    raise SystemExit(main())
