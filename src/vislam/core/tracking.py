"""A stereo feature tracker: rectified stereo image pairs -> stereo feature tracks.

Pure image computation on OpenCV (no file I/O): :class:`StereoTracker` takes one
rectified grey pair at a time and returns the stereo observations of that frame,
``(track_ids, pixels)`` with pixels ``[uL, vL, uR, vR]`` in the rectified images — the
rows of :class:`vislam.core.sequence.StereoObservations`. It keeps only the previous
frame (its left image, its live tracks and their triangulation), so its memory does
not depend on the length of the recording.

Each frame:

1. **Temporal tracking** — pyramidal Lucas-Kanade (KLT) of the live tracks from the
   previous left image into the new one, then back; a track whose round trip misses its
   start by more than ``fb_threshold_px`` is lost (forward-backward check).
2. **Stereo matching** — KLT from the left image into the right one, started at the
   track's previous disparity (new corners: at zero, with a deeper pyramid), then back.
   A match is kept only on the epipolar line of the rectified pair (``|vR - vL| <=
   max_row_difference_px``), with a disparity ``uL - uR`` in
   ``[min_disparity_px, max_disparity_px]`` and a round trip within ``fb_threshold_px``.
   A track without a stereo match ends (tracks are contiguous, as the dataset format wants).
3. **Geometric check** — the previous frame's stereo triangulation of the tracked
   points against their new left pixels: P3P in RANSAC (``cv2.solvePnPRansac``) gives the
   camera motion; a track whose predicted left *or* right pixel is more than
   ``ransac_threshold_px`` from its measurement is rejected (catches wrong temporal and
   wrong stereo matches alike, and points on moving objects).
4. **Detection** — Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) at least
   ``min_distance_px`` from every live track, spread over a ``grid_cols x grid_rows``
   grid: each cell is filled up to its share of ``target_features``. New corners get new
   ids (0, 1, 2, ... in order of detection; ids are never reused).

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


@dataclass(frozen=True)
class TrackerOptions:
    """Options of :class:`StereoTracker` (units in the names; defaults documented inline)."""

    #: Number of live tracks the detector tops up to, spread over the grid.
    target_features: int = 300
    #: Detection grid: columns x rows of cells, each filled to its share of target_features.
    grid_cols: int = 10
    grid_rows: int = 4
    #: Shi-Tomasi quality level (fraction of the best corner's score).
    quality_level: float = 0.005
    #: Smallest distance between two corners / a new corner and a live track (px).
    min_distance_px: float = 12.0
    #: Shi-Tomasi block size (px).
    block_size_px: int = 5
    #: Corners are detected this far from the image border (px).
    border_px: int = 10
    #: KLT window side (px, odd).
    klt_window_px: int = 21
    #: KLT pyramid levels above the full image (temporal tracking).
    klt_levels: int = 3
    #: KLT pyramid levels of the stereo match of a new corner (no disparity guess yet).
    stereo_levels: int = 4
    #: KLT iterations per level and the convergence threshold (px).
    klt_iterations: int = 30
    klt_epsilon_px: float = 0.01
    #: Forward-backward check: largest round-trip error of a KLT match (px).
    fb_threshold_px: float = 0.5
    #: Epipolar constraint of the rectified pair: largest |vR - vL| (px).
    max_row_difference_px: float = 1.0
    #: Disparity range uL - uR accepted (px); must be > 0.
    min_disparity_px: float = 0.5
    max_disparity_px: float = 250.0
    #: Geometric check: largest reprojection error in either image (px); 0 turns it off.
    ransac_threshold_px: float = 1.5
    #: RANSAC iterations of the geometric check.
    ransac_iterations: int = 100
    #: Fewest tracked points for the geometric check (fewer: the check is skipped).
    ransac_min_points: int = 12
    #: Tracks seen in fewer frames are left out of the output (see :func:`finish_tracks`).
    min_track_length: int = 2

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", int):
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                    raise ConfigError(f"{f.name} must be an integer, got {value!r}")
                object.__setattr__(self, f.name, int(value))
                if value < (0 if f.name in ("border_px", "ransac_iterations") else 1):
                    raise ConfigError(f"{f.name} must be >= 1, got {value!r}")
            else:
                if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                        or not math.isfinite(value) or value < 0:
                    raise ConfigError(f"{f.name} must be a finite number >= 0, got {value!r}")
                object.__setattr__(self, f.name, float(value))
        if self.klt_window_px % 2 == 0 or self.klt_window_px < 3:
            raise ConfigError(f"klt_window_px must be odd and >= 3, got {self.klt_window_px}")
        if not 0 < self.quality_level < 1:
            raise ConfigError(f"quality_level must be in (0, 1), got {self.quality_level}")
        if not 0 < self.min_disparity_px < self.max_disparity_px:
            raise ConfigError(f"need 0 < min_disparity_px < max_disparity_px, got {self.min_disparity_px} "
                              f"and {self.max_disparity_px}")
        if self.fb_threshold_px <= 0:
            raise ConfigError(f"fb_threshold_px must be > 0, got {self.fb_threshold_px}")
        if self.ransac_min_points < 4:
            raise ConfigError(f"ransac_min_points must be >= 4 (P3P + 1), got {self.ransac_min_points}")

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
    left_image: int = 0  # left the image

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
            "rejections": {
                "forward_backward": self.lost_temporal,
                "left_image": self.left_image,
                "stereo_tracked": self.rejected_stereo_tracked,
                "stereo_new": self.rejected_stereo_new,
                "geometric": self.rejected_geometric,
            },
        }
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
        self._prev_pyramid = None
        self._ids = np.zeros(0, dtype=np.int64)
        self._pixels = np.zeros((0, 4))  # [uL, vL, uR, vR] of the live tracks in the previous frame
        self._shape = None
        o = self.options
        self._criteria = (self._cv2.TERM_CRITERIA_COUNT | self._cv2.TERM_CRITERIA_EPS, o.klt_iterations,
                          o.klt_epsilon_px)

    # ------------------------------------------------------------------ helpers
    def _klt(self, pyr_a, pyr_b, pts_a, guess_b, levels):
        """Forward KLT a -> b from ``guess_b``, then back; (pts_b, ok, fb_error)."""
        cv2 = self._cv2
        w = self.options.klt_window_px
        n = pts_a.shape[0]
        if n == 0:
            return np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0)
        a = np.ascontiguousarray(pts_a, dtype=np.float32).reshape(-1, 1, 2)
        g = np.ascontiguousarray(guess_b, dtype=np.float32).reshape(-1, 1, 2)
        pb, st, _ = cv2.calcOpticalFlowPyrLK(pyr_a, pyr_b, a, g.copy(), winSize=(w, w), maxLevel=levels,
                                             criteria=self._criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        pa, st2, _ = cv2.calcOpticalFlowPyrLK(pyr_b, pyr_a, pb, a.copy(), winSize=(w, w), maxLevel=levels,
                                              criteria=self._criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        pb = pb.reshape(-1, 2).astype(np.float64)
        fb = np.linalg.norm(pa.reshape(-1, 2).astype(np.float64) - np.asarray(pts_a, np.float64), axis=1)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(pb).all(axis=1)
        return pb, ok, fb

    def _inside(self, pts):
        h, w = self._shape
        m = float(max(2, self.options.klt_window_px // 2 // 2))
        return (pts[:, 0] >= m) & (pts[:, 0] <= w - 1 - m) & (pts[:, 1] >= m) & (pts[:, 1] <= h - 1 - m)

    def _stereo(self, pyr_l, pyr_r, left, disparity_guess, levels):
        """Stereo match of left pixels (n, 2); (pixels (n, 4), ok)."""
        o = self.options
        guess = left.copy()
        guess[:, 0] -= disparity_guess
        right, ok, fb = self._klt(pyr_l, pyr_r, left, guess, levels)
        if left.shape[0] == 0:
            return np.zeros((0, 4)), ok
        disparity = left[:, 0] - right[:, 0]
        ok &= fb <= o.fb_threshold_px
        ok &= np.abs(right[:, 1] - left[:, 1]) <= o.max_row_difference_px
        ok &= (disparity >= o.min_disparity_px) & (disparity <= o.max_disparity_px)
        ok &= self._inside(right)
        return np.concatenate([left, right], axis=1), ok

    def _triangulate(self, pixels):
        """(n, 3) points in the left camera frame from stereo pixels (n, 4)."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        d = pixels[:, 0] - pixels[:, 2]
        z = fx * self.baseline_m / d
        return np.stack([z * (pixels[:, 0] - cx) / fx, z * (pixels[:, 1] - cy) / fy, z], axis=1)

    def _geometric_inliers(self, p_prev, pixels):
        """True for tracks consistent with one rigid motion (see step 3 of the module docstring)."""
        cv2 = self._cv2
        o = self.options
        n = pixels.shape[0]
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
        q = obj @ R.T + tvec.reshape(1, 3)
        good = q[:, 2] > 0
        z = np.where(good, q[:, 2], 1.0)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        uL = fx * q[:, 0] / z + cx
        v = fy * q[:, 1] / z + cy
        uR = fx * (q[:, 0] - self.baseline_m) / z + cx
        err = np.maximum(np.hypot(uL - pixels[:, 0], v - pixels[:, 1]), np.hypot(uR - pixels[:, 2], v - pixels[:, 3]))
        return good & (err <= o.ransac_threshold_px)

    def _detect(self, image, existing):
        """New corners (n, 2) in the cells below their share, away from ``existing`` (m, 2)."""
        cv2 = self._cv2
        o = self.options
        h, w = self._shape
        mask = np.zeros((h, w), np.uint8)
        bd = o.border_px
        mask[bd:h - bd, bd:w - bd] = 255
        r = int(math.ceil(o.min_distance_px))
        for x, y in np.round(existing).astype(int):
            cv2.circle(mask, (int(x), int(y)), r, 0, -1)
        cell_w, cell_h = w / o.grid_cols, h / o.grid_rows
        n_cells = o.grid_cols * o.grid_rows
        quota = int(math.ceil(o.target_features / n_cells))

        def cell_of(p):
            cx = np.clip((p[:, 0] / cell_w).astype(int), 0, o.grid_cols - 1)
            cy = np.clip((p[:, 1] / cell_h).astype(int), 0, o.grid_rows - 1)
            return cy * o.grid_cols + cx

        have = np.bincount(cell_of(existing), minlength=n_cells) if existing.size else np.zeros(n_cells, int)
        need = np.maximum(quota - have, 0)
        if need.sum() == 0 or existing.shape[0] >= o.target_features + n_cells:
            return np.zeros((0, 2))
        corners = cv2.goodFeaturesToTrack(image, maxCorners=4 * o.target_features, qualityLevel=o.quality_level,
                                          minDistance=o.min_distance_px, mask=mask, blockSize=o.block_size_px)
        if corners is None:
            return np.zeros((0, 2))
        corners = corners.reshape(-1, 2).astype(np.float64)  # strongest first
        cells = cell_of(corners)
        # keep, in each cell, the strongest `need[cell]` corners
        order = np.argsort(cells, kind="stable")
        sorted_cells = cells[order]
        first = np.searchsorted(sorted_cells, sorted_cells, side="left")
        rank = np.arange(order.size) - first
        keep = order[rank < need[sorted_cells]]
        return corners[np.sort(keep)]

    # ------------------------------------------------------------------ the step
    def process(self, left, right) -> tuple[np.ndarray, np.ndarray]:
        """Track into the next rectified grey pair (uint8 arrays of one shape).

        Returns ``(ids (n,) int64 strictly increasing, pixels (n, 4) [uL, vL, uR, vR])``.
        """
        cv2 = self._cv2
        o = self.options
        left = np.ascontiguousarray(left)
        right = np.ascontiguousarray(right)
        if left.ndim != 2 or left.shape != right.shape or left.dtype != np.uint8 or right.dtype != np.uint8:
            raise ValueError("process expects two grey uint8 images of one shape")
        if self._shape is None:
            self._shape = left.shape
        elif left.shape != self._shape:
            raise ValueError(f"image size changed from {self._shape} to {left.shape}")
        pyr_l, pyr_r = left, right  # (OpenCV's Python binding takes images, not prebuilt pyramids)
        st = self.stats

        ids = np.zeros(0, np.int64)
        pixels = np.zeros((0, 4))
        if self._ids.size and self._prev_pyramid is not None:
            prev = self._pixels
            cur, ok, fb = self._klt(self._prev_pyramid, pyr_l, prev[:, :2], prev[:, :2], o.klt_levels)
            ok &= fb <= o.fb_threshold_px
            st.lost_temporal += int(np.count_nonzero(~ok))
            inside = self._inside(cur)
            st.left_image += int(np.count_nonzero(ok & ~inside))
            ok &= inside
            prev, cur, tid = prev[ok], cur[ok], self._ids[ok]
            disparity = prev[:, 0] - prev[:, 2]
            stereo, sok = self._stereo(pyr_l, pyr_r, cur, disparity, o.klt_levels)
            st.rejected_stereo_tracked += int(np.count_nonzero(~sok))
            prev, stereo, tid = prev[sok], stereo[sok], tid[sok]
            geo = self._geometric_inliers(prev, stereo)
            st.rejected_geometric += int(np.count_nonzero(~geo))
            ids, pixels = tid[geo], stereo[geo]

        new = self._detect(left, pixels[:, :2])
        if new.shape[0]:
            st.detected += new.shape[0]
            stereo, sok = self._stereo(pyr_l, pyr_r, new, np.zeros(new.shape[0]), o.stereo_levels)
            st.rejected_stereo_new += int(np.count_nonzero(~sok))
            stereo = stereo[sok]
            new_ids = np.arange(self._next_id, self._next_id + stereo.shape[0], dtype=np.int64)
            self._next_id += stereo.shape[0]
            ids = np.concatenate([ids, new_ids])
            pixels = np.concatenate([pixels, stereo])
        order = np.argsort(ids, kind="stable")
        ids, pixels = ids[order], pixels[order]
        self._ids, self._pixels, self._prev_pyramid = ids, pixels, pyr_l
        st.frames += 1
        st.tracks_per_frame.append(int(ids.size))
        return ids.copy(), pixels.copy()


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
