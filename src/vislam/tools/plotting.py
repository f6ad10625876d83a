"""The report's figure: trajectory and landmarks in the world xy plane.

:func:`plot_trajectory_map` draws one or more ``world_T_imu`` trajectories (the world
frame is the first IMU pose: x forward, y left, z up, so xy is the ground plane) with
start and end marked, and the landmarks of a :class:`~vislam.core.results.LandmarkMap`
as small translucent dots (rejected landmarks as red crosses). The view is the extent
of the trajectories plus a margin, so that a few far landmarks do not shrink the drive
to a dot; the legend says how many landmarks fall outside it.

Figures are drawn with matplotlib's object API on the Agg canvas (no pyplot state, no
window) and saved atomically (:func:`vislam.tools.atomic.atomic_path`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence as Seq

import numpy as np

from vislam.tools.atomic import atomic_path

__all__ = ["TrajectoryCurve", "plot_trajectory_map", "view_limits", "FIGSIZE_IN", "DPI"]

FIGSIZE_IN = (8.0, 8.0)
DPI = 120
#: Margin around the trajectories' extent: this share of the larger side, at least MIN_MARGIN_M.
MARGIN_FRACTION = 0.08
MIN_MARGIN_M = 25.0


@dataclass(frozen=True)
class TrajectoryCurve:
    """One trajectory to draw: (T, 4, 4) world_T_imu poses and its style."""

    world_T_imu: np.ndarray
    label: str
    color: str = "tab:blue"
    linestyle: str = "-"
    linewidth: float = 1.6
    zorder: float = 3.0
    mark_ends: bool = True


def view_limits(xy: np.ndarray, margin_fraction: float = MARGIN_FRACTION,
                min_margin_m: float = MIN_MARGIN_M) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax): the extent of the points ``xy`` (N, 2) plus a margin."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if xy.size == 0:
        return -min_margin_m, min_margin_m, -min_margin_m, min_margin_m
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    margin = max(margin_fraction * float(np.max(hi - lo)), min_margin_m)
    return lo[0] - margin, hi[0] + margin, lo[1] - margin, hi[1] + margin


def _outside(xy: np.ndarray, xlim, ylim) -> np.ndarray:
    finite = np.all(np.isfinite(xy), axis=1)
    inside = (xy[:, 0] >= xlim[0]) & (xy[:, 0] <= xlim[1]) & (xy[:, 1] >= ylim[0]) & (xy[:, 1] <= ylim[1])
    return ~(finite & inside)


def plot_trajectory_map(path, curves: Seq[TrajectoryCurve], landmarks=None, title: str = "",
                        subtitle: str | None = None) -> dict:
    """Draw ``curves`` and ``landmarks`` (a LandmarkMap or None) in the xy plane; save a
    PNG at ``path`` (8x8 in, 120 dpi) atomically.

    Returns ``{"xlim", "ylim", "landmarks_outside_view"}`` of the figure drawn.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    fig = Figure(figsize=FIGSIZE_IN, dpi=DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)

    handles: list = []
    p = np.zeros((0, 2))
    if landmarks is not None and len(landmarks):
        p = np.asarray(landmarks.p_lm_in_world, dtype=np.float64)[:, :2]
        rejected = np.asarray(landmarks.status) != 0
        ok = ~rejected
        n_ok, n_rej = int(ok.sum()), int(rejected.sum())
        # small markers with alpha: thousands of points stay readable where they overlap
        size = 10.0 if n_ok <= 500 else 5.0 if n_ok <= 2000 else 2.5
        ax.scatter(p[ok, 0], p[ok, 1], s=size, c="tab:green", alpha=0.5, linewidths=0, rasterized=True, zorder=1)
        handles.append(Line2D([], [], ls="none", marker="o", ms=4, color="tab:green", alpha=0.8,
                              label=f"landmarks ({n_ok})"))
        if n_rej:
            ax.scatter(p[rejected, 0], p[rejected, 1], s=16 if n_rej <= 200 else 9, marker="x", c="red",
                       alpha=0.8, linewidths=0.9 if n_rej <= 200 else 0.7, zorder=2)
            handles.append(Line2D([], [], ls="none", marker="x", ms=6, color="red",
                                  label=f"rejected landmarks ({n_rej})"))
    curve_handles: list = []
    traj_xy = []
    for c in curves:
        xy = np.asarray(c.world_T_imu)[:, :2, 3]
        if xy.shape[0] == 0:
            continue
        traj_xy.append(xy)
        (line,) = ax.plot(xy[:, 0], xy[:, 1], color=c.color, ls=c.linestyle, lw=c.linewidth, zorder=c.zorder,
                          label=c.label)
        curve_handles.append(line)
    # start and end of the first curve that asks for it (all curves start at the origin)
    marked = [c for c in curves if c.mark_ends and len(c.world_T_imu)]
    if marked:
        xy = np.asarray(marked[0].world_T_imu)[:, :2, 3]
        ax.plot(*xy[0], marker="o", ms=9, mfc="white", mec="black", mew=1.8, ls="none", zorder=5)
        ax.plot(*xy[-1], marker="s", ms=8, mfc="black", mec="black", ls="none", zorder=5)
        curve_handles.append(Line2D([], [], ls="none", marker="o", ms=8, mfc="white", mec="black", mew=1.8,
                                    label="start"))
        curve_handles.append(Line2D([], [], ls="none", marker="s", ms=7, mfc="black", mec="black", label="end"))
    handles = curve_handles + handles

    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.set_axisbelow(True)
    if subtitle:
        ax.set_title(subtitle, fontsize=9, color="0.3")
        fig.suptitle(title, fontsize=13)
    else:
        ax.set_title(title, fontsize=13)

    # View: the trajectories' extent plus a margin, widened on the shorter side so that
    # the equal-aspect data box fills the axes box laid out by tight_layout.
    x0, x1, y0, y1 = view_limits(np.concatenate(traj_xy) if traj_xy else np.zeros((0, 2)))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    fig.tight_layout()
    box = ax.get_position()
    box_ratio = (box.width * FIGSIZE_IN[0]) / (box.height * FIGSIZE_IN[1])
    w, h = x1 - x0, y1 - y0
    if w / h < box_ratio:
        grow = (h * box_ratio - w) / 2
        x0, x1 = x0 - grow, x1 + grow
    else:
        grow = (w / box_ratio - h) / 2
        y0, y1 = y0 - grow, y1 + grow
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal", adjustable="box")
    xlim, ylim = (x0, x1), (y0, y1)

    n_outside = int(_outside(p, xlim, ylim).sum()) if p.size else 0
    if n_outside:
        handles.append(Line2D([], [], ls="none", label=f"{n_outside} landmark{'s' if n_outside != 1 else ''} "
                                                        f"outside the view"))
    if handles:
        ax.legend(handles=handles, loc="best", fontsize=9, framealpha=0.9)
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return {"xlim": tuple(map(float, xlim)), "ylim": tuple(map(float, ylim)), "landmarks_outside_view": n_outside}
