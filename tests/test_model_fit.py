"""A run warns when its own statistics say the noise model does not fit the data."""

from __future__ import annotations

import json

import pytest

import vislam
from vislam.cli import main
from vislam.core.results import model_fit_warnings
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools.dataset_io import save_sequence


@pytest.fixture(scope="module")
def noisy_imu_drive():
    """An IMU with the dense files' white noise (0.5 m/s, 0.05 rad/s per sample)."""
    return simulate_drive(SimulationOptions(seed=2, n_frames=200, velocity_noise_mps=0.5, angular_noise_radps=0.05))


def test_clean_imu_model_on_a_noisy_imu_warns(noisy_imu_drive):
    r = vislam.run(noisy_imu_drive.sequence, "slam", vislam.FilterOptions())
    warnings = model_fit_warnings(r)
    assert warnings and all("vislam check" in w for w in warnings)
    assert any("gate" in w for w in warnings)


def test_fitting_model_does_not_warn(noisy_imu_drive):
    r = vislam.run(noisy_imu_drive.sequence, "slam", vislam.FilterOptions(velocity_noise_mps=0.5,
                                                                           angular_noise_radps=0.05))
    assert model_fit_warnings(r) == []


def test_run_prints_and_records_the_warnings(noisy_imu_drive, tmp_path, capsys):
    data = tmp_path / "noisy.npz"
    save_sequence(noisy_imu_drive.sequence, data)
    assert main(["run", str(data), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["warnings"] and summary["nis_mean"] > 0
    assert err.count("vislam: warning:") == len(summary["warnings"])
