"""Noise injection (:func:`vislam.core.noise.inject_noise`) and its command-line flags."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vislam.cli import main
from vislam.core.noise import NoiseSpec, inject_noise
from vislam.core.sequence import StereoObservations
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.errors import ConfigError
from vislam.tools.dataset_io import save_sequence


@pytest.fixture(scope="module")
def long_drive():
    """A 1500-frame drive: 4500 velocity samples per quantity, ~100k observations."""
    return simulate_drive(SimulationOptions(n_frames=1500)).sequence


@pytest.fixture(scope="module")
def short_drive():
    return simulate_drive(SimulationOptions(n_frames=120)).sequence


def with_repeats(sequence, every: int = 7):
    """``sequence`` where every ``every``-th observation that has one in the previous
    frame repeats its pixels bit for bit (the KITTI tracker artifact), chains included."""
    obs = sequence.observations
    prev = obs.previous_index()
    pixels = obs.pixels.copy()
    rows = np.nonzero(prev >= 0)[0][::every]
    for row in rows[np.argsort(obs.frame_index[rows], kind="stable")]:
        pixels[row] = pixels[prev[row]]
    return sequence.replace(observations=StereoObservations(obs.frame_offsets, obs.landmark_ids, pixels,
                                                            obs.n_landmarks))


ALL = NoiseSpec(velocity_noise_mps=0.3, angular_noise_radps=0.01, velocity_bias_mps=(0.1, 0, -0.2),
                angular_bias_radps=(0, 0.001, 0), pixel_noise_px=1.0, outlier_fraction=0.05, seed=3)


def arrays(seq):
    return seq.linear_velocity_in_imu_mps, seq.angular_velocity_in_imu_radps, seq.observations.pixels


def test_same_seed_gives_identical_noise_and_different_seed_different(short_drive):
    a, info_a = inject_noise(short_drive, ALL)
    b, info_b = inject_noise(short_drive, ALL)
    c, _ = inject_noise(short_drive, NoiseSpec(**{**ALL.to_dict(), "seed": 4}))
    for x, y, z, orig in zip(arrays(a), arrays(b), arrays(c), arrays(short_drive)):
        np.testing.assert_array_equal(x, y)
        assert not np.array_equal(x, z)
        assert not np.array_equal(x, orig)
    assert info_a == info_b
    assert info_a["spec"] == ALL.to_dict() and info_a["outliers_injected"] > 0


def test_white_noise_statistics_match_the_spec(long_drive):
    spec = NoiseSpec(velocity_noise_mps=0.4, angular_noise_radps=0.02, pixel_noise_px=1.5, seed=1)
    noisy, _ = inject_noise(long_drive, spec)
    dv = noisy.linear_velocity_in_imu_mps - long_drive.linear_velocity_in_imu_mps
    dw = noisy.angular_velocity_in_imu_radps - long_drive.angular_velocity_in_imu_radps
    dp = noisy.observations.pixels - long_drive.observations.pixels
    for d, sigma in ((dv, 0.4), (dw, 0.02), (dp, 1.5)):
        per_axis_std = d.std(axis=0)
        np.testing.assert_allclose(per_axis_std, sigma, rtol=0.10)
        assert np.all(np.abs(d.mean(axis=0)) < 0.1 * sigma)  # zero mean
    # white: no correlation between consecutive samples
    r = np.corrcoef(dv[1:, 0], dv[:-1, 0])[0, 1]
    assert abs(r) < 0.1


def test_biases_are_added_exactly(short_drive):
    spec = NoiseSpec(velocity_bias_mps=(0.25, -0.5, 0.125), angular_bias_radps=(0.001, 0.0, -0.002))
    noisy, info = inject_noise(short_drive, spec)
    np.testing.assert_allclose(noisy.linear_velocity_in_imu_mps - short_drive.linear_velocity_in_imu_mps,
                               np.broadcast_to([0.25, -0.5, 0.125], (short_drive.n_frames, 3)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(noisy.angular_velocity_in_imu_radps - short_drive.angular_velocity_in_imu_radps,
                               np.broadcast_to([0.001, 0.0, -0.002], (short_drive.n_frames, 3)), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(noisy.observations.pixels, short_drive.observations.pixels)  # pixels untouched
    assert info["outliers_injected"] == 0


@pytest.mark.parametrize("fraction", [0.013, 0.2])
def test_outliers_replace_round_fraction_of_observations(short_drive, fraction):
    obs = short_drive.observations
    noisy, info = inject_noise(short_drive, NoiseSpec(outlier_fraction=fraction, seed=5))
    expected = int(round(fraction * obs.n_observations))
    changed = np.any(noisy.observations.pixels != obs.pixels, axis=1)
    assert info["outliers_injected"] == expected
    assert int(changed.sum()) == expected
    out = noisy.observations.pixels[changed]
    disparity = out[:, 0] - out[:, 2]
    assert np.all((disparity >= 1.0) & (disparity <= 60.0))
    np.testing.assert_array_equal(out[:, 1], out[:, 3])  # same row: must be caught by the gate, not the row check
    lo, hi = obs.pixels[:, :2].min(axis=0), obs.pixels[:, :2].max(axis=0)
    assert np.all((out[:, :2] >= lo) & (out[:, :2] <= hi))
    # the rest of the sequence is untouched
    np.testing.assert_array_equal(noisy.observations.landmark_ids, obs.landmark_ids)
    np.testing.assert_array_equal(noisy.linear_velocity_in_imu_mps, short_drive.linear_velocity_in_imu_mps)


def test_repeated_observations_stay_exact_repeats(short_drive):
    seq = with_repeats(short_drive)
    rep = seq.observations.repeated_mask()
    assert rep.sum() > 50
    noisy, _ = inject_noise(seq, NoiseSpec(pixel_noise_px=2.0, seed=2))
    nobs = noisy.observations
    np.testing.assert_array_equal(nobs.repeated_mask(), rep)
    prev = nobs.previous_index()
    np.testing.assert_array_equal(nobs.pixels[rep], nobs.pixels[prev[rep]])
    assert np.all(np.any(nobs.pixels[~rep] != seq.observations.pixels[~rep], axis=1))  # the others got noise


def test_streams_are_independent(short_drive):
    """Changing the pixel noise leaves the velocity noise of the same seed unchanged."""
    a, _ = inject_noise(short_drive, NoiseSpec(velocity_noise_mps=0.3, seed=9))
    b, _ = inject_noise(short_drive, NoiseSpec(velocity_noise_mps=0.3, pixel_noise_px=1.0, outlier_fraction=0.1,
                                               seed=9))
    np.testing.assert_array_equal(a.linear_velocity_in_imu_mps, b.linear_velocity_in_imu_mps)


def test_zero_spec_returns_the_sequence_unchanged(short_drive):
    for spec in (NoiseSpec(), NoiseSpec(seed=17)):
        out, info = inject_noise(short_drive, spec)
        assert out is short_drive
        assert info["outliers_injected"] == 0 and spec.is_zero


@pytest.mark.parametrize("changes, word", [
    ({"velocity_noise_mps": -0.1}, "velocity_noise_mps"),
    ({"angular_noise_radps": math.nan}, "angular_noise_radps"),
    ({"pixel_noise_px": math.inf}, "pixel_noise_px"),
    ({"pixel_noise_px": "1"}, "pixel_noise_px"),
    ({"outlier_fraction": 1.0}, "outlier_fraction"),
    ({"outlier_fraction": -0.01}, "outlier_fraction"),
    ({"velocity_bias_mps": (0.1, 0.2)}, "velocity_bias_mps"),
    ({"angular_bias_radps": (0, 0, math.nan)}, "angular_bias_radps"),
    ({"angular_bias_radps": 0.1}, "angular_bias_radps"),
    ({"velocity_noise_mps": 1e300}, "velocity_noise_mps must be at most 1e"),  # overflowed the filter's state
    ({"velocity_bias_mps": (0, 1e300, 0)}, "velocity_bias_mps must be within"),
    ({"seed": -1}, "seed"),
    ({"seed": 1.5}, "seed"),
    ({"seed": True}, "seed"),
])
def test_bad_specs_raise_config_error(changes, word):
    with pytest.raises(ConfigError, match=word):
        NoiseSpec(**changes)


# ----------------------------------------------------------------------------- vislam run flags


@pytest.fixture(scope="module")
def data_file(tmp_path_factory, short_drive):
    path = tmp_path_factory.mktemp("noise-data") / "drive.npz"
    save_sequence(short_drive, path)
    return path


def test_run_records_the_injected_noise_in_summary(tmp_path, data_file):
    out = tmp_path / "out"
    code = main(["run", str(data_file), "--mode", "localization", "--out", str(out), "--quiet",
                 "--add-velocity-noise", "0.2", "--add-angular-bias", "0,0,0.001", "--add-outliers", "0.05",
                 "--noise-seed", "7"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    injected = summary["injected_noise"]
    assert injected["velocity_noise_mps"] == 0.2 and injected["angular_bias_radps"] == [0.0, 0.0, 0.001]
    assert injected["seed"] == 7 and injected["pixel_noise_px"] == 0.0
    obs = 0
    with np.load(data_file) as z:
        obs = int(np.count_nonzero(np.any(z["features"] != -1, axis=0)))
    assert injected["outliers_injected"] == round(0.05 * obs)
    assert summary["options"]["velocity_noise_mps"] == 0.02  # the filter's noise model is a separate setting
    # without the flags nothing is injected and nothing recorded
    main(["run", str(data_file), "--mode", "localization", "--out", str(tmp_path / "clean"), "--quiet"])
    assert json.loads((tmp_path / "clean" / "summary.json").read_text()).get("injected_noise") is None


def test_run_with_noise_is_reproducible_and_seed_matters(tmp_path, data_file):
    def trajectory(seed):
        out = tmp_path / f"s{seed}-{len(list(tmp_path.iterdir()))}"
        assert main(["run", str(data_file), "--mode", "localization", "--out", str(out), "--quiet",
                     "--add-velocity-noise", "0.5", "--noise-seed", str(seed)]) == 0
        return (out / "trajectory.tum").read_text()

    assert trajectory(1) == trajectory(1)
    assert trajectory(1) != trajectory(2)


@pytest.mark.parametrize("flags, message", [
    (["--add-velocity-noise", "-1"], "--add-velocity-noise"),
    (["--add-velocity-bias", "1,2"], "--add-velocity-bias"),
    (["--add-angular-bias", "a,b,c"], "--add-angular-bias"),
    (["--add-outliers", "1.5"], "--add-outliers"),
    (["--add-pixel-noise", "1", "--noise-seed", "-3"], "--noise-seed"),
])
def test_bad_noise_flags_one_line_error_nothing_written(tmp_path, data_file, capsys, flags, message):
    out = tmp_path / "out"
    code = main(["run", str(data_file), "--out", str(out), *flags])
    err = capsys.readouterr().err
    assert code != 0
    assert len(err.strip().splitlines()) == 1 and message in err
    assert not out.exists()
