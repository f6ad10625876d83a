"""Run ``vislam run`` from two source trees and compare their outputs numerically.

Usage (from the repository root)::

    git archive e003dd7 src | tar -x -C /tmp/before      # the tree to compare against
    python benchmarks/compare_outputs.py --tree /tmp/before/src --tree src \\
        [--data ../shared/data] [--files sparse/0027,dense/0034] [--modes slam,localization,mapping,auto]

For every shared file and mode, each tree runs the command line in its own process
(``PYTHONPATH`` set to that tree's ``src``) with ``--quiet`` (dense files with the filter
told their IMU noise, ``--velocity-noise 0.5 --angular-noise 0.05``, as
benchmarks/run_benchmarks.py does; mode ``auto`` is SLAM with ``--auto``). It then
compares DIR/trajectory.tum (largest position difference, m, and quaternion difference)
and DIR/landmarks.npz (same ids and tracks, largest position difference, m) and prints
one line per run; the exit code is 1 when a difference exceeds ``--tolerance``
(default 1e-9 m). ``compare_commits.py`` compares the library's results the same way,
without the command line.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

FILES = ["sparse/0020", "sparse/0027", "sparse/0042", "dense/0022", "dense/0027", "dense/0034"]
MODES = ["slam", "localization", "mapping", "auto"]


def run_cli(src: str, data: Path, mode: str, out: Path) -> None:
    """``vislam run`` of ``data`` in ``mode`` from the tree ``src`` into ``out``."""
    args = [sys.executable, "-m", "vislam", "run", str(data), "--out", str(out), "--quiet",
            "--mode", "slam" if mode == "auto" else mode]
    if mode == "auto":
        args.append("--auto")
    if data.parent.name == "dense":
        args += ["--velocity-noise", "0.5", "--angular-noise", "0.05"]
    env = dict(os.environ, PYTHONPATH=str(Path(src).resolve()))
    subprocess.run(args, env=env, check=True)


def load_outputs(out: Path) -> dict:
    tum = np.loadtxt(out / "trajectory.tum", ndmin=2)
    result = {"t": tum[:, 0], "p": tum[:, 1:4], "q": tum[:, 4:8]}
    if (out / "landmarks.npz").exists():
        with np.load(out / "landmarks.npz") as d:
            result["landmarks"] = {k: d[k] for k in d.files}
    return result


def compare(a: dict, b: dict) -> tuple[float, str]:
    """(largest difference in m, a description) of two runs' outputs."""
    if a["p"].shape != b["p"].shape:
        return float("inf"), f"trajectories of {len(a['p'])} and {len(b['p'])} poses"
    dp = float(np.abs(a["p"] - b["p"]).max()) if a["p"].size else 0.0
    dq = float(np.abs(a["q"] - b["q"]).max()) if a["q"].size else 0.0
    text = f"trajectory {dp:.2e} m (quaternion {dq:.1e})"
    worst = max(dp, dq)
    la, lb = a.get("landmarks"), b.get("landmarks")
    if la is not None or lb is not None:
        if la is None or lb is None or set(la) != set(lb):
            return float("inf"), text + "  landmarks: DIFFERENT FILES"
        key = "p_lm_in_world" if "p_lm_in_world" in la else next(k for k in la if la[k].ndim == 2)
        same = all(la[k].shape == lb[k].shape for k in la) and all(
            np.array_equal(la[k], lb[k]) for k in la if la[k].dtype.kind in "iub")
        if not same:
            return float("inf"), text + "  landmarks: DIFFERENT SETS"
        dl = max((float(np.abs(la[k] - lb[k]).max()) for k in la
                  if la[k].dtype.kind == "f" and la[k].size and k.startswith("p")), default=0.0)
        text += f"  landmarks ({len(la[key])}) {dl:.2e} m"
        worst = max(worst, dl)
    return worst, text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", required=True, help="src directory of a tree (give two)")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--files", default=",".join(FILES), help="comma-separated, e.g. sparse/0027,dense/0034")
    ap.add_argument("--modes", default=",".join(MODES), help=f"comma-separated among {', '.join(MODES)}")
    ap.add_argument("--tolerance", type=float, default=1e-9, help="largest accepted difference (m)")
    ap.add_argument("--keep", help="keep the outputs in this directory (default: a temporary one)")
    ap.add_argument("--reuse-first", action="store_true",
                    help="with --keep: reuse the first tree's outputs kept there by an earlier call")
    args = ap.parse_args()
    if len(args.tree) != 2:
        ap.error("give --tree twice")
    data = Path(args.data)
    failures = 0
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.keep) if args.keep else Path(tmp)
        for name in args.files.split(","):
            path = data / f"{name}.npz"
            for mode in args.modes.split(","):
                outs = []
                for i, src in enumerate(args.tree):
                    out = work / f"{'ab'[i]}-{name.replace('/', '-')}-{mode}"
                    if not (i == 0 and args.reuse_first and (out / "summary.json").exists()):
                        run_cli(src, path, mode, out)
                    outs.append(load_outputs(out))
                worst, text = compare(*outs)
                bad = not worst <= args.tolerance
                failures += bad
                print(f"{name:12s} {mode:13s} {text}{'  DIFFERENT' if bad else ''}", flush=True)
    print("all identical within %.0e m" % args.tolerance if not failures else f"{failures} run(s) differ")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
