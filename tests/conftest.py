"""Shared fixtures. Tests that need the shared datasets use the ``shared_data`` fixture
(or the ``shared`` marker) and are skipped cleanly when ``../shared/data`` is absent."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("VISLAM_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))
#: SimulationOptions of half the simulator's default density of landmarks (~34 observations
#: a frame instead of ~66, within the KITTI files' range), for tests of files, tables,
#: messages and options, which do not need a dense scene: each filter run costs half.
HALF_SCENE = dict(facade_density_per_m=0.7, pole_density_per_m=0.02, parked_car_density_per_m=0.05,
                  ground_density_per_m=0.15, background_density_per_m2=0.01)


def in_process(capsys, *args) -> subprocess.CompletedProcess:
    """``vislam ARGS`` by its entry point in this process, as a CompletedProcess (the exit
    code it returns is the process's, see __main__; stdout and stderr from ``capsys``):
    the checks of a subprocess without its Python start-up."""
    from vislam.cli import main

    code = main([str(a) for a in args])
    captured = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, captured.out, captured.err)


def shared_file(relative: str) -> Path:
    """Path to a file of the shared data set; skips the calling test when it is absent."""
    path = SHARED_DATA / relative
    if not path.is_file():
        pytest.skip(f"shared data not available: {path}")
    return path


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not available: {SHARED_DATA}")
    return SHARED_DATA


def drifting_estimate(rng, gt: np.ndarray, sigma_t: float = 0.03, sigma_r: float = 0.002) -> np.ndarray:
    """An estimate that drifts: the relative motions of ``gt`` (N, 4, 4) with random
    errors (σ per axis, m and rad), chained from ``gt[0]``."""
    from vislam.core.lie import se3_exp, se3_inverse

    rel = se3_inverse(gt[:-1]) @ gt[1:]
    noise = se3_exp(np.concatenate([rng.normal(0, sigma_t, (len(rel), 3)), rng.normal(0, sigma_r, (len(rel), 3))], 1))
    est = np.empty_like(gt)
    est[0] = gt[0]
    for k in range(len(rel)):
        est[k + 1] = est[k] @ rel[k] @ noise[k]
    return est


def poison_state_at(monkeypatch, frame: int) -> None:
    """Make the SLAM EKF's covariance non-finite in the prediction to ``frame``: a numerical
    failure its health check must catch (bounded inputs no longer overflow the state: a
    velocity of 1e300 did, before MAX_IMU_SAMPLE)."""
    from vislam.core.filters import SlamFilter

    predict = SlamFilter.predict

    def poisoned(self, *args, **kwargs):
        predict(self, *args, **kwargs)
        if self.frame_index + 1 == frame:
            self._state.cov[0, 0] = np.nan

    monkeypatch.setattr(SlamFilter, "predict", poisoned)
