"""Trajectory error metrics that no library provides: the KITTI odometry metric.

Pure numpy, no I/O. (APE and RPE come from evo; see :mod:`vislam.tools.evaluation`.)

KITTI odometry metric
---------------------
Implemented like the KITTI devkit (``devkit/cpp/evaluate_odometry.cpp``):

* ``dist[i]`` is the distance travelled along the **ground truth** up to frame ``i``
  (sum of the straight-line distances between consecutive positions).
* For every first frame ``f = 0, 10, 20, ...`` and every segment length ``L`` in
  100, 200, ..., 800 m, the last frame ``l`` is the first frame with
  ``dist[l] > dist[f] + L`` (strictly greater, as the devkit's
  ``lastFrameFromSegmentLength``); the pair is skipped when there is no such frame.
* ``pose_error = inv(inv(gt[f]) @ gt[l]) @ (inv(est[f]) @ est[l])``. (The devkit writes
  the inverse of this matrix; a rigid transform and its inverse have the same
  translation norm and rotation angle, so the errors are identical.)
* ``t_err = ||translation(pose_error)|| / L`` (m/m) and
  ``r_err = arccos(clip((trace(R_error) - 1) / 2, -1, 1)) / L`` (rad/m).
* The sequence errors are the means over **all** segments (all lengths pooled), reported
  as ``t_pct`` = 100 · mean(t_err) (%) and ``r_deg_per_100m`` = mean(r_err) in deg/m x 100.

Only relative poses between frames of the same trajectory enter the metric, so it is
invariant to a rigid transform applied to the whole estimate (or the whole ground
truth): no alignment is needed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vislam.core.lie import se3_inverse

__all__ = [
    "KITTI_SEGMENT_LENGTHS_M",
    "KITTI_STEP_FRAMES",
    "KittiOdometryErrors",
    "kitti_odometry_errors",
    "trajectory_distances",
    "rotation_angle_clipped",
]

#: Segment lengths of the KITTI odometry benchmark (m).
KITTI_SEGMENT_LENGTHS_M: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
#: Spacing of the first frames of the segments (the devkit's ``step_size``).
KITTI_STEP_FRAMES = 10


def _as_poses(poses, name: str) -> np.ndarray:
    a = np.asarray(poses, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (N, 4, 4), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


def trajectory_distances(world_T_body) -> np.ndarray:
    """(N,) distance travelled up to each pose: ``d[0] = 0``, ``d[i] = d[i-1] + ||p_i - p_{i-1}||``."""
    poses = _as_poses(world_T_body, "world_T_body")
    if poses.shape[0] == 0:
        return np.zeros(0)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def rotation_angle_clipped(R) -> np.ndarray:
    """Rotation angle (rad) of (..., 3, 3) matrices as the devkit computes it:
    ``arccos(clip((trace(R) - 1) / 2, -1, 1))``."""
    R = np.asarray(R, dtype=np.float64)
    d = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arccos(np.clip(d, -1.0, 1.0))


@dataclass(frozen=True, eq=False)
class KittiOdometryErrors:
    """Result of :func:`kitti_odometry_errors`.

    Per-segment arrays (one entry per evaluated segment, ordered by first frame, then
    length):

    Attributes:
        first_frame: (S,) int, first frame of each segment.
        last_frame: (S,) int, last frame of each segment.
        segment_length_m: (S,) nominal length L of each segment (m).
        t_err: (S,) translational error ||t(pose_error)|| / L (m/m, dimensionless).
        r_err_rad_per_m: (S,) rotational error angle(pose_error) / L (rad/m).
        lengths_m: (K,) the segment lengths evaluated (default 100..800 m).
        n_segments_by_length: (K,) int, number of segments of each length.
        t_pct_by_length: (K,) mean translational error of each length (%); NaN where a
            length has no segment.
        r_deg_per_100m_by_length: (K,) mean rotational error of each length
            (deg/100 m); NaN where a length has no segment.
        t_pct: mean translational error over all segments (%), NaN without segments.
        r_deg_per_100m: mean rotational error over all segments (deg/100 m), NaN
            without segments.
        path_length_m: length of the ground-truth trajectory (m).
        step_frames: spacing of the first frames.
    """

    first_frame: np.ndarray
    last_frame: np.ndarray
    segment_length_m: np.ndarray
    t_err: np.ndarray
    r_err_rad_per_m: np.ndarray
    lengths_m: np.ndarray
    n_segments_by_length: np.ndarray
    t_pct_by_length: np.ndarray
    r_deg_per_100m_by_length: np.ndarray
    t_pct: float
    r_deg_per_100m: float
    path_length_m: float
    step_frames: int = KITTI_STEP_FRAMES

    @property
    def n_segments(self) -> int:
        return int(self.first_frame.shape[0])

    @property
    def has_segments(self) -> bool:
        """False when the ground truth is too short for the shortest segment length
        (then ``t_pct`` and ``r_deg_per_100m`` are NaN)."""
        return self.n_segments > 0

    @property
    def t_pct_segments(self) -> np.ndarray:
        """(S,) translational error of each segment in %."""
        return 100.0 * self.t_err

    @property
    def r_deg_per_100m_segments(self) -> np.ndarray:
        """(S,) rotational error of each segment in deg/100 m."""
        return np.degrees(self.r_err_rad_per_m) * 100.0


def kitti_odometry_errors(
    est_world_T_body,
    gt_world_T_body,
    lengths_m=KITTI_SEGMENT_LENGTHS_M,
    step_frames: int = KITTI_STEP_FRAMES,
) -> KittiOdometryErrors:
    """The KITTI odometry errors of an estimate against its ground truth.

    Args:
        est_world_T_body: (N, 4, 4) estimated poses.
        gt_world_T_body: (N, 4, 4) ground-truth poses of the same N frames (same body
            frame; the two world frames may differ by any rigid transform).
        lengths_m: segment lengths (m), positive.
        step_frames: spacing of the first frames (positive).

    A ground truth shorter than the shortest length yields no segment: the means are
    NaN and ``has_segments`` is False (no exception).
    """
    est = _as_poses(est_world_T_body, "est_world_T_body")
    gt = _as_poses(gt_world_T_body, "gt_world_T_body")
    if est.shape[0] != gt.shape[0]:
        raise ValueError(f"estimate has {est.shape[0]} poses, ground truth {gt.shape[0]}; associate them first")
    lengths = np.asarray(lengths_m, dtype=np.float64).ravel()
    if lengths.size == 0 or np.any(~(lengths > 0)) or not np.all(np.isfinite(lengths)):
        raise ValueError(f"segment lengths must be positive and finite, got {lengths_m!r}")
    step_frames = int(step_frames)
    if step_frames < 1:
        raise ValueError(f"step_frames must be >= 1, got {step_frames}")

    n = gt.shape[0]
    dist = trajectory_distances(gt)
    first_all = np.arange(0, n, step_frames)
    # last frame: first index with dist > dist[first] + L (dist is non-decreasing).
    targets = dist[first_all][:, None] + lengths[None, :]  # (F, K)
    last_all = np.searchsorted(dist, targets, side="right")  # (F, K); n where none
    valid = last_all < n
    fi, ki = np.nonzero(valid)  # ordered by first frame, then length
    first = first_all[fi].astype(np.int64)
    last = last_all[fi, ki].astype(np.int64)
    seg_len = lengths[ki]

    delta_gt = se3_inverse(gt[first]) @ gt[last]
    delta_est = se3_inverse(est[first]) @ est[last]
    pose_error = se3_inverse(delta_gt) @ delta_est
    t_err = np.linalg.norm(pose_error[:, :3, 3], axis=1) / seg_len
    r_err = rotation_angle_clipped(pose_error[:, :3, :3]) / seg_len

    counts = np.bincount(ki, minlength=lengths.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        t_by = 100.0 * np.bincount(ki, weights=t_err, minlength=lengths.size) / counts
        r_by = np.degrees(np.bincount(ki, weights=r_err, minlength=lengths.size) / counts) * 100.0
    t_by[counts == 0] = np.nan
    r_by[counts == 0] = np.nan
    has = t_err.size > 0
    return KittiOdometryErrors(
        first_frame=first,
        last_frame=last,
        segment_length_m=seg_len,
        t_err=t_err,
        r_err_rad_per_m=r_err,
        lengths_m=lengths,
        n_segments_by_length=counts.astype(np.int64),
        t_pct_by_length=t_by,
        r_deg_per_100m_by_length=r_by,
        t_pct=float(100.0 * t_err.mean()) if has else float("nan"),
        r_deg_per_100m=float(np.degrees(r_err.mean()) * 100.0) if has else float("nan"),
        path_length_m=float(dist[-1]) if n else 0.0,
        step_frames=step_frames,
    )
