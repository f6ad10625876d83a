"""Body or levelled velocities? The evidence on the shared files.

1. For the files with ground truth: the recorded vertical velocity against the true
   vertical speed, with the velocities read as levelled (their z is the vertical speed)
   and as body-frame (turned by the true attitude). The ground truth's world is the
   first camera's frame, not levelled: its roll and pitch are fitted first (the tilt
   that makes the true body-frame velocities most horizontal-forward).
2. SLAM and localization with ``velocity_frame: body`` and ``level``, with the options
   ``vislam run --auto`` would use (vislam check's suggestions): ATE and KITTI t-error
   where ground truth exists, the range of the estimated height everywhere.

Usage::

    PYTHONPATH=src python benchmarks/velocity_frame.py [--data ../shared/data] [--files sparse/0020 ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import vislam
from vislam.core.check import check_sequence
from vislam.core.lie import so3_exp
from vislam.core.options import FilterOptions
from vislam.tools.dataset_io import load_sequence
from vislam.tools.evaluation import evaluate, load_ground_truth

FILES = ["sparse/0020", "sparse/0027", "dense/0027", "dense/0034"]


def _yaw_only(R: np.ndarray) -> np.ndarray:
    psi = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    c, s = np.cos(psi), np.sin(psi)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def vertical_speed_check(seq, world_T_imu) -> tuple[float, float, tuple[float, float]]:
    """(rms error levelled, rms error body, fitted (roll, pitch) of the world in deg)."""
    n = len(world_T_imu)
    v = seq.linear_velocity_in_imu_mps[:n]
    R_wb = world_T_imu[:, :3, :3]
    best = None
    for roll in np.radians(np.arange(-4, 4.01, 0.25)):
        for pitch in np.radians(np.arange(-4, 4.01, 0.25)):
            R0 = so3_exp(np.array([0.0, pitch, 0.0])) @ so3_exp(np.array([roll, 0.0, 0.0]))
            R = R0 @ R_wb
            vb = np.einsum("kji,kjl,kl->ki", R, _yaw_only(R), v)  # levelled -> body with the true attitude
            cost = np.mean(vb[:, 1] ** 2) + np.mean(vb[:, 2] ** 2)
            if best is None or cost < best[0]:
                best = (cost, roll, pitch, R0)
    _, roll, pitch, R0 = best
    dt = np.diff(seq.timestamps_s[:n])
    true_vz = (np.diff(world_T_imu[:, :3, 3], axis=0) @ R0[2]) / dt
    level_vz = v[1:, 2]
    body_vz = np.einsum("kj,kj->k", (R0 @ R_wb[:-1])[:, 2, :], v[1:])
    rms = lambda x: float(np.sqrt(np.mean(x ** 2)))  # noqa: E731
    return rms(level_vz - true_vz), rms(body_vz - true_vz), (float(np.degrees(roll)), float(np.degrees(pitch)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    parser.add_argument("--files", nargs="*", default=FILES)
    args = parser.parse_args(argv)
    data = Path(args.data)
    print("| file | frame | mode | ATE (m) | KITTI t (%) | height min / max / end (m) |")
    print("|---|---|---|---:|---:|---|")
    notes = []
    for f in args.files:
        seq = load_sequence(data / f"{f}.npz")
        gt_path = data / "groundtruth" / f"{Path(f).name}.txt"
        gt = load_ground_truth(gt_path, frame="cam", cam_T_imu=seq.cam_T_imu).world_T_body if gt_path.exists() else None
        if gt is not None and f.startswith("sparse"):
            lv, bv, tilt = vertical_speed_check(seq, gt)
            notes.append(f"{f}: vertical speed rms error {lv:.3f} m/s read as levelled, {bv:.3f} m/s as body "
                         f"(world tilt roll {tilt[0]:.2f}°, pitch {tilt[1]:.2f}°)")
        suggested = check_sequence(seq).suggested
        for frame in ("body", "level"):
            options = FilterOptions.from_dict({**suggested, "velocity_frame": frame})
            for mode in ("localization", "slam"):
                result = vislam.run(seq, mode, options)
                z = result.world_T_imu[:, 2, 3]
                ate = kt = "–"
                if gt is not None:
                    m = min(len(gt), len(result.world_T_imu))
                    ev = evaluate(result.world_T_imu[:m], gt[:m])
                    ate, kt = f"{ev.ape.rmse:.3f}", f"{ev.kitti.t_pct:.2f}"
                print(f"| {f} | {frame} | {mode} | {ate} | {kt} | {z.min():.1f} / {z.max():.1f} / {z[-1]:.1f} |",
                      flush=True)
    print()
    for line in notes:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
