"""Compare two vislam source trees on the shared datasets: same results, and filter time.

Usage (from the repository root, with the package's environment active)::

    git worktree add /tmp/before 5279eee          # the tree to compare against
    python benchmarks/compare_commits.py --before /tmp/before/src [--after src] \\
        [--data ../shared/data] [--repeat 5] [--options '{"stalled_tracks": "keep"}']

For each shared file and mode (localization, mapping, SLAM) both trees run in their own
subprocess (``PYTHONPATH`` set to each ``src``); the script prints the largest
difference of the trajectories and of the landmark positions, and, for SLAM on dense
0034 (``--time-file``), the filter time of ``--repeat`` runs per tree, interleaved
(minimum and median). Dense files are run with the filter told their IMU noise
(0.5 m/s, 0.05 rad/s); ``--options`` adds FilterOptions fields for the *after* tree
(e.g. ``stalled_tracks: keep`` to compare the same computation across a refactor).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

CHILD = r"""
import json, sys, numpy as np
from vislam.tools.dataset_io import load_sequence
from vislam.core.estimators import run
from vislam.core.options import FilterOptions
path, mode, out, extra, repeat = sys.argv[1], sys.argv[2], sys.argv[3], json.loads(sys.argv[4]), int(sys.argv[5])
seq = load_sequence(path)
kw = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05) if "/dense/" in path else {}
kw.update(extra)
times = []
for _ in range(repeat):
    r = run(seq, mode, FilterOptions(**kw))
    times.append(r.stats.filter_seconds)
lm = r.landmarks
np.savez(out, world_T_imu=r.world_T_imu, times=np.array(times),
         p=lm.p_lm_in_world if lm is not None else np.zeros((0, 3)),
         ids=lm.ids if lm is not None else np.zeros(0, dtype=np.int64))
"""

FILES = ["sparse/0020", "sparse/0027", "sparse/0042", "dense/0022", "dense/0027", "dense/0034"]


def _run(src: str, path: Path, mode: str, extra: dict, repeat: int, tmp: Path, tag: str) -> dict:
    out = tmp / f"{tag}-{path.parent.name}-{path.stem}-{mode}.npz"
    env = dict(os.environ, PYTHONPATH=str(Path(src).resolve()))
    subprocess.run([sys.executable, "-c", CHILD, str(path), mode, str(out), json.dumps(extra), str(repeat)],
                   env=env, check=True)
    with np.load(out) as d:
        return {k: d[k] for k in d.files}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="src directory of the reference tree")
    ap.add_argument("--after", default="src", help="src directory of the tree under test (default: src)")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--options", default="{}", help="JSON FilterOptions fields for the after tree")
    ap.add_argument("--repeat", type=int, default=5, help="timed runs per tree (SLAM on --time-file)")
    ap.add_argument("--time-file", default="dense/0034")
    ap.add_argument("--no-equivalence", action="store_true", help="only the timing")
    args = ap.parse_args()
    extra = json.loads(args.options)
    data = Path(args.data)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if not args.no_equivalence:
            for name in FILES:
                path = data / f"{name}.npz"
                for mode in ("localization", "mapping", "slam"):
                    a = _run(args.before, path, mode, {}, 1, tmp, "before")
                    b = _run(args.after, path, mode, extra, 1, tmp, "after")
                    dp = float(np.abs(a["world_T_imu"] - b["world_T_imu"]).max())
                    same_ids = a["ids"].shape == b["ids"].shape and bool(np.all(a["ids"] == b["ids"]))
                    dl = float(np.abs(a["p"] - b["p"]).max()) if same_ids and a["p"].size else 0.0
                    print(f"{name:12s} {mode:13s} trajectory {dp:.2e} m  landmarks "
                          f"{'%.2e m' % dl if same_ids else 'DIFFERENT SETS'}", flush=True)
        path = data / f"{args.time_file}.npz"
        before, after = [], []
        for _ in range(2):  # interleaved
            before += list(_run(args.before, path, "slam", {}, args.repeat, tmp, "tb")["times"])
            after += list(_run(args.after, path, "slam", extra, args.repeat, tmp, "ta")["times"])
        for tag, t in (("before", before), ("after", after)):
            print(f"{args.time_file} SLAM filter time, {tag}: min {min(t):.3f} s, median {np.median(t):.3f} s "
                  f"({len(t)} runs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
