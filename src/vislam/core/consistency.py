"""Filter consistency on simulated drives: NEES of the pose and of the landmarks.

A filter is *consistent* when its errors are as large as its covariance says. The
normalized estimation error squared (NEES) of an estimate with error e and covariance
P is ``eᵀ P⁻¹ e``; for a consistent filter it is chi-square with ``dim e`` degrees of
freedom, so its mean is ``dim e`` (6 for the pose, 3 for a landmark). Averaged over N
independent Monte Carlo runs, N · mean is chi-square with N · dof degrees of freedom,
which gives the 95 % band :func:`chi2_band` (as in OpenVINS's evaluation tools).

Error conventions — exactly the filters' (see :mod:`vislam.core.lie`, :mod:`vislam.core.state`):

* the pose covariance is that of a LEFT perturbation of the inverse pose
  ``imu_T_world = exp(δ^) μ`` in (v, ω) order, so the pose error is
  ``δ = log(imu_T_world_true · μ⁻¹)`` (:func:`pose_error`);
* landmarks are perturbed additively: ``e = p_lm_in_world_true − p_lm_in_world_est``.

Landmark NEES per frame: the mean, over the landmarks in the SLAM state after the
frame's update, of each landmark's 3-dof NEES with its marginal covariance, in the
filter's own chart — the position, or with anchored inverse depth (α, β, ρ) against
the true point's (α, β, ρ) in the same anchor frame (the Cartesian covariance of a far
point is only a linearization of the filter's belief) — and for mapping the landmarks
with a track in progress. Its expectation is 3 for a consistent filter;
the band of :func:`chi2_band` with ``dof=3`` is then conservative (the mean over L
landmarks varies less than one chi-square(3) when they are not fully correlated).

:func:`filter_nees` runs one filter over a :class:`~vislam.core.simulate.SimulatedDrive`
step by step and returns the per-frame NEES (:class:`NeesTrace`);
:func:`true_noise_options` tells a :class:`FilterOptions` the simulator's noise.
Pure computation (no I/O): the Monte Carlo orchestration is in
:mod:`vislam.tools.consistency`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vislam.core.lie import se3_inverse, se3_log
from vislam.core.options import FilterOptions

__all__ = ["pose_error", "pose_nees", "point_nees", "world_to_inverse_depth", "chi2_band", "NeesTrace", "filter_nees",
           "true_noise_options", "CONSISTENCY_MODES"]

#: Modes :func:`filter_nees` can run (the three EKFs of the report).
CONSISTENCY_MODES = ("slam", "localization", "mapping")


def pose_error(imu_T_world_true: np.ndarray, imu_T_world_est: np.ndarray) -> np.ndarray:
    """(..., 6) error of the filter's pose in its own convention: the left perturbation
    δ with ``imu_T_world_true = exp(δ^) · imu_T_world_est``, i.e.
    ``δ = log(imu_T_world_true · imu_T_world_est⁻¹)``, (v, ω) order."""
    return se3_log(np.asarray(imu_T_world_true) @ se3_inverse(imu_T_world_est))


def _quadratic(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    """eᵀ P⁻¹ e batched over leading axes (NaN where P is singular)."""
    e = np.asarray(e, dtype=np.float64)
    P = np.asarray(P, dtype=np.float64)
    out = np.full(e.shape[:-1], np.nan)
    flat_e = e.reshape(-1, e.shape[-1])
    flat_P = P.reshape(-1, e.shape[-1], e.shape[-1])
    flat_out = out.reshape(-1)
    for i in range(flat_e.shape[0]):
        try:
            L = np.linalg.cholesky(flat_P[i])
        except np.linalg.LinAlgError:
            continue
        y = np.linalg.solve(L, flat_e[i])
        flat_out[i] = float(y @ y)
    return flat_out.reshape(e.shape[:-1])


def pose_nees(imu_T_world_true: np.ndarray, imu_T_world_est: np.ndarray, pose_covariance: np.ndarray) -> np.ndarray:
    """(...,) 6-dof NEES δᵀ Σ⁻¹ δ of the pose (δ of :func:`pose_error`; NaN where Σ is
    not positive definite, e.g. the exactly known first pose)."""
    return _quadratic(pose_error(imu_T_world_true, imu_T_world_est), pose_covariance)


def point_nees(p_true: np.ndarray, p_est: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """(k,) 3-dof NEES of k points: e = p_true − p_est, eᵀ P⁻¹ e."""
    return _quadratic(np.asarray(p_true) - np.asarray(p_est), covariance)


def world_to_inverse_depth(p_lm_in_world: np.ndarray, world_T_anchor: np.ndarray) -> np.ndarray:
    """(k, 3) anchored inverse-depth parameters (α, β, ρ) of world points (the inverse of
    :func:`vislam.core.state.inverse_depth_to_world`)."""
    q = np.einsum("kij,kj->ki", se3_inverse(world_T_anchor)[:, :3, :3], p_lm_in_world) \
        + se3_inverse(world_T_anchor)[:, :3, 3]
    return np.stack([q[:, 0] / q[:, 2], q[:, 1] / q[:, 2], 1.0 / q[:, 2]], axis=1)


def chi2_band(n_runs: int, dof: int, probability: float = 0.95) -> tuple[float, float]:
    """(low, high): the two-sided ``probability`` band of the NEES averaged over
    ``n_runs`` independent runs, ``chi2.ppf([(1−p)/2, (1+p)/2], n_runs · dof) / n_runs``."""
    from scipy.stats import chi2

    a = (1.0 - probability) / 2.0
    lo, hi = chi2.ppf([a, 1.0 - a], n_runs * dof) / n_runs
    return float(lo), float(hi)


@dataclass
class NeesTrace:
    """Per-frame NEES of one run (NaN where undefined: no covariance, no landmarks).

    Attributes:
        pose_nees: (T,) 6-dof pose NEES.
        landmark_nees: (T,) mean 3-dof NEES of the landmarks in the state after the frame.
        landmark_count: (T,) how many landmarks ``landmark_nees`` averages.
        landmark_depth_nees: (B,) mean landmark NEES per depth bin (over the whole run),
            for the bins of ``depth_bins_m``; ``landmark_depth_count`` how many terms.
        position_error_m: (T,) position error of the pose estimate (m).
        error: the filter's error message when it stopped early (else None).
    """

    pose_nees: np.ndarray
    landmark_nees: np.ndarray
    landmark_count: np.ndarray
    position_error_m: np.ndarray
    depth_bins_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    landmark_depth_nees: np.ndarray = field(default_factory=lambda: np.zeros(0))
    landmark_depth_count: np.ndarray = field(default_factory=lambda: np.zeros(0))
    error: str | None = None


#: Depth bins (m, camera z at the frame) of the landmark NEES breakdown.
DEPTH_BINS_M = np.array([0.0, 10.0, 20.0, 30.0, 45.0, 60.0, np.inf])


def true_noise_options(simulation_options, base: FilterOptions | None = None) -> FilterOptions:
    """``base`` (default FilterOptions()) told the simulator's true noise.

    The simulator adds ``σ_v n`` (m/s) and ``σ_ω n`` (rad/s), n ~ N(0, 1) per axis, to
    each velocity sample, and integrates the true poses with the same step τ_k that the
    filter uses; the filter's process noise per step is ``τ² W`` with W = diag(σ_v², σ_ω²)
    per sample — the same quantity, so the map is one to one. Pixel noise: σ_px on each
    of uL, vL, uR, vR, the filter's V = σ_px² I₄. Zero IMU noise is replaced by a tiny
    value (1e-6) so the covariance stays positive definite."""
    base = base or FilterOptions()
    so = simulation_options
    return base.replace(velocity_noise_mps=max(float(so.velocity_noise_mps), 1e-6),
                        angular_noise_radps=max(float(so.angular_noise_radps), 1e-6),
                        pixel_noise_px=float(so.pixel_noise_px))


def filter_nees(drive, options: FilterOptions, mode: str = "slam") -> NeesTrace:
    """Run the ``mode`` filter over the simulated ``drive`` frame by frame and return its
    per-frame pose and landmark NEES against the simulator's ground truth.

    Mapping runs with the true poses (landmark NEES only; pose NEES is NaN);
    localization has no landmarks. With the stalled-track remap the SLAM filter
    finishes frames late: the pose NEES of every finished frame is taken, the landmark
    NEES at the last frame finished in each step."""
    from vislam.core.filters import LocalizationFilter, MappingFilter, SlamFilter
    from vislam.errors import EstimationError

    if mode not in CONSISTENCY_MODES:
        raise ValueError(f"mode must be one of {CONSISTENCY_MODES}, got {mode!r}")
    seq = drive.sequence
    filt = {"slam": SlamFilter, "localization": LocalizationFilter, "mapping": MappingFilter}[mode](
        seq.calibration, options)
    record = _NeesRecorder(drive, mode)
    error = None
    try:
        for frame in seq.frames():
            if mode == "mapping":
                filt.step(frame, world_T_imu=drive.world_T_imu[frame.index])
            else:
                filt.step(frame)
            record.finished(filt)
        filt.drain()  # frames a delayed filter still holds
        record.finished(filt)
    except EstimationError as exc:
        error = str(exc)
    return record.trace(error)


class _NeesRecorder:
    """The NEES of the frames a filter finishes, against a simulated drive's truth, for
    :func:`filter_nees` (through the filter contract only: ``pop_processed``,
    ``landmark_estimates``)."""

    def __init__(self, drive, mode: str):
        T = drive.sequence.n_frames
        self.drive, self.mode = drive, mode
        self.true_imu_T_world = se3_inverse(drive.world_T_imu)
        self.pose = np.full(T, np.nan)
        self.pos_err = np.full(T, np.nan)
        self.lm = np.full(T, np.nan)
        self.lm_n = np.zeros(T, dtype=np.int64)
        self.bins = DEPTH_BINS_M
        self.bin_sum = np.zeros(self.bins.size - 1)
        self.bin_n = np.zeros(self.bins.size - 1, dtype=np.int64)
        self.moving = np.asarray(drive.landmark_is_moving)
        self.cam_T_imu = np.asarray(drive.cam_T_imu)

    def finished(self, filt) -> None:
        """The pose NEES of every frame finished since the last call, the landmark NEES
        at the last of them."""
        processed = filt.pop_processed()
        for t, mu, cov, _ in processed:
            if cov is not None and self.mode != "mapping":
                self.pose[t] = pose_nees(self.true_imu_T_world[t], mu, cov)
                self.pos_err[t] = np.linalg.norm(se3_inverse(mu)[:3, 3] - self.drive.world_T_imu[t][:3, 3])
        if processed and self.mode != "localization":
            self.landmarks_at(filt, processed[-1][0])

    def landmarks_at(self, filt, t: int) -> None:
        """Mean NEES of the static landmarks being estimated at frame t (in the filter's
        own chart), and its terms per depth bin."""
        if filt.live_landmark_ids.size == 0:
            return
        ids, p_est, cov, anchors = filt.landmark_estimates()
        static = ~self.moving[ids]
        if not np.any(static):
            return
        ids, p_est, cov = ids[static], p_est[static], cov[static]
        p_true = self.drive.p_lm_in_world[ids]
        if anchors is None:
            n = point_nees(p_true, p_est, cov)
        else:
            n = point_nees(world_to_inverse_depth(p_true, anchors[static]), p_est, cov)
        ok = np.isfinite(n)
        if not np.any(ok):
            return
        self.lm[t] = float(n[ok].mean())
        self.lm_n[t] = int(ok.sum())
        cam_T_world = self.cam_T_imu @ self.true_imu_T_world[t]
        depth = p_true[ok] @ cam_T_world[2, :3] + cam_T_world[2, 3]
        bins = self.bins
        b = np.clip(np.searchsorted(bins, depth, side="right") - 1, 0, bins.size - 2)
        np.add.at(self.bin_sum, b, n[ok])
        np.add.at(self.bin_n, b, 1)

    def trace(self, error: str | None) -> NeesTrace:
        with np.errstate(invalid="ignore", divide="ignore"):
            depth_mean = np.where(self.bin_n > 0, self.bin_sum / np.maximum(self.bin_n, 1), np.nan)
        return NeesTrace(self.pose, self.lm, self.lm_n, self.pos_err, self.bins.copy(), depth_mean, self.bin_n, error)
