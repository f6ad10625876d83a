"""Where a whole ``vislam run`` goes outside the filter: the imports, loading the file,
the filter, the outputs and the trajectory figure, timed in one process (wall and CPU).

Usage (from the repository root)::

    PYTHONPATH=src python benchmarks/process_breakdown.py ../shared/data/sparse/0027.npz [--mode slam]

The command line is ``vislam run FILE --mode MODE --out TMP --quiet``, run through
``vislam.cli.main`` in this process with timers around its steps (the imports first, in
the order the command needs them). The trajectory figure is drawn by a helper process
(:mod:`vislam.tools.figure_process`) that imports matplotlib meanwhile; its line is this
process's wait for it. Python's own start-up (about 20 ms) is not included;
``benchmarks/filter_speed.py`` times the whole process from outside.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tempfile
import time

MARKS: list[tuple[str, float, float]] = []


def mark(name: str) -> None:
    MARKS.append((name, time.perf_counter(), time.process_time()))


def _wrap(module, name: str, label: str) -> None:
    inner = getattr(module, name)

    def timed(*args, **kwargs):
        mark(f"(before {label})")
        out = inner(*args, **kwargs)
        mark(label)
        return out

    setattr(module, name, timed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data")
    parser.add_argument("--mode", default="slam")
    args = parser.parse_args()
    mark("start")
    importlib.import_module("numpy")
    mark("import numpy")
    import vislam.cli as cli
    from vislam.cli import common, run as run_command
    mark("import vislam.cli")
    import vislam.core.estimators as estimators
    mark("import the estimators (scipy.linalg)")
    for name in ("vislam.tools.comparison", "vislam.tools.config"):
        importlib.import_module(name)
    import vislam.tools.outputs as outputs
    from vislam.tools.figure_process import FigureProcess
    mark("import the output tools")
    _wrap(run_command, "load_data", "load the recording")
    _wrap(common, "load_data", "load the recording")
    _wrap(estimators, "run", "filter")
    # the figure's helper process imports matplotlib while this one filters: this is the wait for it
    _wrap(FigureProcess, "plot_trajectory_map", "trajectory figure (the helper process)")
    _wrap(outputs, "write_run_outputs", "summary.json (after the figure)")
    with tempfile.TemporaryDirectory() as tmp:
        code = cli.main(["run", args.data, "--mode", args.mode, "--out", f"{tmp}/out", "--quiet"])
    mark("cleaning up (temporary folder)")
    if code:
        sys.exit(code)
    rows = [(name, t - MARKS[i][1], c - MARKS[i][2]) for i, (name, t, c) in enumerate(MARKS[1:])
            if not name.startswith("(before")]
    gaps = [(name, t - MARKS[i][1], c - MARKS[i][2]) for i, (name, t, c) in enumerate(MARKS[1:])
            if name.startswith("(before")]
    print(f"vislam run {args.data} --mode {args.mode}: seconds (wall / CPU)")
    for name, wall, cpu in rows:
        print(f"  {name:50s} {wall:6.3f} / {cpu:6.3f}")
    between = sum(w for _, w, _ in gaps), sum(c for _, _, c in gaps)
    print(f"  {'the rest (parsing, staging, trajectory/map files)':50s} {between[0]:6.3f} / {between[1]:6.3f}")
    total = MARKS[-1][1] - MARKS[0][1], MARKS[-1][2] - MARKS[0][2]
    filt = next((w, c) for name, w, c in rows if name == "filter")
    print(f"  {'total':50s} {total[0]:6.3f} / {total[1]:6.3f}")
    print(f"  {'total outside the filter':50s} {total[0] - filt[0]:6.3f} / {total[1] - filt[1]:6.3f}")


if __name__ == "__main__":
    main()
