"""`--auto` on the shared files with ground truth and on altered copies of them.

For each file (default: dense/0027, sparse/0027, sparse/0020 — the ones with ground
truth), the original and the altered copies of ``check_faults.py`` (a: velocities in a
frame turned 180° about x; b: velocity samples shifted by one index; c: cam_T_imu turned
3° about camera x, y, z): SLAM with ``vislam run --auto``'s options (``vislam check``'s
suggestions, corrections applied by the library's ``run``), graded against the ground
truth, and the ratio of each altered file's ATE to the original's (issue 11 asks ≤ 1.2).
With ``--hand`` the dense files also get the hand-set noise (0.5 m/s, 0.05 rad/s) for
comparison. Prints a Markdown table; ``--json FILE`` writes the rows.

Usage::

    PYTHONPATH=src python benchmarks/auto_faults.py [--data ../shared/data] [--files dense/0027 ...] [--json F]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from check_faults import variants  # noqa: E402

import vislam  # noqa: E402
from vislam.core.check import check_sequence  # noqa: E402
from vislam.core.options import FilterOptions  # noqa: E402
from vislam.tools.dataset_io import load_sequence  # noqa: E402
from vislam.tools.evaluation import evaluate, load_ground_truth  # noqa: E402

FILES = ["dense/0027", "sparse/0027", "sparse/0020"]


def grade(seq, options: FilterOptions, gt_path: Path, original) -> dict:
    # the ground truth is of the left camera; the original file's cam_T_imu converts it
    # (an altered cam_T_imu is the fault, not the truth)
    gt = load_ground_truth(gt_path, frame="cam", cam_T_imu=original.cam_T_imu).world_T_body
    t0 = time.perf_counter()
    result = vislam.run(seq, "slam", options)
    n = min(len(gt), len(result.world_T_imu))
    ev = evaluate(result.world_T_imu[:n], gt[:n])
    return {"ate_m": ev.ape.rmse, "kitti_t_pct": float(ev.kitti.t_pct),
            "seconds": time.perf_counter() - t0, "rejected": result.stats.landmarks_rejected}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    parser.add_argument("--files", nargs="*", default=FILES)
    parser.add_argument("--hand", action="store_true", help="also the hand-set noise on dense files")
    parser.add_argument("--json", help="also write the rows to this JSON file")
    args = parser.parse_args(argv)
    data = Path(args.data)
    rows = []
    for f in args.files:
        original = load_sequence(data / f"{f}.npz")
        gt_path = data / "groundtruth" / f"{Path(f).name}.txt"
        cases = [("original", original)] + [(name, seq) for name, seq, _ in variants(original)]
        base = None
        for name, seq in cases:
            check = check_sequence(seq)
            options = FilterOptions.from_dict(check.suggested)
            row = {"file": f, "variant": name, "suggested": check.suggested, **grade(seq, options, gt_path, original)}
            if name == "original":
                base = row["ate_m"]
            row["ratio"] = row["ate_m"] / base
            rows.append(row)
            print(f"| {f} | {name} | {row['ate_m']:.3f} | {row['ratio']:.2f} | {row['rejected']} | "
                  f"{json.dumps(check.suggested)} |", flush=True)
        if args.hand and f.startswith("dense"):
            options = FilterOptions(velocity_noise_mps=0.5, angular_noise_radps=0.05)
            row = {"file": f, "variant": "original, hand-set noise", "suggested": None,
                   **grade(original, options, gt_path, original)}
            row["ratio"] = row["ate_m"] / base
            rows.append(row)
            print(f"| {f} | hand-set | {row['ate_m']:.3f} | {row['ratio']:.2f} | {row['rejected']} | |", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
