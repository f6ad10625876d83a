"""Filter consistency: the NEES convention (against the filters' left perturbation of the
inverse pose), the localization filter's NEES ≈ 6 over Monte Carlo runs (the correctness
test of the NEES), the anchored inverse-depth landmarks (Jacobians against finite
differences, SLAM recovers a simulated ground truth), and ``vislam consistency``'s outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vislam.cli import main
from vislam.core.consistency import chi2_band, filter_nees, pose_error, pose_nees, true_noise_options
from vislam.core.lie import se3_exp, se3_inverse
from vislam.core.options import FilterOptions
from vislam.core.simulate import KITTI_CAM_T_IMU, SimulationOptions, kitti_stereo_camera, simulate_drive
from vislam.core.state import inverse_depth_to_world
from vislam.core.updaters import StereoModel, _init_geometry, _init_geometry_inverse_depth


def test_pose_error_is_the_filters_left_perturbation_of_the_inverse_pose():
    rng = np.random.default_rng(0)
    mu = se3_exp(rng.normal(0, 0.5, 6))
    delta = rng.normal(0, 0.05, 6)
    truth = se3_exp(delta) @ mu  # imu_T_world = exp(δ^) μ (core/state.py)
    assert np.allclose(pose_error(truth, mu), delta, atol=1e-12)
    P = np.diag(rng.uniform(0.01, 0.1, 6) ** 2)
    assert np.isclose(pose_nees(truth, mu, P), delta @ np.linalg.solve(P, delta), rtol=1e-10)
    # a right perturbation of the same size gives another error (the side matters)
    assert not np.allclose(pose_error(mu @ se3_exp(delta), mu), delta, atol=1e-4)


def test_chi2_band_of_the_average_of_runs():
    from scipy.stats import chi2

    lo, hi = chi2_band(1, 6)
    assert np.isclose(chi2.cdf(lo, 6), 0.025) and np.isclose(chi2.cdf(hi, 6), 0.975)
    lo20, hi20 = chi2_band(20, 6)
    assert lo < lo20 < 6 < hi20 < hi  # narrower around the dof for more runs


def test_localization_nees_is_six_over_monte_carlo_runs():
    """IMU-only prediction is linear-Gaussian up to the SE(3) exponential, so the filter
    told the simulator's noise must be consistent: the pose NEES averaged over runs and
    frames is 6. The per-run time average has a standard deviation of about 2.4 (measured
    over 60 runs of 100 frames), so the mean of 30 runs has about 0.45: ±1.5 is ~3.3 σ."""
    per_run = []
    for seed in range(30):
        sim = SimulationOptions(seed=seed, n_frames=60, velocity_noise_mps=0.5, angular_noise_radps=0.05)
        trace = filter_nees(simulate_drive(sim), true_noise_options(sim), "localization")
        assert np.isnan(trace.pose_nees[0]) and np.all(np.isfinite(trace.pose_nees[1:]))
        per_run.append(np.nanmean(trace.pose_nees))
    mean = float(np.mean(per_run))
    assert abs(mean - 6.0) < 1.5, f"localization pose NEES {mean:.2f}, expected 6"


def test_true_noise_options_match_the_simulator():
    sim = SimulationOptions(velocity_noise_mps=0.3, angular_noise_radps=0.02, pixel_noise_px=0.7)
    opts = true_noise_options(sim)
    # W is the covariance of one velocity sample's noise, as the simulator draws it
    assert np.allclose(np.diag(opts.W), [0.09] * 3 + [0.0004] * 3)
    assert np.allclose(opts.V, 0.49 * np.eye(4))


@pytest.fixture(scope="module")
def model():
    return StereoModel(kitti_stereo_camera(), KITTI_CAM_T_IMU)


def test_inverse_depth_initialization_and_jacobians(model):
    rng = np.random.default_rng(1)
    mu0 = se3_exp(rng.normal(0, 0.3, 6))
    z = np.array([[700.0, 150.0, 690.0, 150.0], [300.0, 250.0, 270.0, 250.0], [1000.0, 100.0, 996.0, 100.0]])
    lam, G_pose, G_pix, anchors = _init_geometry_inverse_depth(model, mu0, z)
    p_w, _, _ = _init_geometry(model, mu0, z)
    p_lam, J = inverse_depth_to_world(lam, anchors)
    assert np.allclose(p_lam, p_w, atol=1e-9)  # same point as the Cartesian triangulation
    assert np.allclose(model.predict(mu0, lam, world_T_anchor=anchors)[0][:, :3], z[:, :3], atol=1e-9)

    mu = se3_exp(rng.normal(0, 0.05, 6)) @ mu0
    _, Hp, Hl, in_front = model.predict(mu, lam, world_T_anchor=anchors)
    assert np.all(in_front)
    for i in range(6):  # left perturbation of the pose
        d = np.zeros(6)
        d[i] = 1e-6
        fd = (model.predict(se3_exp(d) @ mu, lam, world_T_anchor=anchors)[0]
              - model.predict(se3_exp(-d) @ mu, lam, world_T_anchor=anchors)[0]) / 2e-6
        assert np.allclose(fd, Hp[:, :, i], rtol=1e-4, atol=1e-3)
    for i in range(3):  # additive on (α, β, ρ)
        d = np.zeros(3)
        d[i] = 1e-8
        fd = (model.predict(mu, lam + d, world_T_anchor=anchors)[0]
              - model.predict(mu, lam - d, world_T_anchor=anchors)[0]) / 2e-8
        assert np.allclose(fd, Hl[:, :, i], rtol=1e-4, atol=1e-2)
    for i in range(3):  # dp/dλ of the conversion
        d = np.zeros(3)
        d[i] = 1e-8
        fd = (inverse_depth_to_world(lam + d, anchors)[0] - inverse_depth_to_world(lam - d, anchors)[0]) / 2e-8
        assert np.allclose(fd, J[:, :, i], rtol=1e-4, atol=1e-4)

    # dλ/dδ: the same pixels seen from the true pose exp(δ^) μ0, in the fixed anchor frame
    p_c = model.camera.triangulate(z)
    anchor_T_world = se3_inverse(anchors[0])

    def lam_at(T):
        m = se3_inverse(T) @ model.imu_T_cam @ np.c_[p_c, np.ones(len(p_c))].T
        q = (anchor_T_world @ m).T
        return np.c_[q[:, 0] / q[:, 2], q[:, 1] / q[:, 2], 1.0 / q[:, 2]]

    for i in range(6):
        d = np.zeros(6)
        d[i] = 1e-6
        fd = (lam_at(se3_exp(d) @ mu0) - lam_at(se3_exp(-d) @ mu0)) / 2e-6
        assert np.allclose(fd, G_pose[:, :, i], atol=1e-6)
    # G_pix: λ is linear in the pixels
    dz = rng.normal(0, 0.5, z.shape)
    dz[:, 3] = 0.0
    lam2 = _init_geometry_inverse_depth(model, mu0, z + dz)[0]
    assert np.allclose(lam2 - lam, np.einsum("kij,kj->ki", G_pix, dz), atol=1e-12)


@pytest.mark.parametrize("chart,iterations", [("inverse_depth", 1), ("inverse_depth", 3)])
def test_slam_recovers_the_simulated_drive(chart, iterations):
    """SLAM with inverse-depth landmarks (EKF and iterated EKF; the Cartesian default is
    tested in test_estimators) tracks a simulated drive with noisy velocities far better
    than dead reckoning, and its map matches the true landmarks."""
    from vislam.core.estimators import run_localization, run_slam

    sim = SimulationOptions(seed=2, n_frames=40, velocity_noise_mps=0.5, angular_noise_radps=0.05)
    drive = simulate_drive(sim)
    opts = true_noise_options(sim, FilterOptions(landmark_parametrization=chart, update_iterations=iterations))
    result = run_slam(drive.sequence, opts)
    dead = run_localization(drive.sequence, opts)
    assert not result.partial

    def rms(r):
        return np.sqrt(np.mean(np.sum((r.world_T_imu[:, :3, 3] - drive.world_T_imu[:, :3, 3]) ** 2, axis=1)))

    assert rms(result) < 0.15, f"{chart}: RMS position error {rms(result):.3f} m"
    assert rms(result) < 0.2 * rms(dead)
    lm = result.landmarks
    ok = lm.status == 0
    assert ok.sum() > 80
    err = np.linalg.norm(lm.p_lm_in_world[ok] - drive.p_lm_in_world[lm.ids[ok]], axis=1)
    assert np.median(err) < 0.5, f"{chart}: median landmark error {np.median(err):.2f} m"


def test_cli_consistency_writes_json_and_figure(tmp_path, capsys):
    out = tmp_path / "cons"
    assert main(["consistency", "--runs", "2", "--frames", "15", "--out", str(out), "--sequential", "--quiet"]) == 0
    data = json.loads((out / "consistency.json").read_text())
    for key in ("pose_nees_mean", "landmark_nees_mean", "pose_share_inside_band", "landmark_share_inside_band",
                "runs", "frames", "noise_told", "pose_band_95", "landmark_band_95"):
        assert key in data, key
    assert data["runs"] == 2 and data["frames"] == 15
    assert data["noise_told"] == {"velocity_noise_mps": 0.5, "angular_noise_radps": 0.05, "pixel_noise_px": 0.5}
    assert data["pose_nees_mean"] > 0 and 0 <= data["pose_share_inside_band"] <= 1
    assert len(data["pose_nees_per_frame"]) == 15
    assert (out / "consistency.png").stat().st_size > 10_000
    assert main(["consistency", "--runs", "0", "--out", str(out), "--sequential"]) != 0
    assert "--runs must be" in capsys.readouterr().err


def test_iterated_update_reaches_the_map_estimate_of_one_frame(model):
    """With a wide pose prior (0.3 m, 0.03 rad) and 40 precisely known landmarks, the
    iterated update (3 iterations) lands on the maximum a posteriori pose found by
    nonlinear least squares; the single EKF update, linearized at the prior, does not."""
    from scipy.optimize import least_squares

    from vislam.core.lie import se3_log
    from vislam.core.state import SlamState
    from vislam.core.updaters import slam_update_iterated

    rng = np.random.default_rng(0)
    k = 40
    p_c = np.c_[rng.uniform(-10, 10, k), rng.uniform(-2, 2, k), rng.uniform(4, 40, k)]
    p_w = (model.imu_T_cam @ np.c_[p_c, np.ones(k)].T).T[:, :3]  # true pose: identity
    P_pose = np.diag([0.3**2] * 3 + [0.03**2] * 3)
    V = 0.25 * np.eye(4)
    Linv = np.linalg.cholesky(np.linalg.inv(P_pose)).T
    gaps = {1: [], 3: []}
    for _ in range(5):
        mu0 = se3_exp(-rng.multivariate_normal(np.zeros(6), P_pose))
        z = model.predict(np.eye(4), p_w)[0] + rng.normal(0, 0.5, (k, 4))

        def residual(d):
            return np.concatenate([((z - model.predict(se3_exp(d) @ mu0, p_w)[0]) / 0.5).ravel(), Linv @ d])

        mu_map = se3_exp(least_squares(residual, np.zeros(6)).x) @ mu0
        for iterations in (1, 3):
            state = SlamState(mu0, P_pose)
            state.add_landmarks(np.arange(k), p_w, np.zeros((3 * k, 6)), 1e-10 * np.eye(3 * k))
            eps = slam_update_iterated(state, model, np.arange(k), z, V, None, iterations)
            assert np.allclose(se3_exp(eps) @ mu0, state.imu_T_world, atol=1e-9)
            gaps[iterations].append(np.linalg.norm(se3_log(mu_map @ se3_inverse(state.imu_T_world))))
    assert max(gaps[3]) < 1e-3, gaps
    assert np.mean(gaps[1]) > 10 * np.mean(gaps[3])


def test_adaptive_iterated_update_is_the_fixed_one_stopped_at_convergence(model):
    """``tolerance`` > 0 (FilterOptions.update_iteration_tolerance): the iterated update
    stops when the next re-linearization would move the estimate by less than that many
    standard deviations. It must reach the optimum of the fixed iterated update (and be
    exactly the fixed update with the number of updates it chose, covariance included,
    although it rebuilds the prior covariance from the gain's factors instead of a
    copy); with a prior narrow against the pixel noise it stops after one update, the
    EKF update."""
    from vislam.core.lie import se3_log
    from vislam.core.state import SlamState
    from vislam.core.updaters import slam_update_iterated

    rng = np.random.default_rng(3)
    k = 40
    p_c = np.c_[rng.uniform(-10, 10, k), rng.uniform(-2, 2, k), rng.uniform(4, 40, k)]
    p_w = (model.imu_T_cam @ np.c_[p_c, np.ones(k)].T).T[:, :3]  # true pose: identity

    def fresh(mu0, P_pose, lm0):
        state = SlamState(mu0, P_pose)
        state.add_landmarks(np.arange(k), lm0, np.zeros((3 * k, 6)), lm_sd**2 * np.eye(3 * k))
        return state

    for wide in (True, False):
        P_pose = np.diag([0.3**2] * 3 + [0.03**2] * 3) if wide else np.diag([1e-3**2] * 3 + [1e-4**2] * 3)
        px, lm_sd = (0.5, 0.05) if wide else (2.0, 0.001)
        V = px**2 * np.eye(4)
        for trial in range(3):
            mu0 = se3_exp(-rng.multivariate_normal(np.zeros(6), P_pose))
            lm0 = p_w + rng.normal(0, lm_sd, p_w.shape)
            z = model.predict(np.eye(4), p_w)[0] + rng.normal(0, px, (k, 4))
            counts = []
            adaptive = fresh(mu0, P_pose, lm0)
            eps = slam_update_iterated(adaptive, model, np.arange(k), z, V, None, 10, tolerance=0.01, counts=counts)
            assert np.allclose(se3_exp(eps) @ mu0, adaptive.imu_T_world, atol=1e-9)
            n = counts[0]
            if wide:
                assert 2 <= n < 10, n  # iterates, and stops before the maximum
                converged = fresh(mu0, P_pose, lm0)
                slam_update_iterated(converged, model, np.arange(k), z, V, None, 10)
                gap = se3_log(converged.imu_T_world @ se3_inverse(adaptive.imu_T_world))
                sd = np.sqrt(np.diag(adaptive.pose_cov))
                assert np.all(np.abs(gap) < 0.05 * sd), gap / sd  # the same optimum, within 5 % of a σ
                lm_post_sd = np.sqrt(np.diag(adaptive.cov)[6:])
                assert np.all(np.abs(converged.lm_mean - adaptive.lm_mean).ravel() < 0.05 * lm_post_sd)
            else:
                assert n == 1  # the linearization at the prior is good enough: the EKF update
            fixed = fresh(mu0, P_pose, lm0)
            slam_update_iterated(fixed, model, np.arange(k), z, V, None, n)
            assert np.allclose(fixed.imu_T_world, adaptive.imu_T_world, atol=1e-10)
            assert np.allclose(fixed.lm_mean, adaptive.lm_mean, atol=1e-10)
            assert np.allclose(fixed.cov, adaptive.cov, atol=1e-12, rtol=1e-8)


@pytest.mark.parametrize("changes, words", [
    (dict(pixel_noise_px=1e300), "--sim-pixel-noise must be a finite number in [0, 1e+06]"),
    (dict(pixel_noise_px=0.0), "--sim-pixel-noise must be at least 1e-06 px"),
    (dict(velocity_noise_mps=-1.0), "--sim-velocity-noise"),
    (dict(frames=100000), "--frames 100000: simulating it would need about"),
])
def test_bad_settings_name_their_flag_before_any_run(changes, words):
    """Each bad setting is a ConfigError naming the command's flag, raised by the settings
    themselves (before a worker starts); a pixel noise of 1e300 used to fail every run with
    the filter's pixel_noise_px message."""
    from vislam.errors import ConfigError
    from vislam.tools.consistency import ConsistencySettings

    with pytest.raises(ConfigError) as info:
        ConsistencySettings(**changes)
    assert words in str(info.value)
