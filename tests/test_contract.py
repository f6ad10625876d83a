"""The stepwise filter contract (vislam.core.contract): every estimator implements it, and
the batch driver needs nothing beyond it — a filter seen only through the contract's
names gives the same run as the filter itself."""

from __future__ import annotations

import re

import numpy as np
import pytest

import vislam
from vislam.core.contract import FRAME_STAT_FIELDS, FilterDiagnostics, StepwiseFilter
from vislam.core.estimators import drive
from vislam.core.filters import LocalizationFilter, MappingFilter, SlamFilter
from vislam.core.noise import NoiseSpec, inject_noise
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.core.smoother import SmootherFilter

NOISY = dict(velocity_noise_mps=0.5, angular_noise_radps=0.05)

#: What drive() may use of a filter: the contract's names.
CONTRACT = ("mode", "options", "stats", "diagnostics", "step", "drain", "pop_processed", "finish",
            "final_trajectory")


@pytest.fixture(scope="module")
def sim():
    return simulate_drive(SimulationOptions(seed=6, n_frames=60, stall_period=10, moving_fraction=0.1, **NOISY))


class ContractOnly:
    """A filter that exposes nothing but the contract's names of the filter it wraps."""

    def __init__(self, inner: StepwiseFilter):
        for name in CONTRACT:
            object.__setattr__(self, name, getattr(inner, name))


@pytest.mark.parametrize("cls", [LocalizationFilter, MappingFilter, SlamFilter, SmootherFilter])
def test_every_estimator_implements_the_contract(sim, cls):
    f = cls(sim.sequence.calibration, vislam.FilterOptions(**NOISY))
    assert isinstance(f, StepwiseFilter) and isinstance(f.diagnostics, FilterDiagnostics)
    assert f.frame_index == -1
    frames = list(sim.sequence.frames(0, 5))
    for frame in frames:
        if cls is MappingFilter:
            f.step(frame, world_T_imu=sim.world_T_imu[frame.index])
        else:
            f.step(frame)
    assert f.frame_index == 4
    assert f.world_T_imu.shape == (4, 4)
    cov = f.pose_covariance
    assert cov is None or cov.shape == (6, 6)
    f.drain()
    done = f.pop_processed()
    assert [t for t, *_ in done] == list(range(5))  # every frame finished once drained, in order
    for t, imu_T_world, cov, stats in done:
        assert imu_T_world.shape == (4, 4) and stats.frame == t
    est = f.landmark_estimates()
    assert est.ids.shape[0] == est.mean.shape[0] == est.cov.shape[0]
    np.testing.assert_array_equal(est.ids, f.live_landmark_ids)
    f.finish()
    final = f.final_trajectory()
    assert (final is not None) == (cls is SmootherFilter)  # only the smoother's final poses differ from the online


@pytest.mark.parametrize("mode, options", [
    ("slam", vislam.FilterOptions(**NOISY)),  # with the stalled-track remap: drain() finishes frames
    ("slam", vislam.FilterOptions(**NOISY, imu_bias_sigma_mps=0.02, imu_bias_sigma_radps=0.002)),
    ("localization", vislam.FilterOptions(**NOISY)),
    ("smoother", vislam.FilterOptions(**NOISY, smoother_window_s=1.0)),
])
def test_drive_uses_only_the_contract(sim, mode, options):
    seq = sim.sequence
    batch = vislam.run(seq, mode, options)
    cls = {"slam": SlamFilter, "localization": LocalizationFilter, "smoother": SmootherFilter}[mode]
    seen = drive(ContractOnly(cls(seq.calibration, options)), seq)
    np.testing.assert_array_equal(seen.world_T_imu, batch.world_T_imu)
    for name in FRAME_STAT_FIELDS:
        np.testing.assert_array_equal(seen.frame_stats[name], batch.frame_stats[name])
    assert ("imu_bias" in seen.extra) == ("imu_bias" in batch.extra) == options.imu_bias_enabled
    if options.imu_bias_enabled:
        np.testing.assert_array_equal(seen.extra["imu_bias"], batch.extra["imu_bias"])
        assert seen.extra["imu_bias"].shape == (seq.n_frames, 6)
    assert ("online_world_T_imu" in seen.extra) == (mode == "smoother")


def test_diagnostics_innovation_hook_and_failure(sim):
    seq = sim.sequence
    f = SlamFilter(seq.calibration, vislam.FilterOptions(**NOISY))
    calls = []
    f.diagnostics.innovation_hook = lambda r, *rest: calls.append(r.shape[0])
    for frame in seq.frames(0, 20):
        f.step(frame)
    assert calls and sum(calls) > 0  # innovations of in-state landmarks were observed
    assert f.diagnostics.failed is None and f.diagnostics.imu_bias_log is None  # no IMU-error state
    with pytest.raises(vislam.ConfigError):
        f.predict(-1.0, np.zeros(3), np.zeros(3))  # bad input: a ConfigError, the filter stays usable
    assert f.diagnostics.failed is None


@pytest.mark.parametrize("cls", [LocalizationFilter, MappingFilter, SlamFilter, SmootherFilter])
def test_predict_refuses_samples_it_cannot_integrate_and_stays_usable(sim, cls):
    """A NaN, infinite or absurd sample, the wrong number of values or text is a one-line
    ConfigError naming what predict expects (NaN made LocalizationFilter's pose NaN
    silently; 1e200 rad/s was a "math domain error"); the filter goes on as before."""
    seq = sim.sequence
    frames = list(seq.frames(0, 3))
    f = cls(seq.calibration, vislam.FilterOptions(**NOISY))
    f.step(frames[0])
    v, w = frames[1].linear_velocity_mps, frames[1].angular_velocity_radps
    for args, needle in (((0.1, [np.nan, 0, 0], w), "must be finite and within ±1e+09"),
                         ((0.1, v, [np.inf, 0, 0]), "must be finite and within ±1e+09"),
                         ((0.1, v, [1e200, 0, 0]), "must be finite and within ±1e+09"),
                         ((0.1, [-2e9, 0, 0], w), "must be finite and within ±1e+09"),
                         ((0.1, [1.0, 0.0], w), "linear_velocity must be 3 numbers (m/s), got shape (2,)"),
                         ((0.1, v, "fast"), "angular_velocity must be 3 numbers (rad/s), got 'fast'"),
                         (("soon", v, w), "dt_s must be a finite time step >= 0 (s), at most 1e+09, got 'soon'"),
                         ((1e12, v, w), "dt_s must be a finite time step >= 0 (s), at most 1e+09, got 1000000000000.0")):
        with pytest.raises(vislam.ConfigError, match=re.escape(needle)):
            f.predict(*args)
    assert f.diagnostics.failed is None
    for frame in frames[1:]:
        f.step(frame)
    assert np.isfinite(f.world_T_imu).all() and f.diagnostics.failed is None


def test_a_sequence_without_velocities_is_refused_before_any_frame(sim):
    seq = sim.sequence
    v = seq.linear_velocity_in_imu_mps.copy()
    v[7, 1] = np.nan  # e.g. tracked from images without IMU velocities
    bad = seq.replace(linear_velocity_in_imu_mps=v)
    for mode in ("localization", "slam"):
        with pytest.raises(vislam.DatasetError, match=r"the linear velocity of frame 7 is \[.*nan.*\].*--velocities"):
            vislam.run(bad, mode)
    w = seq.angular_velocity_in_imu_radps.copy()
    w[3, 0] = 2e9  # beyond any unit: refused by the sequence itself
    with pytest.raises(ValueError, match="angular_velocity_in_imu_radps has 2e\\+09 at frame 3"):
        seq.replace(angular_velocity_in_imu_radps=w)


def test_corrections_and_added_noise_that_leave_the_bound_are_config_errors(sim):
    seq = sim.sequence
    w = seq.angular_velocity_in_imu_radps.copy()
    w[5, 2] = 1e9
    v = seq.linear_velocity_in_imu_mps.copy()
    v[4, 0] = 5e6
    edge = seq.replace(angular_velocity_in_imu_radps=w, linear_velocity_in_imu_mps=v)
    with pytest.raises(vislam.ConfigError, match="velocity_scale 1000.*linear velocity of frame 4 to 5000000000"):
        vislam.run(edge, "localization", vislam.FilterOptions(velocity_scale=1000))
    with pytest.raises(vislam.ConfigError, match="angular velocity of frame 5 to 1000000001"):
        inject_noise(edge, NoiseSpec(angular_bias_radps=(0.0, 0.0, 1.0)))


@pytest.mark.parametrize("cls", [MappingFilter, SlamFilter, SmootherFilter])
def test_update_refuses_pixels_that_are_not_finite_numbers(sim, cls):
    seq = sim.sequence
    frames = list(seq.frames(0, 2))
    f = cls(seq.calibration, vislam.FilterOptions(**NOISY))
    f.step(frames[0])
    ids, pixels = frames[1].landmark_ids, frames[1].pixels.copy()
    pixels[2, 1] = np.inf  # numpy warned "invalid value" in MappingFilter
    with pytest.raises(vislam.ConfigError, match=rf"pixels must be finite and within ±1e\+06; landmark {ids[2]} has \[.*inf"):
        f.update(ids, pixels)
    with pytest.raises(vislam.ConfigError, match="pixels must be numbers"):
        f.update(ids[:1], [["a", "b", "c", "d"]])
    assert f.diagnostics.failed is None
