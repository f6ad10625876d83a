"""What if the filter read the angular rates as levelled, as the KITTI files hold them?

The files' angular rates are expressed in the levelled (heading-aligned) frame of their
linear velocities (``benchmarks/velocity_truth.py``); the filter uses them as body rates.
This experiment turns them into the body frame with the estimate's attitude, as
``velocity_frame: level`` does for the linear velocity, with the matching transition
(F = Ad(exp(−τ û)) − τ ∂u/∂δ, the ω rows included), and optionally gives the initial
roll and pitch an uncertainty (``initial_rotation_std_rad``) so that the filter can find
the vehicle's initial tilt. It patches :mod:`vislam.core.propagation` for the run (it
is not a filter option) and prints ATE / KITTI t / KITTI r per file and variant.

Usage::

    PYTHONPATH=src python benchmarks/levelled_rates.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

import vislam.core.filters as filters
import vislam.core.propagation as propagation
from vislam.core.lie import se3_adjoint, se3_exp

FILES = [("sparse/0020", "0020", []), ("sparse/0027", "0027", []),
         ("dense/0027", "0027", ["--velocity-noise", "0.5", "--angular-noise", "0.05"])]

_original = (propagation.prediction_twist, propagation.predict_pose, filters.prediction_twist)


def _levelled_prediction_twist(u, imu_T_world, velocity_frame, jacobian):
    if velocity_frame != "level":
        return _original[0](u, imu_T_world, velocity_frame, jacobian)
    u = np.asarray(u, dtype=np.float64)
    out = u.copy()
    out[:3] = propagation.level_to_body(imu_T_world, u[:3])
    out[3:] = propagation.level_to_body(imu_T_world, u[3:])
    if not jacobian:
        return out, None
    h = 1e-6
    poses = np.broadcast_to(imu_T_world, (6, 4, 4)).copy()
    poses[:, :3, :3] = propagation._PERTURB_ROTATIONS @ imu_T_world[:3, :3]
    du = np.zeros((6, 6))
    for rows in (slice(0, 3), slice(3, 6)):
        turned = propagation.level_to_body(poses, np.broadcast_to(u[rows], (6, 3)))
        du[rows, 3:] = (turned[:3] - turned[3:]).T / (2 * h)
    return out, du


def _predict_pose_full_jacobian(imu_T_world, pose_cov, tau, u, W, oc_correction=None, du=None):
    step = se3_exp(-tau * u)
    F = se3_adjoint(step)
    if du is not None:
        F = F - tau * du  # first order in τ: J_l(−τu) ≈ I
    if oc_correction is not None:
        F = F @ se3_adjoint(se3_exp(oc_correction))
    cov = F @ pose_cov @ F.T + (tau * tau) * W
    return step @ imu_T_world, 0.5 * (cov + cov.T), F


def _patch(levelled: bool) -> None:
    if levelled:
        propagation.prediction_twist = filters.prediction_twist = _levelled_prediction_twist
        propagation.predict_pose = _predict_pose_full_jacobian
    else:
        propagation.prediction_twist, propagation.predict_pose, filters.prediction_twist = _original


def main(argv=None) -> int:
    from vislam.cli import main as cli

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    args = parser.parse_args(argv)
    data = Path(args.data)
    print("| file | rates read as | initial roll/pitch σ (rad) | ATE m | KITTI t % | KITTI r °/100 m |")
    print("|---|---|---|---:|---:|---:|")
    for file, gt, extra in FILES:
        path, gt_path = data / f"{file}.npz", data / "groundtruth" / f"{gt}.txt"
        if not (path.exists() and gt_path.exists()):
            print(f"| {file} | skipped: {path} or {gt_path} missing | | | | |")
            continue
        for levelled, std in ((False, 0.0), (True, 0.0), (True, 0.05)):
            _patch(levelled)
            with tempfile.TemporaryDirectory() as tmp:
                config = Path(tmp) / "options.yaml"
                config.write_text(f"initial_rotation_std_rad: {std}\n")
                out = Path(tmp) / "run"
                code = cli(["run", str(path), "--mode", "slam", "--config", str(config), "--gt", str(gt_path),
                            "--out", str(out), "--quiet", *extra])
                if code != 0:
                    print(f"| {file} | run failed ({code}) | | | | |")
                    continue
                e = json.loads((out / "summary.json").read_text())["evaluation"]
            print(f"| {file} | {'levelled' if levelled else 'body (default)'} | {std:g} | {e['ape_rmse_m']:.2f} | "
                  f"{e['kitti_t_pct']:.2f} | {e['kitti_r_deg_per_100m']:.2f} |")
    _patch(False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
