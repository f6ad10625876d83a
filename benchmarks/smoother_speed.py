"""The smoother's frame time of two source trees, interleaved, with their trajectories compared.

Usage (from the repository root)::

    git archive main src | tar -x -C /tmp/before      # the tree to compare against
    nice python benchmarks/smoother_speed.py --tree /tmp/before/src --tree src [--repeat 3] \\
        [--files dense/0034,dense/0027,sparse/0027] [--data ../shared/data] [--json out.json]

Each round runs, for each tree in turn (interleaved, so that both see the same machine
load), ``vislam run``'s smoother (``--mode smoother`` with the defaults; dense files with
the filter told their IMU noise, 0.5 m/s and 0.05 rad/s, as benchmarks/run_benchmarks.py
does) on every file, each in a new process with ``PYTHONPATH`` set to the tree. The child
times every frame's ``step`` in CPU time (``time.process_time``: other work on the
shared machine adds little to it) and in real time (``frame_ms_median`` of
``vislam run``'s summary), and grades the trajectory against the ground truth where the
shared data has one (sparse 0020/0027, dense 0027: ATE after SE(3) alignment, in the
IMU frame, as ``vislam run --gt``). After ``--repeat`` rounds it prints the best
(minimum) of each time, the ratio of the second tree to the first, each tree's ATE and
the largest position difference between the two trees' trajectories.

CPU time on a machine shared by several busy processes still moves by 20-30 % between
rounds (2 virtual CPUs: a busy neighbour slows this one down). ``--instructions A,B``
counts instructions instead, which load does not change: for each tree and file it runs
the smoother over the first A and the first B frames under ``valgrind --tool=callgrind``
(about 50x slower) and prints the instructions per frame of frames A..B (the difference
of the two counts, so start-up and imports cancel out), and their ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FILES = ["dense/0034"]
GROUND_TRUTH = {"sparse/0020": "0020", "sparse/0027": "0027", "dense/0027": "0027"}


def child(data: str, gt: str | None, save: str) -> int:
    """One smoother run in this process (the tree on PYTHONPATH): JSON on stdout."""
    import numpy as np

    from vislam.core import smoother
    from vislam.core.estimators import run
    from vislam.core.options import FilterOptions
    from vislam.tools.dataset_io import load_sequence

    seq = load_sequence(data)
    kw = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05) if Path(data).parent.name == "dense" else {}
    cpu = []
    step = smoother.SmootherFilter.step

    def timed_step(self, frame):
        c0 = time.process_time()
        try:
            return step(self, frame)
        finally:
            cpu.append(time.process_time() - c0)

    smoother.SmootherFilter.step = timed_step
    c0 = time.process_time()
    result = run(seq, "smoother", FilterOptions(**kw))
    out = {"run_cpu_s": time.process_time() - c0, "frame_cpu_ms_median": float(np.median(cpu) * 1e3),
           "frame_ms_median": float(np.median(result.stats.frame_seconds) * 1e3), "ate_m": None}
    if gt:
        from vislam.tools.comparison import evaluate_run, load_run_ground_truth

        out["ate_m"] = float(evaluate_run(result, load_run_ground_truth(gt, seq), seq).ape.rmse)
    np.save(save, result.world_T_imu)
    print(json.dumps(out))
    return 0


def child_frames(data: str, frames: int) -> int:
    """The smoother over the first ``frames`` frames (for instruction counts)."""
    from vislam.core.options import FilterOptions
    from vislam.core.smoother import SmootherFilter
    from vislam.tools.dataset_io import load_sequence

    seq = load_sequence(data)
    kw = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05) if Path(data).parent.name == "dense" else {}
    filt = SmootherFilter(seq.calibration, FilterOptions(**kw))
    for frame in seq.frames(0, frames):
        filt.step(frame)
    filt.finish()
    return 0


def count_instructions(src: str, data: Path, frames: int) -> int:
    """Instructions (callgrind's total Ir) of a process running the smoother over ``frames`` frames."""
    with tempfile.TemporaryDirectory() as tmp:
        args = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={tmp}/cg.out", sys.executable,
                str(Path(__file__).resolve()), "--child", str(data), "--frames", str(frames)]
        env = dict(os.environ, PYTHONPATH=str(Path(src).resolve()))
        done = subprocess.run(args, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    return int(re.search(r"Collected : (\d+)", done.stderr).group(1))


def instructions(trees: list, files: list, data_dir: str, a: int, b: int) -> None:
    per_frame = {}
    for name in files:
        data = Path(data_dir) / f"{name}.npz"
        for tree in trees:
            n_a, n_b = count_instructions(tree, data, a), count_instructions(tree, data, b)
            per_frame[tree, name] = (n_b - n_a) / (b - a)
            print(f"{tree[-32:]:32s} {name:12s} frames {a}..{b}: {per_frame[tree, name] / 1e6:8.2f} M instructions "
                  f"per frame", flush=True)
        if len(trees) == 2:
            print(f"ratio second/first {name:12s} {per_frame[trees[1], name] / per_frame[trees[0], name]:.3f}")


def time_run(src: str, data: Path, gt: Path | None, save: Path) -> dict:
    args = [sys.executable, str(Path(__file__).resolve()), "--child", str(data), "--save", str(save)]
    if gt is not None:
        args += ["--gt", str(gt)]
    env = dict(os.environ, PYTHONPATH=str(Path(src).resolve()))
    done = subprocess.run(args, env=env, check=True, stdout=subprocess.PIPE, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", help="src directory of a tree (give one or two)")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--files", default=",".join(FILES))
    ap.add_argument("--repeat", type=int, default=3, help="rounds (default 3)")
    ap.add_argument("--json", help="also write the results to this file")
    ap.add_argument("--instructions", metavar="A,B", help="count instructions per frame of frames A..B instead "
                    "(valgrind)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--frames", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--gt", help=argparse.SUPPRESS)
    ap.add_argument("--save", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        if args.frames is not None:
            return child_frames(args.child, args.frames)
        return child(args.child, args.gt, args.save)
    if not args.tree:
        ap.error("give --tree (once or twice)")
    if args.instructions:
        a, b = (int(x) for x in args.instructions.split(","))
        instructions(args.tree, args.files.split(","), args.data, a, b)
        return 0
    import numpy as np

    files = args.files.split(",")
    keys = ("frame_cpu_ms_median", "frame_ms_median", "run_cpu_s")
    best = {t: {f: dict.fromkeys(keys, float("inf")) for f in files} for t in args.tree}
    ate: dict = {t: {} for t in args.tree}
    diff: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for rnd in range(args.repeat):
            for name in files:
                data = Path(args.data) / f"{name}.npz"
                gt = Path(args.data) / "groundtruth" / f"{GROUND_TRUTH[name]}.txt" if name in GROUND_TRUTH else None
                for i, tree in enumerate(args.tree):
                    r = time_run(tree, data, gt, Path(tmp) / f"{i}.npy")
                    for k in keys:
                        best[tree][name][k] = min(best[tree][name][k], r[k])
                    ate[tree][name] = r["ate_m"]
                if len(args.tree) == 2:
                    a, b = (np.load(Path(tmp) / f"{i}.npy") for i in range(2))
                    diff[name] = float(np.abs(a[:, :3, 3] - b[:, :3, 3]).max()) if a.shape == b.shape else None
            print(f"round {rnd + 1}/{args.repeat} done", file=sys.stderr, flush=True)
    print(f"best of {args.repeat}, {platform.node()} ({os.cpu_count()} CPUs), Python {platform.python_version()}, "
          f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print(f"{'tree':32s} {'file':12s} {'frame CPU ms':>13s} {'frame ms':>9s} {'run CPU s':>10s} {'ATE m':>8s}")
    for tree in args.tree:
        for name in files:
            r, e = best[tree][name], ate[tree][name]
            print(f"{tree[-32:]:32s} {name:12s} {r['frame_cpu_ms_median']:13.2f} {r['frame_ms_median']:9.2f} "
                  f"{r['run_cpu_s']:10.2f} {'-' if e is None else f'{e:.4f}':>8s}")
    if len(args.tree) == 2:
        a, b = (best[t] for t in args.tree)
        for name in files:
            d = diff.get(name)
            print(f"ratio second/first {name:12s} frame CPU {b[name]['frame_cpu_ms_median'] / a[name]['frame_cpu_ms_median']:.3f}"
                  f"  frame {b[name]['frame_ms_median'] / a[name]['frame_ms_median']:.3f}"
                  f"  run CPU {b[name]['run_cpu_s'] / a[name]['run_cpu_s']:.3f}"
                  f"  max position difference {'-' if d is None else f'{d:.2e}'} m")
    if args.json:
        Path(args.json).write_text(json.dumps({"repeat": args.repeat, "machine": platform.node(),
                                               "cpus": os.cpu_count(), "best": best, "ate_m": ate,
                                               "max_position_difference_m": diff}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
