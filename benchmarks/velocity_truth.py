"""How far are the recorded IMU velocities from the camera's true motion? (ground truth)

For the shared files with ground truth (KITTI left-camera poses, turned into IMU poses
with the file's cam_T_imu), three measurements:

1. **Velocity error per step** against the true motion: the recorded speed against the
   true displacement over the frame interval (sample k+1 describes k -> k+1), and the
   angular velocity against the true relative rotation. RMS, mean, the white part (RMS
   of first differences / sqrt 2) and the autocorrelation of the speed error at a few
   lags: an error that is white has autocorrelation ~0 at lag 1; a slowly varying one
   (bias, scale, smoothing) stays near 1 for many frames.
2. **Reprojection of the tracks** (vislam check's predictions: a point triangulated at
   frame k, predicted up to 5 frames later, median / p75 left-image distance, px) under
   the recorded velocities and under the true motion: which of the two the images agree
   with.
3. **IMU-camera rotation fit with the true motion** (vislam check's robust fit, gyro
   bias off): on the file as stored and with cam_T_imu turned by 3° about each camera
   axis. What a perfect motion source would give the hand-eye fit. Then the same fit
   (file as stored) with the recorded velocities, and with one half of the twist
   recorded and the other true: which part biases check's rotation.
4. **The frame of the recorded angular rates**: their error against the true body
   rates, and against the true rates expressed in the levelled (heading-aligned) frame
   of the linear velocities (the ground truth's world is the first camera's frame:
   its roll and pitch are fitted first, as benchmarks/velocity_frame.py does), with the
   correlation of the pitch-rate error with the yaw rate (a levelled rate read as a
   body rate is off by the tilt times the yaw rate).

Usage::

    PYTHONPATH=src python benchmarks/velocity_truth.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from vislam.core.check import _fit_rotation_and_bias, _TrackPairs, level_velocities_to_body
from vislam.core.corrections import rotate_cam_T_imu
from vislam.core.lie import se3_inverse, se3_log, so3_exp, so3_log
from vislam.tools.dataset_io import load_sequence
from vislam.tools.evaluation import load_ground_truth

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/velocity_frame.py

FILES = [("sparse/0020", "0020"), ("sparse/0027", "0027"), ("dense/0027", "0027")]


def true_twists(seq, world_T_imu: np.ndarray) -> tuple[np.ndarray, int]:
    """(T, 6) body twists whose exponential over each frame interval is the true
    relative motion (sample k+1 for k -> k+1), and the number of frames with truth."""
    n = min(len(world_T_imu), seq.n_frames)
    rel = se3_inverse(world_T_imu[:n - 1]) @ world_T_imu[1:n]
    u = np.zeros((seq.n_frames, 6))
    u[1:n] = se3_log(rel) / np.diff(seq.timestamps_s[:n])[:, None]
    return u, n


def velocity_errors(seq, world_T_imu: np.ndarray) -> None:
    n = min(len(world_T_imu), seq.n_frames)
    dt = np.diff(seq.timestamps_s[:n])
    rel = se3_inverse(world_T_imu[:n - 1]) @ world_T_imu[1:n]
    true_speed = np.linalg.norm(rel[:, :3, 3], axis=1) / dt
    e_v = np.linalg.norm(seq.linear_velocity_in_imu_mps[1:n], axis=1) - true_speed
    e_w = seq.angular_velocity_in_imu_radps[1:n] - so3_log(rel[:, :3, :3]) / dt[:, None]
    white = lambda e: np.sqrt(np.mean(np.diff(e, axis=0) ** 2, axis=0) / 2)  # noqa: E731
    ac = {lag: float(np.corrcoef(e_v[:-lag], e_v[lag:])[0, 1]) for lag in (1, 10, 50)}
    print(f"  speed error: RMS {np.sqrt(np.mean(e_v ** 2)):.3f} m/s, mean {e_v.mean():+.3f}, white part "
          f"{white(e_v):.3f}; autocorrelation lag 1 / 10 / 50: {ac[1]:.2f} / {ac[10]:.2f} / {ac[50]:.2f}")
    print(f"  angular velocity error per axis: RMS {np.array2string(np.sqrt(np.mean(e_w ** 2, axis=0)), precision=4)}"
          f" rad/s, white part {np.array2string(white(e_w), precision=4)}")


def reprojection(seq, u_true: np.ndarray, n: int, rng) -> None:
    pairs = _TrackPairs(seq, 5, 60.0, None, rng)
    sel = pairs.frame + pairs.lag < n
    for label, u in (("recorded velocities", level_velocities_to_body(seq.velocities())), ("true motion", u_true)):
        r = pairs.residuals(pairs.relative_imu(seq.timestamps_s, u, 1), seq.cam_T_imu)
        d = np.linalg.norm(r[:, :2], axis=1)[sel]
        print(f"  tracks under the {label}: median {np.median(d):.2f} px, p75 {np.percentile(d, 75):.2f} px "
              f"({d.size} predictions)")


def _fit_pairs(seq, n: int, rng) -> _TrackPairs:
    """check's prediction pairs within the frames with ground truth, 4000 at random."""
    pairs = _TrackPairs(seq, 5, 60.0, None, rng)
    keep = pairs.frame + pairs.lag < n
    for name in ("frame", "lag", "landmark", "points", "target"):
        setattr(pairs, name, getattr(pairs, name)[keep])
    return pairs.subset(4000, rng)


def rotation_with_truth(seq, u_true: np.ndarray, n: int, rng) -> None:
    pairs = _fit_pairs(seq, n, rng)
    for axis in (None, 0, 1, 2):
        C = np.array(seq.cam_T_imu)
        if axis is not None:
            phi = np.zeros(3)
            phi[axis] = 3.0
            C = rotate_cam_T_imu(C, phi)
        x, _, _ = _fit_rotation_and_bias(pairs, seq.timestamps_s, u_true, C, 1, 3.0, np.zeros(3), fit_bias=False)
        what = "as stored" if axis is None else f"turned 3° about camera {'xyz'[axis]}"
        print(f"  rotation fit with the true motion, cam_T_imu {what}: correction "
              f"{np.array2string(np.degrees(x[:3]), precision=2)}°, |φ| {np.degrees(np.linalg.norm(x[:3])):.2f}°")


def rotation_sources(seq, u_true: np.ndarray, n: int, rng) -> None:
    pairs = _fit_pairs(seq, n, rng)
    u_rec = level_velocities_to_body(seq.velocities())
    for label, u in (("recorded velocities", u_rec),
                     ("true linear + recorded angular", np.concatenate([u_true[:, :3], u_rec[:, 3:]], axis=1)),
                     ("recorded linear + true angular", np.concatenate([u_rec[:, :3], u_true[:, 3:]], axis=1))):
        x, _, _ = _fit_rotation_and_bias(pairs, seq.timestamps_s, u, np.array(seq.cam_T_imu), 1, 3.0, np.zeros(3),
                                         fit_bias=False)
        print(f"  rotation fit with the {label}: correction {np.array2string(np.degrees(x[:3]), precision=2)}°")


def rate_frame(seq, world_T_imu: np.ndarray) -> None:
    from velocity_frame import _yaw_only, vertical_speed_check  # noqa: E402 (this folder)

    n = min(len(world_T_imu), seq.n_frames)
    W = world_T_imu[:n]
    _, _, (roll, pitch) = vertical_speed_check(seq, W)
    R0 = so3_exp(np.array([0.0, np.radians(pitch), 0.0])) @ so3_exp(np.array([np.radians(roll), 0.0, 0.0]))
    rel = se3_inverse(W[:-1]) @ W[1:]
    w_body = so3_log(rel[:, :3, :3]) / np.diff(seq.timestamps_s[:n])[:, None]
    R = R0 @ W[:-1, :3, :3]
    level_R_body = np.einsum("kji,kjl->kil", _yaw_only(R), R)
    w_level = np.einsum("kij,kj->ki", level_R_body, w_body)
    w_rec = seq.angular_velocity_in_imu_radps[1:n]
    for label, w in (("true body rates", w_body), ("true rates in the levelled frame", w_level)):
        e = w_rec - w
        print(f"  recorded angular rates against the {label}: RMS per axis "
              f"{np.array2string(np.sqrt(np.mean(e ** 2, axis=0)), precision=4)} rad/s; correlation of the "
              f"pitch-rate error with the yaw rate {np.corrcoef(e[:, 1], w_body[:, 2])[0, 1]:+.2f}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    args = parser.parse_args(argv)
    data = Path(args.data)
    for file, gt in FILES:
        path, gt_path = data / f"{file}.npz", data / "groundtruth" / f"{gt}.txt"
        if not (path.exists() and gt_path.exists()):
            print(f"{file}: skipped ({path} or {gt_path} missing)")
            continue
        seq = load_sequence(path)
        world_T_imu = load_ground_truth(gt_path, frame="cam", cam_T_imu=seq.cam_T_imu).world_T_body
        u_true, n = true_twists(seq, world_T_imu)
        print(f"{file} ({n} frames with ground truth)")
        velocity_errors(seq, world_T_imu)
        reprojection(seq, u_true, n, np.random.default_rng(0))
        rotation_with_truth(seq, u_true, n, np.random.default_rng(0))
        rotation_sources(seq, u_true, n, np.random.default_rng(0))
        if file.startswith("sparse"):  # the dense files' rates carry 0.05 rad/s of white noise
            rate_frame(seq, world_T_imu)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
