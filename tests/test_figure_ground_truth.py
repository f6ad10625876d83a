"""The ground truth drawn beside an estimate is moved into the estimate's world frame from
the same start pose (a ground truth recorded in another world frame was drawn hundreds of
metres away from the estimate, and the figure's view followed it)."""

from __future__ import annotations

import numpy as np
import pytest

from vislam.core.lie import se3_exp
from vislam.tools.comparison import ground_truth_from_start, start_anchor
from vislam.tools.evaluation import evaluate
from vislam.tools.plotting import SIDE_VIEW_GT_NOTE, TrajectoryCurve, plot_trajectory_map


def _drive(n: int = 300, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) a curving drive starting at the identity, about 300 m long."""
    rng = np.random.default_rng(seed)
    twists = np.zeros((n, 6))
    twists[:, 0] = 1.0 + 0.1 * rng.standard_normal(n)  # forward, m per step
    twists[:, 5] = 0.01 + 0.002 * rng.standard_normal(n)  # yaw, rad per step
    twists[:, 4] = 0.002 * rng.standard_normal(n)  # some pitch
    poses = [np.eye(4)]
    for xi in se3_exp(twists):
        poses.append(poses[-1] @ xi)
    return np.array(poses[:n])


def _rigid(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = se3_exp(rng.normal(0.0, 1.0, (1, 6)))[0]
    T[:3, 3] = rng.uniform(-1000.0, 1000.0, 3)
    return T


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_ground_truth_in_another_world_frame_is_drawn_from_the_estimates_start(seed):
    truth = _drive(seed=seed)
    est = truth.copy()
    est[:, :3, 3] += 0.01 * np.arange(truth.shape[0])[:, None]  # drifting, from the same start
    elsewhere = _rigid(seed) @ truth  # e.g. a motion-capture room's or a map's world frame
    evaluation = evaluate(est, elsewhere)
    drawn = ground_truth_from_start(evaluation)
    np.testing.assert_allclose(drawn, truth, atol=1e-8)
    # the ATE does not depend on it (SE(3)-aligned), the drawing does
    assert evaluation.ape.rmse == pytest.approx(evaluate(est, truth).ape.rmse, rel=1e-6)
    # other poses of the same ground truth (a comparison draws all of its frames) move alike
    np.testing.assert_allclose(ground_truth_from_start(evaluation, elsewhere[::7]), truth[::7], atol=1e-8)


def test_a_ground_truth_that_starts_at_the_estimates_first_pose_is_drawn_as_it_is():
    truth = _drive(seed=4)
    est = truth.copy()
    est[1:, :3, 3] += 0.3
    evaluation = evaluate(est, truth)
    np.testing.assert_allclose(start_anchor(evaluation), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(ground_truth_from_start(evaluation), truth, atol=1e-12)


def test_the_side_view_says_how_the_ground_truth_is_drawn(tmp_path):
    import matplotlib.figure

    truth = _drive(seed=5)
    titles = []
    real_savefig = matplotlib.figure.Figure.savefig

    def spy(fig, *args, **kwargs):
        titles.extend(ax.get_title() for ax in fig.axes)
        return real_savefig(fig, *args, **kwargs)

    matplotlib.figure.Figure.savefig = spy
    try:
        plot_trajectory_map(tmp_path / "with.png", [TrajectoryCurve(truth, "ground truth", ground_truth=True),
                                                     TrajectoryCurve(truth, "estimate")])
        with_gt = list(titles)
        titles.clear()
        plot_trajectory_map(tmp_path / "without.png", [TrajectoryCurve(truth, "estimate")])
    finally:
        matplotlib.figure.Figure.savefig = real_savefig
    assert any(SIDE_VIEW_GT_NOTE in t for t in with_gt)
    assert not any(SIDE_VIEW_GT_NOTE in t for t in titles)
    assert (tmp_path / "with.png").stat().st_size > 0 and (tmp_path / "without.png").stat().st_size > 0
