"""The SLAM filter's optional IMU-error state b = (b_v, b_ω) (vislam.core.propagation)."""

from __future__ import annotations

import numpy as np
import pytest

import vislam
from vislam.core.filters import single_thread_blas
from vislam.core.lie import se3_curly_hat, se3_exp, se3_inverse, se3_left_jacobian, se3_log
from vislam.core.noise import NoiseSpec, inject_noise
from vislam.core.options import FilterOptions
from vislam.core.propagation import (ImuBias, bias_transition, bias_twist_jacobian, body_twist, predict_state,
                                     prediction_twist)
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.core.state import SlamState
from vislam.errors import ConfigError
from vislam.tools.outputs import absolute_trajectory_error

RNG = np.random.default_rng(7)
#: A tilted pose (roll and pitch of a few degrees, some heading), so that levelled
#: velocities really turn.
MU = se3_exp(np.array([1.0, -2.0, 0.5, 0.06, -0.08, 0.9]))
U_MEAS = np.array([9.0, 0.4, -0.3, 0.02, -0.01, 0.25])  # a recorded sample (v, ω)
B_HAT = np.array([0.2, -0.05, 0.03, 0.001, -0.002, 0.004])
TAU = 0.1


@pytest.mark.parametrize("scale", [0.0, 1e-4, 0.05, 1.5])
def test_se3_left_jacobian_is_the_series(scale):
    xi = np.concatenate([RNG.normal(size=3) * 2.0, RNG.normal(size=3) * scale])
    A = se3_curly_hat(xi)
    series, term = np.zeros((6, 6)), np.eye(6)
    for n in range(60):  # J_l = Σ ad(ξ)ⁿ/(n+1)!
        series += term
        term = term @ A / (n + 2)
    np.testing.assert_allclose(se3_left_jacobian(xi), series, rtol=0, atol=1e-11)


def _step(b, velocity_frame, mu=MU):
    """The pose step of the mean with IMU-error b: exp(−τ body(u_meas − b, μ)) μ."""
    return se3_exp(-TAU * body_twist(U_MEAS - b, mu, velocity_frame)) @ mu


@pytest.mark.parametrize("velocity_frame", ["level", "body"])
def test_pose_step_jacobian_wrt_bias_matches_finite_differences(velocity_frame):
    """G = ∂δ'/∂b = τ J_l(−τ û) D against central differences of the left perturbation
    log(step(b̂ + h e_j) step(b̂)⁻¹)."""
    u = body_twist(U_MEAS - B_HAT, MU, velocity_frame)
    G = bias_transition(TAU, u, bias_twist_jacobian(MU, velocity_frame))
    h = 1e-6
    num = np.empty((6, 6))
    for j in range(6):
        e = np.zeros(6)
        e[j] = h
        plus, minus = _step(B_HAT + e, velocity_frame), _step(B_HAT - e, velocity_frame)
        num[:, j] = (se3_log(plus @ se3_inverse(_step(B_HAT, velocity_frame)))
                     - se3_log(minus @ se3_inverse(_step(B_HAT, velocity_frame)))) / (2 * h)
    np.testing.assert_allclose(G, num, rtol=0, atol=1e-7)
    assert np.abs(G).max() > 0.05  # not trivially zero
    if velocity_frame == "level":  # the level->body rotation matters: not the body-frame Jacobian
        assert np.abs(G - bias_transition(TAU, u, np.eye(6))).max() > 1e-3


@pytest.mark.parametrize("velocity_frame", ["level", "body"])
def test_core_transition_of_predict_state_matches_finite_differences(velocity_frame):
    """The whole core transition Φ = ∂(δ', b')/∂(δ, b) of predict_state (attitude
    Jacobian of levelled velocities included) against finite differences of the mean
    map; read off Σ_cl' = Φ Σ_cl with Σ_cl = I (four landmarks, 12 columns)."""
    model = ImuBias(np.full(6, 0.1), 5.0)
    a = model.decay(TAU)
    state = SlamState(MU, np.eye(6), inverse_depth=False, bias_covariance=np.eye(6))
    state.add_landmarks(np.arange(4), RNG.normal(size=(4, 3)), np.zeros((12, 12)), np.eye(12))
    state.cov[:12, 12:24] = np.eye(12)
    state.cov[12:24, :12] = np.eye(12)
    state.imu_bias = B_HAT.copy()
    u, du = prediction_twist(U_MEAS - B_HAT, MU, velocity_frame, True)
    predict_state(state, TAU, u, np.zeros((6, 6)), None, du, model, bias_twist_jacobian(MU, velocity_frame))
    Phi = state.cov[:12, 12:24]

    def mean_map(x):
        T = se3_exp(x[:6]) @ MU
        b = B_HAT + x[6:]
        T1 = se3_exp(-TAU * body_twist(U_MEAS - b, T, velocity_frame)) @ T
        return np.concatenate([se3_log(T1 @ se3_inverse(state.imu_T_world)), a * b - state.imu_bias])

    h = 1e-6
    num = np.column_stack([(mean_map(h * e) - mean_map(-h * e)) / (2 * h) for e in np.eye(12)])
    np.testing.assert_allclose(Phi, num, rtol=0, atol=1e-6)
    np.testing.assert_allclose(state.imu_bias, a * B_HAT)  # b̂' = a b̂


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(SimulationOptions(seed=2, n_frames=300, velocity_noise_mps=0.05, angular_noise_radps=0.001))


@pytest.fixture(scope="module")
def short_drive():
    return simulate_drive(SimulationOptions(seed=2, n_frames=120, velocity_noise_mps=0.05, angular_noise_radps=0.001))


NOISE = dict(velocity_noise_mps=0.05, angular_noise_radps=0.001)


def test_off_is_the_filter_without_the_state(short_drive):
    """Both σ_b 0 (whatever T_c): exactly the filter without the option; a tiny σ_b runs
    the 12-row core (landmarks at core_dim, bias rows in every update) and agrees with it
    to rounding."""
    short = short_drive.sequence
    ref = vislam.run(short, "slam", FilterOptions(**NOISE))
    off = vislam.run(short, "slam", FilterOptions(**NOISE, imu_bias_sigma_mps=0.0, imu_bias_sigma_radps=0.0,
                                                  imu_bias_time_constant_s=17.0))
    np.testing.assert_array_equal(off.world_T_imu, ref.world_T_imu)
    np.testing.assert_array_equal(off.pose_covariance, ref.pose_covariance)
    np.testing.assert_array_equal(off.landmarks.p_lm_in_world, ref.landmarks.p_lm_in_world)
    tiny = vislam.run(short, "slam", FilterOptions(**NOISE, imu_bias_sigma_mps=1e-12, imu_bias_sigma_radps=1e-12))
    np.testing.assert_allclose(tiny.world_T_imu, ref.world_T_imu, rtol=0, atol=1e-7)
    np.testing.assert_array_equal(tiny.landmarks.ids, ref.landmarks.ids)
    np.testing.assert_allclose(tiny.landmarks.p_lm_in_world, ref.landmarks.p_lm_in_world, rtol=0, atol=1e-6)


def _run_stepwise(seq, options):
    """(world_T_imu (T, 4, 4), last b̂, last Σ_bb, max asymmetry of Σ, min eigenvalue of Σ
    over the frames)."""
    f = vislam.SlamFilter(seq.calibration, options)
    poses, asym, min_eig = [], 0.0, np.inf
    with single_thread_blas():  # eigvalsh of a few hundred rows: threads only slow it down
        for k, frame in enumerate(seq.frames()):
            f.step(frame)
            poses += [se3_inverse(T) for _, T, _, _ in f.pop_processed()]
            if k % 10 == 0 and f.state.has_bias:
                C = f.state.cov
                asym = max(asym, float(np.abs(C - C.T).max()))
                min_eig = min(min_eig, float(np.linalg.eigvalsh(0.5 * (C + C.T)).min() / np.abs(np.diag(C)).max()))
        f.drain()
    poses += [se3_inverse(T) for _, T, _, _ in f.pop_processed()]
    return np.array(poses), f.imu_bias, f.imu_bias_covariance, asym, min_eig


def test_a_constant_bias_is_recovered_and_lowers_the_ate(drive):
    """Velocities with b_v = (0.3, 0, 0) m/s (forward, levelled) and b_ω = (0, 0, 0.003)
    rad/s added: the IMU-error state (T_c long: a nearly constant bias) finds both within
    0.05 m/s and 0.0007 rad/s and the ATE drops from metres to centimetres; Σ stays
    symmetric and PSD throughout."""
    truth = np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.003])
    seq, _ = inject_noise(drive.sequence, NoiseSpec(velocity_bias_mps=tuple(truth[:3]),
                                                    angular_bias_radps=tuple(truth[3:])))
    off = _run_stepwise(seq, FilterOptions(**NOISE))
    on = _run_stepwise(seq, FilterOptions(**NOISE, imu_bias_sigma_mps=0.5, imu_bias_sigma_radps=0.01,
                                          imu_bias_time_constant_s=1000.0))
    assert off[1] is None and on[1] is not None
    ate_off = absolute_trajectory_error(off[0], drive.world_T_imu)
    ate_on = absolute_trajectory_error(on[0], drive.world_T_imu)
    assert ate_on < 0.2 < 1.0 < ate_off
    b, cov = on[1], on[2]
    assert np.abs(b[:3] - truth[:3]).max() < 0.05
    assert np.abs(b[3:] - truth[3:]).max() < 7e-4
    # the estimate agrees with its own covariance (3σ per component)
    assert np.all(np.abs(b - truth) < 3 * np.sqrt(np.diag(cov)))
    assert on[3] == 0.0 or on[3] < 1e-12  # symmetric
    assert on[4] > -1e-12  # PSD (relative to the largest variance)


@pytest.mark.parametrize("extra", [dict(ekf="standard"), dict(landmark_parametrization="cartesian"),
                                   dict(landmark_motion=True), dict(stalled_tracks="keep")],
                         ids=["standard", "cartesian", "motion", "no-remap"])
def test_bias_state_in_the_other_variants(short_drive, extra):
    """The variants that share the code path — standard EKF, Cartesian landmarks, the
    landmark motion model (lm_dim 6), no stall buffer — on a clean drive (no injected
    bias): the trajectory stays close to the truth and b̂ near zero; the result holds b̂
    per frame."""
    drive = short_drive
    r = vislam.run(drive.sequence, "slam", FilterOptions(**NOISE, imu_bias_sigma_mps=0.3,
                                                         imu_bias_sigma_radps=0.003, **extra))
    assert not r.partial
    assert absolute_trajectory_error(r.world_T_imu, drive.world_T_imu) < 0.3
    b = r.extra["imu_bias"]
    assert b.shape == (drive.n_frames, 6)
    assert np.abs(b[-1, :3]).max() < 0.1 and np.abs(b[-1, 3:]).max() < 1e-3


def test_body_velocities_bias_is_recovered():
    """Body-frame velocity samples (the report's model): an injected b_v along the IMU y
    axis is found."""
    sim = simulate_drive(SimulationOptions(seed=4, n_frames=200, velocity_noise_mps=0.05, angular_noise_radps=0.001,
                                           velocity_frame="body"))
    seq, _ = inject_noise(sim.sequence, NoiseSpec(velocity_bias_mps=(0.0, 0.2, 0.0)))
    opts = FilterOptions(**NOISE, velocity_frame="body", imu_bias_sigma_mps=0.5, imu_bias_sigma_radps=0.01,
                         imu_bias_time_constant_s=1000.0)
    r = vislam.run(seq, "slam", opts)
    off = vislam.run(seq, "slam", opts.replace(imu_bias_sigma_mps=0.0, imu_bias_sigma_radps=0.0))
    b = r.extra["imu_bias"][-1]
    assert abs(b[1] - 0.2) < 0.05 and abs(b[0]) < 0.05 and abs(b[2]) < 0.05
    assert absolute_trajectory_error(r.world_T_imu, sim.world_T_imu) \
        < 0.5 * absolute_trajectory_error(off.world_T_imu, sim.world_T_imu)


@pytest.mark.parametrize("changes, message", [
    (dict(imu_bias_sigma_mps=-0.1), "imu_bias_sigma_mps must be >= 0"),
    (dict(imu_bias_sigma_radps=(0.1, 0.2)), "imu_bias_sigma_radps must be three numbers"),
    (dict(imu_bias_time_constant_s=0.0), "imu_bias_time_constant_s must be > 0"),
    (dict(imu_bias_time_constant_s=float("inf")), "imu_bias_time_constant_s must be a finite number"),
])
def test_bad_bias_options_are_refused(changes, message):
    with pytest.raises(ConfigError, match=message):
        FilterOptions(**changes)


def test_bias_options_load_from_a_mapping():
    opts = FilterOptions.from_dict({"imu_bias_sigma_mps": [0.3, 0.2, 0.1], "imu_bias_sigma_radps": 0.003,
                                    "imu_bias_time_constant_s": 20})
    assert opts.imu_bias_enabled
    np.testing.assert_array_equal(opts.imu_bias_sigma, [0.3, 0.2, 0.1, 0.003, 0.003, 0.003])
    assert opts.imu_bias_time_constant_s == 20.0
    assert not FilterOptions().imu_bias_enabled


def test_run_flags_set_the_bias_options():
    import argparse

    from vislam.cli.run import add_filter_arguments, options_from_args

    parser = argparse.ArgumentParser()
    add_filter_arguments(parser)
    opts = options_from_args(parser.parse_args(["--imu-bias-sigma", "0.3,0.003", "--imu-bias-time-constant", "20"]))
    assert (opts.imu_bias_sigma_mps, opts.imu_bias_sigma_radps, opts.imu_bias_time_constant_s) == (0.3, 0.003, 20.0)
    assert not options_from_args(parser.parse_args([])).imu_bias_enabled
    with pytest.raises(SystemExit):
        parser.parse_args(["--imu-bias-sigma", "0.3"])
    with pytest.raises(ConfigError, match="--imu-bias-time-constant"):
        options_from_args(parser.parse_args(["--imu-bias-time-constant", "0"]))


@pytest.mark.parametrize("mode", ["localization", "mapping", "smoother"])
def test_bias_flags_outside_slam_are_one_line_and_exit_2(short_drive, tmp_path, capsys, mode):
    """The IMU-error state is SLAM's: its flags with another mode are refused, not ignored."""
    from vislam.cli import main
    from vislam.tools.dataset_io import save_sequence

    data = tmp_path / "d.npz"
    save_sequence(short_drive.sequence, data)
    out = tmp_path / "out"
    assert main(["run", str(data), "--mode", mode, "--imu-bias-sigma", "0.3,0.003", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--imu-bias-sigma is only used by --mode slam" in err
    assert not out.exists()
