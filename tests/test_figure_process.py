"""The figures' helper process (vislam.tools.figure_process) draws the very PNGs this
process draws — the trajectory figure and the error-over-distance figure — and a helper
that is gone or broken costs the figures nothing: they are drawn here instead."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from vislam.core.lie import se3_exp
from vislam.tools import plotting
from vislam.tools.evaluation import ErrorFigureData, evaluate, plot_error_over_distance
from vislam.tools.figure_process import FigureProcess, _decode_call, _encode
from vislam.tools.plotting import TrajectoryCurve


class _Map:
    def __init__(self, p, status):
        self.p_lm_in_world, self.status = p, status

    def __len__(self):
        return len(self.p_lm_in_world)


@pytest.fixture(scope="module")
def call():
    """A figure's arguments: a curving drive with its ground truth, landmarks (some rejected,
    some far outside the view) and a non-ASCII title."""
    rng = np.random.default_rng(3)
    steps = np.zeros((120, 6))
    steps[:, 0], steps[:, 5] = 1.0, 0.02
    world_T_imu = np.empty((121, 4, 4))
    world_T_imu[0] = np.eye(4)
    for i, T in enumerate(se3_exp(steps)):
        world_T_imu[i + 1] = world_T_imu[i] @ T
    truth = world_T_imu.copy()
    truth[:, :3, 3] += rng.normal(0, 0.5, (121, 3))
    curves = [TrajectoryCurve(truth, "ground truth", color="0.25", linewidth=3.2, zorder=2, mark_ends=False),
              TrajectoryCurve(world_T_imu, "trajectory")]
    p = np.concatenate([rng.uniform(-20, 80, (300, 3)), [[5000.0, 0.0, 0.0]]])
    status = (rng.uniform(size=301) < 0.1).astype(np.int8)
    return curves, _Map(p, status), "sparse/0027.npz — Visual-inertial SLAM", "120 frames · 301 landmarks"


@pytest.fixture(scope="module")
def evaluation(call):
    """An evaluation with a camera-frame part (as `vislam run --gt` with KITTI ground truth)."""
    curves, _, _, _ = call
    truth, est = curves[0].world_T_imu, curves[1].world_T_imu
    cam_T_imu = se3_exp(np.array([0.1, -0.2, 0.3, 0.05, -0.02, 0.01]))
    return evaluate(est, truth, gt_world_T_cam=cam_T_imu @ truth @ np.linalg.inv(cam_T_imu), cam_T_imu=cam_T_imu)


def _decode(payload: bytes) -> list:
    """The calls of an _encode archive, decoded as the helper process decodes them."""
    with np.load(io.BytesIO(payload), allow_pickle=False) as z:
        return [_decode_call(z, i, call) for i, call in enumerate(json.loads(str(z["calls"])))]


def _assert_same_fields(a, b):
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if hasattr(x, "__dataclass_fields__"):
            _assert_same_fields(x, y)
        elif isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y)
            assert x.dtype == y.dtype, name
        else:
            assert x == y or (x != x and y != y), name  # (NaN == NaN)


def test_the_wire_format_carries_the_calls_unchanged(call, evaluation, tmp_path):
    curves, lm, title, subtitle = call
    data = ErrorFigureData.from_result(evaluation)
    sent = [("error_over_distance", (data, tmp_path / "e.png", "errors — x")),
            ("trajectory_map", (tmp_path / "f.png", curves, lm, title, subtitle))]
    (kind_e, (data2, path_e, title_e)), (kind_m, (path, curves2, lm2, title2, subtitle2)) = _decode(_encode(sent))
    assert (kind_e, kind_m) == ("error_over_distance", "trajectory_map")
    assert path_e == str((tmp_path / "e.png").resolve()) and title_e == "errors — x"
    assert data.camera is not None
    _assert_same_fields(data, data2)
    assert path == str((tmp_path / "f.png").resolve()) and (title2, subtitle2) == (title, subtitle)
    assert len(curves2) == len(curves)
    for a, b in zip(curves, curves2):
        assert (a.label, a.color, a.linestyle, a.linewidth, a.zorder, a.mark_ends) == \
               (b.label, b.color, b.linestyle, b.linewidth, b.zorder, b.mark_ends)
        np.testing.assert_array_equal(a.world_T_imu, b.world_T_imu)
    np.testing.assert_array_equal(lm2.p_lm_in_world, lm.p_lm_in_world)
    np.testing.assert_array_equal(lm2.status, lm.status)
    assert _decode(_encode([("trajectory_map", (tmp_path / "g.png", curves, None, "", None))]))[0][1][2] is None


def test_the_helper_draws_the_pngs_this_process_draws(call, evaluation, tmp_path, monkeypatch):
    curves, lm, title, subtitle = call
    here = plotting.plot_trajectory_map(tmp_path / "here.png", curves, lm, title=title, subtitle=subtitle)
    plot_error_over_distance(evaluation, tmp_path / "here-errors.png", title="errors — x")

    def not_here(*args, **kwargs):  # the helper must answer: no fallback to this process
        raise AssertionError("drawn in this process")

    monkeypatch.setattr(plotting, "plot_trajectory_map", not_here)
    monkeypatch.setattr("vislam.tools.evaluation.plot_error_over_distance", not_here)
    with FigureProcess() as helper:
        assert helper.start(only_if_useful=False)
        assert helper.plot_error_over_distance(evaluation, tmp_path / "there-errors.png", title="errors — x") is None
        assert not (tmp_path / "there-errors.png").exists()  # queued: sent with the trajectory figure
        there = helper.plot_trajectory_map(tmp_path / "there.png", curves, lm, title=title, subtitle=subtitle)
    assert there == here and there["landmarks_outside_view"] >= 1
    assert (tmp_path / "there.png").read_bytes() == (tmp_path / "here.png").read_bytes()
    assert (tmp_path / "there-errors.png").read_bytes() == (tmp_path / "here-errors.png").read_bytes()


def test_a_figure_the_helper_cannot_draw_is_drawn_here(call, evaluation, tmp_path, monkeypatch):
    """Each figure on its own: when the helper cannot draw one (here: its call arrives
    without its data), that one is drawn here and the helper still draws the other."""
    from vislam.tools import figure_process

    curves, lm, title, subtitle = call
    plot_error_over_distance(evaluation, tmp_path / "ref.png", title="t")
    monkeypatch.setattr(figure_process, "_encode_error",
                        lambda arrays, prefix, data, path, title: {"kind": "error_over_distance", "path": str(path)})

    def not_here(*args, **kwargs):
        raise AssertionError("the helper should have drawn the trajectory figure")

    monkeypatch.setattr(plotting, "plot_trajectory_map", not_here)
    with FigureProcess() as helper:
        assert helper.start(only_if_useful=False)
        helper.plot_error_over_distance(evaluation, tmp_path / "errors.png", title="t")
        view = helper.plot_trajectory_map(tmp_path / "map.png", curves, lm, title=title, subtitle=subtitle)
    assert (tmp_path / "errors.png").read_bytes() == (tmp_path / "ref.png").read_bytes()
    assert (tmp_path / "map.png").is_file() and view["landmarks_outside_view"] >= 1


def test_queued_figures_are_dropped_when_the_command_fails(evaluation, tmp_path):
    with FigureProcess() as helper:
        helper.start(only_if_useful=False)
        helper.plot_error_over_distance(evaluation, tmp_path / "errors.png")
    assert list(tmp_path.iterdir()) == []
    idle = FigureProcess()  # no helper: drawn at once
    idle.plot_error_over_distance(evaluation, tmp_path / "now.png")
    assert (tmp_path / "now.png").is_file()


def test_a_helper_that_is_gone_or_broken_costs_nothing(call, tmp_path, monkeypatch):
    curves, lm, title, subtitle = call
    expected = plotting.plot_trajectory_map(tmp_path / "ref.png", curves, lm, title=title, subtitle=subtitle)
    killed = FigureProcess()
    killed.start(only_if_useful=False)
    killed._proc.kill()
    assert killed.plot_trajectory_map(tmp_path / "a.png", curves, lm, title=title, subtitle=subtitle) == expected
    closed = FigureProcess()
    closed.start(only_if_useful=False)
    closed.close()
    assert closed.plot_trajectory_map(tmp_path / "b.png", curves, lm, title=title, subtitle=subtitle) == expected
    # a helper that fails (here: it cannot decode the call) exits non-zero: drawn here
    monkeypatch.setattr("vislam.tools.figure_process._encode", lambda *a: b"not an npz archive")
    broken = FigureProcess()
    broken.start(only_if_useful=False)
    assert broken.plot_trajectory_map(tmp_path / "c.png", curves, lm, title=title, subtitle=subtitle) == expected
    for name in ("a", "b", "c"):
        assert (tmp_path / f"{name}.png").read_bytes() == (tmp_path / "ref.png").read_bytes()
    assert broken._proc is None and killed._proc is None


def test_closing_an_unused_helper_ends_it(tmp_path):
    helper = FigureProcess()
    assert helper.start(only_if_useful=False) and helper.start(only_if_useful=False)  # started once
    proc = helper._proc
    helper.close()
    assert proc.poll() is not None and helper._proc is None
    helper.close()  # twice: nothing to do
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("deliver", ["signal", "interrupt_main"])
def test_an_interrupt_while_the_helper_starts_leaves_no_helper_behind(monkeypatch, deliver):
    """Ctrl-C that lands inside Popen, after the fork (a signal, or the launcher's
    interrupt held back during an import and delivered by ``_thread.interrupt_main``): the
    interrupt is raised once the helper is known, so that closing ends it (it was left
    running, unreferenced, until its own import finished)."""
    import _thread
    import signal
    import subprocess

    from vislam.tools import figure_process

    real = subprocess.Popen
    started = []

    def popen(*args, **kwargs):
        proc = real(*args, **kwargs)
        started.append(proc)
        signal.raise_signal(signal.SIGINT) if deliver == "signal" else _thread.interrupt_main()
        return proc

    monkeypatch.setattr(figure_process.subprocess, "Popen", popen)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    helper = FigureProcess()
    try:
        with pytest.raises(KeyboardInterrupt):
            helper.start(only_if_useful=False)
        assert helper._proc is started[0]
    finally:
        helper.close()
        signal.signal(signal.SIGINT, previous)
        for proc in started:
            proc.kill()
            proc.wait()
    assert helper._proc is None and started[0].returncode is not None


def test_the_helper_starts_only_where_it_saves_time(call, tmp_path):
    """Where matplotlib is imported already (here: by this test) there is no helper, and
    the figure is drawn here all the same."""
    import matplotlib.figure  # noqa: F401

    idle = FigureProcess()
    assert not idle.start() and idle._proc is None
    curves, lm, title, subtitle = call
    view = idle.plot_trajectory_map(tmp_path / "f.png", curves, lm, title=title, subtitle=subtitle)
    assert view == plotting.plot_trajectory_map(tmp_path / "g.png", curves, lm, title=title, subtitle=subtitle)
