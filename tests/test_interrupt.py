"""Ctrl-C during ``vislam run`` leaves either complete outputs or none, and says so in
one line — at any moment, including while Python is still importing (the first delays
land there, see ``vislam._launcher``). A signal that arrives before the interpreter
has run any of vislam's code (its own start-up, ~20-100 ms) is Python's to report."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.tools.dataset_io import save_sequence

EXPECTED = {"trajectory.tum", "trajectory.kitti", "trajectory.png", "summary.json", "landmarks.ply", "landmarks.npz"}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "drive.npz"
    save_sequence(simulate_drive(SimulationOptions(seed=0, n_frames=600)).sequence, path)
    return path


@pytest.mark.skipif(os.name != "posix", reason="SIGINT delivery")
@pytest.mark.parametrize("delay_s", [0.1, 0.2, 0.3, 0.5, 0.8, 1.5, 3.0])
def test_sigint_leaves_all_or_nothing(dataset, tmp_path, delay_s):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "vislam", "run", str(dataset), "--mode", "slam", "--out", str(out),
                             "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(delay_s)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert "Traceback" not in stderr
    present = {p.name for p in out.iterdir()} if out.exists() else set()
    if proc.returncode == 0:  # finished before the signal arrived
        assert EXPECTED <= present
    else:
        assert proc.returncode == 130
        assert len(stderr.strip().splitlines()) == 1 and "interrupt" in stderr.lower()
        assert present in (set(), EXPECTED | present) and (not present or EXPECTED <= present)
        assert not [p for p in present if p.startswith(".")]  # no staging debris
