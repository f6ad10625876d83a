"""Stalled feature tracks: detection, the remap that puts them back in sync, and a
ground-truth-free check of both.

The KITTI feature files re-detect features every ~10 frames. At each such re-detection
frame ``r`` every *continuing* track repeats its previous frame's pixels bit for bit
(:meth:`~vislam.core.sequence.StereoObservations.repeated_mask`). Across r−1 -> r+1 such
a track moves only half as far as the odometry says, as if it were one frame late from
then on (its observation at frame k taken at frame k − 1; L frames late after L
re-detection frames); tracks that start at or after ``r`` are in sync. The remap here
implements that *lag model* (issue 12).

What the data say about the model (:func:`segment_timing_residuals`, no ground truth;
numbers in benchmarks/results/stalled_tracks.json): between two stalls, a track's
observations are one static point with the poses of *their own* frames, not of the
lagged ones, and the repeat itself fits the segment it opens, in sync. So at a stall
the tracker restarts from the stale pixels and follows the point found there (a new
point, in sync), the behaviour of the estimators' ``repeated_observations="split"``.
That new point Q is seen from camera r where the old point P was seen from camera r−1
(all four pixels are copied, disparity included), so for a constant camera motion it is
seen from camera k exactly where P was seen from camera k−1: the lag model is the
constant-velocity approximation of the restart, and it keeps the landmark (and what the
filter knows about it) across the stall.

Definitions used here:

* a **track** is a run of consecutive frames in which one landmark id is observed; a
  frame without the id ends it, and a later observation of the id starts a new track
  (the KITTI files have contiguous tracks, so there a track is a landmark);
* the **lag** of an observation (:func:`track_lags`) is the number of exact repeats in
  its track up to and including itself. Its pixels were taken at frame ``k − lag``. A
  repeat's lag counts itself: its pixels, like those of the previous observation, belong
  to frame ``k − lag``, which the previous observation already covers;
* a **stall frame** is a frame holding at least one repeat.

:func:`remap_stalled_tracks` drops every repeat and moves each remaining observation
from frame k to frame ``k − lag``.

Edge cases (each is handled by the rule above, nothing special-cased):

* several repeats in a row (a track frozen for several frames) count one stall each and
  are all dropped;
* a track that starts at a stall frame has no repeat there (no previous pixels): it is
  in sync;
* a landmark id seen again after a gap starts a new track with lag 0;
* collisions cannot happen: within a track the kept observations land on consecutive
  frames from the track's first frame on (each repeat between two kept observations
  both adds one frame and one unit of lag), so the track stays contiguous, inside its
  original frame range, and two tracks of one id (disjoint ranges, separated by at
  least one frame) stay disjoint and separated. The result is checked anyway (a
  ``ValueError`` would be a bug). Ids stay strictly increasing within each frame;
* a track with total lag L ends L frames earlier than before; no non-repeated
  observation is lost, and frame count and landmark ids are unchanged;
* the result contains no repeats (the first kept observation after a run of repeats
  differs from the repeated pixels by definition), so the remap is idempotent, and
  data without repeats is returned unchanged.

:func:`stall_diagnostics` checks the remap without ground truth: it compares the pixel
motion of tracks with the motion predicted by dead-reckoned odometry (see
:class:`FlowRatio`), across stalls (continuing tracks), after them (new tracks) and on
ordinary steps, before and after the remap, and adds the segment timing residuals.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from vislam.core.bookkeeping import sorted_positions
from vislam.core.lie import se3_inverse
from vislam.core.propagation import dead_reckoning
from vislam.core.sequence import Frame, Sequence, StereoObservations

__all__ = [
    "track_lags",
    "stall_frames",
    "remap_stalled_tracks",
    "remap_sequence",
    "StallRemapBuffer",
    "FlowRatio",
    "StallDiagnostics",
    "odometry_flow_ratios",
    "segment_timing_residuals",
    "stall_diagnostics",
    "rounded_pixels",
    "repeat_decisions",
]

#: Groups of :func:`odometry_flow_ratios`, in report order.
FLOW_GROUPS = ("continuing", "continuing_lagged", "new", "ordinary")


def _lags(observations: StereoObservations, repeated: np.ndarray) -> np.ndarray:
    """Lag of each observation given its repeat flags (see the module docstring)."""
    n = observations.n_observations
    out = np.zeros(n, dtype=np.int64)
    if n == 0 or not np.any(repeated):
        return out
    order = np.lexsort((observations.frame_index, observations.landmark_ids))  # by id, then frame
    ids = observations.landmark_ids[order]
    frames = observations.frame_index[order]
    new_track = np.ones(n, dtype=bool)
    new_track[1:] = (ids[1:] != ids[:-1]) | (frames[1:] != frames[:-1] + 1)
    rep = repeated[order].astype(np.int64)
    running = np.cumsum(rep)
    track = np.cumsum(new_track) - 1
    before_track = (running - rep)[new_track]  # repeats of earlier tracks
    out[order] = running - before_track[track]
    return out


def track_lags(observations: StereoObservations) -> np.ndarray:
    """(N,) int64: number of exact repeats (stalls) in each observation's track up to and
    including the observation itself. Its pixels were taken at frame ``k − lag``."""
    return _lags(observations, observations.repeated_mask())


def stall_frames(observations: StereoObservations) -> np.ndarray:
    """Sorted frames that hold at least one exact repeat."""
    return np.unique(observations.frame_index[observations.repeated_mask()])


def remap_stalled_tracks(observations: StereoObservations, repeated: np.ndarray | None = None) -> StereoObservations:
    """Drop the repeats (``repeated``, default ``observations.repeated_mask()``) and move
    every other observation from frame k to ``k − lag`` (see the module docstring for the
    rule and its edge cases)."""
    repeated = observations.repeated_mask() if repeated is None else repeated
    if not np.any(repeated):
        return observations
    lag = _lags(observations, repeated)
    keep = ~repeated
    frames = observations.frame_index[keep] - lag[keep]
    ids = observations.landmark_ids[keep]
    pixels = observations.pixels[keep]
    order = np.lexsort((ids, frames))  # by frame, then id
    frames, ids, pixels = frames[order], ids[order], pixels[order]
    if frames.size and frames[0] < 0:  # pragma: no cover - lag <= frames since the track began
        raise ValueError("remap_stalled_tracks: an observation moved before frame 0")
    same = (frames[1:] == frames[:-1]) & (ids[1:] == ids[:-1])
    if np.any(same):  # pragma: no cover - impossible by construction (module docstring)
        raise ValueError(f"remap_stalled_tracks: landmark {ids[1:][same][0]} lands twice on frame "
                         f"{frames[1:][same][0]}")
    T = observations.n_frames
    offsets = np.zeros(T + 1, dtype=np.int64)
    np.cumsum(np.bincount(frames, minlength=T), out=offsets[1:])
    return StereoObservations(offsets, ids, pixels, observations.n_landmarks)


def remap_sequence(sequence: Sequence) -> Sequence:
    """``sequence`` with :func:`remap_stalled_tracks` applied to its observations (itself
    if it has no repeats)."""
    remapped = remap_stalled_tracks(sequence.observations, sequence.repeated_mask())
    if remapped is sequence.observations:
        return sequence
    return sequence.replace(observations=remapped)


# ----------------------------------------------------------------------------- diagnostics


@dataclass(frozen=True)
class FlowRatio:
    """Observed pixel motion of tracks against the motion the odometry predicts.

    For a track observed at frames a and b, its point is triangulated from the stereo
    observation at a, moved into the camera at b with the dead-reckoned relative pose
    and projected: ``ẑ_b``. With the predicted flow ``f = ẑ_b − z_a`` and the observed
    flow ``g = z_b − z_a`` (4-vectors uL, vL, uR, vR), the track's ratio is
    ``g·f / |f|²``: 1 when the pixels move as the odometry says, 0.5 when they cover
    half the motion (a track one frame late across a two-frame window).

    The same ratio of the disparity changes, ``(d_b − d_a) / (d̂_b − d_a)`` with
    ``d = uL − uR``, is insensitive to rotation (a small rotation shifts uL and uR alike),
    so it stays unbiased when the angular velocities are noisy: on the dense files the
    gyro noise (0.05 rad/s per sample, ~5 px of flow over two frames) is in the
    predicted flow ``f`` and pulls the pixel ratio below 1 unless ``min_flow_px`` is
    large, while the disparity ratio is driven by the forward motion, which the
    odometry predicts to a few percent. Across a stall a one-frame disparity change over
    the two-frame one is a little below 0.5 (disparity grows faster as a point comes
    closer: 0.45 for a point 10 m ahead moving 1 m per frame). The disparity ratio is
    itself sensitive to pixel noise on small disparity changes (selection by the
    predicted change, which depends on the noisy first disparity): on the simulator with
    0.5 px noise it reads 0.83-0.90 on ordinary steps, while on the KITTI files it reads
    0.98-1.01; read the two ratios together.

    Attributes:
        n_windows: frame windows (a, b) that contributed.
        n_tracks: track pairs used for the pixel ratio (predicted flow at least
            ``min_flow_px``).
        median, q25, q75: median and quartiles of the pixel ratios (NaN without
            tracks); robust to the ~10 % gross outliers and moving points.
        residual_median_px: median of |z_b − ẑ_b| (px, 4-vector norm).
        disparity_n_tracks: track pairs used for the disparity ratio (predicted
            disparity change at least ``min_disparity_change_px``).
        disparity_median, disparity_q25, disparity_q75: median and quartiles of the
            disparity ratios.
    """

    n_windows: int
    n_tracks: int
    median: float
    q25: float
    q75: float
    residual_median_px: float
    disparity_n_tracks: int = 0
    disparity_median: float = float("nan")
    disparity_q25: float = float("nan")
    disparity_q75: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        return {"n_windows": self.n_windows, "n_tracks": self.n_tracks, "median": self.median, "q25": self.q25,
                "q75": self.q75, "residual_median_px": self.residual_median_px,
                "disparity_n_tracks": self.disparity_n_tracks, "disparity_median": self.disparity_median,
                "disparity_q25": self.disparity_q25, "disparity_q75": self.disparity_q75}


def _quartiles(x: np.ndarray) -> tuple[float, float, float]:
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    q25, med, q75 = np.percentile(x, [25, 50, 75])
    return float(q25), float(med), float(q75)


@dataclass(frozen=True)
class StallDiagnostics:
    """Stalls of a sequence and the odometry check of the remap (no ground truth).

    Attributes:
        n_frames, n_observations: size of the sequence.
        n_repeats: exact repeats (dropped by the remap).
        stall_frames: frames with at least one repeat.
        n_isolated_stalls: stall frames r with no stall at r−1, r+1, r+2 (the windows
            of the flow check).
        repeat_share_at_stalls: repeats / continuing observations at the stall frames
            (1.0: every continuing track repeats).
        lagged_share: share of the non-repeated observations with lag > 0.
        max_lag: largest lag (frames).
        before, after: :func:`odometry_flow_ratios` of the sequence and of the remapped
            sequence, by group ("continuing", "new", "ordinary"), with the same windows.
        min_flow_px: the smallest predicted flow used.
        timing: :func:`segment_timing_residuals` by hypothesis.
    """

    n_frames: int
    n_observations: int
    n_repeats: int
    stall_frames: np.ndarray
    n_isolated_stalls: int
    repeat_share_at_stalls: float
    lagged_share: float
    max_lag: int
    before: dict[str, FlowRatio] = field(default_factory=dict)
    after: dict[str, FlowRatio] = field(default_factory=dict)
    min_flow_px: float = 0.0
    timing: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def n_stall_frames(self) -> int:
        return int(self.stall_frames.size)

    def to_dict(self) -> dict[str, Any]:
        return {
            "n_frames": self.n_frames,
            "n_observations": self.n_observations,
            "n_repeats": self.n_repeats,
            "n_stall_frames": self.n_stall_frames,
            "stall_period_median_frames": float(np.median(np.diff(self.stall_frames)))
            if self.stall_frames.size > 1 else None,
            "n_isolated_stalls": self.n_isolated_stalls,
            "repeat_share_at_stalls": self.repeat_share_at_stalls,
            "lagged_share": self.lagged_share,
            "max_lag": self.max_lag,
            "min_flow_px": self.min_flow_px,
            "flow_ratio_before": {k: v.to_dict() for k, v in self.before.items()},
            "flow_ratio_after": {k: v.to_dict() for k, v in self.after.items()},
            "segment_timing_residuals": self.timing,
        }


def _isolated(stalls: np.ndarray, T: int) -> np.ndarray:
    """Stall frames r with 1 <= r <= T−3 and no other stall frame among r−1, r+1, r+2."""
    is_stall = np.zeros(T + 3, dtype=bool)
    is_stall[stalls] = True
    r = stalls[(stalls >= 1) & (stalls <= T - 3)]
    return r[~is_stall[r - 1] & ~is_stall[r + 1] & ~is_stall[r + 2]]


def _track_start_frames(observations: StereoObservations) -> np.ndarray:
    """(N,) first frame of the track (run of consecutive frames of one id) of each observation."""
    n = observations.n_observations
    out = np.zeros(n, dtype=np.int64)
    if n == 0:
        return out
    order = np.lexsort((observations.frame_index, observations.landmark_ids))
    ids, frames = observations.landmark_ids[order], observations.frame_index[order]
    new_track = np.ones(n, dtype=bool)
    new_track[1:] = (ids[1:] != ids[:-1]) | (frames[1:] != frames[:-1] + 1)
    out[order] = frames[new_track][np.cumsum(new_track) - 1]
    return out


def _windows(observations: StereoObservations, stalls: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Row pairs (rows at a, rows at b) of each group; see :func:`odometry_flow_ratios`."""
    T, M = observations.n_frames, observations.n_landmarks
    fr, ids = observations.frame_index, observations.landmark_ids
    keys = fr * M + ids  # strictly increasing: rows are sorted by frame, then id

    def row(frame, lm):
        frame = np.asarray(frame)
        pos = np.minimum(np.searchsorted(keys, frame * M + lm), max(keys.size - 1, 0))
        hit = (keys[pos] == frame * M + lm) if keys.size else np.zeros(np.shape(lm), dtype=bool)
        return np.where(hit, pos, -1)

    is_stall = np.zeros(T, dtype=bool)
    is_stall[stalls] = True
    iso = _isolated(stalls, T)
    out = {}
    # continuing: observed at r−1, r and r+1; window r−1 -> r+1
    sel = np.isin(fr, iso - 1)
    a = np.flatnonzero(sel)
    mid, b = row(fr[a] + 1, ids[a]), row(fr[a] + 2, ids[a])
    ok = (mid >= 0) & (b >= 0)
    out["continuing"] = (a[ok], b[ok])
    # continuing_lagged: those of them that already went through an earlier stall (the
    # track began before the previous stall frame), i.e. are already late at r−1
    start = _track_start_frames(observations)
    prev_stall = np.full(T, -1, dtype=np.int64)
    if stalls.size:
        idx = np.searchsorted(stalls, np.arange(T), side="left") - 1  # last stall frame < t
        prev_stall = np.where(idx >= 0, stalls[np.maximum(idx, 0)], -1)
    a, b = out["continuing"]
    lagged = start[a] < prev_stall[fr[a] + 1]
    out["continuing_lagged"] = (a[lagged], b[lagged])
    # new: first seen at r (not at r−1), observed at r+2; window r -> r+2
    sel = np.isin(fr, iso)
    a = np.flatnonzero(sel)
    prev, mid, b = row(fr[a] - 1, ids[a]), row(fr[a] + 1, ids[a]), row(fr[a] + 2, ids[a])
    ok = (prev < 0) & (mid >= 0) & (b >= 0)
    out["new"] = (a[ok], b[ok])
    # ordinary: k−1 -> k+1 with no stall frame at k or k+1, observed at all three
    k = fr + 1
    sel = (k + 1 < T) & ~is_stall[np.minimum(k, T - 1)] & ~is_stall[np.minimum(k + 1, T - 1)]
    a = np.flatnonzero(sel)
    mid, b = row(fr[a] + 1, ids[a]), row(fr[a] + 2, ids[a])
    ok = (mid >= 0) & (b >= 0)
    out["ordinary"] = (a[ok], b[ok])
    return out


def odometry_flow_ratios(
    sequence: Sequence,
    stalls: np.ndarray,
    imu_T_world: np.ndarray | None = None,
    min_flow_px: float = 20.0,
    min_disparity_px: float = 2.0,
    min_disparity_change_px: float = 2.0,
) -> dict[str, FlowRatio]:
    """:class:`FlowRatio` of three groups of two-frame windows:

    * ``"continuing"``: tracks observed at r−1, r and r+1 for each isolated stall frame r
      (see :class:`StallDiagnostics`), window r−1 -> r+1;
    * ``"continuing_lagged"``: those of them that began before the previous stall frame,
      so are already late at r−1: about 0.5 before the remap if every stall adds one
      frame of lag, about 1 after it if the remap moved them by their whole lag;
    * ``"new"``: tracks that start at r and are observed at r+1 and r+2, window r -> r+2;
    * ``"ordinary"``: tracks observed at k−1, k, k+1 with no stall frame at k or k+1,
      window k−1 -> k+1.

    ``stalls`` are the stall frames (of the original sequence, also when ``sequence`` is
    its remap, so that both are measured on the same windows). ``imu_T_world`` (T, 4, 4):
    the poses that predict the motion; by default dead reckoning of the sequence's
    velocities. Pairs whose first observation has a disparity below
    ``min_disparity_px`` or whose predicted point is not in front of the camera at b are
    left out, and so are pairs with a predicted flow below ``min_flow_px`` (pixel
    ratio) or a predicted disparity change below ``min_disparity_change_px`` (disparity
    ratio).
    """
    obs = sequence.observations
    if imu_T_world is None:
        imu_T_world, _ = dead_reckoning(sequence, np.zeros((6, 6)), np.zeros((6, 6)))
    cam = sequence.camera
    fr = obs.frame_index
    out = {}
    for name, (a, b) in _windows(obs, np.asarray(stalls, dtype=np.int64)).items():
        za, zb = obs.pixels[a], obs.pixels[b]
        ok = cam.disparity_px(za) >= min_disparity_px
        a, b, za, zb = a[ok], b[ok], za[ok], zb[ok]
        q_a = cam.triangulate(za) if a.size else np.zeros((0, 3))
        # cam_b_T_cam_a = cam_T_imu · imu_b_T_world · world_T_imu_a · imu_T_cam
        rel = sequence.cam_T_imu @ imu_T_world[fr[b]] @ se3_inverse(imu_T_world[fr[a]]) @ sequence.imu_T_cam
        q_b = np.einsum("nij,nj->ni", rel[:, :3, :3], q_a) + rel[:, :3, 3]
        front = q_b[:, 2] > 0.1
        z_pred = np.full_like(zb, np.nan)
        if np.any(front):
            z_pred[front] = cam.project(q_b[front])
        f_pred = z_pred - za
        f_obs = zb - za
        norm2 = np.einsum("ni,ni->n", f_pred, f_pred)
        use = front & (norm2 >= min_flow_px**2)
        ratio = np.einsum("ni,ni->n", f_obs[use], f_pred[use]) / norm2[use]
        resid = np.linalg.norm(zb[use] - z_pred[use], axis=1)
        q25, med, q75 = _quartiles(ratio)
        res = float(np.median(resid)) if resid.size else float("nan")
        d_a = cam.disparity_px(za)
        dd_pred = cam.disparity_px(z_pred) - d_a
        use_d = front & (np.abs(dd_pred) >= min_disparity_change_px)
        d_ratio = (cam.disparity_px(zb[use_d]) - d_a[use_d]) / dd_pred[use_d]
        dq25, dmed, dq75 = _quartiles(d_ratio)
        out[name] = FlowRatio(int(np.unique(fr[a[use | use_d]]).size), int(ratio.size), med, q25, q75, res,
                              int(d_ratio.size), dmed, dq25, dq75)
    return out


#: Timing hypotheses of :func:`segment_timing_residuals`: the pose an observation at
#: frame k with lag L is taken from.
TIMING_HYPOTHESES = ("in_sync", "one_frame_late", "lag")


def _group_medians(values: np.ndarray, group: np.ndarray, n_groups: int) -> np.ndarray:
    """(n_groups, d) per-group median of rows of ``values`` (NaN for empty groups)."""
    out = np.full((n_groups, values.shape[1]), np.nan)
    if group.size == 0:
        return out
    order = np.argsort(group, kind="stable")
    g = group[order]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    ends = np.r_[starts[1:], g.size]
    for a, b in zip(starts, ends):
        out[g[a]] = np.median(values[order[a:b]], axis=0)
    return out


def segment_timing_residuals(
    sequence: Sequence,
    imu_T_world: np.ndarray | None = None,
    min_observations: int = 3,
    min_disparity_px: float = 2.0,
) -> dict[str, dict[str, float]]:
    """Which frame do the observations of a stalled track belong to? No ground truth.

    A *segment* is the part of a track between two stalls (constant lag L). Under a
    timing hypothesis, each observation at frame k is triangulated with the pose of
    frame ``k − h`` into the world; the segment's point is the median of these points
    (over its non-repeated observations), and the observations' reprojection residuals
    from it measure how well the segment is one static point under that hypothesis:

    * ``"in_sync"``: h = 0 (the observation belongs to its own frame);
    * ``"one_frame_late"``: h = min(L, 1);
    * ``"lag"``: h = L (the model of :func:`remap_stalled_tracks`).

    For each hypothesis: the median residual (px, 4-vector norm) of the non-repeated
    observations with L >= 1 (``"lagged_median_px"``, ``"n_lagged"``), of the lag-0
    observations (``"in_sync_tracks_median_px"``, the same under every hypothesis: the
    reference), and of the repeats, held out of the fit, against the point of the
    segment they open (``"repeat_median_px"``, ``"n_repeats"``). Segments with fewer than
    ``min_observations`` non-repeated observations (first disparity below
    ``min_disparity_px`` excluded) are left out. ``imu_T_world``: by default dead
    reckoning; with noisy velocities (the dense files) the residuals grow for all
    hypotheses alike, so compare them with each other, not with a pixel noise.
    """
    obs = sequence.observations
    cam = sequence.camera
    if imu_T_world is None:
        imu_T_world, _ = dead_reckoning(sequence, np.zeros((6, 6)), np.zeros((6, 6)))
    world_T_imu = se3_inverse(imu_T_world)
    repeated = sequence.repeated_mask()
    lag = _lags(obs, repeated)
    rows = np.flatnonzero(cam.disparity_px(obs.pixels) >= min_disparity_px)
    start = _track_start_frames(obs)[rows]
    # segment key: (landmark, track start, lag)
    keys = np.stack([obs.landmark_ids[rows], start, lag[rows]], axis=1)
    _, seg = np.unique(keys, axis=0, return_inverse=True)
    seg = seg.ravel()
    n_seg = int(seg.max()) + 1 if seg.size else 0
    rep = repeated[rows]
    fit = ~rep
    n_fit = np.bincount(seg[fit], minlength=n_seg)
    usable = n_fit[seg] >= min_observations
    L = lag[rows]
    q = cam.triangulate(obs.pixels[rows]) if rows.size else np.zeros((0, 3))
    q_h = np.concatenate([q, np.ones((q.shape[0], 1))], axis=1)
    frames = obs.frame_index[rows]
    out = {}
    for name in TIMING_HYPOTHESES:
        h = {"in_sync": np.zeros_like(L), "one_frame_late": np.minimum(L, 1), "lag": L}[name]
        pose_frame = frames - h
        p_world = np.einsum("nij,nj->ni", world_T_imu[pose_frame] @ sequence.imu_T_cam, q_h)[:, :3]
        point = _group_medians(p_world[fit], seg[fit], n_seg)
        cam_T_world = sequence.cam_T_imu @ imu_T_world[pose_frame]
        p_cam = np.einsum("nij,nj->ni", cam_T_world[:, :3, :3], point[seg]) + cam_T_world[:, :3, 3]
        front = usable & (p_cam[:, 2] > 0.1)
        resid = np.full(rows.size, np.nan)
        if np.any(front):
            resid[front] = np.linalg.norm(cam.project(p_cam[front]) - obs.pixels[rows[front]], axis=1)

        def med(mask):
            m = mask & np.isfinite(resid)
            return (float(np.median(resid[m])) if np.any(m) else float("nan")), int(m.sum())

        lagged, n_lagged = med(fit & (L >= 1))
        ref, _ = med(fit & (L == 0))
        rep_med, n_rep = med(rep)
        out[name] = {"lagged_median_px": lagged, "n_lagged": n_lagged, "in_sync_tracks_median_px": ref,
                     "repeat_median_px": rep_med, "n_repeats": n_rep}
    return out


def stall_diagnostics(sequence: Sequence, min_flow_px: float = 20.0) -> StallDiagnostics:
    """Stall counts of ``sequence`` and :func:`odometry_flow_ratios` before and after
    :func:`remap_sequence`, on the same windows and with the same dead-reckoned poses."""
    obs = sequence.observations
    repeated = sequence.repeated_mask()
    lag = _lags(obs, repeated)
    stalls = np.unique(obs.frame_index[repeated])
    continuing = obs.previous_index() >= 0
    at_stall = np.isin(obs.frame_index, stalls)
    n_cont = int(np.sum(continuing & at_stall))
    kept = ~repeated
    imu_T_world, _ = dead_reckoning(sequence, np.zeros((6, 6)), np.zeros((6, 6)))
    before = odometry_flow_ratios(sequence, stalls, imu_T_world, min_flow_px)
    after = odometry_flow_ratios(remap_sequence(sequence), stalls, imu_T_world, min_flow_px)
    return StallDiagnostics(
        n_frames=sequence.n_frames,
        n_observations=obs.n_observations,
        n_repeats=int(repeated.sum()),
        stall_frames=stalls,
        n_isolated_stalls=int(_isolated(stalls, sequence.n_frames).size),
        repeat_share_at_stalls=float(repeated.sum() / n_cont) if n_cont else float("nan"),
        lagged_share=float(np.mean(lag[kept] > 0)) if np.any(kept) else 0.0,
        max_lag=int(lag.max()) if lag.size else 0,
        before=before,
        after=after,
        min_flow_px=float(min_flow_px),
        timing=segment_timing_residuals(sequence, imu_T_world),
    )


# ----------------------------------------------------------------------------- online


class StallRemapBuffer:
    """The remap of :func:`remap_stalled_tracks`, online: frames go in as they arrive and
    come out, remapped, ``max_delay_frames`` frames later.

    An observation at frame k with lag L (repeats so far in its track) belongs to frame
    k − L; frame j is complete once frame j + D has arrived (D = ``max_delay_frames``),
    so it is released then. Repeats are dropped (counted in :attr:`repeats`);
    observations whose lag exceeds D are dropped too (counted in :attr:`dropped`; on
    the shared files 0.2-0.3 % of the dense files' observations at D = 10, 6 % of the
    sparse files', whose tracks live for hundreds of frames). With D at least the
    largest lag the output equals :func:`remap_stalled_tracks` frame for frame.

    Memory: one row per track in view and the D buffered frames.
    """

    def __init__(self, max_delay_frames: int, camera=None):
        from collections import deque

        from vislam.core.bookkeeping import FrameRepeats

        if max_delay_frames < 0:
            raise ValueError("max_delay_frames must be >= 0")
        self.max_delay_frames = int(max_delay_frames)
        self._repeats = FrameRepeats(camera)  # the rule of StereoObservations.repeated_mask
        # the tracks in view: every track alive at frame k was observed at k − 1 (a gap
        # ends it), so they are exactly the last frame's observations — its ids (strictly
        # increasing), pixels and the lag of each track
        self._ids = np.zeros(0, dtype=np.int64)
        self._lag = np.zeros(0, dtype=np.int64)
        self._pending = deque()  # [frame, id parts, pixel parts], oldest first
        self._next = 0  # index of the next frame pushed
        self.repeats = 0
        self.dropped = 0

    @property
    def n_pending(self) -> int:
        """Frames received but not released yet."""
        return len(self._pending)

    def pending_frames(self) -> list:
        """The frames received but not released (their IMU samples, for propagation)."""
        return [entry[1] for entry in self._pending]

    def push(self, frame) -> list:
        """Take the next frame; return the frames now complete (remapped, in order)."""
        k = self._next
        self._next += 1
        ids = np.asarray(frame.landmark_ids, dtype=np.int64)
        z = np.asarray(frame.pixels, dtype=np.float64)
        # continuing tracks (observed in frame k − 1 too) keep their lag; the others start
        # at lag 0 (tracks not observed now have ended: a gap starts a new track)
        pos, cont = sorted_positions(ids, self._ids)
        lag = np.where(cont, self._lag[pos], 0) if self._ids.size else np.zeros(ids.size, dtype=np.int64)
        if k > 0:
            self._repeats.set_motion(frame.dt_s, frame.linear_velocity_mps, frame.angular_velocity_radps)
        rep = self._repeats(k, ids, z)
        n_rep = int(np.count_nonzero(rep))
        if n_rep:
            lag += rep
        self._ids, self._lag = ids.copy(), lag  # (the caller may reuse its arrays)
        self.repeats += n_rep
        # the kept observations (not repeats) whose lag the buffer can still place
        sel = np.flatnonzero(~rep) if n_rep else np.arange(ids.size)
        kept_lag = lag[sel] if n_rep else lag
        ok = kept_lag <= self.max_delay_frames
        n_ok = int(np.count_nonzero(ok))
        self.dropped += int(kept_lag.size) - n_ok
        if n_ok < kept_lag.size:
            sel, kept_lag = sel[ok], kept_lag[ok]
        self._pending.append([k, frame, [], []])
        base = k - (len(self._pending) - 1)  # number of the oldest pending frame
        if sel.size == 0:
            groups = ()
        elif kept_lag.any():
            # group by target frame k − lag (a stable sort keeps the ids increasing in each group)
            sel = sel[np.argsort(kept_lag, kind="stable")]
            target = k - lag[sel]
            cuts = (np.flatnonzero(np.diff(target)) + 1).tolist()
            groups = zip([0, *cuts], [*cuts, sel.size], target[[0, *cuts]].tolist())
        else:  # no lagged track: every observation belongs to frame k
            groups = ((0, sel.size, k),)
        for a, b, j in groups:
            entry = self._pending[j - base]
            entry[2].append(ids[sel[a:b]])
            entry[3].append(z[sel[a:b]])
        ready = []
        while self._pending and self._pending[0][0] <= k - self.max_delay_frames:
            ready.append(self._release())
        return ready

    def flush(self) -> list:
        """The frames still pending (the recording ended): release them all."""
        return [self._release() for _ in range(len(self._pending))]

    def _release(self):
        _, frame, id_parts, px_parts = self._pending.popleft()
        if len(id_parts) == 1:  # one push contributed: its ids are increasing already
            ids, pixels = id_parts[0], px_parts[0]
        elif id_parts:
            ids = np.concatenate(id_parts)
            pixels = np.concatenate(px_parts)
            order = np.argsort(ids, kind="stable")
            ids, pixels = ids[order], pixels[order]
            if ids.size > 1 and (np.diff(ids) <= 0).any():  # cannot happen (see remap_stalled_tracks)
                raise ValueError(f"stall remap: two observations of one landmark in frame {frame.index}")
        else:
            ids, pixels = np.zeros(0, dtype=np.int64), np.zeros((0, 4))
        if type(frame) is Frame:  # dataclasses.replace, without its field-by-field introspection
            return Frame(frame.index, frame.timestamp_s, frame.dt_s, frame.linear_velocity_mps,
                         frame.angular_velocity_radps, ids, pixels)
        return replace(frame, landmark_ids=ids, pixels=pixels)


def rounded_pixels(sequence: Sequence) -> Sequence:
    """``sequence`` with its pixels rounded to integers (a quantizing tracker's output)."""
    obs = sequence.observations
    return sequence.replace(observations=StereoObservations(obs.frame_offsets, obs.landmark_ids,
                                                            np.round(obs.pixels), obs.n_landmarks))


def repeat_decisions(sequence: Sequence) -> tuple[np.ndarray, np.ndarray, int]:
    """The repeat decisions of every detector on ``sequence``: the whole-sequence mask
    (:meth:`Sequence.repeated_mask`), the online one of the filters
    (:class:`~vislam.core.bookkeeping.FrameRepeats`, frame by frame, per observation)
    and the number of repeats SLAM's :class:`StallRemapBuffer` drops."""
    from vislam.core.bookkeeping import FrameRepeats

    detector, online, buffer = FrameRepeats(sequence.camera), [], StallRemapBuffer(1000, sequence.camera)
    for frame in sequence.frames():
        if frame.index:
            detector.set_motion(frame.dt_s, frame.linear_velocity_mps, frame.angular_velocity_radps)
        online.append(detector(frame.index, frame.landmark_ids, frame.pixels))
        buffer.push(frame)
    return sequence.repeated_mask(), np.concatenate(online), buffer.repeats
