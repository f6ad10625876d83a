"""SLAM on the shared KITTI drive sparse 0027, each frame's final pose graded against the
ground truth. Needs ../shared/data next to the checkout (or VISLAM_SHARED_DATA)."""

import os
from pathlib import Path

import numpy as np

import vislam
from vislam.tools.evaluation import load_ground_truth

NEEDS_SHARED_DATA = True
data = Path(os.environ.get("VISLAM_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))

seq = vislam.load_sequence(data / "sparse" / "0027.npz")
f = vislam.SlamFilter(seq.calibration, vislam.FilterOptions())
poses = np.array([world_T_imu for _, world_T_imu in vislam.final_poses(f, seq.frames())])

gt = load_ground_truth(data / "groundtruth" / "0027.txt", "kitti", frame="cam", cam_T_imu=seq.cam_T_imu)
n = min(len(poses), len(gt.world_T_body))
ev = vislam.evaluate(poses[:n], gt.world_T_body[:n])
print(f"sparse 0027: ATE {ev.ape.rmse:.2f} m, KITTI {ev.kitti.t_pct:.2f} % over {n} frames")
