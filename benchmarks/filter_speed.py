"""EKF filter time, whole-process time and ``vislam --help`` time of two source trees.

Usage (from the repository root)::

    git archive e003dd7 src | tar -x -C /tmp/before      # the tree to compare against
    nice python benchmarks/filter_speed.py --tree /tmp/before/src --tree src [--repeat 5] \\
        [--files sparse/0020,sparse/0027,dense/0034] [--data ../shared/data] [--json out.json]

Each round runs, for each tree in turn (interleaved, so that both see the same machine
load), ``vislam run DATA --mode slam --out DIR --quiet`` on every file (dense files with
``--velocity-noise 0.5 --angular-noise 0.05``, as benchmarks/run_benchmarks.py does) and
``vislam --help``, each in a new process with ``PYTHONPATH`` set to the tree. It records
``filter_seconds`` from DIR/summary.json and the wall and CPU time of the whole process. After
``--repeat`` rounds it prints the best (minimum) of each, and the ratio of the second tree
to the first. Best-of is the figure to compare on a shared machine: other work only ever
adds time. ``--gt`` runs every file with its ground truth (``--gt DATA/groundtruth/STEM.txt``:
the evaluation, metrics.json and its figure in the whole process), e.g.::

    python benchmarks/filter_speed.py --tree /tmp/before/src --tree src --files sparse/0027 --gt
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FILES = ["sparse/0020", "sparse/0027", "dense/0034"]


def _env(src: str) -> dict:
    return dict(os.environ, PYTHONPATH=str(Path(src).resolve()))


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def time_run(src: str, data: Path, out: Path, gt: Path | None = None) -> tuple[float, float, float]:
    """(filter_seconds, whole-process wall seconds, whole-process CPU seconds) of one ``vislam run``."""
    args = [sys.executable, "-m", "vislam", "run", str(data), "--mode", "slam", "--out", str(out), "--quiet"]
    if data.parent.name == "dense":
        args += ["--velocity-noise", "0.5", "--angular-noise", "0.05"]
    if gt is not None:
        args += ["--gt", str(gt)]
    t0, c0 = time.perf_counter(), _children_cpu()
    subprocess.run(args, env=_env(src), check=True)
    wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
    return float(json.loads((out / "summary.json").read_text())["filter_seconds"]), wall, cpu


def time_help(src: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "vislam", "--help"], env=_env(src), check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", required=True, help="src directory of a tree (give one or two)")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--files", default=",".join(FILES))
    ap.add_argument("--repeat", type=int, default=5, help="rounds (default 5)")
    ap.add_argument("--json", help="also write the results to this file")
    ap.add_argument("--gt", action="store_true", help="run with each file's ground truth (DATA/groundtruth/STEM.txt)")
    args = ap.parse_args()
    files = args.files.split(",")
    gts = {f: Path(args.data) / "groundtruth" / f"{Path(f).name}.txt" if args.gt else None for f in files}
    missing = [str(g) for g in gts.values() if g is not None and not g.is_file()]
    if missing:
        ap.error(f"--gt: no ground truth {', '.join(missing)}")
    best: dict = {t: {"help_s": float("inf"), **{f: {"filter_s": float("inf"), "process_s": float("inf"), "process_cpu_s": float("inf")}
                                                 for f in files}} for t in args.tree}
    with tempfile.TemporaryDirectory() as tmp:
        for rnd in range(args.repeat):
            for tree in args.tree:
                b = best[tree]
                b["help_s"] = min(b["help_s"], time_help(tree))
                for name in files:
                    filt, wall, cpu = time_run(tree, Path(args.data) / f"{name}.npz", Path(tmp) / "out", gts[name])
                    b[name]["filter_s"] = min(b[name]["filter_s"], filt)
                    b[name]["process_s"] = min(b[name]["process_s"], wall)
                    b[name]["process_cpu_s"] = min(b[name]["process_cpu_s"], cpu)
            print(f"round {rnd + 1}/{args.repeat} done", file=sys.stderr, flush=True)
    print(f"best of {args.repeat}, {platform.node()} ({os.cpu_count()} CPUs), Python {platform.python_version()}, "
          f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print(f"{'tree':40s} {'file':12s} {'filter s':>9s} {'process s':>10s} {'process - filter':>17s} "
          f"{'process CPU s':>14s}")
    for tree in args.tree:
        for name in files:
            r = best[tree][name]
            print(f"{tree[-40:]:40s} {name:12s} {r['filter_s']:9.3f} {r['process_s']:10.3f} "
                  f"{r['process_s'] - r['filter_s']:17.3f} {r['process_cpu_s']:14.3f}")
        print(f"{tree[-40:]:40s} {'--help':12s} {'':9s} {best[tree]['help_s']:10.3f}")
    if len(args.tree) == 2:
        a, b = (best[t] for t in args.tree)
        for name in files:
            print(f"ratio second/first {name:12s} filter {b[name]['filter_s'] / a[name]['filter_s']:.3f}  "
                  f"process {b[name]['process_s'] / a[name]['process_s']:.3f}  "
                  f"process CPU {b[name]['process_cpu_s'] / a[name]['process_cpu_s']:.3f}")
        print(f"ratio second/first --help {b['help_s'] / a['help_s']:.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"repeat": args.repeat, "machine": platform.node(),
                                               "cpus": os.cpu_count(), "best": best}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
