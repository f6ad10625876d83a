"""The report's figure: trajectory and landmarks in the world xy plane.

:func:`plot_trajectory_map` draws one or more ``world_T_imu`` trajectories (the world
frame is the first IMU pose: x forward, y left, z up, so xy is the ground plane) with
start and end marked, and the landmarks of a :class:`~vislam.core.results.LandmarkMap`
as small translucent dots (rejected landmarks as faint red crosses under them). The view
is the extent of the trajectories plus a margin, so that a few far landmarks do not
shrink the drive to a dot; the legend, below the map and off the data, says how many
landmarks fall outside it.

:func:`plot_comparison_map` draws several estimates on one figure (the report's Figs
7–11): each :class:`MapLayer` is a trajectory with, optionally, its landmarks as small
dots in the same colour, over an optional ground truth.

Figures are drawn with matplotlib's object API on the Agg canvas (no pyplot state, no
window) and saved atomically (:func:`vislam.tools.atomic.atomic_path`).
"""

from __future__ import annotations

import textwrap
import warnings

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence as Seq

import numpy as np

from vislam.tools.atomic import atomic_path

__all__ = ["TrajectoryCurve", "MapLayer", "plot_trajectory_map", "plot_comparison_map", "plot_grouped_bars",
           "view_limits", "FIGSIZE_IN", "DPI"]

FIGSIZE_IN = (8.0, 11.0)
#: Size of :func:`plot_comparison_map`'s figure (legend below the map, then the side view).
COMPARISON_FIGSIZE_IN = (8.0, 11.5)
#: Height ratio of the top view to the side view (height over distance) below it.
SIDE_VIEW_RATIOS = (4.0, 1.25)
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
    #: the ground truth (the side view's title then says how it is drawn)
    ground_truth: bool = False


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


#: Characters of a subtitle line (9 pt) before it wraps: what fits the 8 in wide map figures.
SUBTITLE_CHARS = 100


def _label_map_axes(fig, ax, title: str, subtitle: str | None) -> None:
    """Axis labels in metres, grid, and the title (with the subtitle under it, smaller)."""
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, lw=0.4, alpha=0.5)
    ax.set_axisbelow(True)
    if subtitle:
        # each line wrapped to the figure's width (a line of five methods' ATEs was cut off at both sides)
        lines = [textwrap.fill(line, SUBTITLE_CHARS, break_long_words=False) for line in subtitle.split("\n")]
        ax.set_title("\n".join(lines), fontsize=9, color="0.3")
        fig.suptitle(title, fontsize=13)
    else:
        ax.set_title(title, fontsize=13)


def _distance_travelled(world_T_imu: np.ndarray) -> np.ndarray:
    """(T,) cumulative 3D path length (m) of a trajectory."""
    p = np.asarray(world_T_imu, dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
    if p.shape[0] == 0:
        return np.zeros(0)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(np.where(np.isfinite(step), step, 0.0))])


#: The side view's title, and its note when a ground truth is drawn: both start at the same
#: pose, unaligned, so a small error of the initial attitude shows as a height difference
#: growing with the distance from the start, which the SE(3)-aligned ATE does not count.
SIDE_VIEW_TITLE = "side view: height over distance"
SIDE_VIEW_GT_NOTE = "ground truth from the same start pose, not aligned as for the ATE"


def _side_view(ax, series, ground_truth: bool = False) -> None:
    """Height z over distance travelled, one line per ``(world_T_imu, color, linestyle,
    linewidth, alpha)``: what a top view hides (a filter climbing with a gyro bias).
    ``ground_truth``: one of the series is the ground truth (the title says how it is drawn)."""
    zs = []
    for world_T_imu, color, ls, lw, alpha in series:
        poses = np.asarray(world_T_imu, dtype=np.float64).reshape(-1, 4, 4)
        if poses.shape[0] == 0:
            continue
        z = poses[:, 2, 3]
        zs.append(z[np.isfinite(z)])
        ax.plot(_distance_travelled(poses), z, color=color, ls=ls, lw=lw, alpha=alpha)
    ax.set_xlabel("distance travelled [m]")
    ax.set_ylabel("height z [m]")
    ax.set_title(SIDE_VIEW_TITLE + (f" ({SIDE_VIEW_GT_NOTE})" if ground_truth else ""), fontsize=9, color="0.3")
    ax.grid(True, lw=0.4, alpha=0.5)
    z = np.concatenate(zs) if zs else np.zeros(0)
    if z.size:  # at least ±5 m, so that centimetre wiggles do not look like hills
        mid, half = 0.5 * (z.min() + z.max()), max(0.5 * (z.max() - z.min()) * 1.1, 5.0)
        ax.set_ylim(mid - half, mid + half)


def layout_once(fig, **tight_layout_kwargs) -> None:
    """Lay ``fig`` out once with tight_layout and leave it without a layout engine, so that
    saving it neither lays it out again nor draws it twice (``set_layout_engine(None)``:
    "none" would keep a placeholder engine, for which savefig draws twice). Legends and
    side views outside the axes make matplotlib say it cannot fit every decoration
    exactly; the layout it does apply is the one wanted, so that warning is dropped."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        fig.tight_layout(**tight_layout_kwargs)
    fig.set_layout_engine(None)


def _fit_equal_aspect(fig, ax, limits) -> tuple[tuple[float, float], tuple[float, float]]:
    """Set the view ``limits`` (x0, x1, y0, y1), widened on the shorter side so that the
    equal-aspect data box fills the axes box laid out by tight_layout; returns (xlim, ylim)."""
    x0, x1, y0, y1 = limits
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    layout_once(fig)  # final: the view below is fitted to it
    box = ax.get_position()
    fig_w, fig_h = fig.get_size_inches()
    box_ratio = (box.width * fig_w) / (box.height * fig_h)
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
    return (x0, x1), (y0, y1)


def plot_trajectory_map(path, curves: Seq[TrajectoryCurve], landmarks=None, title: str = "",
                        subtitle: str | None = None) -> dict:
    """Draw ``curves`` and ``landmarks`` (a LandmarkMap or None) in the xy plane, with a
    side view (height over distance travelled) below; save a PNG at ``path`` (8x11 in,
    120 dpi) atomically.

    Returns ``{"xlim", "ylim", "landmarks_outside_view"}`` of the figure drawn.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    fig = Figure(figsize=FIGSIZE_IN, dpi=DPI)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 1, height_ratios=SIDE_VIEW_RATIOS, hspace=0.5)
    ax = fig.add_subplot(grid[0])
    _side_view(fig.add_subplot(grid[1]), [(c.world_T_imu, c.color, c.linestyle, c.linewidth, 1.0) for c in curves],
               ground_truth=any(c.ground_truth for c in curves))

    p, handles = _map_landmarks(ax, landmarks)
    curve_handles, traj_xy = _map_curves(ax, curves)
    handles = curve_handles + handles

    _label_map_axes(fig, ax, title, subtitle)

    # The legend goes below the map, off the data; it is laid out before the view is
    # fitted, with the count of landmarks outside the view set afterwards.
    limits = view_limits(np.concatenate(traj_xy) if traj_xy else np.zeros((0, 2)))

    def outside_count(xlim, ylim) -> int:
        return int(_outside(p, xlim, ylim).sum()) if p.size else 0

    def outside_text(n: int) -> str:
        return f"{n} landmark{'s' if n != 1 else ''} outside the view" if n else "no landmark outside the view"

    first = outside_count(limits[:2], limits[2:])
    if first:
        handles.append(Line2D([], [], ls="none", label=outside_text(first)))
    legend = ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=2, fontsize=9,
                       frameon=False) if handles else None
    xlim, ylim = _fit_equal_aspect(fig, ax, limits)
    n_outside = outside_count(xlim, ylim)
    if first and legend is not None:
        legend.get_texts()[-1].set_text(outside_text(n_outside))
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return {"xlim": tuple(map(float, xlim)), "ylim": tuple(map(float, ylim)), "landmarks_outside_view": n_outside}


def _map_landmarks(ax, landmarks) -> tuple[np.ndarray, list]:
    """The map's landmarks (green dots; rejected ones faint red crosses under them):
    (xy of every landmark, legend handles)."""
    from matplotlib.lines import Line2D

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
        if n_rej:  # faint, under the kept ones: they must not hide the map
            ax.scatter(p[rejected, 0], p[rejected, 1], s=10 if n_rej <= 200 else 5, marker="x", c="tab:red",
                       alpha=0.25, linewidths=0.6, rasterized=True, zorder=0.5)
            handles.append(Line2D([], [], ls="none", marker="x", ms=5, color="tab:red", alpha=0.5,
                                  label=f"rejected landmarks ({n_rej})"))
    return p, handles


def _map_curves(ax, curves) -> tuple[list, list]:
    """The trajectories, with start and end of the first curve that asks for it (all
    curves start at the origin): (legend handles, xy of each curve drawn)."""
    from matplotlib.lines import Line2D

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
    return curve_handles, traj_xy


@dataclass(frozen=True)
class MapLayer:
    """One estimate of :func:`plot_comparison_map`: its (T, 4, 4) world_T_imu poses, its
    landmarks (a LandmarkMap or None; rejected ones are not drawn) and its style."""

    world_T_imu: np.ndarray
    label: str
    color: str
    landmarks: object = None
    linestyle: str = "-"
    linewidth: float = 1.6
    #: Short name in the landmarks' legend entry (default: ``label``).
    short: str | None = None


def _span(xy: np.ndarray) -> float:
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    return float(np.max(np.ptp(xy, axis=0))) if xy.shape[0] else 0.0


def _inside(xy: np.ndarray, limits) -> bool:
    x0, x1, y0, y1 = limits
    return bool(np.all(np.isfinite(xy)) and np.all((xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0)
                                                     & (xy[:, 1] <= y1)))


def plot_comparison_map(path, layers: Seq[MapLayer], title: str, subtitle: str | None = None,
                        ground_truth: np.ndarray | None = None, ground_truth_label: str = "ground truth") -> dict:
    """Several estimates in the xy plane on one figure: each layer's trajectory and its
    landmarks (small dots, same colour), the ground truth (``(T, 4, 4)`` world_T_imu, grey)
    when given; start marked once, each end with a square of its colour. Saved as a PNG
    (8x9 in, 120 dpi) at ``path``, atomically.

    View: the ground truth's extent (without it, the union of the layers, leaving out a
    trajectory more than 10 times larger than the smallest: a diverged run) plus a margin,
    extended to every trajectory that stays within half a span of it. A trajectory that
    leaves the view says so in the legend, as do landmarks outside it.

    Returns ``{"xlim", "ylim", "landmarks_outside_view", "layers_leaving_view"}``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=COMPARISON_FIGSIZE_IN, dpi=DPI)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 1, height_ratios=SIDE_VIEW_RATIOS, hspace=0.55)
    ax = fig.add_subplot(grid[0])
    side = [] if ground_truth is None else [(ground_truth, "0.2", "-", 3.0, 0.45)]
    _side_view(fig.add_subplot(grid[1]), side + [(layer.world_T_imu, layer.color, layer.linestyle, layer.linewidth,
                                                  1.0) for layer in layers], ground_truth=ground_truth is not None)
    layer_xy = [np.asarray(layer.world_T_imu, dtype=np.float64).reshape(-1, 4, 4)[:, :2, 3] for layer in layers]
    gt_xy = None if ground_truth is None else np.asarray(ground_truth, dtype=np.float64).reshape(-1, 4, 4)[:, :2, 3]

    limits, fits = _comparison_view(layer_xy, gt_xy)
    p, lm_handles = _comparison_landmarks(ax, layers)  # under the trajectories
    handles, leaving = _comparison_trajectories(ax, layers, layer_xy, fits, gt_xy, ground_truth_label)
    handles += lm_handles
    _label_map_axes(fig, ax, title, subtitle)
    xlim, ylim, n_outside = _legend_below_and_fit(fig, ax, handles, p, limits)
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return {"xlim": tuple(map(float, xlim)), "ylim": tuple(map(float, ylim)), "landmarks_outside_view": n_outside,
            "layers_leaving_view": leaving}


def _comparison_view(layer_xy: list, gt_xy: np.ndarray | None) -> tuple[tuple, list[bool]]:
    """The view of :func:`plot_comparison_map`: (limits (x0, x1, y0, y1), whether each
    layer's trajectory stays within half a span of the base extent)."""
    if gt_xy is not None and gt_xy.shape[0]:
        base = [gt_xy]
    else:
        spans = [_span(xy) for xy in layer_xy if xy.shape[0]]
        smallest = max(min(spans), 2 * MIN_MARGIN_M) if spans else 0.0
        base = [xy for xy in layer_xy if xy.shape[0] and _span(xy) <= 10 * smallest]
    limits = view_limits(np.concatenate(base) if base else np.zeros((0, 2)))
    half = 0.5 * max(limits[1] - limits[0], limits[3] - limits[2])
    window = (limits[0] - half, limits[1] + half, limits[2] - half, limits[3] + half)
    fits = [xy.shape[0] > 0 and _inside(xy, window) for xy in layer_xy]
    limits = view_limits(np.concatenate(base + [xy for xy, ok in zip(layer_xy, fits) if ok]) if base or any(fits)
                         else np.zeros((0, 2)))
    return limits, fits


def _comparison_landmarks(ax, layers) -> tuple[np.ndarray, list]:
    """Each layer's landmarks in the map (small dots of its colour; rejected ones not
    drawn): (all xy drawn, legend handles)."""
    from matplotlib.lines import Line2D

    lm_handles: list = []
    all_lm = []
    n_lm_total = sum(len(layer.landmarks) for layer in layers if layer.landmarks is not None)
    size = 10.0 if n_lm_total <= 600 else 5.0 if n_lm_total <= 3000 else 2.0
    for layer in layers:
        lm = layer.landmarks
        if lm is None:
            continue
        ok = np.asarray(lm.status) == 0
        p = np.asarray(lm.p_lm_in_world, dtype=np.float64).reshape(-1, 3)[ok, :2]
        all_lm.append(p)
        ax.scatter(p[:, 0], p[:, 1], s=size, c=layer.color, alpha=0.45, linewidths=0, rasterized=True, zorder=1)
        n_rej = int((~ok).sum())
        text = f"{layer.short or layer.label}: {int(ok.sum())} landmarks" + (
            f" ({n_rej} rejected, not shown)" if n_rej else "")
        lm_handles.append(Line2D([], [], ls="none", marker="o", ms=4, color=layer.color, alpha=0.7, label=text))
    return (np.concatenate(all_lm) if all_lm else np.zeros((0, 2))), lm_handles


def _comparison_trajectories(ax, layers, layer_xy: list, fits: list, gt_xy, ground_truth_label: str):
    """The ground truth and each layer's trajectory, its end a square of its colour, the
    start marked once: (legend handles, labels of the layers that leave the view)."""
    from matplotlib.lines import Line2D

    handles: list = []
    if gt_xy is not None and gt_xy.shape[0]:
        (line,) = ax.plot(gt_xy[:, 0], gt_xy[:, 1], color="0.2", lw=3.0, alpha=0.45, zorder=2,
                          label=ground_truth_label)
        handles.append(line)
    leaving = []
    for layer, xy, ok in zip(layers, layer_xy, fits):
        if xy.shape[0] == 0:
            continue
        label = layer.label + ("" if ok else " (leaves the view)")
        if not ok:
            leaving.append(layer.label)
        (line,) = ax.plot(xy[:, 0], xy[:, 1], color=layer.color, ls=layer.linestyle, lw=layer.linewidth, zorder=3,
                          label=label)
        handles.append(line)
        ax.plot(*xy[-1], marker="s", ms=7, mfc=layer.color, mec="black", mew=0.8, ls="none", zorder=5)
    starts = [xy[0] for xy in ([gt_xy] if gt_xy is not None else []) + layer_xy if xy is not None and xy.shape[0]]
    if starts:
        ax.plot(*starts[0], marker="o", ms=9, mfc="white", mec="black", mew=1.8, ls="none", zorder=6)
        handles.append(Line2D([], [], ls="none", marker="o", ms=8, mfc="white", mec="black", mew=1.8, label="start"))
        handles.append(Line2D([], [], ls="none", marker="s", ms=7, mfc="0.7", mec="black", mew=0.8,
                              label="end (colour of its trajectory)"))
    return handles, leaving


def _legend_below_and_fit(fig, ax, handles: list, p: np.ndarray, limits) -> tuple:
    """The legend goes below the axes (several estimates and landmark sets would hide
    part of the drive); it is laid out before the view is fitted, with the count of
    landmarks outside the view updated afterwards (the fitted view only grows).
    Returns (xlim, ylim, landmarks outside the view)."""
    from matplotlib.lines import Line2D

    def outside_text(xlim, ylim) -> str | None:
        n = int(_outside(p, xlim, ylim).sum()) if p.size else 0
        return f"{n} landmark{'s' if n != 1 else ''} outside the view" if n else None

    first = outside_text(limits[:2], limits[2:])
    if first:
        handles.append(Line2D([], [], ls="none", label=first))
    legend = ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=2, fontsize=8.5,
                       frameon=False) if handles else None
    xlim, ylim = _fit_equal_aspect(fig, ax, limits)
    final = outside_text(xlim, ylim)
    n_outside = int(_outside(p, xlim, ylim).sum()) if p.size else 0
    if first and legend is not None:
        legend.get_texts()[-1].set_text(final or "no landmark outside the view")
    return xlim, ylim, n_outside


def plot_grouped_bars(path, panels, series, ylabel: str, title: str) -> None:
    """Grouped bar chart, one panel (row) per entry of ``panels``: ``(panel_title,
    group_labels, {series_key: [value or None per group]})``; ``series`` is a list of
    ``(key, legend label, colour)``. Each bar is labelled with its value ("n/a" for None).
    Saved as a PNG at ``path`` (9 in wide, 3.6 in per panel, 120 dpi), atomically."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n = len(panels)
    fig = Figure(figsize=(9.0, 1.0 + 3.4 * n), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(n, 1, squeeze=False)[:, 0]
    fig.suptitle(title, fontsize=13)
    width = 0.8 / max(len(series), 1)
    for ax, (panel_title, groups, values) in zip(axes, panels):
        x = np.arange(len(groups))
        top = max([v for key, _, _ in series for v in values.get(key, []) if v is not None and np.isfinite(v)],
                  default=1.0)
        for i, (key, label, color) in enumerate(series):
            vals = values.get(key, [None] * len(groups))
            pos = x - 0.4 + width * (i + 0.5)
            heights = [v if v is not None and np.isfinite(v) else 0.0 for v in vals]
            bars = ax.bar(pos, heights, width * 0.92, color=color, label=label, zorder=2)
            for b, v in zip(bars, vals):
                text = "n/a" if v is None or not np.isfinite(v) else f"{v:.2f}"
                ax.text(b.get_x() + b.get_width() / 2, b.get_height() + 0.015 * top, text, ha="center",
                        va="bottom", fontsize=8)
        ax.set_xticks(x, groups, fontsize=8.5)
        ax.set_ylabel(ylabel)
        ax.set_ylim(0, top * 1.18)
        ax.set_title(panel_title, fontsize=10.5)
        ax.grid(True, axis="y", lw=0.4, alpha=0.5, zorder=0)
        ax.legend(loc="upper left", fontsize=8.5, framealpha=0.9)
    with atomic_path(Path(path), suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
