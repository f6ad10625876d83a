"""Tests of the KITTI odometry metric (vislam.core.metrics) on trajectories of known error."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import drifting_estimate
from vislam.core.lie import make_pose, se3_exp, so3_exp
from vislam.core.metrics import (
    KITTI_SEGMENT_LENGTHS_M,
    kitti_odometry_errors,
    rotation_angle_clipped,
    trajectory_distances,
)


def rz(angle) -> np.ndarray:
    angle = np.asarray(angle, dtype=np.float64)
    return so3_exp(np.stack([np.zeros_like(angle), np.zeros_like(angle), angle], axis=-1))


def straight_line(n: int, step_m: float) -> np.ndarray:
    """Poses along +x, identity rotation, ``step_m`` between frames."""
    p = np.zeros((n, 3))
    p[:, 0] = step_m * np.arange(n)
    return make_pose(np.broadcast_to(np.eye(3), (n, 3, 3)), p)


def planar_drive(n: int, step_m: float, turn_rate: float = 0.004) -> np.ndarray:
    """A planar drive: heading about z changes by ``turn_rate`` rad per frame (sinusoidally
    modulated), position advances ``step_m`` along the heading."""
    heading = np.cumsum(turn_rate * np.sin(np.arange(n) / 60.0))
    heading -= heading[0]
    fwd = np.stack([np.cos(heading), np.sin(heading), np.zeros(n)], axis=1)
    p = np.concatenate([[np.zeros(3)], np.cumsum(step_m * fwd[:-1], axis=0)])
    return make_pose(rz(heading), p)


def random_drive(rng, n: int) -> np.ndarray:
    """A random 3-D trajectory: body-frame twists integrated on SE(3), ~1.5 m per frame."""
    xi = np.zeros((n - 1, 6))
    xi[:, 0] = rng.uniform(0.5, 2.5, n - 1)
    xi[:, 1:3] = rng.normal(0, 0.05, (n - 1, 2))
    xi[:, 3:] = rng.normal(0, 0.02, (n - 1, 3))
    steps = se3_exp(xi)
    poses = np.empty((n, 4, 4))
    poses[0] = make_pose(so3_exp(rng.normal(0, 1, 3)), rng.normal(0, 10, 3))
    for k in range(n - 1):
        poses[k + 1] = poses[k] @ steps[k]
    return poses


def reference_kitti(est, gt, lengths=KITTI_SEGMENT_LENGTHS_M, step=10):
    """Straightforward transcription of the devkit's calcSequenceErrors."""
    dist = [0.0]
    for i in range(1, len(gt)):
        dist.append(dist[-1] + float(np.linalg.norm(gt[i, :3, 3] - gt[i - 1, :3, 3])))
    out = []
    for first in range(0, len(gt), step):
        for length in lengths:
            last = -1
            for i in range(first, len(dist)):
                if dist[i] > dist[first] + length:
                    last = i
                    break
            if last == -1:
                continue
            d_gt = np.linalg.inv(gt[first]) @ gt[last]
            d_est = np.linalg.inv(est[first]) @ est[last]
            err = np.linalg.inv(d_est) @ d_gt  # the devkit's order
            a, b, c = err[0, 0], err[1, 1], err[2, 2]
            r = np.arccos(max(min(0.5 * (a + b + c - 1.0), 1.0), -1.0))
            out.append((first, last, length, np.linalg.norm(err[:3, 3]) / length, r / length))
    return out


def test_identical_trajectories_have_zero_error():
    gt = random_drive(np.random.default_rng(1), 700)
    res = kitti_odometry_errors(gt, gt)
    assert res.has_segments and res.n_segments > 100
    # zero up to rounding (the devkit's arccos resolves angles only down to ~1e-8 rad)
    assert abs(res.t_pct) < 1e-12
    assert abs(res.r_deg_per_100m) < 1e-6
    np.testing.assert_allclose(res.t_err, 0.0, atol=1e-14)
    np.testing.assert_allclose(res.r_err_rad_per_m, 0.0, atol=1e-9)


@pytest.mark.parametrize("s", [0.01, -0.03, 0.2])
def test_scaled_straight_line_gives_scale_error(s):
    step = 1.3
    gt = straight_line(800, step)
    est = gt.copy()
    est[:, :3, 3] *= 1.0 + s
    res = kitti_odometry_errors(est, gt)
    assert res.has_segments
    # Each segment: the estimate travels (1 + s) times the true segment distance, so
    # ||t_err|| = |s| (dist[last] - dist[first]) / L exactly.
    true_len = step * (res.last_frame - res.first_frame)
    np.testing.assert_allclose(res.t_err, abs(s) * true_len / res.segment_length_m, rtol=1e-12, atol=1e-15)
    # The devkit picks the first frame strictly beyond L: L < true_len <= L + step.
    assert np.all(true_len > res.segment_length_m) and np.all(true_len <= res.segment_length_m + step + 1e-9)
    assert 100 * abs(s) <= res.t_pct <= 100 * abs(s) * (1 + step / 100.0)
    np.testing.assert_allclose(res.r_err_rad_per_m, 0.0, atol=1e-15)


def test_scaled_straight_line_fine_sampling_converges_to_scale():
    s = 0.05
    gt = straight_line(20001, 0.05)  # 1 km in 5 cm steps
    est = gt.copy()
    est[:, :3, 3] *= 1.0 + s
    res = kitti_odometry_errors(est, gt)
    np.testing.assert_allclose(res.t_pct, 100 * s, rtol=1e-3)
    np.testing.assert_allclose(res.t_pct_by_length, 100 * s, rtol=1e-3)


def test_constant_extra_yaw_rate_gives_analytic_rotation_error():
    omega = 2e-4  # rad per frame of extra yaw
    step = 1.1
    gt = planar_drive(900, step)
    est = gt @ make_pose(rz(omega * np.arange(900)), np.zeros((900, 3)))
    res = kitti_odometry_errors(est, gt)
    assert res.has_segments
    # Planar rotations commute: the error rotation is Rz(omega (last - first)).
    expected = omega * (res.last_frame - res.first_frame) / res.segment_length_m
    np.testing.assert_allclose(res.r_err_rad_per_m, expected, rtol=1e-7)
    np.testing.assert_allclose(res.r_deg_per_100m, np.degrees(expected.mean()) * 100, rtol=1e-7)
    # and close to the yaw rate per metre, omega / step (the segments overshoot L by < 1 step)
    np.testing.assert_allclose(res.r_deg_per_100m, np.degrees(omega / step) * 100, rtol=0.015)


def test_metric_is_invariant_to_a_rigid_transform_of_the_estimate():
    rng = np.random.default_rng(2)
    gt = random_drive(rng, 700)
    A = make_pose(so3_exp([0.3, -1.2, 2.0]), [100.0, -50.0, 7.0])
    res = kitti_odometry_errors(A @ gt, gt)
    np.testing.assert_allclose(res.t_err, 0.0, atol=1e-9)
    # arccos near 1 resolves angles only to ~sqrt(2 eps) ~ 2e-8 rad
    np.testing.assert_allclose(res.r_err_rad_per_m, 0.0, atol=1e-8)

    est = drifting_estimate(rng, gt, sigma_t=0.02)
    base = kitti_odometry_errors(est, gt)
    moved = kitti_odometry_errors(A @ est, gt)
    assert base.t_pct > 0.1
    np.testing.assert_allclose(moved.t_err, base.t_err, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(moved.r_err_rad_per_m, base.r_err_rad_per_m, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_segments_match_straightforward_loop(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(300, 700))
    gt = random_drive(rng, n)
    est = drifting_estimate(rng, gt, sigma_t=0.05, sigma_r=0.003)
    res = kitti_odometry_errors(est, gt)
    ref = reference_kitti(est, gt)
    assert res.n_segments == len(ref) > 0
    first, last, length, t_err, r_err = map(np.array, zip(*ref))
    np.testing.assert_array_equal(res.first_frame, first)
    np.testing.assert_array_equal(res.last_frame, last)
    np.testing.assert_array_equal(res.segment_length_m, length)
    np.testing.assert_allclose(res.t_err, t_err, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.r_err_rad_per_m, r_err, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(res.t_pct, 100 * t_err.mean(), rtol=1e-9)
    np.testing.assert_allclose(res.r_deg_per_100m, np.degrees(r_err.mean()) * 100, rtol=1e-7)
    for k, L in enumerate(res.lengths_m):
        sel = length == L
        assert res.n_segments_by_length[k] == sel.sum()
        if sel.any():
            np.testing.assert_allclose(res.t_pct_by_length[k], 100 * t_err[sel].mean(), rtol=1e-9)
        else:
            assert np.isnan(res.t_pct_by_length[k])


def test_step_and_lengths_parameters():
    rng = np.random.default_rng(6)
    gt = random_drive(rng, 300)
    est = drifting_estimate(rng, gt, sigma_t=0.02)
    res = kitti_odometry_errors(est, gt, lengths_m=(50.0, 150.0), step_frames=3)
    ref = reference_kitti(est, gt, lengths=(50.0, 150.0), step=3)
    assert res.n_segments == len(ref)
    np.testing.assert_array_equal(res.first_frame, [r[0] for r in ref])
    with pytest.raises(ValueError):
        kitti_odometry_errors(est, gt, step_frames=0)
    with pytest.raises(ValueError):
        kitti_odometry_errors(est, gt, lengths_m=(-1.0,))


def test_short_trajectory_has_no_segments_and_nan_means():
    gt = straight_line(50, 1.0)  # 49 m
    res = kitti_odometry_errors(gt, gt)
    assert not res.has_segments and res.n_segments == 0
    assert np.isnan(res.t_pct) and np.isnan(res.r_deg_per_100m)
    assert np.all(np.isnan(res.t_pct_by_length)) and np.all(res.n_segments_by_length == 0)
    assert res.path_length_m == pytest.approx(49.0)
    # a single pose, and no pose at all, do not crash either
    assert not kitti_odometry_errors(gt[:1], gt[:1]).has_segments
    assert not kitti_odometry_errors(gt[:0], gt[:0]).has_segments


def test_length_mismatch_and_bad_shapes_raise():
    gt = straight_line(20, 1.0)
    with pytest.raises(ValueError, match="associate"):
        kitti_odometry_errors(gt[:10], gt)
    with pytest.raises(ValueError):
        kitti_odometry_errors(gt[:, :3], gt[:, :3])
    bad = gt.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        kitti_odometry_errors(bad, gt)


def test_trajectory_distances_and_clipped_angle():
    gt = straight_line(5, 2.0)
    np.testing.assert_allclose(trajectory_distances(gt), [0, 2, 4, 6, 8])
    # a rotation whose trace exceeds 3 by rounding gives 0, not NaN
    R = np.eye(3) * (1 + 1e-12)
    assert rotation_angle_clipped(R) == 0.0
    angles = np.array([0.0, 0.3, 1.5, np.pi])
    np.testing.assert_allclose(rotation_angle_clipped(rz(angles)), angles, atol=1e-7)
