"""SLAM on dense 0027 over fresh IMU-noise draws and with injected outliers.

One file's ATE moves a lot with small changes, so option defaults are compared over
several runs of the same drive:

* ``as shared``: dense 0027 as it is;
* ``outliers sN``: dense 0027 with 5 % of its observations replaced by gross outliers
  (``inject_noise(NoiseSpec(outlier_fraction=0.05, seed=N))``, N = 1, 2);
* ``draw N``: dense 0027's features with *fresh* IMU noise — sparse 0027's clean
  velocities (the same drive) plus white noise of the dense files' level (0.5 m/s,
  0.05 rad/s per axis and sample; ``numpy.random.default_rng(100 + N)``), N = 0..3.

Every run is SLAM (``--mode smoother`` for the smoother) with ``--velocity-noise 0.5
--angular-noise 0.05`` plus the options given as JSON, for each value of ``max_depth_m``
listed; graded against the ground truth in the camera frame (the estimate turned into
left-camera poses with the cam_T_imu the filter used). ``--lever-arm corrected`` runs
with the IMU-camera translation corrected (the files store imu_T_cam's, see
vislam.core.rigs.swapped_translation), ``file`` (the default) with the file's. Prints
each run and the mean ATE / KITTI t-error per setting. The lever-arm comparison::

    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --outlier-seeds '' --lever-arm file
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --outlier-seeds '' --lever-arm corrected
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --outlier-seeds '' --lever-arm corrected --mode smoother

The measurements behind ``FilterOptions.max_depth_m``'s default::

    PYTHONPATH=src python benchmarks/noise_draws.py --depths 60,100,200
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 \
        --options '{"landmark_parametrization": "inverse_depth", "update_iterations": 3}'
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import vislam
from vislam.core.noise import NoiseSpec, inject_noise
from vislam.core.options import FilterOptions
from vislam.tools.dataset_io import load_sequence
from vislam.core.rigs import swapped_translation
from vislam.core.lie import se3_inverse
from vislam.tools.evaluation import evaluate
from vislam.tools.trajectory_io import read_trajectory


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    parser.add_argument("--depths", default="60,100,200", help="max_depth_m values, comma-separated")
    parser.add_argument("--draws", default="0,1,2,3", help="fresh noise draws, comma-separated")
    parser.add_argument("--outlier-seeds", default="1,2", help="outlier injection seeds ('' for none)")
    parser.add_argument("--options", default="{}", help="other FilterOptions as JSON")
    parser.add_argument("--lever-arm", choices=("file", "corrected"), default="file",
                        help="the files' cam_T_imu, or with its translation corrected (swapped)")
    parser.add_argument("--mode", choices=("slam", "smoother"), default="slam")
    args = parser.parse_args(argv)
    data = Path(args.data)
    dense = load_sequence(data / "dense" / "0027.npz")
    sparse = load_sequence(data / "sparse" / "0027.npz")
    gt_cam = read_trajectory(data / "groundtruth" / "0027.txt", "kitti").world_T_body
    extra = json.loads(args.options)
    if args.lever_arm == "corrected":
        C = np.array(dense.cam_T_imu)
        C[:3, 3] = swapped_translation(dense.cam_T_imu)
        extra["cam_T_imu"] = C.tolist()
    depths = [float(x) for x in args.depths.split(",")]
    cases = [("as shared", dense)]
    for seed in [int(x) for x in args.outlier_seeds.split(",") if x]:
        cases.append((f"outliers s{seed}", inject_noise(dense, NoiseSpec(outlier_fraction=0.05, seed=seed))[0]))
    for n in [int(x) for x in args.draws.split(",") if x]:
        rng = np.random.default_rng(100 + n)
        v = sparse.linear_velocity_in_imu_mps + rng.normal(0, 0.5, sparse.linear_velocity_in_imu_mps.shape)
        w = sparse.angular_velocity_in_imu_radps + rng.normal(0, 0.05, sparse.angular_velocity_in_imu_radps.shape)
        cases.append((f"draw {n}", dense.replace(linear_velocity_in_imu_mps=v, angular_velocity_in_imu_radps=w)))
    results = {d: [] for d in depths}
    for name, seq in cases:
        line = []
        for d in depths:
            opts = FilterOptions(velocity_noise_mps=0.5, angular_noise_radps=0.05, max_depth_m=d, **extra)
            r = vislam.run(seq, args.mode, opts)
            cam = r.world_T_imu @ se3_inverse(np.asarray(r.calibration.cam_T_imu))  # world_T_cam
            m = min(len(gt_cam), len(cam))
            ev = evaluate(cam[:m], gt_cam[:m])
            results[d].append((ev.ape.rmse, ev.kitti.t_pct))
            line.append(f"{d:g} m: {ev.ape.rmse:.2f} m {ev.kitti.t_pct:.2f} %")
        print(f"{name:12s} " + " | ".join(line), flush=True)
    for d in depths:
        a = np.array(results[d])
        print(f"max_depth_m {d:g}: mean ATE {a[:, 0].mean():.2f} m (worst {a[:, 0].max():.2f}), "
              f"mean KITTI t {a[:, 1].mean():.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
