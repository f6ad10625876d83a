"""Figures and progress say what was run: the file (sparse and dense 0027 share the drive's
name) and the method (a refined smoother is not "the smoother"); the refinement names
itself on the progress bar."""

from __future__ import annotations

import os

import numpy as np
import pytest

from vislam.core.options import FilterOptions
from vislam.core.results import RunResult, RunStats
from vislam.tools.outputs import display_name, file_label, method_title


def _result(mode: str, **options) -> RunResult:
    return RunResult(mode, "0027", np.zeros(1), np.eye(4)[None], None, None, FilterOptions(**options), RunStats())


def test_titles_name_the_file_not_only_the_drive():
    assert file_label("/data/dense/0027.npz") == "dense/0027.npz"
    assert file_label("0027.npz") == "0027.npz"
    assert display_name({"name": "0027", "path": "/x/sparse/0027.npz"}) == "sparse/0027.npz"
    noisy = {"name": "0027", "label": "0027 + noise (v 0.1)", "path": "/x/dense/0027.npz"}
    assert display_name(noisy) == "dense/0027.npz + noise (v 0.1)"
    assert display_name({"name": "sim", "label": "Simulator, static", "path": "/t/s.npz"}) == "Simulator, static"
    assert display_name({"name": "0027"}) == "0027"


def test_title_of_an_undecodable_file_name_is_printable():
    raw = os.fsdecode(b"/d/caf\xe9.npz")  # a Latin-1 name on a UTF-8 system: a surrogate escape
    label = file_label(raw)
    label.encode("utf-8")  # no UnicodeEncodeError in matplotlib or JSON
    assert label.startswith("d/caf") and label.endswith(".npz")


def test_method_title_says_refined_smoother():
    assert method_title(_result("slam")) == "Visual-inertial SLAM"
    assert method_title(_result("smoother")) == "Sliding-window smoother"
    assert method_title(_result("smoother", refine=True)) == "Sliding-window smoother + batch refinement"


def test_refine_phase_is_announced_on_the_progress_bar():
    pytest.importorskip("gtsam")
    from vislam.core.estimators import run
    from vislam.core.simulate import SimulationOptions, simulate_drive

    seq = simulate_drive(SimulationOptions(seed=1, n_frames=25)).sequence
    calls = []

    def progress(done):
        calls.append(done)

    progress.phase = lambda text: calls.append(text)
    result = run(seq, "smoother", FilterOptions(refine=True, smoother_window_s=1.0), progress=progress)
    assert "smoother_world_T_imu" in result.extra  # it refined
    assert calls[-1].startswith("refining the whole drive (25 poses")
    assert calls[-2] == seq.n_frames  # after the frames
