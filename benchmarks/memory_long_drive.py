"""Peak RSS of ``vislam run`` on long drives in the shared files' layout (issue 22.8).

A simulated drive of ``--base`` frames (``vislam.simulate_drive``, default options) is
tiled N times into one npz in the shared files' layout — C-ordered ``features`` (4, M, T)
of float64, -1 where unobserved, deflate-compressed — whose landmarks x frames grow as
the shared files' do (each tile brings its own landmarks, M ∝ T). The file is written
stream-wise (the dense array of a 10,000-frame drive would be ~11 GB). Then each
``vislam run FILE --mode MODE --quiet`` runs in a child under ``/usr/bin/time -f %M``
and its peak RSS is recorded.

    python benchmarks/memory_long_drive.py                      # 2,500 and 10,000 frames, slam
    python benchmarks/memory_long_drive.py --tiles 2,8 --modes localization,slam --out benchmarks/results/memory_long_drive.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from vislam.core.simulate import SimulationOptions, simulate_drive  # noqa: E402


def write_tiled(path: Path, seq, tiles: int, block: int = 256) -> tuple[int, int, int]:
    """Write ``tiles`` copies of ``seq`` one after the other (new landmark ids per tile)."""
    obs = seq.observations
    T0, M0 = seq.n_frames, obs.n_landmarks
    T, M = T0 * tiles, M0 * tiles
    dense0 = obs.dense()  # (4, M0, T0)
    t0 = seq.timestamps_s
    step = float(np.median(np.diff(t0)))
    stamps = np.concatenate([t0 + k * (t0[-1] - t0[0] + step) for k in range(tiles)])
    small = {"time_stamps": stamps[None, :], "linear_velocity": np.tile(seq.linear_velocity_in_imu_mps.T, tiles),
             "rotational_velocity": np.tile(seq.angular_velocity_in_imu_radps.T, tiles), "K": seq.camera.K,
             "b": np.array(seq.camera.baseline_m), "cam_T_imu": seq.cam_T_imu}
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1, allowZip64=True) as zf:
        for name, a in small.items():
            with zf.open(f"{name}.npy", "w") as fp:
                np.lib.format.write_array(fp, np.ascontiguousarray(a), allow_pickle=False)
        with zf.open("features.npy", "w", force_zip64=True) as fp:
            np.lib.format.write_array_header_1_0(fp, {"descr": "<f8", "fortran_order": False, "shape": (4, M, T)})
            for c in range(4):
                for k in range(tiles):
                    for j in range(0, M0, block):
                        rows = np.full((min(block, M0 - j), T), -1.0)
                        rows[:, k * T0:(k + 1) * T0] = dense0[c, j:j + block]
                        fp.write(rows.tobytes())
    return T, M, obs.n_observations * tiles


def peak_rss_kb(args: list[str]) -> tuple[int, float, int]:
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", ""))
    with tempfile.NamedTemporaryFile("r", suffix=".time") as tf:
        tic = time.perf_counter()
        proc = subprocess.run(["/usr/bin/time", "-f", "%M", "-o", tf.name, sys.executable, "-m", "vislam", *args],
                              capture_output=True, text=True, env=env)
        seconds = time.perf_counter() - tic
        text = Path(tf.name).read_text().strip().splitlines()
    if proc.returncode != 0:
        print(proc.stderr, file=sys.stderr)
    return int(text[-1]), seconds, proc.returncode


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=int, default=1250, help="frames of the simulated drive that is tiled")
    parser.add_argument("--tiles", default="2,8", help="comma-separated tile counts (default 2,8: 2,500 and 10,000 frames)")
    parser.add_argument("--modes", default="slam")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "memory_long_drive.json"))
    parser.add_argument("--work", default=None, help="folder for the npz files (default: a temporary one)")
    args = parser.parse_args()
    seq = simulate_drive(SimulationOptions(n_frames=args.base)).sequence
    rows = []
    with tempfile.TemporaryDirectory(dir=args.work) as work:
        for tiles in [int(x) for x in args.tiles.split(",")]:
            path = Path(work) / f"drive{tiles}.npz"
            T, M, N = write_tiled(path, seq, tiles)
            for mode in args.modes.split(","):
                kb, seconds, rc = peak_rss_kb(["run", str(path), "--mode", mode, "--quiet", "--out",
                                              str(Path(work) / f"out{tiles}{mode}")])
                row = {"frames": T, "landmarks": M, "observations": N, "cells": 4 * M * T,
                       "npz_mb": round(path.stat().st_size / 1e6, 1), "mode": mode, "peak_rss_mb": round(kb / 1024, 1),
                       "seconds": round(seconds, 1), "returncode": rc}
                print(json.dumps(row), flush=True)
                rows.append(row)
            path.unlink()
    by_mode = {}
    for r in rows:
        by_mode.setdefault(r["mode"], []).append(r)
    ratios = {m: rs[-1]["peak_rss_mb"] / rs[0]["peak_rss_mb"] for m, rs in by_mode.items() if len(rs) > 1}
    out = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "load_average": os.getloadavg(), "base_frames": args.base,
           "rows": rows, "peak_rss_ratio_longest_to_shortest": ratios}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print("peak RSS ratio (longest / shortest):", {m: round(v, 2) for m, v in ratios.items()})
    return 0 if all(r["returncode"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
