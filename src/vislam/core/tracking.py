"""A stereo feature tracker: rectified stereo image pairs -> stereo feature tracks.

Pure image computation on OpenCV (no file I/O): :class:`StereoTracker` takes one
rectified grey pair at a time and returns the stereo observations of that frame,
``(track_ids, pixels)`` with pixels ``[uL, vL, uR, vR]`` in the rectified images — the
rows of :class:`vislam.core.sequence.StereoObservations`. It keeps only the previous
frame (its left image, its live tracks and their triangulation), so its memory does
not depend on the length of the recording.

Each frame (:meth:`StereoTracker.process`, one method per step):

1. **Temporal tracking** (``_track_temporal``) — pyramidal Lucas-Kanade (KLT) of the live
   tracks from the previous left image into the new one, started where the last camera
   motion predicts them, then back; a track whose round trip misses its start by more than
   ``fb_threshold_px`` is lost (forward-backward check).
2. **Stereo matching** (``_track_stereo``) — the right position of a tracked point is its
   new left position moved by the disparity the last motion predicts, refined by the affine
   step (2b; ``stereo_tracked_levels`` > 0: a KLT first). A match is kept only on the
   epipolar line of the rectified pair (``|vR - vL| <= max_row_difference_px``), with a
   disparity ``uL - uR`` in ``[min_disparity_px, max_disparity_px]``. A track that fails a
   check ends (tracks are contiguous: ids are never reused).
2b. **Affine refinement** — each track keeps the (2r+1)² template of its first left
   appearance; every new left and right position is refined by inverse-compositional
   Gauss-Newton over an affine warp of that template (plus gain and bias), so the position
   follows the surface point the track started on rather than drifting with the
   translation-only KLT. The template's steepest-descent images are computed once per
   track (no image gradients). A track whose warp leaves a residual above
   ``affine_max_residual`` of the template's contrast (or ``affine_relative_residual`` times
   its own first right match's residual, if larger) ends — unless it is within
   ``affine_confirm_factor`` times that bound and agrees with the geometry of the same frame
   (step 3) to the tight ``affine_confirm_px`` (``_confirm_suspects``; it keeps its template);
   one whose warp has scaled the template by ``affine_reanchor_scale`` takes its current
   appearance as the template.
3. **Geometric check** (``_check_geometry``) — the previous frame's stereo triangulation of
   the tracked points against their new left pixels: P3P in RANSAC (``cv2.solvePnPRansac``)
   gives the camera motion; a track whose predicted ``[uL, v, uR]`` is more than
   ``ransac_threshold_px`` from its measurement is rejected — measured in the metric of the
   prediction's uncertainty (the stereo triangulation's covariance from ``stereo_sigma_px``,
   carried to the pixels: a far point's uncertain depth lets it move further along its flow),
   and never more than ``gate_max_factor`` times the threshold in plain pixels.
3b. **Drift check** — the camera poses chained from the frame-to-frame P3P motions carry
   each track's first stereo triangulation (and its covariance) to the current frame; a track
   whose left or right position is more than ``drift_threshold_px`` from it (same metric) ends.
4. **Detection** (``_new_tracks``) — Shi-Tomasi corners (``cv2.goodFeaturesToTrack``, on each
   cell alone) at least ``min_distance_px`` from every live track, in the cells of a
   ``grid_cols x grid_rows`` grid below their share of ``target_features``; matched into the
   right image by normalised cross-correlation along the row on pyramid level
   ``stereo_search_level`` (all corners at once; a best score below ``stereo_min_score`` or a
   second peak within ``stereo_uniqueness`` of it refuses the corner) and the affine step. A corner whose stereo point leaves the view under the last motion within
   ``min_expected_frames`` is not started; a cell whose try started few tracks rests
   (``detect_retry_frames``). New corners get new ids (0, 1, 2, ... in order of detection).

Every track end is counted under its check with the track's length
(:class:`TrackerStatistics`, ``track_ends``).

Frames: pixels (u right, v down) of the rectified left/right images; 3-D points in the
left camera frame of the previous image (x right, y down, z forward).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from typing import Any, Mapping

import numpy as np

from vislam.errors import ConfigError

__all__ = ["TrackerOptions", "TrackerStatistics", "StereoTracker", "require_cv2"]


def require_cv2():
    """The ``cv2`` module, or a ConfigError saying how to install it."""
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - the test extra installs it
        raise ConfigError("the visual front end needs OpenCV: pip install 'vislam[frontend]' "
                          f"(opencv-python-headless; import failed: {exc})") from None
    return cv2


#: Upper bounds of TrackerOptions' integers: far beyond any image or sensible search, and
#: below what OpenCV and numpy can allocate or loop over (grid_cols 1e9 asked for 30 GB,
#: klt_levels 1e9 was OpenCV's bad_alloc, min_expected_frames 1e9 a loop without end).
_TRACKER_INT_MAX = {"grid_cols": 200, "grid_rows": 200, "block_size_px": 99, "klt_window_px": 201,
                    "stereo_window_px": 201, "refine_window_px": 201, "affine_radius_px": 50, "klt_levels": 8,
                    "stereo_levels": 8, "stereo_tracked_levels": 8, "stereo_search_level": 8,
                    "min_expected_frames": 10_000, "detect_retry_frames": 10_000, "border_px": 10_000}
_TRACKER_INT_MAX_DEFAULT = 1_000_000
#: Upper bound of TrackerOptions' numbers (pixels, factors, σ): min_distance_px 1e300
#: crashed OpenCV's corner detector.
_TRACKER_FLOAT_MAX = 1e5


@dataclass(frozen=True)
class TrackerOptions:
    """Options of :class:`StereoTracker` (units in the names; defaults documented inline)."""

    #: Number of live tracks the detector tops up to, spread over the grid.
    target_features: int = 800
    #: Detection grid: columns x rows of cells, each filled to its share of target_features.
    grid_cols: int = 10
    grid_rows: int = 4
    #: A cell whose last detection started fewer than a quarter of its corners as tracks is not
    #: tried again for this many frames (doubled after each further idle try, at most 32).
    detect_retry_frames: int = 4
    #: Shi-Tomasi quality level (fraction of the best corner's score).
    quality_level: float = 0.005
    #: Smallest distance between two corners / a new corner and a live track (px).
    min_distance_px: float = 12.0
    #: Shi-Tomasi block size (px).
    block_size_px: int = 5
    #: Corners are detected this far from the image border (px).
    border_px: int = 10
    #: ... and not in a band of this fraction of the width at the left and right edges, where
    #: forward motion takes features out of view within a frame or two (0 = detect up to border_px).
    side_band_fraction: float = 0.15
    #: KLT window side (px, odd) of the frame-to-frame tracking (started at the predicted position).
    klt_window_px: int = 11
    #: ... and of the stereo match of a new corner (no disparity guess: a larger window, fewer false
    #: matches on weak real texture).
    stereo_window_px: int = 21
    #: Refinement of every KLT match on the full image with this smaller window (px, odd; 0 =
    #: off): a large window finds the match, a small one centred on the corner places it, so
    #: the flow elsewhere in the large window (perspective, divergence) does not shift it.
    refine_window_px: int = 0
    #: Affine refinement against each track's first appearance: half-size of the template
    #: (px; the template is (2r+1)^2 pixels; 0 = off) and the largest residual it may leave,
    #: relative to the template's contrast (RMS / standard deviation).
    affine_radius_px: int = 6
    affine_max_residual: float = 0.4
    #: ... or this multiple of the residual of the track's own first right-image match, if larger: a
    #: template whose two views differed at birth (noise on a weak texture) is not held to a bound
    #: that its first frame barely met (0 = only affine_max_residual).
    affine_relative_residual: float = 1.5
    #: A track whose left warp has scaled its template by more than this (linear, area = square)
    #: takes its current appearance as the new template (0 = never: tracks end when the warp's
    #: determinant leaves (0.2, 5)). Approaching points grow and show finer texture than at first.
    affine_reanchor_scale: float = 1.5
    #: A track whose residual is above its bound (affine_max_residual / affine_relative_residual) but
    #: within this multiple of it is not ended by the appearance check: it is kept (with its template)
    #: if it passes the geometric and drift checks of the same frame to affine_confirm_px (0 or 1 =
    #: off: the appearance check alone ends it). A third of the tracks the appearance check ended
    #: on the rendered drives were within 1 px of their true point: the texture had changed
    #: (finer detail coming into view, perspective), not the point.
    affine_confirm_factor: float = 1.5
    #: ... and such a track is held to this bound (px, in the metric of the geometric and drift checks)
    #: instead of ransac_threshold_px / drift_threshold_px (0 = the checks' own thresholds): the texture
    #: may change, but the position must agree with the geometry's prediction closely.
    affine_confirm_px: float = 0.5
    #: Gauss-Newton iterations of the affine refinement, at most; a track stops when its step is
    #: below affine_step_px.
    affine_iterations: int = 5
    affine_step_px: float = 0.01
    #: KLT pyramid levels above the full image (temporal tracking).
    klt_levels: int = 2
    #: KLT pyramid levels of the stereo match of a tracked point (started at its last disparity).
    stereo_tracked_levels: int = 0
    #: KLT pyramid levels of the stereo match of a new corner (no disparity guess yet; only with
    #: stereo_min_score 0).
    stereo_levels: int = 4
    #: Stereo match of a new corner by normalised cross-correlation of its stereo_window_px patch
    #: along its row of the right image (the disparity range): the best score must reach this, and
    #: the best score outside +-2 px of it must be stereo_uniqueness lower (repeated texture, the
    #: road); sub-pixel by a parabola, then the affine step. 0 = KLT from zero disparity instead.
    stereo_min_score: float = 0.8
    stereo_uniqueness: float = 0.05
    #: ... searched on this pyramid level (0 = the full image; each level halves the images).
    stereo_search_level: int = 2
    #: KLT iterations per level and the convergence threshold (px).
    klt_iterations: int = 10
    klt_epsilon_px: float = 0.03
    #: Forward-backward check: largest round-trip error of a KLT match (px).
    fb_threshold_px: float = 1.0
    #: Epipolar constraint of the rectified pair: largest |vR - vL| (px).
    max_row_difference_px: float = 1.0
    #: Disparity range uL - uR accepted (px); must be > 0.
    min_disparity_px: float = 0.5
    max_disparity_px: float = 250.0
    #: Geometric check: largest reprojection error in either image (px); 0 turns it off.
    ransac_threshold_px: float = 1.5
    #: Drift check: a track's first stereo triangulation, carried to the current frame by the
    #: chained P3P motions, must reproject within this many pixels of the current left and right
    #: positions (catches slow slides, e.g. of corners made by an occluding edge); 0 = off.
    drift_threshold_px: float = 2.0
    #: The geometric and drift checks allow for the uncertainty of the stereo triangulation they
    #: predict from: the error [uL, v, uR] is measured against I + J C J^T (J: the prediction's
    #: Jacobian; C: the triangulation's covariance from this pixel noise of the stereo match, px),
    #: so a far point, whose depth is uncertain, may move further along its epipolar flow than a
    #: near one. 0 = the plain pixel distances (ransac_threshold_px / drift_threshold_px).
    stereo_sigma_px: float = 0.3
    #: ... but the plain pixel distance stays below this multiple of the check's threshold.
    gate_max_factor: float = 1.5
    #: RANSAC iterations of the geometric check.
    ransac_iterations: int = 100
    #: Fewest tracked points for the geometric check (fewer: the check is skipped).
    ransac_min_points: int = 12
    #: A new corner is started only if its stereo point, carried by the last frame-to-frame motion
    #: (constant velocity), stays in view for at least this many frames (0 = off; before the first
    #: motion is known every corner is started). On a forward-moving car the corners at the image
    #: sides leave within a few frames; the budget goes to those that stay.
    min_expected_frames: int = 12
    #: Tracks seen in fewer frames are left out of the output (see :func:`finish_tracks`).
    min_track_length: int = 3

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", int):
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                    raise ConfigError(f"{f.name} must be an integer, got {value!r}")
                object.__setattr__(self, f.name, int(value))
                if value < (0 if f.name in ("border_px", "ransac_iterations", "refine_window_px", "affine_radius_px", "stereo_tracked_levels", "detect_retry_frames", "stereo_search_level",
                                             "min_expected_frames") else 1):
                    raise ConfigError(f"{f.name} must be >= 1, got {value!r}")
                most = _TRACKER_INT_MAX.get(f.name, _TRACKER_INT_MAX_DEFAULT)
                if value > most:
                    raise ConfigError(f"{f.name} must be at most {most}, got {value!r}")
            else:
                if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                        or not math.isfinite(value) or value < 0:
                    raise ConfigError(f"{f.name} must be a finite number >= 0, got {value!r}")
                if value > _TRACKER_FLOAT_MAX:
                    raise ConfigError(f"{f.name} must be at most {_TRACKER_FLOAT_MAX:g}, got {value!r}")
                object.__setattr__(self, f.name, float(value))
        for name in ("klt_window_px", "stereo_window_px"):
            if getattr(self, name) % 2 == 0 or getattr(self, name) < 3:
                raise ConfigError(f"{name} must be odd and >= 3, got {getattr(self, name)}")
        if self.refine_window_px and (self.refine_window_px % 2 == 0 or self.refine_window_px < 3):
            raise ConfigError(f"refine_window_px must be 0 (off) or odd and >= 3, got {self.refine_window_px}")
        if not 0 < self.quality_level < 1:
            raise ConfigError(f"quality_level must be in (0, 1), got {self.quality_level}")
        if not 0 < self.min_disparity_px < self.max_disparity_px:
            raise ConfigError(f"need 0 < min_disparity_px < max_disparity_px, got {self.min_disparity_px} "
                              f"and {self.max_disparity_px}")
        if self.fb_threshold_px <= 0:
            raise ConfigError(f"fb_threshold_px must be > 0, got {self.fb_threshold_px}")
        if not 0 <= self.side_band_fraction < 0.4:
            raise ConfigError(f"side_band_fraction must be in [0, 0.4), got {self.side_band_fraction}")
        if self.ransac_min_points < 4:
            raise ConfigError(f"ransac_min_points must be >= 4 (P3P + 1), got {self.ransac_min_points}")

    def min_image_size_px(self) -> tuple[int, int]:
        """The smallest (width, height) of a rectified image in which a corner can be detected:
        the region ``border_px`` from the border and outside the ``side_band_fraction`` bands must
        hold a Shi-Tomasi block and an affine template. A smaller image can give no track."""
        k = max(self.block_size_px, 2 * self.affine_radius_px + 1)
        height = 2 * self.border_px + k
        width = height
        while width - 2 * max(self.border_px, int(round(self.side_band_fraction * width))) < k:
            width += 1  # side_band_fraction < 0.4: ends within k / 0.2 steps
        return width, height

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], source: str = "options") -> "TrackerOptions":
        """Build from a mapping; unknown keys and bad values raise ConfigError naming ``source``."""
        if not isinstance(values, Mapping):
            raise ConfigError(f"{source}: expected a mapping of tracker option names to values, "
                              f"got {type(values).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(str(k) for k in values if k not in known)
        if unknown:
            raise ConfigError(f"{source}: unknown tracker option(s) {', '.join(unknown)}; "
                              f"known: {', '.join(sorted(known))}")
        try:
            return cls(**dict(values))
        except (ConfigError, TypeError) as exc:
            raise ConfigError(f"{source}: {exc}") from None


@dataclass
class TrackerStatistics:
    """Counts accumulated by :class:`StereoTracker` over the frames it processed."""

    frames: int = 0
    #: observations output per frame (list, one entry per frame)
    tracks_per_frame: list = field(default_factory=list)
    detected: int = 0  # new corners detected
    lost_temporal: int = 0  # KLT failed or forward-backward check failed
    rejected_stereo_new: int = 0  # new corners without a stereo match
    rejected_stereo_tracked: int = 0  # tracked points whose stereo match failed (track ended)
    rejected_geometric: int = 0  # rejected by the P3P-RANSAC check
    rejected_affine: int = 0  # the affine refinement against the first appearance failed
    rejected_drift: int = 0  # drifted from the track's first triangulation
    left_image: int = 0  # left the image
    reanchored: int = 0  # templates replaced by the current appearance (affine_reanchor_scale)
    confirmed: int = 0  # tracks past their appearance bound kept by the geometric checks (affine_confirm_factor)
    not_started: int = 0  # new corners expected to leave the view too soon (min_expected_frames)
    #: per end reason (the keys of "rejections" but stereo_new): how many frames the ended tracks lasted,
    #: as a histogram (index = length, the last bin holds everything longer)
    end_lengths: dict = field(default_factory=dict)

    _REASONS = {"forward_backward": "lost_temporal", "left_image": "left_image",
                "stereo_tracked": "rejected_stereo_tracked", "appearance": "rejected_affine",
                "geometric": "rejected_geometric", "drift": "rejected_drift"}
    _MAX_LENGTH = 100

    def count_end(self, reason: str, lengths: np.ndarray) -> None:
        """Tracks that ended for ``reason`` after ``lengths`` frames."""
        setattr(self, self._REASONS[reason], getattr(self, self._REASONS[reason]) + int(lengths.size))
        hist = np.bincount(np.minimum(lengths, self._MAX_LENGTH), minlength=self._MAX_LENGTH + 1)
        self.end_lengths[reason] = self.end_lengths.get(reason, 0) + hist

    def to_dict(self, track_lengths: np.ndarray | None = None) -> dict[str, Any]:
        counts = np.asarray(self.tracks_per_frame, dtype=float)
        out: dict[str, Any] = {
            "frames": self.frames,
            "tracks_per_frame": {
                "mean": float(counts.mean()) if counts.size else 0.0,
                "min": int(counts.min()) if counts.size else 0,
                "median": float(np.median(counts)) if counts.size else 0.0,
                "max": int(counts.max()) if counts.size else 0,
            },
            "detected": self.detected,
            "not_started": self.not_started,
            "reanchored": self.reanchored,
            "confirmed": self.confirmed,
            "rejections": {
                "forward_backward": self.lost_temporal,
                "left_image": self.left_image,
                "stereo_tracked": self.rejected_stereo_tracked,
                "stereo_new": self.rejected_stereo_new,
                "geometric": self.rejected_geometric,
                "appearance": self.rejected_affine,
                "drift": self.rejected_drift,
            },
        }
        out["track_ends"] = {}
        for reason, hist in sorted(self.end_lengths.items()):
            cum = np.cumsum(hist)
            out["track_ends"][reason] = {"count": int(cum[-1]),
                                         "median_length": int(np.searchsorted(cum, cum[-1] / 2.0)),
                                         "ended_within_4_frames": int(cum[4])}
        if track_lengths is not None:
            lengths = np.asarray(track_lengths)
            out["tracks"] = int(lengths.size)
            out["track_length"] = {
                "mean": float(lengths.mean()) if lengths.size else 0.0,
                "median": float(np.median(lengths)) if lengths.size else 0.0,
                "max": int(lengths.max()) if lengths.size else 0,
            }
        return out


class StereoTracker:
    """Track stereo features through rectified grey image pairs (see the module docstring).

    Args:
        K: (3, 3) intrinsics of the rectified left camera (px); the right camera has the
            same intrinsics, ``baseline_m`` to the right.
        baseline_m: stereo baseline (m), > 0.
        options: :class:`TrackerOptions`.
    """

    def __init__(self, K, baseline_m: float, options: TrackerOptions | None = None):
        self._cv2 = require_cv2()
        self.options = options or TrackerOptions()
        self.K = np.asarray(K, dtype=np.float64)
        self.baseline_m = float(baseline_m)
        self.stats = TrackerStatistics()
        self._next_id = 0
        self._prev_left = None  # the previous left image
        self._shape = None
        self._motion = None  # (R, t) of the last frame-to-frame camera motion, q_new = R q_old + t
        self._motion_ok = False  # whether the last frame's P3P check found the motion
        self._cam_T_ref = np.eye(4)  # chained motions: current camera from the first frame's camera
        r = self.options.affine_radius_px
        g = np.arange(-r, r + 1, dtype=np.float32)
        gx, gy = np.meshgrid(g, g)
        self._offsets = np.stack([gx.ravel(), gy.ravel()], axis=1)  # (m, 2)
        g = np.arange(-r - 1, r + 2, dtype=np.float32)
        gx, gy = np.meshgrid(g, g)
        self._offsets_ext = np.stack([gx.ravel(), gy.ravel()], axis=1)  # one pixel more, for dT/dx
        self._live = _Tracks.empty(self._offsets.shape[0])
        self._cell_rest = None  # per detection cell: frames until it is tried again
        self._cells_tried = np.zeros(0, np.int64)
        o = self.options
        self._criteria = (self._cv2.TERM_CRITERIA_COUNT | self._cv2.TERM_CRITERIA_EPS, o.klt_iterations,
                          o.klt_epsilon_px)

    # ------------------------------------------------------------------ helpers
    def _klt(self, pyr_a, pyr_b, pts_a, guess_b, levels, window=None):
        """Forward KLT a -> b from ``guess_b``, then back; (pts_b, ok, fb_error)."""
        cv2 = self._cv2
        w = window or self.options.klt_window_px
        n = pts_a.shape[0]
        if n == 0:
            return np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0)
        a = np.ascontiguousarray(pts_a, dtype=np.float32).reshape(-1, 1, 2)
        g = np.ascontiguousarray(guess_b, dtype=np.float32).reshape(-1, 1, 2)
        pb, st, _ = cv2.calcOpticalFlowPyrLK(pyr_a, pyr_b, a, g.copy(), winSize=(w, w), maxLevel=levels,
                                             criteria=self._criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        pa, st2, _ = cv2.calcOpticalFlowPyrLK(pyr_b, pyr_a, pb, a.copy(), winSize=(w, w), maxLevel=levels,
                                              criteria=self._criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        r = self.options.refine_window_px
        if r:
            pb, st3, _ = cv2.calcOpticalFlowPyrLK(pyr_a, pyr_b, a, pb.copy(), winSize=(r, r), maxLevel=0,
                                                  criteria=self._criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
            pa, st4, _ = cv2.calcOpticalFlowPyrLK(pyr_b, pyr_a, pb, pa.copy(), winSize=(r, r), maxLevel=0,
                                                  criteria=self._criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
            st = st & st3
            st2 = st2 & st4
        pb = pb.reshape(-1, 2).astype(np.float64)
        fb = np.linalg.norm(pa.reshape(-1, 2).astype(np.float64) - np.asarray(pts_a, np.float64), axis=1)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(pb).all(axis=1)
        return pb, ok, fb

    def _inside(self, pts):
        h, w = self._shape
        m = float(max(2, self.options.klt_window_px // 2 // 2))
        return (pts[:, 0] >= m) & (pts[:, 0] <= w - 1 - m) & (pts[:, 1] >= m) & (pts[:, 1] <= h - 1 - m)

    def _stereo(self, pyr_l, pyr_r, left, disparity_guess, levels, window=None):
        """Stereo match of left pixels (n, 2); (pixels (n, 4), ok)."""
        o = self.options
        guess = left.copy()
        guess[:, 0] -= disparity_guess
        right, ok, fb = self._klt(pyr_l, pyr_r, left, guess, levels, window)
        if left.shape[0] == 0:
            return np.zeros((0, 4)), ok
        disparity = left[:, 0] - right[:, 0]
        ok &= fb <= o.fb_threshold_px
        ok &= np.abs(right[:, 1] - left[:, 1]) <= o.max_row_difference_px
        ok &= (disparity >= o.min_disparity_px) & (disparity <= o.max_disparity_px)
        ok &= self._inside(right)
        return np.concatenate([left, right], axis=1), ok

    def _search_images(self, frame):
        """Left and right images on level ``stereo_search_level`` (float32) and the right image's
        local mean and variance over the search patch (box filter), once per frame."""
        cv2 = self._cv2
        o = self.options
        if "search" not in frame:
            imgs = [frame["left"], frame["right"]]
            for _ in range(o.stereo_search_level):
                imgs = [cv2.pyrDown(i) for i in imgs]
            L, R = (i.astype(np.float32) for i in imgs)
            k = 2 * max(2, (o.stereo_window_px >> o.stereo_search_level) // 2) + 1
            mean = cv2.boxFilter(R, cv2.CV_32F, (k, k), borderType=cv2.BORDER_REPLICATE)
            var = cv2.boxFilter(R * R, cv2.CV_32F, (k, k), borderType=cv2.BORDER_REPLICATE) - mean * mean
            frame["search"] = (L, R, var)
        return frame["search"]

    def _stereo_search(self, frame, left):
        """Stereo match of new corners (n, 2) by NCC along their row (see ``stereo_min_score``).

        The search runs on pyramid level ``stereo_search_level`` (images halved that many times;
        the patch shrinks with them, at least 5 px), all corners at once: the zero-mean left patch
        correlated with every right patch of the disparity range, over the right patch's standard
        deviation (box filter) — OpenCV's TM_CCOEFF_NORMED. The affine step then places the match
        on the full image. Returns (pixels (n, 4), ok)."""
        o = self.options
        n = left.shape[0]
        if n == 0:
            return np.zeros((0, 4)), np.zeros(0, bool)
        L, R, var = self._search_images(frame)
        s = float(2 ** o.stereo_search_level)
        h, w = L.shape
        r = max(2, (o.stereo_window_px >> o.stereo_search_level) // 2)
        if h <= 2 * r or w <= 2 * r:  # the patch does not fit the image on that level: no match (a warning follows)
            return np.zeros((n, 4)), np.zeros(n, bool)
        m = (2 * r + 1) ** 2
        d_lo, d_hi = int(math.floor(o.min_disparity_px / s)), int(math.ceil(o.max_disparity_px / s))
        u, v = (np.round(left / s).astype(int)).T
        inside = (v >= r) & (v < h - r) & (u >= r) & (u < w - r)
        u, v = np.where(inside, u, r), np.where(inside, v, r)
        dy = np.arange(-r, r + 1)
        T = L[(v[:, None, None] + dy[None, :, None]), (u[:, None, None] + dy[None, None, :])]  # (n, k, k)
        T = T - T.mean(axis=(1, 2), keepdims=True)
        t_norm = np.sqrt((T * T).sum(axis=(1, 2)))
        P = d_hi - d_lo + 1  # candidate disparities d_hi ... d_lo (right centre x = u - d)
        xs = u[:, None] - d_hi + np.arange(P)[None, :]  # (n, P) right centre columns
        cols = np.clip(u[:, None] - d_hi - r + np.arange(P + 2 * r)[None, :], 0, w - 1)
        strip = R[v[:, None, None] + dy[None, :, None], cols[:, None, :]]  # (n, k, P + 2r): the right rows
        corr = np.zeros((n, P), np.float32)
        for j in range(2 * r + 1):  # column j of every patch
            corr += np.einsum("nyp,ny->np", strip[:, :, j:j + P], T[:, :, j])
        valid = (xs >= r) & (xs < w - r)
        sd = np.sqrt(np.maximum(var[v[:, None], np.clip(xs, 0, w - 1)], 0.0))
        score = np.where(valid & (sd > 0.5), corr / (np.sqrt(m) * sd * t_norm[:, None] + 1e-9), -1.0)
        k = np.argmax(score, axis=1)
        idx = np.arange(n)
        best = score[idx, k]
        far = np.abs(np.arange(P)[None, :] - k[:, None]) > 2
        second = np.where(far, score, -1.0).max(axis=1)
        ok = inside & (best >= o.stereo_min_score) & (second <= best - o.stereo_uniqueness) & (k > 0) & (k < P - 1)
        a, c = score[idx, np.maximum(k - 1, 0)], score[idx, np.minimum(k + 1, P - 1)]
        den = a - 2 * best + c
        sub = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
        right = left.copy()
        right[:, 0] = left[:, 0] - s * (u - (xs[idx, k] + sub))
        stereo = np.concatenate([left, right], axis=1)
        return stereo, ok & self._stereo_ok(stereo)

    def _triangulate(self, pixels):
        """(n, 3) points in the left camera frame from stereo pixels (n, 4)."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        d = pixels[:, 0] - pixels[:, 2]
        z = fx * self.baseline_m / d
        return np.stack([z * (pixels[:, 0] - cx) / fx, z * (pixels[:, 1] - cy) / fy, z], axis=1)

    def _geometric_inliers(self, p_prev, pixels, threshold_px=None):
        """True for tracks consistent with one rigid motion (see step 3 of the module docstring);
        ``threshold_px``: per-track bounds (n,), default ``ransac_threshold_px``."""
        cv2 = self._cv2
        o = self.options
        n = pixels.shape[0]
        bound = o.ransac_threshold_px if threshold_px is None else threshold_px
        self._motion_ok = False
        if o.ransac_threshold_px <= 0 or n < o.ransac_min_points:
            return np.ones(n, bool)
        obj = self._triangulate(p_prev)
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj.astype(np.float64), pixels[:, :2].astype(np.float64), self.K, None,
            iterationsCount=o.ransac_iterations, reprojectionError=o.ransac_threshold_px, confidence=0.999,
            flags=cv2.SOLVEPNP_P3P)
        if not ok or inliers is None or len(inliers) < 4:
            return np.ones(n, bool)  # no consensus: keep them rather than guess (logged in the stats by callers)
        inl = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], pixels[inl, :2].astype(np.float64), self.K, None, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        self._motion = (R, tvec.reshape(3))
        self._motion_ok = True
        q = obj @ R.T + tvec.reshape(1, 3)
        good = q[:, 2] > 0
        z = np.where(good, q[:, 2], 1.0)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        uL = fx * q[:, 0] / z + cx
        v = fy * q[:, 1] / z + cy
        uR = fx * (q[:, 0] - self.baseline_m) / z + cx
        if o.stereo_sigma_px > 0:
            pred = np.stack([uL, v, uR, v], axis=1)
            cov = R @ self._point_covariance(p_prev) @ R.T
            return good & self._gate(pred, pixels, q, cov, bound)
        err = np.maximum(np.hypot(uL - pixels[:, 0], v - pixels[:, 1]), np.hypot(uR - pixels[:, 2], v - pixels[:, 3]))
        return good & (err <= bound)

    def _point_covariance(self, pixels):
        """(n, 3, 3) covariance of the stereo triangulation of ``pixels`` (n, 4) in the left camera,
        from stereo_sigma_px on uL, v and uR (the Jacobian by finite differences)."""
        eps = 1e-3
        base = self._triangulate(pixels)
        J = np.empty((pixels.shape[0], 3, 3))
        for j, col in enumerate((0, 1, 2)):
            p = pixels.copy()
            p[:, col] += eps
            if col == 1:
                p[:, 3] += eps
            J[:, :, j] = (self._triangulate(p) - base) / eps
        return self.options.stereo_sigma_px ** 2 * (J @ J.transpose(0, 2, 1))

    def _gate(self, pred, pixels, q, cov, threshold_px):
        """True where the measured [uL, v, uR] (of ``pixels``) is within ``threshold_px`` of the
        predicted ``pred`` (n, 4) in the metric I + J cov J^T (J: projection Jacobian at the
        predicted points ``q`` (n, 3), ``cov`` their covariance (n, 3, 3)), and the plain distance
        in either image within ``gate_max_factor`` times it."""
        fx, fy = self.K[0, 0], self.K[1, 1]
        x, y, z = q[:, 0], q[:, 1], np.where(q[:, 2] > 0.1, q[:, 2], np.nan)
        zero = np.zeros_like(z)
        J = np.stack([np.stack([fx / z, zero, -fx * x / z ** 2], 1),
                      np.stack([zero, fy / z, -fy * y / z ** 2], 1),
                      np.stack([fx / z, zero, -fx * (x - self.baseline_m) / z ** 2], 1)], axis=1)
        S = np.eye(3) + J @ cov @ J.transpose(0, 2, 1)
        r = pixels[:, :3] - pred[:, :3]
        ok = np.isfinite(S).all(axis=(1, 2)) & np.isfinite(r).all(axis=1)
        r, S = np.where(ok[:, None], r, 0.0), np.where(ok[:, None, None], S, np.eye(3))
        d2 = np.einsum("ni,ni->n", r, np.linalg.solve(S, r[..., None])[..., 0])
        cap = self.options.gate_max_factor * threshold_px
        plain = np.maximum(np.hypot(r[:, 0], r[:, 1]), np.hypot(r[:, 2], pixels[:, 3] - pred[:, 3]))
        return ok & (d2 <= threshold_px ** 2) & (plain <= cap) & (np.abs(pixels[:, 3] - pred[:, 3]) <= threshold_px)

    def _sample(self, image, pts, A, offsets=None):
        """(n, m) values of the float32 ``image`` at ``pts + A @ offsets`` (bilinear)."""
        cv2 = self._cv2
        offsets = self._offsets if offsets is None else offsets
        if pts.shape[0] == 0:
            return np.zeros((0, offsets.shape[0]), np.float32)
        ox, oy = offsets[None, :, 0], offsets[None, :, 1]
        pts, A = pts.astype(np.float32), A.astype(np.float32)
        mx = pts[:, 0:1] + A[:, 0, 0:1] * ox + A[:, 0, 1:2] * oy
        my = pts[:, 1:2] + A[:, 1, 0:1] * ox + A[:, 1, 1:2] * oy
        return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def _templates(self, image, pts):
        """(n, m, 8) float32 per new track: the Jacobian of the affine step's residual, the
        steepest-descent images dT/dp of the six affine parameters (central differences) of its
        (2r+1)^2 patch T of ``image`` at ``pts``, then T (gain) and 1 (bias); T is ``[..., 6]``."""
        r = self.options.affine_radius_px
        s = 2 * r + 3
        patch = self._sample(image, pts, np.tile(np.eye(2), (pts.shape[0], 1, 1)), self._offsets_ext)
        patch = patch.reshape(-1, s, s)
        T = patch[:, 1:-1, 1:-1].reshape(pts.shape[0], -1)
        Tx = (0.5 * (patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2])).reshape(pts.shape[0], -1)
        Ty = (0.5 * (patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1])).reshape(pts.shape[0], -1)
        x, y = self._offsets[None, :, 0], self._offsets[None, :, 1]
        return np.stack([Tx, Ty, Tx * x, Tx * y, Ty * x, Ty * y, T, np.ones_like(T)], axis=-1).astype(np.float32)

    @staticmethod
    def _normal_inverse(jac):
        """(n, 8, 8) inverse normal matrices (J^T J + 1e-6 I)^-1 of the affine step, fixed per
        template (inverse compositional); NaN where the batch has a singular one."""
        H = np.matmul(jac.transpose(0, 2, 1), jac).astype(np.float64) + 1e-6 * np.eye(8)
        try:
            return np.linalg.inv(H)
        except np.linalg.LinAlgError:
            return np.full(H.shape, np.nan)

    def _affine(self, image, templates, pts, A, normal_inv, max_residual=None):
        """Inverse-compositional Gauss-Newton of ``image(pts + A x) = g T(x) + c`` per track.

        The template's steepest-descent images (:meth:`_templates`) and with them the inverse
        normal matrix (``normal_inv``, :meth:`_normal_inverse`, kept with the template) are
        fixed, so each iteration samples the float32 ``image`` once (no image gradients).
        ``max_residual``: per-track bound on the residual relative to the template's contrast
        (default ``affine_max_residual``). Returns (pts, A, ok, residual)."""
        o = self.options
        n = pts.shape[0]
        if n == 0:
            return pts, A, np.zeros(0, bool), np.zeros(0)
        pts = pts.astype(np.float64).copy()
        A = A.astype(np.float64).copy()
        J = templates
        T_all = J[..., 6]
        if np.isnan(normal_inv[:, 0, 0]).any():  # a singular normal matrix in the batch
            return pts, A, np.zeros(n, bool), np.full(n, np.inf)
        gain = np.ones(n, np.float32)
        bias = np.zeros(n, np.float32)
        active = np.arange(n)  # tracks still moving by more than affine_step_px per iteration
        for _ in range(o.affine_iterations):
            sel = active if active.size < n else slice(None)  # all tracks: views instead of copies
            S = self._sample(image, pts[sel], A[sel])  # (k, m)
            r = S - gain[sel, None] * T_all[sel] - bias[sel, None]
            b = np.matmul(r[:, None, :], J[sel])  # (k, 1, 8)
            d = np.matmul(normal_inv[sel], b.transpose(0, 2, 1).astype(np.float64))[..., 0]
            d = np.where(np.isfinite(d), d, 0.0)
            g = np.maximum(gain[sel], 0.1)
            a, b_, c, e = (d[:, 2 + i] / g for i in range(4))  # dA = I + [[a, b], [c, e]]
            det = (1 + a) * (1 + e) - b_ * c
            det = np.where(np.abs(det) > 1e-3, det, 1.0)
            dA_inv = np.stack([1 + e, -b_, -c, 1 + a], axis=1).reshape(-1, 2, 2) / det[:, None, None]
            A_new = A[sel] @ dA_inv  # W(x; p) o W(x; dp)^-1
            step = -np.einsum("kij,kj->ki", A_new, d[:, :2] / g[:, None])
            pts[sel] += step
            A[sel] = A_new
            gain[sel] += d[:, 6]
            bias[sel] += d[:, 7]
            active = active[np.abs(step).max(axis=1) >= o.affine_step_px]
            if active.size == 0:
                break
        T = T_all.astype(np.float64)
        I = self._sample(image, pts, A).astype(np.float64)
        rms = np.sqrt(np.mean((I - gain[:, None] * T - bias[:, None]) ** 2, axis=1))
        contrast = T.std(axis=1) + 1e-6
        det = np.linalg.det(A)
        residual = rms / contrast
        ok = (residual <= (o.affine_max_residual if max_residual is None else max_residual)) & (det > 0.2) & (det < 5.0) & (gain > 0.3) & (gain < 3.0)
        ok &= np.isfinite(pts).all(axis=1) & self._inside(pts)
        return pts, A, ok, residual

    def _predict(self, prev):
        """Predicted left pixels (n, 2) and disparities (n,) of the live tracks from the last motion
        (constant velocity); without one, where they were."""
        disparity = prev[:, 0] - prev[:, 2]
        if self._motion is None or prev.shape[0] == 0:
            return prev[:, :2].copy(), disparity
        R, t = self._motion
        q = self._triangulate(prev) @ R.T + t
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        good = q[:, 2] > 0.1
        z = np.where(good, q[:, 2], 1.0)
        pred = np.stack([fx * q[:, 0] / z + cx, fy * q[:, 1] / z + cy], axis=1)
        h, w = self._shape
        good &= (pred[:, 0] > -w) & (pred[:, 0] < 2 * w) & (pred[:, 1] > -h) & (pred[:, 1] < 2 * h)
        return np.where(good[:, None], pred, prev[:, :2]), np.where(good, fx * self.baseline_m / z, disparity)

    def _stereo_ok(self, stereo):
        o = self.options
        disparity = stereo[:, 0] - stereo[:, 2]
        return ((np.abs(stereo[:, 3] - stereo[:, 1]) <= o.max_row_difference_px) & (disparity >= o.min_disparity_px)
                & (disparity <= o.max_disparity_px) & self._inside(stereo[:, 2:]))

    def _project(self, q):
        """(n, 4) stereo pixels of points q (n, 3) in the left camera; NaN behind it."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        z = np.where(q[:, 2] > 0.1, q[:, 2], np.nan)
        v = fy * q[:, 1] / z + cy
        return np.stack([fx * q[:, 0] / z + cx, v, fx * (q[:, 0] - self.baseline_m) / z + cx, v], axis=1)

    def _expected_frames(self, stereo, horizon: int) -> np.ndarray:
        """(n,) frames (up to ``horizon``) the stereo points stay in both images under the last motion."""
        R, t = self._motion
        q = self._triangulate(stereo)
        frames = np.zeros(stereo.shape[0], np.int64)
        alive = np.ones(stereo.shape[0], bool)
        for _ in range(horizon):
            px = self._project(q)
            alive &= np.isfinite(px).all(axis=1) & self._inside(px[:, :2]) & self._inside(px[:, 2:])
            frames += alive
            q = q @ R.T + t
        return frames

    def _drift_ok(self, p_in_ref, pixels, cov_ref=None, threshold_px=None):
        """True where the chained first triangulation reprojects within drift_threshold_px (or the
        per-track ``threshold_px`` (n,))."""
        o = self.options
        bound = o.drift_threshold_px if threshold_px is None else threshold_px
        if o.drift_threshold_px <= 0 or pixels.shape[0] == 0:
            return np.ones(pixels.shape[0], bool)
        q = p_in_ref @ self._cam_T_ref[:3, :3].T + self._cam_T_ref[:3, 3]
        pred = self._project(q)
        if o.stereo_sigma_px > 0 and cov_ref is not None:
            R = self._cam_T_ref[:3, :3]
            keep = self._gate(pred, pixels, q, R @ cov_ref @ R.T, bound)
            return keep | ~np.isfinite(pred).all(axis=1)  # NaN (no reference point): kept
        err = np.maximum(np.hypot(pred[:, 0] - pixels[:, 0], pred[:, 1] - pixels[:, 1]),
                         np.hypot(pred[:, 2] - pixels[:, 2], pred[:, 3] - pixels[:, 3]))
        return ~(err > bound)  # NaN (no reference point): kept

    def _cell_of(self, p):
        o = self.options
        h, w = self._shape
        cx = np.clip((p[:, 0] / (w / o.grid_cols)).astype(int), 0, o.grid_cols - 1)
        cy = np.clip((p[:, 1] / (h / o.grid_rows)).astype(int), 0, o.grid_rows - 1)
        return cy * o.grid_cols + cx

    def _detect(self, image, existing):
        """New corners (n, 2) in the cells below their share, away from ``existing`` (m, 2).

        Shi-Tomasi runs on each such cell alone (not on the whole image), for up to twice the
        cell's need (some fail the stereo match or leave too soon); a cell whose last attempt
        started no track rests for ``detect_retry_frames`` frames (sky, far road)."""
        cv2 = self._cv2
        o = self.options
        h, w = self._shape
        n_cells = o.grid_cols * o.grid_rows
        if self._cell_rest is None:
            self._cell_rest = np.zeros(n_cells, np.int64)
            self._cell_fails = np.zeros(n_cells, np.int64)  # consecutive idle tries
        self._cell_rest = np.maximum(self._cell_rest - 1, 0)
        quota = int(math.ceil(o.target_features / n_cells))
        have = np.bincount(self._cell_of(existing), minlength=n_cells) if existing.size else np.zeros(n_cells, int)
        need = np.where(self._cell_rest == 0, np.maximum(quota - have, 0), 0)
        self._cells_tried, self._need = np.flatnonzero(need), need
        if need.sum() == 0 or existing.shape[0] >= o.target_features + n_cells:
            self._cells_tried = np.zeros(0, np.int64)
            return np.zeros((0, 2))
        mask = np.zeros((h, w), np.uint8)
        bd = o.border_px
        side = max(bd, int(round(o.side_band_fraction * w)))
        mask[bd:h - bd, side:w - side] = 255
        r = int(math.ceil(o.min_distance_px))
        for x, y in np.round(existing).astype(int):
            cv2.circle(mask, (int(x), int(y)), r, 0, -1)
        out = []
        for c in self._cells_tried:
            x0, x1 = int(c % o.grid_cols * w / o.grid_cols), int((c % o.grid_cols + 1) * w / o.grid_cols)
            y0, y1 = int(c // o.grid_cols * h / o.grid_rows), int((c // o.grid_cols + 1) * h / o.grid_rows)
            if not mask[y0:y1, x0:x1].any():
                continue
            corners = cv2.goodFeaturesToTrack(image[y0:y1, x0:x1], maxCorners=2 * int(need[c]),
                                              qualityLevel=o.quality_level, minDistance=o.min_distance_px,
                                              mask=np.ascontiguousarray(mask[y0:y1, x0:x1]),
                                              blockSize=o.block_size_px)
            if corners is not None:
                out.append(corners.reshape(-1, 2).astype(np.float64) + (x0, y0))
        return np.concatenate(out) if out else np.zeros((0, 2))

    def _within_need(self, corners) -> np.ndarray:
        """True for the first (strongest) corners of each cell up to the cell's need."""
        cells = self._cell_of(corners) if corners.size else np.zeros(0, int)
        order = np.argsort(cells, kind="stable")
        first = np.searchsorted(cells[order], cells[order], side="left")
        keep = np.zeros(cells.size, bool)
        keep[order] = (np.arange(order.size) - first) < self._need[cells[order]]
        return keep

    def _rest_cells(self, tried, started) -> None:
        """Cells tried this frame that started fewer than a quarter of their ``tried`` (n, 2)
        corners as tracks (``started``, (k, 2)) rest for ``detect_retry_frames`` frames, twice as
        long after each further idle try (at most 32 frames)."""
        if self._cells_tried.size:
            n_cells = self._cell_rest.size
            n_tried = np.bincount(self._cell_of(tried), minlength=n_cells) if tried.size else np.zeros(n_cells, int)
            n_started = np.bincount(self._cell_of(started), minlength=n_cells) if started.size else np.zeros(n_cells, int)
            tried_cells = self._cells_tried
            idle = 4 * n_started[tried_cells] < n_tried[tried_cells]
            self._cell_fails[tried_cells] = np.where(idle, self._cell_fails[tried_cells] + 1, 0)
            fails = self._cell_fails[tried_cells[idle]]
            self._cell_rest[tried_cells[idle]] = np.minimum(self.options.detect_retry_frames * 2 ** (fails - 1), 32)

    # ------------------------------------------------------------------ the step
    def process(self, left, right) -> tuple[np.ndarray, np.ndarray]:
        """Track into the next rectified grey pair (uint8 arrays of one shape).

        Returns ``(ids (n,) int64 strictly increasing, pixels (n, 4) [uL, vL, uR, vR])``.
        """
        frame = self._frame(left, right)
        tracks = self._live
        # A calibration with an absurd baseline (1e300 m) overflows the triangulated points'
        # covariances: no floating-point warnings here; the track command warns of the depths.
        with np.errstate(over="ignore", invalid="ignore"):
            if len(tracks) and self._prev_left is not None:
                tracks = self._track_temporal(frame, tracks)
                tracks = self._track_stereo(frame, tracks)
                tracks = self._check_geometry(tracks)
                tracks = self._confirm_suspects(tracks)
            tracks = tracks.concat(self._new_tracks(frame, tracks))
        return self._commit(frame, tracks)

    def _frame(self, left, right) -> dict:
        """The checked pair and what the steps share of it (gradients for the affine step)."""
        left = np.ascontiguousarray(left)
        right = np.ascontiguousarray(right)
        if left.ndim != 2 or left.shape != right.shape or left.dtype != np.uint8 or right.dtype != np.uint8:
            raise ValueError("process expects two grey uint8 images of one shape")
        if self._shape is None:
            self._shape = left.shape
        elif left.shape != self._shape:
            raise ValueError(f"image size changed from {self._shape} to {left.shape}")
        frame = {"left": left, "right": right}
        if self.options.affine_radius_px > 0:
            frame["left_f"], frame["right_f"] = left.astype(np.float32), right.astype(np.float32)
        return frame

    def _end(self, tracks: "_Tracks", keep: np.ndarray, reason: str) -> "_Tracks":
        """Tracks where ``keep``; the others end, counted under ``reason`` with their length."""
        ended = ~keep
        n = int(np.count_nonzero(ended))
        if n:
            self.stats.count_end(reason, self.stats.frames - tracks.born[ended])
        return tracks.take(keep)

    def _track_temporal(self, frame, tracks: "_Tracks") -> "_Tracks":
        """Step 1: KLT of the live tracks from the previous left image, forward-backward check."""
        o = self.options
        guess, d_pred = self._predict(tracks.pixels)
        cur, ok, fb = self._klt(self._prev_left, frame["left"], tracks.pixels[:, :2], guess, o.klt_levels)
        ok &= fb <= o.fb_threshold_px
        tracks, cur, d_pred = self._end(tracks, ok, "forward_backward"), cur[ok], d_pred[ok]
        inside = self._inside(cur)
        tracks, cur, d_pred = self._end(tracks, inside, "left_image"), cur[inside], d_pred[inside]
        tracks.prev, tracks.pixels = tracks.pixels, np.stack([cur[:, 0], cur[:, 1], cur[:, 0] - d_pred, cur[:, 1]], 1)
        return tracks

    def _track_stereo(self, frame, tracks: "_Tracks") -> "_Tracks":
        """Step 2 and 2b: left-to-right match from the predicted disparity, affine refinement of both.

        With ``stereo_tracked_levels`` 0 (and the affine step on) there is no stereo KLT: the right
        position is the refined left one moved by the predicted disparity, refined in its turn."""
        o = self.options
        disparity = tracks.pixels[:, 0] - tracks.pixels[:, 2]  # predicted by _track_temporal
        if o.stereo_tracked_levels > 0 or o.affine_radius_px <= 0:
            stereo, sok = self._stereo(frame["left"], frame["right"], tracks.pixels[:, :2], disparity,
                                       max(1, o.stereo_tracked_levels))
            tracks = self._end(tracks, sok, "stereo_tracked")
            tracks.pixels = stereo[sok]
            if o.affine_radius_px <= 0:
                return tracks
        bound = np.maximum(o.affine_max_residual, o.affine_relative_residual * tracks.residual0)
        soft = bound * max(1.0, o.affine_confirm_factor)
        pl, AL, okl, rl = self._affine(frame["left_f"], tracks.templates, tracks.pixels[:, :2], tracks.warps[:, 0],
                                       tracks.normal_inv, soft)
        guess_r = tracks.pixels[:, 2:] + (pl - tracks.pixels[:, :2]) if o.stereo_tracked_levels > 0 else \
            pl - np.stack([disparity, np.zeros_like(disparity)], axis=1)
        pr, AR, okr, rr = self._affine(frame["right_f"], tracks.templates, guess_r, tracks.warps[:, 1],
                                       tracks.normal_inv, soft)
        tracks.pixels = np.concatenate([pl, pr], axis=1)
        tracks.warps = np.stack([AL, AR], axis=1)
        tracks.suspect = np.maximum(rl, rr) > bound  # past the bound, within soft: up to the geometric checks
        tracks = self._end(tracks, okl & okr & self._stereo_ok(tracks.pixels), "appearance")
        return self._reanchor(frame, tracks)

    def _reanchor(self, frame, tracks: "_Tracks") -> "_Tracks":
        """Tracks whose left warp has grown past ``affine_reanchor_scale`` (the point came closer)
        take their current left appearance as the template; the right warp follows."""
        s = self.options.affine_reanchor_scale
        if s <= 0 or not len(tracks):
            return tracks
        grown = np.flatnonzero((np.linalg.det(tracks.warps[:, 0]) > s * s) & ~tracks.suspect)
        self._new_template(frame, tracks, grown)
        self.stats.reanchored += int(grown.size)
        return tracks

    def _new_template(self, frame, tracks: "_Tracks", rows: np.ndarray) -> None:
        """Tracks ``rows`` take their current left appearance as the template; the right warp follows."""
        if rows.size:
            AL_inv = np.linalg.inv(tracks.warps[rows, 0])
            tracks.templates[rows] = self._templates(frame["left_f"], tracks.pixels[rows, :2])
            tracks.normal_inv[rows] = self._normal_inverse(tracks.templates[rows])
            tracks.warps[rows, 1] = tracks.warps[rows, 1] @ AL_inv
            tracks.warps[rows, 0] = np.eye(2)

    def _confirm_suspects(self, tracks: "_Tracks") -> "_Tracks":
        """Tracks past their appearance bound (``affine_confirm_factor``) that passed this frame's
        geometric and drift checks (to ``affine_confirm_px``) are kept, with their template; without
        a motion to check them against (or with the drift check off), they end under the
        appearance check."""
        if not tracks.suspect.any():
            return tracks
        if not self._motion_ok or self.options.drift_threshold_px <= 0:
            return self._end(tracks, ~tracks.suspect, "appearance")
        self.stats.confirmed += int(np.count_nonzero(tracks.suspect))
        tracks.suspect = np.zeros(len(tracks), bool)
        return tracks

    def _check_geometry(self, tracks: "_Tracks") -> "_Tracks":
        """Steps 3 and 3b: P3P-RANSAC against the previous triangulation, then the drift check.

        Tracks past their appearance bound (``suspect``) are held to ``affine_confirm_px`` in both
        checks; one that fails ends under the appearance check."""
        o = self.options
        tight = o.affine_confirm_px if o.affine_confirm_px > 0 else math.inf
        ok = self._geometric_inliers(tracks.prev, tracks.pixels,
                                     np.where(tracks.suspect, min(tight, o.ransac_threshold_px), o.ransac_threshold_px))
        tracks = self._end_suspects(tracks, ok, "geometric")
        if not self._motion_ok:  # the chain is broken: no drift reference for the tracks alive now
            tracks.refs = np.full_like(tracks.refs, np.nan)
            return tracks
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = self._motion
        self._cam_T_ref = step @ self._cam_T_ref
        ok = self._drift_ok(tracks.refs, tracks.pixels, tracks.refs_cov,
                            np.where(tracks.suspect, min(tight, o.drift_threshold_px), o.drift_threshold_px))
        return self._end_suspects(tracks, ok, "drift")

    def _end_suspects(self, tracks: "_Tracks", keep: np.ndarray, reason: str) -> "_Tracks":
        """Like :meth:`_end`, but the suspects (past their appearance bound) that end are counted
        under the appearance check."""
        passed = keep | tracks.suspect
        tracks = self._end(tracks, passed, reason)
        return self._end(tracks, keep[passed] | ~tracks.suspect, "appearance")

    def _new_tracks(self, frame, tracks: "_Tracks") -> "_Tracks":
        """Step 4: corners in the cells below their share, matched into the right image."""
        o = self.options
        new = self._detect(frame["left"], tracks.pixels[:, :2])
        st = self.stats
        st.detected += new.shape[0]
        tpl = np.zeros((new.shape[0], self._offsets.shape[0], 8), np.float32)
        if o.affine_radius_px > 0 and new.shape[0]:
            tpl = self._templates(frame["left_f"], new)
            contrast = tpl[..., 6].std(axis=1) > 2.0  # not the featureless sky
            st.rejected_stereo_new += int(np.count_nonzero(~contrast))
            new, tpl = new[contrast], tpl[contrast]
        tried = new
        if o.stereo_min_score > 0:
            stereo, sok = self._stereo_search(frame, new)
        else:
            stereo, sok = self._stereo(frame["left"], frame["right"], new, np.zeros(new.shape[0]), o.stereo_levels,
                                       o.stereo_window_px)
        st.rejected_stereo_new += int(np.count_nonzero(~sok))
        stereo, tpl = stereo[sok], tpl[sok]
        if o.min_expected_frames > 0 and self._motion_ok:
            stay = self._expected_frames(stereo, o.min_expected_frames) >= o.min_expected_frames
            st.not_started += int(np.count_nonzero(~stay))
            stereo, tpl = stereo[stay], tpl[stay]
        A = np.tile(np.eye(2), (stereo.shape[0], 2, 1, 1))
        if o.affine_radius_px > 0 and stereo.shape[0]:
            h_inv = self._normal_inverse(tpl)
            pr, A[:, 1], okr, res0 = self._affine(frame["right_f"], tpl, stereo[:, 2:], A[:, 1], h_inv)
            stereo = np.concatenate([stereo[:, :2], pr], axis=1)
            aok = okr & self._stereo_ok(stereo)
            st.rejected_stereo_new += int(np.count_nonzero(~aok))
            stereo, tpl, A, res0, h_inv = stereo[aok], tpl[aok], A[aok], res0[aok], h_inv[aok]
        else:
            res0 = np.zeros(stereo.shape[0])
            h_inv = np.zeros((stereo.shape[0], 8, 8))
        cap = self._within_need(stereo[:, :2])
        stereo, tpl, A, res0, h_inv = stereo[cap], tpl[cap], A[cap], res0[cap], h_inv[cap]
        self._rest_cells(tried, stereo[:, :2])
        n = stereo.shape[0]
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        ref_T_cam = np.linalg.inv(self._cam_T_ref)
        refs = self._triangulate(stereo) @ ref_T_cam[:3, :3].T + ref_T_cam[:3, 3]
        cov = ref_T_cam[:3, :3] @ self._point_covariance(stereo) @ ref_T_cam[:3, :3].T
        return _Tracks(ids, stereo, np.full((n, 4), np.nan), tpl, h_inv, A, refs, np.full(n, st.frames, np.int64),
                       res0, cov)

    def _commit(self, frame, tracks: "_Tracks") -> tuple[np.ndarray, np.ndarray]:
        """Keep this frame's tracks (sorted by id) and its left image for the next one."""
        tracks = tracks.take(np.argsort(tracks.ids, kind="stable"))
        self._live, self._prev_left = tracks, frame["left"]
        self.stats.frames += 1
        self.stats.tracks_per_frame.append(len(tracks))
        return tracks.ids.copy(), tracks.pixels.copy()


@dataclass
class _Tracks:
    """The live tracks, one row per track in every array."""

    ids: np.ndarray  # (n,) int64
    pixels: np.ndarray  # (n, 4) [uL, vL, uR, vR] in the current frame
    prev: np.ndarray  # (n, 4) ... in the previous frame (NaN for new tracks)
    templates: np.ndarray  # (n, m, 8) float32: the first left appearance's dT/dp, T, 1 (affine step)
    normal_inv: np.ndarray  # (n, 8, 8): the affine step's inverse normal matrix of each template
    warps: np.ndarray  # (n, 2, 2, 2): left and right affine warps of the template
    refs: np.ndarray  # (n, 3): first triangulation in the first frame's camera (NaN: none)
    born: np.ndarray  # (n,) int64: frame index of the first observation
    residual0: np.ndarray  # (n,): the affine residual (relative to contrast) of its first right match
    refs_cov: np.ndarray  # (n, 3, 3): covariance of refs (stereo_sigma_px)
    suspect: np.ndarray = None  # (n,) bool: past the appearance bound, kept only if the geometry confirms it

    def __post_init__(self):
        if self.suspect is None:
            self.suspect = np.zeros(self.ids.size, bool)

    @classmethod
    def empty(cls, m: int) -> "_Tracks":
        return cls(np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros((0, 4)), np.zeros((0, m, 8), np.float32),
                   np.zeros((0, 8, 8)), np.zeros((0, 2, 2, 2)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0),
                   np.zeros((0, 3, 3)))

    def __len__(self) -> int:
        return int(self.ids.size)

    def take(self, keep) -> "_Tracks":
        return _Tracks(*(getattr(self, f.name)[keep] for f in fields(self)))

    def concat(self, other: "_Tracks") -> "_Tracks":
        return _Tracks(*(np.concatenate([getattr(self, f.name), getattr(other, f.name)]) for f in fields(self)))


def finish_tracks(frames: list[tuple[np.ndarray, np.ndarray]], min_track_length: int):
    """Per-frame ``(ids, pixels)`` -> :class:`~vislam.core.sequence.StereoObservations`.

    Tracks seen in fewer than ``min_track_length`` frames are dropped; the others are
    renumbered 0..M-1 in order of their first frame (ids grow with detection, so the
    order is kept).
    """
    from vislam.core.sequence import StereoObservations

    counts = np.array([f[0].size for f in frames], dtype=np.int64)
    all_ids = np.concatenate([f[0] for f in frames]) if frames else np.zeros(0, np.int64)
    all_px = np.concatenate([f[1] for f in frames]) if frames else np.zeros((0, 4))
    n_ids = int(all_ids.max()) + 1 if all_ids.size else 0
    lengths = np.bincount(all_ids, minlength=n_ids)
    keep_id = lengths >= max(1, min_track_length)
    new_id = np.cumsum(keep_id) - 1
    keep = keep_id[all_ids]
    frame_of = np.repeat(np.arange(len(frames)), counts)
    kept_counts = np.bincount(frame_of[keep], minlength=len(frames))
    offsets = np.zeros(len(frames) + 1, dtype=np.int64)
    np.cumsum(kept_counts, out=offsets[1:])
    return StereoObservations(offsets, new_id[all_ids[keep]], all_px[keep], int(keep_id.sum()))
