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
each run and the mean ATE / KITTI t-error per setting. ``--lever-arm-shift X,Y,Z`` adds to that translation (camera frame; +Z moves the IMU
forward). The lever-arm comparison (docs/data.md, "The dense files and the EKF")::

    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm file \
        --options '{"repeated_observations": "skip"}'
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm corrected \
        --options '{"repeated_observations": "skip"}'
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm corrected
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm file
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm corrected --lever-arm-shift 0,0,1
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm corrected --mode smoother
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm corrected --outlier-seeds '' \
        --no-file --draw-gyro-bias 0.0041,0.0049,0.0049      # with and without --options skip
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm corrected --outlier-seeds '' \
        --no-file --draws 0,1,2 --draw-velocities truth --options '{"repeated_observations": "skip"}'
    PYTHONPATH=src python benchmarks/noise_draws.py --depths 200 --lever-arm corrected --outlier-seeds '' \
        --draws '' --heading --options '{"repeated_observations": "skip"}'   # where the heading goes wrong

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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from velocity_truth import true_twists  # noqa: E402


def heading_error(world_T_cam: np.ndarray, gt_world_T_cam: np.ndarray) -> str:
    """The estimate's heading error about the first camera's vertical (its y axis; both
    trajectories start at the same pose): at the end, and summed over the frames where the
    ground truth turns (> 0.01 rad per frame) and where it does not, degrees."""
    est = gt_world_T_cam[0] @ se3_inverse(world_T_cam[0]) @ world_T_cam  # start at the same pose

    def yaw(T):
        return np.unwrap(np.arctan2(T[:, 0, 2], T[:, 2, 2]))

    gt_yaw = yaw(gt_world_T_cam)
    err = np.degrees(yaw(est) - gt_yaw)
    d_err, turning = np.gradient(err), np.abs(np.gradient(gt_yaw)) > 0.01
    return (f"heading {err[-1]:+.2f} deg (turns {d_err[turning].sum():+.2f}, straights {d_err[~turning].sum():+.2f}; "
            f"turned {np.degrees(np.abs(np.diff(gt_yaw)).sum()):.0f} deg)")


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
    parser.add_argument("--lever-arm-shift", default="0,0,0", metavar="X,Y,Z",
                        help="added to cam_T_imu's translation (camera frame, m): +Z moves the IMU forward")
    parser.add_argument("--draw-velocities", choices=("clean", "truth"), default="clean",
                        help="what the draws add noise to: sparse 0027's clean velocities, or the ground "
                             "truth's own twists (the IMU motion under the published calibration)")
    parser.add_argument("--draw-gyro-bias", default="0,0,0", metavar="X,Y,Z",
                        help="a constant added to the draws' angular rates (rad/s, IMU frame)")
    parser.add_argument("--no-file", action="store_true", help="leave out the file as shared")
    parser.add_argument("--heading", action="store_true",
                        help="also print each run's heading error: at the end, and accumulated in turns and on "
                             "straights (the ground truth's yaw rate above / below 0.01 rad per frame)")
    args = parser.parse_args(argv)
    data = Path(args.data)
    dense = load_sequence(data / "dense" / "0027.npz")
    sparse = load_sequence(data / "sparse" / "0027.npz")
    gt_cam = read_trajectory(data / "groundtruth" / "0027.txt", "kitti").world_T_body
    extra = json.loads(args.options)
    C_pub = np.array(dense.cam_T_imu)  # the published calibration: the files store imu_T_cam's translation
    C_pub[:3, 3] = swapped_translation(dense.cam_T_imu)
    shift = np.array([float(x) for x in args.lever_arm_shift.split(",")])
    if args.lever_arm == "corrected" or shift.any():
        C = (C_pub if args.lever_arm == "corrected" else np.array(dense.cam_T_imu)).copy()
        C[:3, 3] += shift
        extra["cam_T_imu"] = C.tolist()
    depths = [float(x) for x in args.depths.split(",")]
    base_v, base_w = sparse.linear_velocity_in_imu_mps, sparse.angular_velocity_in_imu_radps
    if args.draw_velocities == "truth":
        twist, _ = true_twists(sparse, gt_cam @ C_pub)  # sample k+1 describes k -> k+1
        base_v, base_w = twist[:, :3], twist[:, 3:]
    gyro_bias = np.array([float(x) for x in args.draw_gyro_bias.split(",")])
    cases = [] if args.no_file else [("as shared", dense)]
    for seed in [int(x) for x in args.outlier_seeds.split(",") if x]:
        cases.append((f"outliers s{seed}", inject_noise(dense, NoiseSpec(outlier_fraction=0.05, seed=seed))[0]))
    for n in [int(x) for x in args.draws.split(",") if x]:
        rng = np.random.default_rng(100 + n)
        v = base_v + rng.normal(0, 0.5, base_v.shape)
        w = base_w + rng.normal(0, 0.05, base_w.shape) + gyro_bias
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
            if args.heading:
                line.append(heading_error(cam[:m], gt_cam[:m]))
        print(f"{name:12s} " + " | ".join(line), flush=True)
    for d in depths:
        a = np.array(results[d])
        print(f"max_depth_m {d:g}: mean ATE {a[:, 0].mean():.2f} m (worst {a[:, 0].max():.2f}), "
              f"mean KITTI t {a[:, 1].mean():.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
