"""What a recording says about itself: noise, biases and conventions, without ground truth.

:func:`check_sequence` runs every analysis on a :class:`~vislam.core.sequence.Sequence`
and returns a :class:`CheckResult`: the estimates with their uncertainties, a list of
:class:`Finding` (stable ``code``, ``severity`` OK / WARN / ERROR, a one-line message
saying what it means and what to do) and the :class:`~vislam.core.options.FilterOptions`
values that correct what was found (``suggested``; see :mod:`vislam.core.corrections`).

The analyses
------------
* **IMU white noise, per axis** (:func:`estimate_white_noise`). The velocity signal is
  the vehicle's motion plus white noise. Its variogram ``γ(h) = ½ E[(u_{t+h} − u_t)²]``
  is ``σ² + γ_motion(h)`` with ``γ_motion(0) = 0``; a quadratic in h fitted to
  γ(1..6) and extrapolated to h = 0 gives σ² (the "nugget"). Smooth motion (a trend,
  accelerations) goes into the linear and quadratic terms, so on clean GPS/INS
  velocities the nugget is ~0 while the differences of the signal are not. The
  uncertainty is the spread over 8 contiguous blocks of the recording.
* **Reprojection consistency** (:class:`_TrackPairs`). Every in-sync stereo observation
  (before its track's first exact repeat, see :func:`in_sync_mask`: at the KITTI files'
  re-detection frames every continuing track repeats its previous pixels and is one
  frame late from then on) is triangulated and predicted in the
  same landmark's observations up to ``window`` frames later, with the relative camera
  motion that the IMU velocities give (dead reckoning over the window, through
  cam_T_imu). The residuals (left-image distance, px) say how well velocities,
  association, extrinsic rotation and time base fit the images.
* **The timestamps' unit**: a camera's median frame interval is 5 ms–1 s; outside it,
  the first of ms, µs, ns that brings it inside is named and suggested
  (``timestamp_scale``), and the analyses below run in seconds.
* **The speeds' scale** (a unit mistake: km/h, mph, knots, cm/s; or an odometry scale
  error): a factor on the linear velocities is fitted with the rotation below, started
  from a log grid; a unit is corrected with its exact factor (``velocity_scale``).
* **Landmarks that do not follow the world's motion** (vehicles in traffic alongside,
  mismatched tracks): those whose predictions reproject with a median above
  ``moving_landmark_px`` (and 4x the landmarks' first quartile) at the best start are
  left out of the fits below; the best start is the one with the most predictions
  within that distance (with traffic, most predictions may belong to vehicles).
* **IMU-camera rotation** (and optionally a gyro bias): the rotation correction ``φ`` (camera frame,
  ``R ← exp(φ) R``) and a gyro bias ``b`` that minimize the robust (Cauchy) stereo
  reprojection error of those predictions — a hand-eye calibration through the
  images. It is started from the identity and from 180° turns about each camera axis,
  so axis-convention mismatches (a frame turned 180°) are recognized. Uncertainty: the
  Gauss-Newton covariance, inflated by the number of predictions per landmark, plus a
  systematic part for a ground vehicle's body roll in turns (levelled INS rates, as
  KITTI's, do not roll with the camera: on a drive whose turns go mostly one way the
  roll looks like a rotation about the forward axis). It is reported (WARN) above 2°
  when significant at 99 % in its own covariance (chi-square, 3 dof).
* **IMU-camera translation** (the lever arm, :func:`_imu_camera_translation`): the same
  robust fit for cam_T_imu's translation with the rotation, in the plane perpendicular to
  the vehicle's yaw axis (the translation is seen through rotation, and a ground vehicle
  turns about that axis only: the component along it is not observed), the velocities
  averaged over ``translation_smoothing_s`` first when the IMU is noisy. The recorded
  translation is tested against the swapped one (:func:`swapped_translation`: imu_T_cam's
  translation stored as cam_T_imu's) by a paired comparison of their costs over
  landmarks, and against the free estimate: ERROR when the swapped one fits better
  (z >= 3) and lies nearer the free estimate, WARN when the free estimate is further
  than ``translation_warn_m`` and significant at 99 %, WARN also when the tracks cannot
  tell the two conventions apart (z above −``translation_decided_z``).
* **Velocity association** (which sample describes the interval k -> k+1: sample k+1,
  "next", or k, "current", or further off) and a **camera-IMU time offset**: the
  candidate with the smallest robust reprojection cost; the time offset is refined on a
  grid of ±1 frame around it with a parabola (the velocities shifted by a Fourier phase
  shift, which keeps their white noise white: linear interpolation would smooth it and
  favour half-frame offsets), its uncertainty from a bootstrap over landmarks plus a
  systematic floor. ``time_offset_s`` is relative to the chosen association;
  ``time_offset_effective_s`` relative to "next".
* **Roll/pitch-rate means**: for a ground vehicle the roll and pitch rates average to
  ~0 over a drive (a car ends as level as it started); a mean beyond what the noise and
  a 3° change of attitude over the drive explain is a gyro bias.
* **Pixel noise and gross outliers** of the tracks (:func:`estimate_pixel_noise`): third
  differences along tracks for σ, peaks of second differences for outliers.
* What ``vislam info`` reports: exact repeats and non-positive disparities.

Everything is pure computation (no I/O, no printing); the CLI (``vislam check``) prints
the verdict and writes check.json and suggested.yaml.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from vislam.core.corrections import apply_corrections
from vislam.core.lie import se3_exp, se3_inverse, so3_exp
from vislam.core.options import FilterOptions
from vislam.core.results import JOB_LIMITS, frozen_stretch
from vislam.core.rigs import match_known_rig, swapped_translation
from vislam.core.sequence import (CAMERA_FRAME_INTERVAL_S, Sequence, StereoObservations, imu_dropouts,
                                  imu_samples_beyond_limits, imu_spikes,
                                  timestamp_unit_guess)

__all__ = ["CheckOptions", "Finding", "CheckResult", "Analysis", "ANALYSES", "check_sequence", "estimate_white_noise",
           "estimate_pixel_noise",
           "stereo_depths", "stereo_depth_finding",
           "in_sync_mask", "usable_observations",
           "SEVERITIES",
           "FINDING_CODES"]

logger = logging.getLogger(__name__)

SEVERITIES = ("OK", "WARN", "ERROR")
#: Stable codes of the findings, in the order they are reported.
FINDING_CODES = ("timestamps", "imu-samples", "imu-camera-rotation", "imu-camera-translation", "velocity-association",
                 "velocity-scale", "time-offset", "imu-bias", "noise", "pixel-noise", "reprojection", "repeated-observations", "disparity",
                 "stereo-rows", "stereo-depth", "duplicate-observations")


@dataclass(frozen=True)
class CheckOptions:
    """Thresholds and sizes of the analyses (defaults suit 10 Hz KITTI-like recordings)."""

    #: Predict each observation this many frames ahead (1..window).
    window: int = 3
    #: At most this many prediction pairs enter the rotation/bias fit (a random subset).
    max_pairs: int = 40000
    #: Landmarks farther than this (m) are not used (their depth is too uncertain).
    max_depth_m: float = 40.0
    #: Scale (px) of the Cauchy loss on the reprojection residuals.
    loss_scale_px: float = 2.0
    #: A landmark whose predictions reproject with a median above this (px), and above 4x
    #: the first quartile of the landmarks' medians, does not follow the world's motion
    #: (a vehicle in traffic, a mismatched track): it is left out of the rotation,
    #: association and time-offset fits. On sparse 0042 (a highway with traffic alongside)
    #: 19 of 44 landmarks, 70 % of the predictions (median 42 px, 2.0 px without them); on
    #: the other shared files 0-4 % of the landmarks. None: keep every landmark.
    moving_landmark_px: float | None = 12.0
    #: A camera's frame interval (s, median): outside it the timestamps' unit is suspect.
    frame_interval_s: tuple[float, float] = CAMERA_FRAME_INTERVAL_S
    #: Predictions (a random subset) scored for each start of the fit (rotation x factor).
    start_pairs: int = 5000
    #: Factors on the linear velocities searched (a unit mistake: km/h stored as m/s is
    #: 3.6, mph 2.24); () searches none, the velocities are taken as metric.
    velocity_scale_range: tuple[float, float] = (0.2, 5.0)
    #: A factor further than this from 1 (and beyond 3σ) is reported and corrected.
    velocity_scale_warn: float = 0.05
    #: Shares of the observations with non-positive disparity (and of those whose rows
    #: differ beyond the filter's row guard) above which the disparity (stereo-rows)
    #: finding is a WARN and an ERROR. The shared files have 0-0.3 %, sparse 0042 (a
    #: highway: far points) 6.5 % (rows: 0 %); exchanged left and right pixels, 100 %.
    disparity_warn_share: float = 0.2
    disparity_error_share: float = 0.5
    #: Shares of the triangulated depths within the filter's depth guards below which the
    #: stereo-depth finding is a WARN and an ERROR. The shared files: 95-99.6 %, sparse
    #: 0042 76 %; a baseline in millimetres, 0 %.
    depth_warn_share: float = 0.5
    depth_error_share: float = 0.1
    #: Systematic uncertainty of the factor, added in quadrature: the KITTI files' speeds
    #: are off the true motion by 1 % on average and 0.3 m/s RMS, slowly varying
    #: (benchmarks/velocity_truth.py).
    velocity_scale_floor: float = 0.01
    #: IMU-camera rotation errors above this angle (deg) are an axis-convention mismatch (ERROR).
    rotation_error_deg: float = 10.0
    #: ... and above this one (and significant at 99 %) a calibration error worth correcting (WARN).
    rotation_warn_deg: float = 2.0
    #: Systematic uncertainty of the rotation estimate (deg), added in quadrature to the
    #: statistical one: on the reference KITTI files the velocities and the images
    #: disagree by 1-3° even where the calibration is right (ground truth poses agree
    #: with cam_T_imu to 0.3°), so smaller angles are not actionable.
    rotation_floor_deg: float = 0.5
    #: Gyro biases above this (rad/s, and 3σ) are reported and corrected.
    bias_warn_radps: float = 0.002
    #: Time offsets above this (s, and 3σ) are reported and corrected.
    time_offset_warn_s: float = 0.03
    #: Systematic uncertainty of the time offset (s), added in quadrature: on dense and
    #: sparse 0027 (the same drive) the estimates differ by 20 ms, and applying dense
    #: 0027's -45 ms makes its SLAM ATE worse (4.67 -> 4.86 m).
    time_offset_floor_s: float = 0.02
    #: When the tracks still reproject with a larger median (px) under the best rotation
    #: and association, the IMU and images disagree beyond what check models: rotation,
    #: association and time offset are not reported (far or mismatched features).
    max_fit_median_px: float = 12.0
    #: Velocity noise is reported when this many times the filter's default on some axis.
    noise_factor_warn: float = 3.0
    #: Also fit a gyro bias together with the IMU-camera rotation (recorded as
    #: ``gyro_bias_visual_radps``, for information: it absorbs other model errors).
    fit_gyro_bias: bool = False
    #: Prior 1σ (deg per m/s² of lateral acceleration) of the vehicle's body roll in
    #: turns (passenger cars roll 0.3-0.8 outward), a nuisance for the rotation fit when the rates
    #: are levelled (see roll_tilted): on a drive whose turns go mostly one way it looks
    #: like a rotation error about the forward axis, so the rotation's uncertainty
    #: includes what this much roll would change (``body_roll_sensitivity_deg``). 0: off.
    roll_gradient_prior_deg_per_mps2: float = 0.3
    #: IMU-camera translation (lever arm): a free estimate further than this (m) from the
    #: recorded translation, in the plane the data sees (perpendicular to the vehicle's
    #: yaw axis), and significant at 99 %, is reported. Smaller errors barely move the
    #: camera: 0.3 m at a yaw rate of 0.3 rad/s is 0.09 m/s.
    translation_warn_m: float = 0.3
    #: Systematic uncertainty of the translation estimate (m, per axis of that plane),
    #: added in quadrature to the statistical one.
    translation_floor_m: float = 0.1
    #: With white IMU noise beyond the filter's (finding ``noise``), the velocities enter
    #: the translation fit averaged over this many seconds (centred): the lever arm is
    #: seen through the angular rates, and noise in them pulls the estimate (errors in
    #: variables: the noise the rates add to the predicted camera motion, ω_noise × t,
    #: is smallest for a translation along the optical axis, which the fit then prefers).
    #: A ground vehicle's motion is smooth on that scale. Measured on the dense files
    #: (0.05 rad/s white noise): raw rates prefer the recorded translation on dense 0027
    #: (z = −5.9), 0.9 s leaves dense 0034 undecided, 1.5 s and 2.5 s find the swapped
    #: one on all three (z = 15.2, 15.0, 5.4 at 1.5 s).
    translation_smoothing_s: float = 1.5
    #: At most this many prediction pairs enter the translation fits (a random subset).
    translation_pairs: int = 15000
    #: The recorded translation is verified only when the tracks prefer it to the swapped
    #: convention by at least this z (paired over landmarks); below it, and with the two
    #: more than ``translation_warn_m`` apart, the recording cannot tell them apart and the
    #: check says so (WARN). Sparse 0042 (25 landmarks that follow the world's motion):
    #: z = −1.4; the simulator's noisy 400-frame drive −1.7, 800 frames −2.9, clean −7 to −10.
    translation_decided_z: float = 2.0
    #: Seed of the random subsets and bootstraps.
    seed: int = 0


@dataclass(frozen=True)
class Finding:
    code: str
    severity: str
    message: str

    def to_dict(self) -> dict[str, str]:
        return {"code": self.code, "severity": self.severity, "message": self.message}


@dataclass
class CheckResult:
    """Everything :func:`check_sequence` found. ``estimates`` is JSON-ready (lists, floats,
    None); ``suggested`` maps FilterOptions fields to values (only those that differ from
    the defaults)."""

    name: str
    source: str
    estimates: dict[str, Any]
    findings: list[Finding]
    suggested: dict[str, Any]
    elapsed_s: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def worst_severity(self) -> str:
        return max((f.severity for f in self.findings), key=SEVERITIES.index, default="OK")

    def finding(self, code: str) -> Finding | None:
        return next((f for f in self.findings if f.code == code), None)

    def suggested_options(self, base: FilterOptions | None = None) -> FilterOptions:
        base = base or FilterOptions()
        return FilterOptions.from_dict({**base.to_dict(), **self.suggested}, source="check suggestions")

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "source": self.source, **self.estimates,
                "findings": [f.to_dict() for f in self.findings], "suggested_options": self.suggested,
                "elapsed_s": self.elapsed_s, "notes": list(self.notes)}


# ----------------------------------------------------------------------------- tracks


def in_sync_mask(obs: StereoObservations, repeated: np.ndarray | None = None) -> np.ndarray:
    """(N,) True for the observations of a track before its first repeat (``repeated``,
    default ``obs.repeated_mask()``)."""
    n = obs.n_observations
    out = np.ones(n, dtype=bool)
    if n < 2:
        return out
    rep = obs.repeated_mask() if repeated is None else repeated
    order = np.lexsort((obs.frame_index, obs.landmark_ids))
    ids = obs.landmark_ids[order]
    c = np.cumsum(rep[order])
    start = np.r_[True, ids[1:] != ids[:-1]]
    before = np.where(start, np.r_[0, c[:-1]], 0)
    base = np.maximum.accumulate(before)  # repeats counted before each landmark's first row
    out[order] = (c - base) == 0
    return out


def describe_repeat_evidence(evidence: Mapping[str, int]) -> str:
    """One phrase for :meth:`StereoObservations.repeat_evidence`'s counts (check, info)."""
    parts = []
    if evidence.get("frames_fractional"):
        parts.append(f"{evidence['frames_fractional']} frames of bit-identical sub-pixel values")
    if evidence.get("frames_new_tracks"):
        parts.append(f"{evidence['frames_new_tracks']} frames of integer pixels where every continuing track "
                     f"repeats as new tracks start")
    if evidence.get("frames_odometry"):
        parts.append(f"{evidence['frames_odometry']} frames of integer pixels where every continuing track repeats "
                     f"while the odometry moves them")
    text = "evidence: " + ("; ".join(parts) if parts else "none")
    if evidence.get("integer_coincidences"):
        text += (f"; {evidence['integer_coincidences']} other bit-identical integer observations are coincidences "
                 f"of the quantization (not counted)")
    return text


def usable_observations(sequence: Sequence, min_disparity_px: float = 1.0, max_row_difference_px: float = 3.0,
                        max_depth_m: float = 60.0) -> np.ndarray:
    """(N,) in-sync observations with a disparity and row agreement good for triangulation."""
    obs = sequence.observations
    px = obs.pixels
    disparity = px[:, 0] - px[:, 2]
    depth = np.divide(sequence.camera.fsu * sequence.camera.baseline_m, disparity,
                      out=np.full(disparity.shape, np.inf), where=disparity > 0)
    return (in_sync_mask(obs, sequence.repeated_mask()) & (disparity >= min_disparity_px)
            & (np.abs(px[:, 1] - px[:, 3]) <= max_row_difference_px)
            & (depth <= max_depth_m))


# ----------------------------------------------------------------------------- noise


def _nugget(u: np.ndarray, max_lag: int = 6) -> np.ndarray:
    """(k,) variance nugget of each column of (T, k) ``u``: quadratic fit of γ(1..max_lag) at h=0."""
    g = np.array([0.5 * np.mean((u[h:] - u[:-h]) ** 2, axis=0) for h in range(1, max_lag + 1)])
    hs = np.arange(1, max_lag + 1, dtype=np.float64)
    A = np.column_stack([np.ones_like(hs), hs, hs * hs])
    coef = np.linalg.lstsq(A, g, rcond=None)[0]
    return coef[0]


def estimate_white_noise(u: np.ndarray, n_blocks: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """White-noise σ of each column of the (T, k) signal ``u`` and its standard error.

    σ² is the variogram nugget (see the module docstring), clipped at 0; the standard
    error comes from the spread of the nuggets of ``n_blocks`` contiguous blocks.
    """
    u = np.asarray(u, dtype=np.float64)
    T = u.shape[0]
    if T < 20:
        return np.full(u.shape[1], np.nan), np.full(u.shape[1], np.nan)
    var = _nugget(u)
    blocks = [b for b in np.array_split(u, n_blocks) if b.shape[0] >= 20] if T >= 20 * n_blocks else []
    sigma = np.sqrt(np.maximum(var, 0.0))
    if len(blocks) >= 3:
        v = np.array([_nugget(b) for b in blocks])
        var_se = np.std(v, axis=0, ddof=1) / math.sqrt(len(blocks))
    else:
        var_se = np.full(u.shape[1], np.nan)
    # σ = √var: δσ ≈ δvar / (2σ); near zero, √δvar bounds it
    sigma_se = np.where(sigma > np.sqrt(var_se), var_se / (2 * np.maximum(sigma, 1e-300)), np.sqrt(var_se))
    return sigma, sigma_se


# ----------------------------------------------------------------------------- reprojection


class _TrackPairs:
    """Pairs (observation at k, same landmark at k+j, 1 <= j <= window), both in sync and
    triangulable; the point triangulated at k is predicted at k+j with IMU motion."""

    def __init__(self, sequence: Sequence, window: int, max_depth_m: float, max_pairs: int | None, rng):
        obs = sequence.observations
        ok = usable_observations(sequence, max_depth_m=max_depth_m)
        rows = np.nonzero(ok)[0]
        lm = obs.landmark_ids[rows]
        fr = obs.frame_index[rows]
        order = np.lexsort((fr, lm))
        rows, lm, fr = rows[order], lm[order], fr[order]
        first, second, lag = [], [], []
        for s in range(1, window + 1):
            same = (lm[s:] == lm[:-s]) & (fr[s:] - fr[:-s] <= window)
            first.append(rows[:-s][same])
            second.append(rows[s:][same])
            lag.append(fr[s:][same] - fr[:-s][same])
        first = np.concatenate(first)
        second = np.concatenate(second)
        lag = np.concatenate(lag)
        keep = lag >= 1
        first, second, lag = first[keep], second[keep], lag[keep]
        # de-duplicate (a lag can be reached by several s when frames are missing)
        key = first * (window + 1) + lag
        _, uniq = np.unique(key, return_index=True)
        first, second, lag = first[uniq], second[uniq], lag[uniq]
        if max_pairs is not None and first.size > max_pairs:
            pick = np.sort(rng.choice(first.size, size=max_pairs, replace=False))
            first, second, lag = first[pick], second[pick], lag[pick]
        self.frame = obs.frame_index[first]
        self.lag = lag
        self.landmark = obs.landmark_ids[first]
        self.points = sequence.camera.triangulate(obs.pixels[first]) if first.size else np.zeros((0, 3))
        self.target = obs.pixels[second]
        self.camera = sequence.camera
        self.window = window
        self.n_frames = sequence.n_frames
        self._inverse_cache = None  # see _relative_inverse
        self._groups = None  # see landmark_medians

    @property
    def n_pairs(self) -> int:
        return int(self.frame.shape[0])

    @property
    def n_clusters(self) -> int:
        """The blocks of frames the fits' sandwich covariance sums its scores over
        (:func:`_sandwich_covariance`)."""
        return int(np.unique(self.frame // (2 * self.window + 1)).size)

    def subset(self, max_pairs: int, rng) -> "_TrackPairs":
        """At most ``max_pairs`` of the pairs, chosen at random (self if there are fewer)."""
        if self.n_pairs <= max_pairs:
            return self
        keep = np.zeros(self.n_pairs, dtype=bool)
        keep[rng.choice(self.n_pairs, size=max_pairs, replace=False)] = True
        return self.select(keep)

    def select(self, keep: np.ndarray) -> "_TrackPairs":
        """The pairs where ``keep`` (boolean, one per pair) is true."""
        import copy

        out = copy.copy(self)
        for name in ("frame", "lag", "landmark", "points", "target"):
            setattr(out, name, getattr(self, name)[keep])
        out._inverse_cache = out._groups = None
        return out

    def relative_imu(self, timestamps: np.ndarray, u: np.ndarray, shift: int = 1) -> np.ndarray:
        """(T, window+1, 4, 4) imu_k_T_imu_{k+j}: sample k+shift describes k -> k+1."""
        T = self.n_frames
        tau = np.diff(timestamps)
        idx = np.clip(np.arange(T - 1) + shift, 0, T - 1)
        steps = se3_exp(tau[:, None] * u[idx])  # (T-1, 4, 4) imu_k_T_imu_{k+1}
        out = np.broadcast_to(np.eye(4), (T, self.window + 1, 4, 4)).copy()
        for j in range(1, min(self.window, T - 1) + 1):
            # out[k, j] = out[k, j-1] @ steps[k + j - 1] for k < T - j
            out[:T - j, j] = out[:T - j, j - 1] @ steps[j - 1:T - 1]
        return out

    @property
    def groups(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:func:`_landmark_groups` of the pairs' landmarks (ids, each pair's index into
        them, ...), made once."""
        if self._groups is None:
            self._groups = _landmark_groups(self.landmark)
        return self._groups

    def landmark_medians(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`_group_medians` of ``d`` (one value per pair) over the pairs' landmarks."""
        return _group_medians(self.groups, d)

    def landmark_inliers(self, d: np.ndarray, px: float) -> int:
        """How many landmarks reproject with a median left distance within ``px``."""
        return int(np.count_nonzero(self.landmark_medians(d)[1] <= px))

    def _relative_inverse(self, rel_imu: np.ndarray) -> tuple[np.ndarray, bool]:
        """(inv(imu_k_T_imu_{k+j}), gathered): at the pairs' (k, j) when there are fewer
        pairs than (k, j) cells (gathered), else at every cell. Kept for the next call with
        the same ``rel_imu``, which callers do not change in place (a fit that varies only
        cam_T_imu calls with one array; the reference held keeps its id from being reused)."""
        cached = self._inverse_cache
        if cached is None or cached[0] is not rel_imu:
            gathered = self.n_pairs < rel_imu.shape[0] * rel_imu.shape[1]
            inv = se3_inverse(rel_imu[self.frame, self.lag] if gathered else rel_imu)
            cached = self._inverse_cache = (rel_imu, inv, gathered)
        return cached[1], cached[2]

    def residuals(self, rel_imu: np.ndarray, cam_T_imu: np.ndarray) -> np.ndarray:
        """(P, 4) stereo reprojection residuals (px) of the predictions."""
        imu_T_cam = se3_inverse(cam_T_imu)
        inv_rel, gathered = self._relative_inverse(rel_imu)
        # cam_{k+j}_T_cam_k = cam_T_imu @ inv(imu_k_T_imu_{k+j}) @ imu_T_cam, for every (k, j)
        G = cam_T_imu @ inv_rel @ imu_T_cam
        if not gathered:
            G = G[self.frame, self.lag]
        q = np.matmul(G[:, :3, :3], self.points[:, :, None])[:, :, 0] + G[:, :3, 3]
        c = self.camera
        z = np.maximum(q[:, 2], 0.1)
        uL = c.fsu * q[:, 0] / z + c.cu
        vL = c.fsv * q[:, 1] / z + c.cv
        r = np.empty((q.shape[0], 4))
        r[:, 0] = uL - self.target[:, 0]
        r[:, 1] = vL - self.target[:, 1]
        r[:, 2] = uL - c.fsu * c.baseline_m / z - self.target[:, 2]
        r[:, 3] = vL - self.target[:, 3]
        r[q[:, 2] < 0.1] = 1e3  # behind the camera: a gross misfit
        return r


def _cauchy_cost(r: np.ndarray, scale: float) -> np.ndarray:
    """Per-pair Cauchy cost of (P, 4) residuals."""
    return np.sum(np.log1p((r / scale) ** 2), axis=1)


def _landmark_groups(landmark: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(ids, index of each entry's landmark, the two middle positions of each landmark's
    entries once sorted by landmark)."""
    lms, inv = np.unique(landmark, return_inverse=True)
    counts = np.bincount(inv, minlength=lms.size)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if lms.size else counts
    return lms, inv, starts + (counts - 1) // 2, starts + counts // 2


def _group_medians(groups, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ids, median of ``d`` per landmark, index of each entry's landmark) for the
    :func:`_landmark_groups` of the entries' landmarks."""
    lms, inv, lo, hi = groups
    if lms.size == 0:
        return lms, np.zeros(0), inv
    d_sorted = d[np.lexsort((d, inv))]  # by landmark, then value
    return lms, 0.5 * (d_sorted[lo] + d_sorted[hi]), inv


def _left_distance(r: np.ndarray) -> np.ndarray:
    return np.hypot(r[:, 0], r[:, 1])


def _percentiles(d: np.ndarray) -> dict[str, float | None]:
    if d.size == 0:
        return {"median": None, "p90": None}
    return {"median": float(np.median(d)), "p90": float(np.percentile(d, 90))}


def level_velocities_to_body(u: np.ndarray, half_window: int = 25) -> np.ndarray:
    """The (T, 6) twists with levelled linear velocities (x forward, z up; see
    FilterOptions.velocity_frame) turned into a ground vehicle's body frame without an
    attitude estimate: a car moves along its body x axis, so its pitch is the grade the
    velocities show, θ = atan2(v_z, v_x) (averaged over ±``half_window`` samples against
    white noise); v_body = Ry(θ) v_level. Roll, which barely moves a car sideways, is
    not undone."""
    k = 2 * half_window + 1
    kernel = np.ones(k) / k
    pad = np.pad(u[:, [0, 2]], ((half_window, half_window), (0, 0)), mode="edge")
    vx = np.convolve(pad[:, 0], kernel, mode="valid")
    vz = np.convolve(pad[:, 1], kernel, mode="valid")
    # a road's grade: at most 15°, and none while (nearly) standing
    theta = np.where(np.abs(vx) > 1.0, np.clip(np.arctan(vz / np.where(vx == 0, 1.0, vx)), -0.26, 0.26), 0.0)
    c, s = np.cos(theta), np.sin(theta)
    out = u.copy()
    out[:, 0] = c * u[:, 0] + s * u[:, 2]
    out[:, 2] = -s * u[:, 0] + c * u[:, 2]
    return out


def vehicle_axes(u: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(forward, up) unit axes of a ground vehicle in the velocities' frame: the mean
    direction of travel and the principal axis of the angular velocity (yaw), made
    orthogonal. None when the recording barely moves or turns."""
    v, w = u[:, :3], u[:, 3:]
    moving = np.linalg.norm(v, axis=1) > 1.0
    if np.count_nonzero(moving) < 10:
        return None
    fwd = np.mean(v[moving], axis=0)
    if np.linalg.norm(fwd) < 0.5:
        return None
    fwd /= np.linalg.norm(fwd)
    _, evecs = np.linalg.eigh(np.cov(w.T))
    up = evecs[:, -1] - fwd * (evecs[:, -1] @ fwd)
    if np.linalg.norm(up) < 0.5:
        return None
    return fwd, up / np.linalg.norm(up)


def roll_tilted(u: np.ndarray, gain: float, axes) -> np.ndarray:
    """The velocities with the angular rates turned about the forward axis by
    ``gain`` (rad per m/s²) times the lateral acceleration |v|·ω_up of each sample —
    the body roll in turns that a gravity-levelled rate frame (e.g. an INS's
    forward/left/up rates, as in KITTI's OXTS) does not share with the body-fixed
    camera. First order in the (≤ 2°) angle."""
    if axes is None or gain == 0.0:
        return u
    fwd, up = axes
    a_lat = np.linalg.norm(u[:, :3], axis=1) * (u[:, 3:] @ up)  # (T,) m/s²
    tilt = (gain * a_lat)[:, None] * fwd  # (T, 3) rotation vectors
    out = u.copy()
    out[:, 3:] = u[:, 3:] + np.cross(tilt, u[:, 3:])  # ω' = exp(tilt) ω ≈ ω + tilt × ω
    return out


def _turned(cam_T_imu: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """cam_T_imu with its rotation turned by exp(φ) on the camera side (φ in rad; a
    copy): the candidate calibrations of the fits."""
    C = cam_T_imu.copy()
    C[:3, :3] = so3_exp(phi) @ cam_T_imu[:3, :3]
    return C


def _scaled(u: np.ndarray, factor: float) -> np.ndarray:
    """The (T, 6) twists with the linear velocities times ``factor`` (a copy)."""
    out = u.copy()
    out[:, :3] *= factor
    return out


def _debiased(u: np.ndarray, gyro_bias) -> np.ndarray:
    """The (T, 6) twists with ``gyro_bias`` (3,) subtracted from the angular velocities (a copy)."""
    out = u.copy()
    out[:, 3:] -= gyro_bias
    return out


def _fit_rotation_and_bias(pairs: _TrackPairs, timestamps, u, cam_T_imu, shift: int, scale: float,
                           phi0: np.ndarray, fit_bias: bool = True, fit_scale: bool = False,
                           log_scale0: float = 0.0):
    """Least squares (Cauchy loss) over φ (camera-frame rotation vector, rad), with
    ``fit_bias`` the gyro bias b, and with ``fit_scale`` the log of a factor on the
    linear velocities (started at ``log_scale0``; held there otherwise). Returns
    (x (6,), cov (6, 6), cost, (log scale, its variance)); without the bias its entries
    are 0 and its covariance NaN, without the scale its variance is NaN."""
    from scipy.optimize import least_squares

    n_rb = 6 if fit_bias else 3

    def fun(x):
        ub = u.copy()
        if fit_bias:
            ub[:, 3:] -= x[3:6]
        ub[:, :3] *= math.exp(x[n_rb] if fit_scale else log_scale0)
        rel = pairs.relative_imu(timestamps, ub, shift)
        return pairs.residuals(rel, _turned(cam_T_imu, x[:3])).ravel()

    x0 = np.concatenate([phi0, np.zeros(3)])[:n_rb]
    x_scale = np.array([0.01] * 3 + [0.001] * 3)[:n_rb]
    if fit_scale:
        x0, x_scale = np.append(x0, log_scale0), np.append(x_scale, 0.01)
    sol = least_squares(fun, x0, loss="cauchy", f_scale=scale, x_scale=x_scale, diff_step=1e-4, max_nfev=40)
    r = sol.fun.reshape(-1, 4)
    cov_fit = _sandwich_covariance(pairs, sol, scale)
    x = np.zeros(6)
    x[:n_rb] = sol.x[:n_rb]
    cov = np.full((6, 6), np.nan)
    cov[:n_rb, :n_rb] = cov_fit[:n_rb, :n_rb]
    log_s = (float(sol.x[n_rb]), float(cov_fit[n_rb, n_rb])) if fit_scale else (float(log_scale0), float("nan"))
    return x, cov, float(np.sum(_cauchy_cost(r, scale))), log_s


def _sandwich_covariance(pairs: _TrackPairs, sol, scale: float) -> np.ndarray:
    """Covariance of a robust (Cauchy, ``scale`` px) least-squares fit over ``pairs``
    (``sol`` from scipy's least_squares, residuals (P, 4) raveled): a sandwich with the
    IRLS weights at the solution, the scores summed over blocks of frames first, because
    predictions that start in nearby frames share the same velocity samples, so their
    errors are correlated. NaN where the information matrix is singular."""
    J = sol.jac
    r = sol.fun.reshape(-1, 4)
    w = np.repeat(1.0 / (1.0 + (np.linalg.norm(r, axis=1) / scale) ** 2), 4)
    H = J.T @ (w[:, None] * J)
    scores = J * (w * sol.fun)[:, None]  # (4P, n_par)
    group = np.repeat(pairs.frame // (2 * pairs.window + 1), 4)
    _, inv = np.unique(group, return_inverse=True)
    g = np.zeros((inv.max() + 1, J.shape[1]))
    np.add.at(g, inv, scores)
    try:
        Hinv = np.linalg.inv(H)
        return Hinv @ (g.T @ g) @ Hinv
    except np.linalg.LinAlgError:
        return np.full((J.shape[1], J.shape[1]), np.nan)


def _moving_landmarks(pairs: _TrackPairs, timestamps, u, cam_T_imu, phi: np.ndarray,
                      threshold_px: float | None) -> dict[str, Any]:
    """The landmarks whose predictions (rotation ``phi``, association "next") reproject
    with a median left-image distance above ``threshold_px`` and above 4x the first
    quartile of the landmarks' medians (see CheckOptions.moving_landmark_px)."""
    lms = pairs.groups[0]
    out: dict[str, Any] = {"landmarks": 0, "of_landmarks": int(lms.size), "predictions_share": 0.0,
                           "landmark_ids": []}
    if threshold_px is None or lms.size == 0:
        return out
    d = _left_distance(pairs.residuals(pairs.relative_imu(timestamps, u, 1), _turned(cam_T_imu, phi)))
    lms, med, inv = pairs.landmark_medians(d)
    bad = med > max(float(threshold_px), 4.0 * float(np.percentile(med, 25)))
    out.update(landmarks=int(bad.sum()), predictions_share=float(np.mean(bad[inv])),
               landmark_ids=lms[bad].tolist())
    return out


def _with_translation(cam_T_imu: np.ndarray, t_cam: np.ndarray) -> np.ndarray:
    """cam_T_imu with its translation replaced by ``t_cam`` (camera frame, m; a copy)."""
    C = np.array(cam_T_imu, dtype=np.float64)
    C[:3, 3] = t_cam
    return C


def _smoothed(u: np.ndarray, k: int) -> np.ndarray:
    """The (T, 6) twists averaged over ``k`` samples (centred, ends held)."""
    if k <= 1:
        return u
    from scipy.ndimage import uniform_filter1d

    return uniform_filter1d(u, size=k, axis=0, mode="nearest")


def _fit_translation(pairs: _TrackPairs, rel: np.ndarray, cam_T_imu: np.ndarray, phi0: np.ndarray,
                     plane: np.ndarray | None, scale: float):
    """Robust fit of the camera-frame rotation correction φ with (``plane`` (3, 2), an
    orthonormal basis) a translation change δ in that plane: cam_T_imu's translation
    becomes t + plane δ. Returns (φ, δ, cov of δ (2, 2), per-pair Cauchy costs); without
    a plane only φ is fitted (δ and its covariance empty)."""
    from scipy.optimize import least_squares

    t0 = np.asarray(cam_T_imu, dtype=np.float64)[:3, 3]
    n_d = 0 if plane is None else plane.shape[1]

    def candidate(x):
        C = _turned(cam_T_imu, x[:3])
        if n_d:
            C[:3, 3] = t0 + plane @ x[3:]
        return C

    sol = least_squares(lambda x: pairs.residuals(rel, candidate(x)).ravel(), np.concatenate([phi0, np.zeros(n_d)]),
                        loss="cauchy", f_scale=scale, x_scale=np.array([0.01] * 3 + [0.1] * n_d), diff_step=1e-4,
                        max_nfev=40)
    cost = _cauchy_cost(sol.fun.reshape(-1, 4), scale)
    cov = _sandwich_covariance(pairs, sol, scale)[3:, 3:] if n_d else np.zeros((0, 0))
    return sol.x[:3], sol.x[3:], cov, cost


def _suggested_cam_T_imu(C0: np.ndarray, t_cam: np.ndarray) -> list:
    """``suggested.yaml``'s cam_T_imu: ``C0`` with its translation replaced by ``t_cam``, as 4 rows."""
    return [list(map(float, row)) for row in _with_translation(C0, t_cam)]


def _swapped_rig(est: dict[str, Any], rig, C0: np.ndarray, se3d, evidence: str) -> tuple[dict[str, Any], Finding, Any]:
    """The ERROR for a cam_T_imu whose rotation is a published calibration's
    (:func:`vislam.core.rigs.match_known_rig`) and whose translation is that calibration's
    imu_T_cam translation; ``evidence`` says what the tracks show."""
    t_stored, t_swapped = C0[:3, 3], swapped_translation(C0)
    est["imu_camera_translation_m"] = t_swapped.tolist()
    est["imu_camera_translation_m_se"] = se3d
    return est, Finding(
        "imu-camera-translation", "ERROR",
        f"cam_T_imu's rotation is the published {rig.name} calibration and its translation {_fmt_vec(t_stored, '.3f')} m "
        f"is that calibration's imu_T_cam translation (the camera's position in the IMU frame): cam_T_imu's "
        f"translation is {_fmt_vec(t_swapped, '.3f')} m ({evidence}); run with the suggested cam_T_imu"), \
        _suggested_cam_T_imu(C0, t_swapped)


@dataclass
class _TranslationEvidence:
    """What the tracks say of cam_T_imu's translation (see :func:`_translation_evidence`)."""

    t_free: np.ndarray  # the free estimate (camera frame, m), its unobserved component filled in
    se3d: list  # its standard error per camera axis, None along the yaw axis
    se_txt: str  # the same, for messages
    plane: np.ndarray  # (3, 2) orthonormal basis of the observed plane
    z_swap: float  # paired z of swapped vs recorded (> 0: the swapped one fits better)
    d_stored: float  # distance (m, in the plane) of the free estimate from the recorded translation
    chi_stored: float  # ... as a chi-square (2 dof) in the free estimate's covariance
    d_swapped: float  # distance (m, in the plane) from the swapped translation


def _imu_camera_translation(pairs: _TrackPairs, timestamps, u, cam_T_imu, phi, gyro_bias, shift: int, scale: float,
                            smoothing_frames: int, opts: CheckOptions) -> tuple[dict[str, Any], Finding, Any]:
    """Hand-eye estimate of cam_T_imu's translation through the images (see
    :func:`check_sequence`). Returns (estimates, the finding, the suggested cam_T_imu as
    4 rows or None)."""
    C0 = np.asarray(cam_T_imu, dtype=np.float64)
    t_stored = C0[:3, 3].copy()
    t_swapped = swapped_translation(C0)
    ub = _smoothed(_debiased(u, gyro_bias), smoothing_frames)
    est: dict[str, Any] = {"imu_camera_translation_m": None, "imu_camera_translation_m_se": None,
                           "imu_camera_translation_stored_m": t_stored.tolist(),
                           "imu_camera_translation_swapped_m": t_swapped.tolist(),
                           "imu_camera_translation_smoothing_frames": int(smoothing_frames)}
    rig = match_known_rig(C0)
    est["imu_camera_translation_known_rig"] = None if rig is None else rig.name
    axes = vehicle_axes(ub)
    if axes is None and rig is not None and rig.translation == "swapped":
        return _swapped_rig(est, rig, C0, None, "the recording barely turns: the tracks cannot see the translation")
    if axes is None:
        return est, Finding("imu-camera-translation", "OK",
                            "the recording barely moves or turns: the IMU-camera translation is not observable "
                            "(it is seen through turns); the recorded one is assumed"), None
    ev = _translation_evidence(pairs, pairs.relative_imu(timestamps, ub, shift), C0, phi, axes, scale, opts, est)
    if rig is not None and rig.translation == "swapped":
        tracks = ("agree" if ev.z_swap >= 3.0 else "cannot tell the two apart" if ev.z_swap > -3.0
                  else "prefer the recorded one")
        return _swapped_rig(est, rig, C0, ev.se3d, f"the tracks {tracks}: z = {ev.z_swap:.1f}; free estimate "
                                                    f"{_fmt_vec(ev.t_free, '.2f')} {ev.se_txt}")
    return _translation_finding(est, ev, rig, C0, int(pairs.groups[0].size), opts)


def _translation_evidence(pairs: _TrackPairs, rel: np.ndarray, C0: np.ndarray, phi, axes, scale: float,
                          opts: CheckOptions, est: dict[str, Any]) -> _TranslationEvidence:
    """The free fit of the translation in the plane perpendicular to the yaw axis and the
    paired test of the two recorded conventions; records them in ``est``."""
    t_stored, t_swapped = C0[:3, 3], swapped_translation(C0)
    # The translation is seen through rotation, (R_rel − I) t: a ground vehicle turns
    # about its yaw axis only, so the component along that axis is not observed.
    up_cam = _turned(C0, phi)[:3, :3] @ axes[1]
    e1 = np.cross(up_cam, [0.0, 0.0, 1.0]) if abs(up_cam[2]) < 0.9 else np.cross(up_cam, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    plane = np.column_stack([e1, np.cross(up_cam, e1)])
    _, delta, cov, cost_free = _fit_translation(pairs, rel, C0, phi, plane, scale)
    t_free = t_stored + plane @ delta
    cov_p = cov + opts.translation_floor_m ** 2 * np.eye(2)
    # per camera axis; None for the axis along the yaw axis (not observed)
    se3d = [None if abs(up_cam[i]) > 0.7 else float(v)
            for i, v in enumerate(np.sqrt(np.clip(np.diag(plane @ cov_p @ plane.T), 0, None)))]
    # the two recorded conventions, each with its rotation refitted
    _, _, _, cost_stored = _fit_translation(pairs, rel, C0, phi, None, scale)
    _, _, _, cost_swapped = _fit_translation(pairs, rel, _with_translation(C0, t_swapped), phi, None, scale)
    z_swap = _paired_z(cost_stored - cost_swapped, pairs.landmark)  # > 0: the swapped one fits better

    def off(t):  # (distance in the plane, chi-square 2 dof) of the free estimate from t
        d = plane.T @ (t_free - t)
        try:
            return float(np.linalg.norm(d)), float(d @ np.linalg.solve(cov_p, d))
        except np.linalg.LinAlgError:
            return float(np.linalg.norm(d)), float("nan")

    d_stored, chi_stored = off(t_stored)
    d_swapped, _ = off(t_swapped)
    # the unobserved component: that of the recorded convention nearer in the plane
    t_axis = t_swapped if d_swapped < d_stored else t_stored
    t_free = t_free + up_cam * (up_cam @ (t_axis - t_free))
    est.update({"imu_camera_translation_free_m": t_free.tolist(), "imu_camera_translation_free_m_se": se3d,
                "imu_camera_translation_unobserved_axis": up_cam.tolist(),
                "imu_camera_translation_free_from_stored_m": d_stored,
                "imu_camera_translation_free_from_swapped_m": d_swapped,
                "imu_camera_translation_chi2": chi_stored, "imu_camera_translation_swapped_z": z_swap,
                "imu_camera_translation_costs": {"stored": float(np.sum(cost_stored)),
                                                 "swapped": float(np.sum(cost_swapped)),
                                                 "free": float(np.sum(cost_free))}})
    se_txt = ("± (" + ", ".join("unobserved" if v is None else f"{v:.2f}" for v in se3d) + f") m, the "
              f"component along the yaw axis {_fmt_vec(up_cam, '.2f')} unobserved")
    return _TranslationEvidence(t_free, se3d, se_txt, plane, z_swap, d_stored, chi_stored, d_swapped)


def _translation_finding(est: dict[str, Any], ev: _TranslationEvidence, rig, C0: np.ndarray, n_landmarks: int,
                         opts: CheckOptions) -> tuple[dict[str, Any], Finding, Any]:
    """The finding (and the suggested cam_T_imu) from the evidence, for a rig that is not a
    published calibration with its translation swapped."""
    t_stored, t_swapped = C0[:3, 3].copy(), swapped_translation(C0)
    est["imu_camera_translation_m_se"] = ev.se3d
    if rig is not None and rig.translation == "published":
        est["imu_camera_translation_m"] = t_stored.tolist()
        return est, Finding("imu-camera-translation", "OK",
                            f"cam_T_imu is the published {rig.name} calibration (the tracks' free estimate "
                            f"{_fmt_vec(ev.t_free, '.2f')} {ev.se_txt}; swapped vs recorded z = {ev.z_swap:.1f}); "
                            f"nothing to do"), None
    if ev.d_stored <= opts.translation_warn_m or not ev.chi_stored > _CHI2_2DOF_99:
        est["imu_camera_translation_m"] = t_stored.tolist()
        apart = float(np.linalg.norm(ev.plane.T @ (t_stored - t_swapped)))
        if apart > opts.translation_warn_m and ev.z_swap > -opts.translation_decided_z:
            return est, Finding(
                "imu-camera-translation", "WARN",
                f"the tracks cannot tell the recorded cam_T_imu translation {_fmt_vec(t_stored, '.3f')} m from the "
                f"swapped convention's {_fmt_vec(t_swapped, '.3f')} m (imu_T_cam's translation stored as "
                f"cam_T_imu's; {apart:.1f} m apart): z = {ev.z_swap:.1f} over {n_landmarks} landmarks, at least "
                f"{opts.translation_decided_z:.0f} needed (free estimate {_fmt_vec(ev.t_free, '.2f')} {ev.se_txt}); "
                f"verify the translation against the calibration's source (KITTI raw: R_rect_00 T_velo->cam "
                f"T_imu->velo)"), None
        return est, Finding("imu-camera-translation", "OK",
                            f"the tracks support the recorded IMU-camera translation {_fmt_vec(t_stored, '.3f')} m "
                            f"(free estimate {_fmt_vec(ev.t_free, '.2f')} {ev.se_txt}); nothing to do"), None
    if ev.z_swap >= 3.0 and ev.d_swapped < ev.d_stored:
        est["imu_camera_translation_m"] = t_swapped.tolist()
        return est, Finding(
            "imu-camera-translation", "ERROR",
            f"cam_T_imu's translation {_fmt_vec(t_stored, '.3f')} m is imu_T_cam's (the camera's position in the IMU "
            f"frame): the tracks fit cam_T_imu's translation {_fmt_vec(t_swapped, '.3f')} m better (z = "
            f"{ev.z_swap:.1f}), and their free estimate {_fmt_vec(ev.t_free, '.2f')} {ev.se_txt} lies "
            f"{ev.d_swapped:.2f} m from it and {ev.d_stored:.2f} m from the recorded one; run with the suggested "
            f"cam_T_imu"), _suggested_cam_T_imu(C0, t_swapped)
    est["imu_camera_translation_m"] = ev.t_free.tolist()
    return est, Finding(
        "imu-camera-translation", "WARN",
        f"cam_T_imu's translation is off by {ev.d_stored:.2f} m: the tracks support {_fmt_vec(ev.t_free, '.2f')} "
        f"{ev.se_txt} (recorded {_fmt_vec(t_stored, '.3f')} m); run with the suggested cam_T_imu"), \
        _suggested_cam_T_imu(C0, ev.t_free)


def _timestamp_unit(dt: float, opts: CheckOptions) -> tuple[float, Finding]:
    """(factor to seconds, the finding) for the median frame interval ``dt`` of the
    recording's timestamps: a camera's interval is within ``opts.frame_interval_s``;
    outside it, the first of ms, µs, ns that brings it inside is suggested."""
    lo, hi = opts.frame_interval_s
    if dt <= 0 or lo <= dt <= hi:
        return 1.0, Finding("timestamps", "OK", f"frames are {dt:.4g} s apart ({1 / dt:.3g} Hz); nothing to do"
                            if dt > 0 else "fewer than two frames: nothing to check")
    guess = timestamp_unit_guess(dt, opts.frame_interval_s)
    if guess is not None:
        factor, name = guess
        return factor, Finding("timestamps", "WARN",
                               f"frames are {dt:.4g} apart in the recording's time unit, {dt * factor:.4g} s "
                               f"({1 / (dt * factor):.3g} Hz) if it is {name}: run with the suggested "
                               f"timestamp_scale {factor:g} (the rest of this check assumed it)")
    return 1.0, Finding("timestamps", "ERROR",
                        f"frames are {dt:.4g} s apart, outside a camera's {lo:g}-{hi:g} s in seconds and in ms, µs or "
                        f"ns: the timestamps are not a frame clock; the filter's prediction steps will be wrong")


#: Units a speed may have been recorded in by mistake: (recorded value per m/s, name).
_SPEED_UNITS = ((3.6, "km/h"), (1 / 0.44704, "mph"), (1 / 0.514444, "knots"), (100.0, "cm/s"), (1000.0, "mm/s"))


def _velocity_scale_finding(k: float, k_se: float | None, opts: CheckOptions, suggested: dict,
                            noise_to_speed: float = 0.0) -> Finding:
    """The velocity-scale finding for the fitted factor ``k`` (corrected = recorded x k);
    adds ``velocity_scale`` (and rescales a suggested velocity noise) to ``suggested``.
    ``noise_to_speed`` (white noise over the median speed) widens the tolerance: noise in
    the velocities biases the fitted factor low (dense 0027 / 0022 / 0034: 0.97 / 0.97 /
    0.94 at 0.5 m/s per axis, against 0.995 on the clean sparse 0027)."""
    se_txt = f" ± {k_se:.3f}" if k_se is not None else ""
    if k_se is None or abs(k - 1.0) <= max(opts.velocity_scale_warn, 3 * k_se, noise_to_speed):
        return Finding("velocity-scale", "OK", f"the speeds match the motion the camera sees (factor {k:.3f}{se_txt}); "
                                               f"nothing to do")
    # a unit mistake is corrected with the unit's exact factor (the fit is within ~1 %)
    tolerance = max(0.05, noise_to_speed)
    unit = next(((factor, name) for factor, name in _SPEED_UNITS if abs(math.log(1 / k / factor)) < tolerance), None)
    suggested["velocity_scale"] = float(f"{1 / unit[0]:.6g}") if unit else float(f"{k:.4g}")
    if "velocity_noise_mps" in suggested:  # estimated in the recording's units
        suggested["velocity_noise_mps"] = [float(f"{v * suggested['velocity_scale']:.3g}")
                                           for v in suggested["velocity_noise_mps"]]
    hint = f" (speeds in {unit[1]}? its exact factor is suggested)" if unit else ""
    return Finding("velocity-scale", "WARN",
                   f"the recorded speeds are {1 / k:.3g}x the motion the camera sees{hint} (factor {k:.4g}{se_txt} "
                   f"to m/s): run with the suggested velocity_scale")


def _scale_grid(value_range: tuple[float, float]) -> list[float]:
    """Factors on the linear velocities tried at the start of the fit: 1 first, then a
    log grid over ``value_range`` (about 12 % apart)."""
    if not value_range:
        return [1.0]
    lo, hi = value_range
    if not lo < 1.0 < hi:
        return [1.0]
    n = int(math.ceil(math.log(hi / lo) / math.log(1.12))) + 1
    grid = np.exp(np.linspace(math.log(lo), math.log(hi), n))
    return [1.0] + [float(k) for k in grid if abs(math.log(k)) > 0.05]


def _starts() -> list[np.ndarray]:
    """Initial rotation vectors: none, and 180° about each camera axis."""
    return [np.zeros(3)] + [math.pi * e for e in np.eye(3)]


# ----------------------------------------------------------------------------- pixels


def _track_windows(lm: np.ndarray, fr: np.ndarray, n: int) -> np.ndarray:
    """(len - n + 1,) True where rows i..i+n-1 are n consecutive frames of one landmark."""
    m = np.ones(max(len(lm) - n + 1, 0), dtype=bool)
    for i in range(1, n):
        m &= (lm[i:len(lm) - n + 1 + i] == lm[:len(lm) - n + 1]) & (fr[i:len(fr) - n + 1 + i] - fr[:len(fr) - n + 1] == i)
    return m


def estimate_pixel_noise(sequence: Sequence, usable: np.ndarray | None = None) -> dict[str, Any]:
    """Pixel noise of the tracks (px per coordinate) and the share of gross outliers.

    σ: third differences along tracks, ``z_{k+2} − 3 z_{k+1} + 3 z_k − z_{k−1}``, which
    cancel the smooth (up to quadratic) image motion and have standard deviation σ √20 for
    white noise; robust σ from their median absolute value (left image). Outliers: an
    observation whose second difference ``z_k − (z_{k−1} + z_{k+1}) / 2`` exceeds
    max(10 px, 8 σ √1.5) and is the largest of its neighbours' (a jump at k shows half as
    large at k ± 1).
    """
    obs = sequence.observations
    ok = usable_observations(sequence, max_depth_m=1e9) if usable is None else usable
    rows = np.nonzero(ok)[0]
    lm, fr = obs.landmark_ids[rows], obs.frame_index[rows]
    order = np.lexsort((fr, lm))
    rows, lm, fr = rows[order], lm[order], fr[order]
    empty = {"sigma_px": None, "sigma_px_se": None, "outlier_share": None, "outlier_threshold_px": None,
             "n_windows": 0}
    if rows.size < 5:
        return empty
    px = obs.pixels[rows][:, :2]
    m4 = _track_windows(lm, fr, 4)
    n4 = m4.size
    d3 = (px[3:3 + n4] - 3 * px[2:2 + n4] + 3 * px[1:1 + n4] - px[:n4])[m4].ravel()
    if d3.size < 10:
        return empty
    sigma = 1.4826 * float(np.median(np.abs(d3))) / math.sqrt(20.0)
    m3 = _track_windows(lm, fr, 3)
    n3 = m3.size
    d2 = np.linalg.norm(px[1:1 + n3] - 0.5 * (px[:n3] + px[2:2 + n3]), axis=1)
    d2 = np.where(m3, d2, 0.0)
    threshold = max(10.0, 8.0 * sigma * math.sqrt(1.5))
    prev = np.r_[0.0, d2[:-1]]
    nxt = np.r_[d2[1:], 0.0]
    peak = m3 & (d2 > threshold) & (d2 >= prev) & (d2 >= nxt)
    # second pass: σ again without the windows that contain an outlier
    bad = np.zeros(rows.size, dtype=bool)
    bad[1:1 + n3][peak] = True
    touched = bad[:n4] | bad[1:1 + n4] | bad[2:2 + n4] | bad[3:3 + n4]
    d3_clean = (px[3:3 + n4] - 3 * px[2:2 + n4] + 3 * px[1:1 + n4] - px[:n4])[m4 & ~touched].ravel()
    if d3_clean.size >= 10:
        d3 = d3_clean
        sigma = 1.4826 * float(np.median(np.abs(d3))) / math.sqrt(20.0)
    return {"sigma_px": sigma, "sigma_px_se": sigma / math.sqrt(d3.size), "outlier_share": float(np.mean(peak[m3])),
            "outlier_threshold_px": threshold, "n_windows": int(np.count_nonzero(m3)),
            "method": "sigma from third differences along tracks; outliers: peaks of second differences"}


# ----------------------------------------------------------------------------- main


def _fmt_vec(v, spec: str = ".3g") -> str:
    return "(" + ", ".join(format(float(x), spec) for x in v) + ")"


@dataclass
class Analysis:
    """What one analysis of :func:`check_sequence` found: its estimates (JSON-ready), its
    findings, the FilterOptions values it suggests and notes on what it could not do."""

    estimates: dict[str, Any] = field(default_factory=dict)
    findings: list[Finding] = field(default_factory=list)
    suggested: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


class _Check:
    """One run of :func:`check_sequence`: the inputs, what the analyses so far found
    (merged, in order) and the values they hand on to the later ones (the sequence in
    seconds, the velocities as the reprojection analyses see them, the track pairs, the
    fitted rotation, bias, association)."""

    def __init__(self, sequence: Sequence, opts: CheckOptions, base: FilterOptions):
        self.sequence, self.opts, self.base = sequence, opts, base
        self.rng = np.random.default_rng(opts.seed)
        self.est: dict[str, Any] = {}
        self.suggested: dict[str, Any] = {}
        self.findings: list[Finding] = []
        self.notes: list[str] = []
        self.T = sequence.n_frames
        self.ts = sequence.timestamps_s
        self.u = sequence.velocities()
        self.dt = float(np.median(np.diff(self.ts))) if self.T > 1 else 0.0
        self.C0 = np.array(sequence.cam_T_imu, dtype=np.float64)
        self.scale = opts.loss_scale_px
        self.shift = 1
        self.noisy = False
        self.sv = self.sw = np.full(3, np.nan)

    def merge(self, found: Analysis) -> None:
        self.est.update(found.estimates)
        self.findings.extend(found.findings)
        self.notes.extend(found.notes)
        for key, value in found.suggested.items():
            problem = self._unusable(key, value)
            if problem:  # its finding still says what was found, and why nothing is suggested
                self.notes.append(f"{key} {value!r} not suggested: {problem}")
                logger.info("check of %s: %s %r not suggested: %s", self.sequence.name, key, value, problem)
                self.suggested.pop(key, None)
                self.findings = [dataclasses.replace(f, message=re.sub(
                    rf"run with the suggested {key}\b[^;]*", f"{key} {value!r} is not suggested ({problem})",
                    f.message)) for f in self.findings]
            else:
                self.suggested[key] = value

    def _unusable(self, key: str, value) -> str | None:
        """Why a run could not take this suggestion with those before it, or None: a value
        beyond its option's range (a velocity factor of 1e5 from frames 1 µs apart), or data
        corrections that together refuse this recording (a time offset as long as a
        two-frame recording) — ``--auto`` would stop with an options error on a legal file."""
        from vislam.core.options import DATA_CORRECTION_FIELDS
        from vislam.errors import ConfigError

        values = {**self.suggested, key: value}
        try:
            options = FilterOptions.from_dict(values, source="suggested")
            if key in DATA_CORRECTION_FIELDS and key != "timestamp_scale":  # (the sequence here is in seconds)
                apply_corrections(self.sequence, options.replace(timestamp_scale=1.0))
        except ConfigError as exc:
            return str(exc)
        return None


def check_sequence(sequence: Sequence, options: CheckOptions | None = None,
                   filter_options: FilterOptions | None = None) -> CheckResult:
    """Analyse ``sequence`` (see the module docstring): the analyses of :data:`ANALYSES`
    in order, each adding its estimates, findings and suggestions. ``filter_options`` is
    the reference the noise is compared with (default: FilterOptions())."""
    import time

    t_start = time.perf_counter()
    run = _Check(sequence, options or CheckOptions(), filter_options or FilterOptions())
    for _name, analysis in ANALYSES:
        run.merge(analysis(run))
    findings = run.findings
    order = {c: i for i, c in enumerate(FINDING_CODES)}
    findings.sort(key=lambda f: order.get(f.code, len(order)))
    elapsed = time.perf_counter() - t_start
    logger.info("checked %s in %.1f s: %s", run.sequence.name, elapsed,
                ", ".join(f"{f.code} {f.severity}" for f in findings if f.severity != "OK") or "all OK")
    return CheckResult(name=run.sequence.name, source=run.sequence.source, estimates=run.est, findings=findings,
                       suggested=run.suggested, elapsed_s=elapsed, notes=run.notes)


def _analyse_timestamps(run: _Check) -> Analysis:
    """The timestamps' unit: a camera's frame interval is 5 ms to 1 s (the later
    analyses see seconds)."""
    factor, finding = _timestamp_unit(run.dt, run.opts)
    out = Analysis({"frame_interval_s": run.dt * factor, "timestamp_scale": factor}, [finding])
    if factor != 1.0:
        out.suggested["timestamp_scale"] = factor
        run.sequence = run.sequence.replace(timestamps_s=run.sequence.timestamps_s * factor)
        run.ts = run.sequence.timestamps_s
        run.dt *= factor
    return out


def _analyse_observations(run: _Check) -> Analysis:
    """What ``vislam info`` reports: exact repeats and non-positive disparities."""
    obs = run.sequence.observations
    disparity = obs.pixels[:, 0] - obs.pixels[:, 2]
    repeated, evidence = obs.repeat_evidence(run.sequence.repeat_motion())
    duplicated = obs.duplicate_mask()
    # the longest run of frames whose observations (nearly all) repeat: a frozen camera or tracker
    repeats = np.bincount(obs.frame_index[repeated], minlength=obs.n_frames)
    seconds, first, last = frozen_stretch(obs.counts_per_frame(), repeats, run.sequence.timestamps_s)
    return Analysis({"observations": {
        "total": obs.n_observations, "repeated": int(np.count_nonzero(repeated)),
        "repeated_longest_run": {"seconds": seconds, "first_frame": first, "last_frame": last},
        "repeated_share": float(np.mean(repeated)) if obs.n_observations else 0.0, "repeat_evidence": evidence,
        "non_positive_disparity": int(np.count_nonzero(disparity <= 0)),
        "negative_disparity": int(np.count_nonzero(disparity < 0)),
        "row_difference": _row_differences(obs.pixels, run.base),
        "duplicated": _duplicate_counts(obs, duplicated)},
        "stereo_depth": stereo_depths(run.sequence.camera, disparity, run.base)})


def _row_differences(pixels: np.ndarray, base: FilterOptions) -> dict:
    """|vL - vR| of the observations against the filter's row guard (max_row_difference_px:
    beyond it no landmark starts): how many are beyond, and the median."""
    rows = np.abs(pixels[:, 1] - pixels[:, 3])
    limit = float(base.max_row_difference_px)
    return {"beyond_guard": int(np.count_nonzero(~(rows <= limit))), "guard_px": limit,
            "median_px": float(np.median(rows)) if rows.size else None}


#: Factors on the baseline tried when most depths fall outside the filter's depth guards
#: (a baseline stored in millimetres is the file's value x 1e-3).
_BASELINE_FACTORS = (1e-3, 1e-2, 1e-1, 10.0, 100.0, 1000.0)


def stereo_depths(camera, disparity: np.ndarray, base: FilterOptions) -> dict:
    """Depths Z = fsu b / d of the observations with positive disparity against the
    filter's depth guards [min_depth_m, max_depth_m] (outside, no landmark starts): their
    median, 10-90 % range, the share within the guards, and the factors on the baseline
    (of :data:`_BASELINE_FACTORS`, in that order) that would put more of them within the
    guards than the file's, at least half and 90 % of the best factor's share, each with
    its share. A scene's depth does not say its unit: a plane at one depth fits x 0.001
    and x 0.01 alike, so every such factor is listed."""
    d = disparity[np.isfinite(disparity) & (disparity > 0)]
    lo, hi = float(base.min_depth_m), float(base.max_depth_m)
    out = {"observations": int(d.size), "baseline_m": float(camera.baseline_m), "fsu_px": float(camera.fsu),
           "guards_m": [lo, hi], "median_m": None, "p10_m": None, "p90_m": None, "within_guards_share": None,
           "baseline_factors": []}
    if d.size == 0:
        return out
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        z = camera.fsu * camera.baseline_m / d

        def within(factor: float) -> float:
            zf = z * factor
            return float(np.mean((zf >= lo) & (zf <= hi)))

        share = within(1.0)
        shares = {f: within(f) for f in _BASELINE_FACTORS}
    top = max(shares.values())
    p10, med, p90 = (float(x) for x in np.percentile(z, [10, 50, 90]))
    out.update(median_m=med, p10_m=p10, p90_m=p90, within_guards_share=share,
               baseline_factors=[[f, v] for f, v in shares.items() if v > share and v >= max(0.5, 0.9 * top)])
    return out


def _duplicate_counts(obs, duplicated: np.ndarray) -> dict:
    """Observations that copy another landmark's pixels in the same frame: how many, in
    how many frames, how many landmarks, and the first (frame, id kept, id copying)."""
    n = int(np.count_nonzero(duplicated))
    out = {"observations": n, "frames": int(np.unique(obs.frame_index[duplicated]).size),
           "landmarks": int(np.unique(obs.landmark_ids[duplicated]).size), "example": None}
    if n:
        i = int(np.flatnonzero(duplicated)[0])
        t = int(obs.frame_index[i])
        ids, pix = obs.frame(t)
        first = int(ids[np.flatnonzero(np.all(pix == obs.pixels[i], axis=1))[0]])
        out["example"] = {"frame": t, "landmark": first, "copy": int(obs.landmark_ids[i])}
    return out


def _imu_samples_finding(u: np.ndarray) -> Finding:
    """Velocities that are exactly 0 in every sample: no sensor reads that, a file whose
    velocities were missing and filled with zeros does (the filters would see a vehicle
    standing still, or never turning)."""
    n = u.shape[0]
    linear, angular = bool(n and not np.any(u[:, :3])), bool(n and not np.any(u[:, 3:]))
    if linear:
        return Finding("imu-samples", "ERROR",
                       f"all {n} linear-velocity samples are exactly 0{' (and the angular rates too)' if angular else ''}"
                       ": no sensor reads that; were the velocities missing and filled with zeros? The filters would "
                       "see a vehicle standing still")
    if angular:
        return Finding("imu-samples", "WARN", f"all {n} angular-rate samples are exactly 0: no gyro reads that; were "
                                              "the rates missing and filled with zeros? The filters would see a "
                                              "vehicle that never turns")
    dropouts = imu_dropouts(u[:, :3], u[:, 3:])
    if dropouts:
        return Finding("imu-samples", "WARN", "; ".join(dropouts) + ": no sensor reads that; the filters would "
                                              "take them for the vehicle's motion")
    return Finding("imu-samples", "OK", "the velocity samples vary; nothing to do")


def _analyse_imu_noise(run: _Check) -> Analysis:
    """IMU white noise per axis against the filter's noise model (and samples that are
    all exactly 0)."""
    u, opts, base = run.u, run.opts, run.base
    sv, sv_se = estimate_white_noise(u[:, :3])
    sw, sw_se = estimate_white_noise(u[:, 3:])
    run.sv, run.sw = sv, sw
    out = Analysis({"imu_noise": {"velocity_mps": sv.tolist(), "velocity_mps_se": sv_se.tolist(),
                                  "angular_radps": sw.tolist(), "angular_radps_se": sw_se.tolist(),
                                  "method": "variogram nugget (quadratic fit of lags 1-6), per axis"}},
                   [_imu_samples_finding(u)])
    default_v = base.velocity_noise_per_axis
    default_w = base.angular_noise_per_axis
    corrupt = imu_samples_beyond_limits(u[:, :3], u[:, 3:]) + imu_spikes(u[:, :3], u[:, 3:])
    if corrupt:  # one such sample makes the white noise look huge: say what it is, suggest no noise
        out.findings.append(Finding(
            "noise", "WARN", f"{'; '.join(corrupt)}: not a vehicle's motion — another unit, or corrupt samples; "
                             f"the white noise per axis ({_fmt_vec(sv)} m/s, {_fmt_vec(sw)} rad/s with them) is not "
                             f"suggested: fix or remove those samples"))
        return out
    run.noisy = bool(np.any(sv > opts.noise_factor_warn * default_v) or np.any(sw > opts.noise_factor_warn * default_w))
    if run.noisy:
        out.suggested["velocity_noise_mps"] = [float(f"{x:.3g}") for x in np.maximum(np.nan_to_num(sv), default_v)]
        out.suggested["angular_noise_radps"] = [float(f"{x:.3g}") for x in np.maximum(np.nan_to_num(sw), default_w)]
        out.findings.append(Finding(
            "noise", "WARN", f"IMU white noise per axis {_fmt_vec(sv)} m/s and {_fmt_vec(sw)} rad/s is far above "
                             f"the filter's {_fmt_vec(default_v)} m/s, {_fmt_vec(default_w)} rad/s: the filter "
                             f"would trust the IMU too much and reject landmarks; run with the suggested noise"))
    else:
        out.findings.append(Finding(
            "noise", "OK", f"IMU white noise per axis {_fmt_vec(sv)} m/s and {_fmt_vec(sw)} rad/s is within "
                           f"{opts.noise_factor_warn:g}x of the filter's noise; nothing to do"))
    return out


def _analyse_gyro_bias(run: _Check) -> Analysis:
    """Gyro bias from the roll/pitch-rate means (a ground vehicle ends as level as it
    started); then the velocities the reprojection analyses see: without the bias found,
    in the body frame (levelled velocities turned by the grade they show)."""
    opts, u = run.opts, run.u
    duration = max(run.sequence.duration_s, 1e-9)
    mean_w = np.mean(u[:, 3:], axis=0)
    # a 3° change of roll or pitch over the drive, and the white noise
    mean_se = np.sqrt((np.radians(3.0) / duration) ** 2 + np.nan_to_num(run.sw) ** 2 / max(run.T, 1))
    # The roll/pitch means are the estimate: the visual fit (fit_gyro_bias) is recorded
    # for information only; on the reference files it finds yaw "biases" of 0.003-0.012
    # rad/s that make dead reckoning far worse (it absorbs other model errors).
    b_est = np.array([mean_w[0], mean_w[1], np.nan])
    b_se = np.array([mean_se[0], mean_se[1], np.nan])
    out = Analysis({"angular_rate_mean_radps": mean_w.tolist(), "angular_rate_mean_radps_se": mean_se.tolist(),
                    "gyro_bias_radps": b_est.tolist(), "gyro_bias_radps_se": b_se.tolist()})
    significant = np.isfinite(b_est) & (np.abs(b_est) > np.maximum(opts.bias_warn_radps, 3 * np.nan_to_num(b_se)))
    averages = f"the roll and pitch rates average to {_fmt_vec(b_est[:2])} ± {_fmt_vec(b_se[:2], '.1g')} rad/s"
    if np.any(significant):
        out.suggested["gyro_bias_radps"] = [float(f"{x:.3g}") for x in np.where(significant, b_est, 0.0)]
        out.findings.append(Finding("imu-bias", "WARN",
                                    f"{averages} over the drive, which no ground vehicle does: a gyro bias, dead "
                                    f"reckoning tilts and climbs; run with the suggested gyro_bias_radps (a yaw bias "
                                    f"is not observable this way)"))
        u = _debiased(u, np.asarray(out.suggested["gyro_bias_radps"]))
    else:
        out.findings.append(Finding("imu-bias", "OK", f"{averages}: no gyro bias beyond {opts.bias_warn_radps:g} "
                                                      f"rad/s; nothing to do"))
    run.u = level_velocities_to_body(u) if run.base.velocity_frame == "level" else u
    return out


def _analyse_track_pairs(run: _Check) -> Analysis:
    """The predictions of the reprojection analyses: all for the association and the
    time offset (cheap: a few cost evaluations), a random subset for the rotation fit."""
    run.all_pairs = _TrackPairs(run.sequence, run.opts.window, run.opts.max_depth_m, None, run.rng)
    run.pairs = run.all_pairs.subset(run.opts.max_pairs, run.rng)
    return Analysis({"prediction_pairs": run.all_pairs.n_pairs})


def _analyse_conventions(run: _Check) -> Analysis:
    """The reprojection analyses in order (:data:`CONVENTION_ANALYSES`), or, with fewer
    than 30 predictions, WARN findings saying they were not checked."""
    if run.pairs.n_pairs >= 30:
        out = Analysis()
        for _name, analysis in CONVENTION_ANALYSES:
            found = analysis(run)
            run.merge(found)  # the later steps read what the earlier ones found
        return out
    n = run.pairs.n_pairs
    out = Analysis({"imu_camera_rotation_error_deg": None, "conventions_checked": False})
    out.notes.append(f"only {n} track predictions: rotation, translation, association and time offset not checked")
    for code in ("imu-camera-rotation", "imu-camera-translation", "velocity-association", "velocity-scale",
                 "time-offset"):
        out.findings.append(Finding(code, "WARN", f"not enough in-sync stereo tracks ({n} predictions) "
                                                  f"to check this; the recording's conventions are assumed"))
    return out


def _analyse_best_start(run: _Check) -> Analysis:
    """The start of the rotation fit: rotation and speed factor with the most landmarks
    whose predictions reproject within moving_landmark_px (median)."""
    opts, pairs, ts, u, C0 = run.opts, run.pairs, run.ts, run.u, run.C0
    run.r_before = pairs.residuals(pairs.relative_imu(ts, run.sequence.velocities(), 1), C0)  # the data as recorded
    out = Analysis({"reprojection_before_px": _percentiles(_left_distance(run.r_before))})
    # the loss scale follows the residual level, so that most residuals are in the
    # quadratic part of the Cauchy loss (its Gauss-Newton covariance is then honest)
    run.scale = max(run.scale, 1.5 * float(np.median(np.linalg.norm(run.r_before, axis=1))))
    # A consensus of landmarks rather than of predictions, because with traffic
    # alongside most predictions may belong to a few long-tracked vehicles (sparse
    # 0042: 70 % of the predictions, 43 % of the landmarks), which a wrong velocity
    # factor would make look static. Ties: predictions within, then the robust cost.
    # The linear velocities' scale is searched too (a unit mistake, km/h stored as
    # m/s, would otherwise look like a rotation error): a log grid of factors.
    inlier_px = opts.moving_landmark_px if opts.moving_landmark_px is not None else 12.0
    starts = [(phi0, k) for k in _scale_grid(opts.velocity_scale_range) for phi0 in _starts()]
    few = pairs.subset(opts.start_pairs, np.random.default_rng(opts.seed))  # the search: a subset suffices
    rel_by_k = {1.0: few.relative_imu(ts, u, 1)}  # the IMU motions of each factor, for every rotation start
    costs = []
    for phi0, k in starts:
        if k not in rel_by_k:
            rel_by_k[k] = few.relative_imu(ts, _scaled(u, k), 1)
        r0 = few.residuals(rel_by_k[k], _turned(C0, phi0))
        d0 = _left_distance(r0)
        costs.append((-few.landmark_inliers(d0, inlier_px), -int(np.count_nonzero(d0 <= inlier_px)),
                      float(np.sum(_cauchy_cost(r0, run.scale)))))
    run.phi_start, run.k_start = starts[min(range(len(costs)), key=costs.__getitem__)]
    # the residuals the loss scale follows: the recorded data's, or at the factor found
    run.u_start, run.r_scale = u, run.r_before
    if run.k_start != 1.0:
        run.u_start = _scaled(u, run.k_start)
        run.r_scale = pairs.residuals(pairs.relative_imu(ts, run.u_start, 1), _turned(C0, run.phi_start))
        run.scale = max(opts.loss_scale_px, 1.5 * float(np.median(np.linalg.norm(run.r_scale, axis=1))))
    return out


def _analyse_moving_landmarks(run: _Check) -> Analysis:
    """Landmarks that do not follow the world's motion (traffic, mismatched tracks),
    judged at the best start: left out of the fits."""
    moving = _moving_landmarks(run.all_pairs, run.ts, run.u_start, run.C0, run.phi_start, run.opts.moving_landmark_px)
    out = Analysis({"moving_landmarks": moving})
    if moving["landmarks"]:
        ids = np.asarray(moving["landmark_ids"])
        keep = ~np.isin(run.pairs.landmark, ids)
        keep_all = ~np.isin(run.all_pairs.landmark, ids)
        if np.count_nonzero(keep) >= 30:
            run.scale = max(run.opts.loss_scale_px, 1.5 * float(np.median(np.linalg.norm(run.r_scale[keep], axis=1))))
            run.pairs, run.all_pairs = run.pairs.select(keep), run.all_pairs.select(keep_all)
            out.estimates["reprojection_before_static_px"] = _percentiles(_left_distance(run.r_before[keep]))
        else:
            moving["kept"] = "fewer than 30 predictions would remain: every landmark kept"
    return out


def _analyse_velocity_scale(run: _Check) -> Analysis:
    """The robust fit of rotation (and bias) with the linear velocities' factor; the
    later analyses see the velocities times that factor."""
    opts = run.opts
    run.x, run.cov, _, (log_k, log_k_var) = _fit_rotation_and_bias(
        run.pairs, run.ts, run.u, run.C0, 1, run.scale, run.phi_start, opts.fit_gyro_bias, fit_scale=True,
        log_scale0=math.log(run.k_start))
    k_hat = math.exp(log_k)
    k_se = k_hat * math.sqrt(log_k_var) if math.isfinite(log_k_var) and log_k_var >= 0 else None
    k_se = math.hypot(k_se, opts.velocity_scale_floor) if k_se is not None else None
    run.k_hat, run.k_se = k_hat, k_se
    run.u = _scaled(run.u, k_hat)
    return Analysis({"velocity_scale": k_hat, "velocity_scale_se": k_se})


def _analyse_association(run: _Check) -> Analysis:
    """Velocity association: the shift with the smallest cost at the fitted rotation
    and bias (rotation and bias refitted with another shift), and its significance."""
    all_pairs = run.all_pairs

    def shifted_cost(s: int, phi: np.ndarray, b: np.ndarray) -> np.ndarray:
        rel = all_pairs.relative_imu(run.ts, _debiased(run.u, b), s)
        return _cauchy_cost(all_pairs.residuals(rel, _turned(run.C0, phi)), run.scale)

    x = run.x
    shift_costs = {s: shifted_cost(s, x[:3], x[3:]) for s in (-1, 0, 1, 2, 3)}
    totals = {s: float(np.sum(c)) for s, c in shift_costs.items()}
    shift = min(totals, key=totals.get)
    if shift != 1:  # refit rotation and bias with the chosen association
        run.x, run.cov, _, _ = _fit_rotation_and_bias(run.pairs, run.ts, run.u, run.C0, shift, run.scale, x[:3],
                                                      run.opts.fit_gyro_bias)
        shift_costs = {s: shifted_cost(s, run.x[:3], run.x[3:]) for s in shift_costs}
        totals = {s: float(np.sum(c)) for s, c in shift_costs.items()}
        shift = min(totals, key=totals.get)
    # significance: paired difference of per-landmark costs, best vs "next"
    run.z_assoc = _paired_z(shift_costs[1] - shift_costs[shift], all_pairs.landmark)
    run.shift, run.totals = shift, totals
    return Analysis({"velocity_association": {
        "best_shift": int(shift), "costs": {str(s): c for s, c in totals.items()}, "z_vs_next": run.z_assoc,
        "meaning": "shift s: the velocity sample of frame k+s describes the interval k -> k+1 (1 = 'next')"}})


def _body_roll_covariance(run: _Check, phi: np.ndarray, phi_cov: np.ndarray) -> tuple[np.ndarray, Any]:
    """Body roll in turns (a nuisance, see roll_tilted): refit with the rates tilted by
    one prior σ of the roll gradient; the change of φ is a systematic error of the
    constant-rotation model, added to its covariance. It is large where the drive's
    turns go mostly one way (sparse 0020: 0.9° about the optical axis for 0.3°/(m/s²)),
    small where they balance (dense 0027: 0.2°). With ground-truth poses, sparse 0020's
    rates fit the camera best with an outward roll of 0.55° per m/s² and a constant
    1.3° (as 0027, same day) instead of 2.7°. Returns (covariance, sensitivity in ° or None)."""
    opts = run.opts
    axes = vehicle_axes(run.u) if opts.roll_gradient_prior_deg_per_mps2 > 0 else None
    if axes is None:
        return phi_cov, None
    u_tilt = roll_tilted(run.u, math.radians(opts.roll_gradient_prior_deg_per_mps2), axes)
    x_tilt, _, _, _ = _fit_rotation_and_bias(run.pairs, run.ts, u_tilt, run.C0, run.shift, run.scale, phi,
                                             opts.fit_gyro_bias)
    d_phi = x_tilt[:3] - phi
    return phi_cov + np.outer(d_phi, d_phi), np.degrees(d_phi).tolist()


def _analyse_rotation(run: _Check) -> Analysis:
    """IMU-camera rotation: the fitted correction, its uncertainty (with body roll) and
    significance; whether the best fit is good enough to report the conventions."""
    opts, x = run.opts, run.x
    phi = run.phi = x[:3]
    phi_cov, roll = _body_roll_covariance(run, phi, run.cov[:3, :3])
    out = Analysis({"body_roll_sensitivity_deg": roll})
    angle = run.angle = float(np.degrees(np.linalg.norm(phi)))
    angle_se = float(np.degrees(math.sqrt(max(np.trace(phi_cov), 0.0)))) if np.all(np.isfinite(phi_cov)) else None
    if angle_se is not None:
        angle_se = math.hypot(angle_se, opts.rotation_floor_deg)
    run.angle_se = angle_se
    # significance in the estimate's own metric (its uncertainty differs by axis:
    # body roll only blurs the rotation about the forward axis)
    floor = math.radians(opts.rotation_floor_deg)
    try:
        rotation_z2 = float(phi @ np.linalg.solve(phi_cov + floor**2 * np.eye(3), phi))
    except np.linalg.LinAlgError:
        rotation_z2 = float("nan")
    if not math.isfinite(rotation_z2):  # no usable covariance: the floor alone
        rotation_z2 = float(phi @ phi) / floor**2
    run.rotation_z2 = rotation_z2
    run.rotation_clusters = run.pairs.n_clusters
    rel_fit = run.pairs.relative_imu(run.ts, _debiased(run.u, x[3:]), run.shift)
    run.fit_median = float(np.median(_left_distance(run.pairs.residuals(rel_fit, _turned(run.C0, phi)))))
    run.reliable = run.fit_median <= opts.max_fit_median_px
    run.bias = x[3:]
    # the fit cannot tell a bias from the mean of this recording's gyro noise: add it
    bias_se = np.sqrt(np.clip(np.diag(run.cov[3:, 3:]), 0, None) + np.nan_to_num(run.sw) ** 2 / max(run.T, 1))
    out.estimates.update({
        "imu_camera_rotation_chi2": rotation_z2, "reprojection_best_fit_median_px": run.fit_median,
        "conventions_checked": run.reliable, "imu_camera_rotation_error_deg": angle,
        "imu_camera_rotation_error_deg_se": angle_se, "imu_camera_rotation_correction_deg": np.degrees(phi).tolist(),
        "imu_camera_rotation_correction_deg_se": np.degrees(np.sqrt(np.clip(np.diag(phi_cov), 0, None))).tolist(),
        "gyro_bias_visual_radps": run.bias.tolist(), "gyro_bias_visual_radps_se": bias_se.tolist()})
    return out


def _analyse_time_offset(run: _Check) -> Analysis:
    """Camera-IMU time offset: grid around the chosen association, parabola at the minimum."""
    time_offset, time_se, grid = _time_offset(run.all_pairs, run.ts, run.u, run.C0, run.x, run.shift, run.dt,
                                              run.scale, run.rng)
    if time_se is not None:
        time_se = math.hypot(time_se, run.opts.time_offset_floor_s)
    run.time_offset, run.time_se = time_offset, time_se
    # the same relative to the filter's convention ("next"): a sample stamped t
    # describes the motion at t + this; one frame = the "current" association
    return Analysis({"time_offset_s": time_offset, "time_offset_s_se": time_se,
                     "time_offset_effective_s": (1 - run.shift) * run.dt + time_offset, "time_offset_grid": grid})


def _rotation_finding(run: _Check) -> Analysis:
    """The rotation's finding (ERROR beyond ``rotation_error_deg``, WARN when
    significant); with an unreliable fit none, and the conventions' estimates withdrawn."""
    opts, phi, angle = run.opts, run.phi, run.angle
    if not run.reliable:
        out = Analysis({"conventions_checked": False})
        out.notes.append(f"the tracks reproject with a median {run.fit_median:.1f} px even under the best rotation "
                         f"and association: rotation, association and time offset not reported")
        for key in ("imu_camera_rotation_error_deg", "imu_camera_rotation_error_deg_se",
                    "imu_camera_rotation_correction_deg", "imu_camera_rotation_correction_deg_se",
                    "time_offset_s", "time_offset_s_se", "time_offset_effective_s"):
            out.estimates[key] = None
        out.estimates["gyro_bias_visual_radps"] = [None] * 3
        out.estimates["gyro_bias_visual_radps_se"] = [None] * 3
        out.estimates["velocity_scale"] = out.estimates["velocity_scale_se"] = None
        return out
    out = Analysis()
    se_txt = f" ± {run.angle_se:.2f}" if run.angle_se is not None else ""
    if angle > opts.rotation_error_deg:
        out.findings.append(Finding("imu-camera-rotation", "ERROR",
                                    f"the velocities and cam_T_imu disagree by a {angle:.1f}{se_txt}° rotation "
                                    f"(axis-convention mismatch, e.g. a frame turned 180°): features reproject "
                                    f"with a median {run.est['reprojection_before_px']['median']:.1f} px under dead "
                                    f"reckoning; run with the suggested imu_camera_rotation_correction_deg"))
        out.suggested["imu_camera_rotation_correction_deg"] = [round(float(v), 3) for v in np.degrees(phi)]
    elif angle > opts.rotation_warn_deg and run.rotation_z2 > _cluster_threshold(3, run.rotation_clusters):
        out.findings.append(Finding("imu-camera-rotation", "WARN",
                                    f"cam_T_imu's rotation is off by {angle:.2f}{se_txt}° (correction "
                                    f"{_fmt_vec(np.degrees(phi), '.2f')}° about camera x, y, z): run with the "
                                    f"suggested imu_camera_rotation_correction_deg"))
        out.suggested["imu_camera_rotation_correction_deg"] = [round(float(v), 3) for v in np.degrees(phi)]
    else:
        out.findings.append(Finding("imu-camera-rotation", "OK",
                                    f"velocities and cam_T_imu agree (rotation error {angle:.2f}{se_txt}°); "
                                    f"nothing to do"))
    return out


def _association_findings(run: _Check) -> Analysis:
    """With a reliable fit: the findings of velocity association, velocity scale and
    time offset. The whole-frame part of the offset relative to "next" is the
    association when the comparison of whole-frame shifts agrees (else none); the rest
    is a time offset."""
    out = Analysis()
    if not run.reliable:
        return out
    opts, dt, shift, suggested = run.opts, run.dt, run.shift, out.suggested
    effective = (1 - shift) * dt + run.time_offset
    n_off = int(round(effective / dt)) if dt > 0 else 0
    if n_off != 1 - shift:
        n_off = 0
    frac = effective - n_off * dt
    if n_off != 0:
        if n_off == 1:
            suggested["velocity_association"] = "current"
            what = "the sample of frame k describes the interval k -> k+1, not the sample of k+1"
            fix = "velocity_association: current"
        else:
            suggested["time_offset_s"] = round(n_off * dt, 4)
            what = f"the sample of frame k{1 - n_off:+d} describes the interval k -> k+1"
            fix = f"time_offset_s: {suggested['time_offset_s']}"
        out.findings.append(Finding("velocity-association", "WARN",
                                    f"{what} (reprojection cost {run.totals[shift]:.0f} vs {run.totals[1]:.0f} for "
                                    f"k+1, z = {run.z_assoc:.1f}; offset {effective * 1000:.0f} ms): run with the "
                                    f"suggested {fix}"))
    else:
        out.findings.append(Finding("velocity-association", "OK",
                                    "the sample of frame k+1 describes the interval k -> k+1 (the filter's "
                                    f"convention; offset {effective * 1000:.0f} ms); nothing to do"))
    speed = float(np.median(np.linalg.norm(run.sequence.linear_velocity_in_imu_mps, axis=1)))
    noise = float(np.linalg.norm(np.nan_to_num(run.sv)))
    out.findings.append(_velocity_scale_finding(run.k_hat, run.k_se, opts, suggested,
                                                noise / speed if speed > 0 else 0.0))
    time_se = run.time_se
    ts_txt = f" ± {time_se * 1000:.0f}" if time_se is not None else ""
    if time_se is not None and abs(frac) > max(opts.time_offset_warn_s, 3 * time_se):
        suggested["time_offset_s"] = round(suggested.get("time_offset_s", 0.0) + frac, 4)
        out.findings.append(Finding("time-offset", "WARN",
                                    f"the velocities are {frac * 1000:.0f}{ts_txt} ms off the images (a sample "
                                    f"stamped t describes the motion at t + offset): run with the suggested "
                                    f"time_offset_s"))
    else:
        out.findings.append(Finding("time-offset", "OK",
                                    f"no camera-IMU time offset beyond {opts.time_offset_warn_s * 1000:.0f} ms "
                                    f"(estimate {frac * 1000:.0f}{ts_txt} ms); nothing to do"))
    return out


def _analyse_translation(run: _Check) -> Analysis:
    """With a reliable fit: the IMU-camera translation (:func:`_imu_camera_translation`)."""
    if not run.reliable:
        return Analysis()
    dt = run.dt
    k = int(round(run.opts.translation_smoothing_s / dt)) if run.noisy and dt > 0 else 1
    t_est, t_finding, t_cam_T_imu = _imu_camera_translation(
        run.pairs.subset(run.opts.translation_pairs, run.rng), run.ts, run.u, run.C0, run.phi, run.bias, run.shift,
        run.scale, max(1, k) | 1, run.opts)
    out = Analysis(t_est, [t_finding])
    if t_cam_T_imu is not None:
        out.suggested["cam_T_imu"] = t_cam_T_imu
    return out


def _analyse_pixel_noise(run: _Check) -> Analysis:
    """Pixel noise and gross outliers of the tracks (:func:`estimate_pixel_noise`)."""
    pix = estimate_pixel_noise(run.sequence)
    out = Analysis({"pixel_noise": pix})
    base = run.base
    if pix["sigma_px"] is None:
        out.findings.append(Finding("pixel-noise", "WARN", "too few tracks of 3+ frames to measure the pixel noise"))
        return out
    sev = "WARN" if pix["sigma_px"] > 2 * base.pixel_noise_px or pix["outlier_share"] > 0.2 else "OK"
    out.findings.append(Finding("pixel-noise", sev,
                                f"tracks scatter by {pix['sigma_px']:.2f} px per coordinate, "
                                f"{100 * pix['outlier_share']:.1f} % gross jumps (> {pix['outlier_threshold_px']:.0f} "
                                f"px); " + ("raise pixel_noise_px" if sev == "WARN" else
                                            f"the filter's {base.pixel_noise_px:g} px covers it")))
    return out


def _analyse_reprojection(run: _Check) -> Analysis:
    """Reprojection under dead reckoning after the corrections found (with 30+ predictions)."""
    if run.pairs.n_pairs < 30:
        return Analysis()
    opts, suggested, pairs = run.opts, run.suggested, run.pairs
    corrected = apply_corrections(run.sequence, FilterOptions.from_dict(
        {k: v for k, v in suggested.items()
         if k not in ("velocity_noise_mps", "angular_noise_radps", "timestamp_scale")}))  # (already applied)
    r_after = pairs.residuals(pairs.relative_imu(corrected.timestamps_s, corrected.velocities(), 1),
                              np.asarray(corrected.cam_T_imu))
    a = _percentiles(_left_distance(r_after))
    out = Analysis({"reprojection_after_px": a})
    b = run.est["reprojection_before_px"]
    sev = "OK" if a["median"] <= opts.max_fit_median_px else "WARN"
    changed = any(k in suggested for k in ("imu_camera_rotation_correction_deg", "cam_T_imu",
                                           "velocity_association", "time_offset_s", "gyro_bias_radps"))
    text = (f"tracks reproject under dead-reckoned poses (1-{opts.window} frames ahead) with median "
            f"{b['median']:.2f} px, p90 {b['p90']:.2f} px")
    moving = run.est.get("moving_landmarks") or {}
    if "reprojection_before_static_px" in run.est:
        bs = run.est["reprojection_before_static_px"]
        text += (f"; {moving['landmarks']} of {moving['of_landmarks']} landmarks "
                 f"({100 * moving['predictions_share']:.0f} % of the predictions) do not follow the world's motion "
                 f"(traffic or mismatched tracks) and were left out of the checks; the others: median "
                 f"{bs['median']:.2f} px, p90 {bs['p90']:.2f} px")
    if changed:
        text += f"; after the suggested corrections {a['median']:.2f} px, p90 {a['p90']:.2f} px"
    if sev == "OK":
        text += "; nothing to do"
    else:
        text += ("; the IMU and the images disagree beyond what check models (far, moving or mismatched "
                 "features?): IMU-camera rotation, velocity association and time offset could not be checked")
    out.findings.append(Finding("reprojection", sev, text))
    return out


def _analyse_tracker_artifacts(run: _Check) -> Analysis:
    """The findings on what ``vislam info`` counts: exact repeats, non-positive disparity."""
    o = run.est["observations"]
    rep_share = o["repeated_share"]
    frozen = o["repeated_longest_run"]
    text = (f"{o['repeated']} observations ({100 * rep_share:.1f} %) repeat the previous frame's pixels exactly "
            f"(tracker artifact: there the tracks restart on a new point; "
            f"{describe_repeat_evidence(o['repeat_evidence'])})")
    if frozen["seconds"] > JOB_LIMITS["frozen_s"]:
        repeated = Finding("repeated-observations", "WARN",
                           f"{text}; in frames {frozen['first_frame']}-{frozen['last_frame']} "
                           f"({frozen['seconds']:.1f} s) nearly every observation repeats (expected single frames, "
                           f"at most {JOB_LIMITS['frozen_s']:g} s): the images or the tracker froze while the IMU "
                           f"moved; those frames give the filters no visual update")
    else:
        repeated = Finding("repeated-observations", "OK", text + ": " + (
            "the filters handle them by default (repeated_observations: auto); nothing to do" if rep_share > 0
            else "nothing to do"))
    return Analysis(findings=[
        repeated,
        _disparity_finding(o, run.opts),
        _stereo_rows_finding(o, run.opts),
        stereo_depth_finding(run.est["stereo_depth"], run.opts),
        _duplicate_finding(o["duplicated"])])


def _disparity_finding(o: dict, opts: CheckOptions) -> Finding:
    """Non-positive disparities (uL <= uR): a few are far points or mismatches; most of
    them, a stereo pair whose left and right pixels are exchanged or not rectified."""
    n, npd, neg = o["total"], o["non_positive_disparity"], o["negative_disparity"]
    share = npd / n if n else 0.0
    text = f"{npd} observations ({100 * share:.1f} %) with non-positive disparity (uL <= uR)"
    if share <= opts.disparity_warn_share:
        return Finding("disparity", "OK", text + (": they cannot be triangulated; the filter skips them; nothing to do"
                                                  if npd else ": nothing to do"))
    text += ": the filters cannot triangulate them and skip them"
    if neg / n > 0.5:
        text += (f"; {100 * neg / n:.0f} % have uR > uL, as if the left and right pixels were exchanged "
                 "(uR, vR stored as uL, vL)")
    else:
        text += "; is the stereo pair rectified, and are the tracks matched between the images?"
    severity = "ERROR" if share > opts.disparity_error_share else "WARN"
    return Finding("disparity", severity, text + "; fix the features")


def _stereo_rows_finding(o: dict, opts: CheckOptions) -> Finding:
    """Rows that disagree (|vL - vR| beyond the filter's row guard): a rectified pair sees a
    point on the same row in both images; most of them beyond it, and no landmark starts."""
    n, r = o["total"], o["row_difference"]
    share = r["beyond_guard"] / n if n else 0.0
    text = (f"{r['beyond_guard']} observations ({100 * share:.1f} %) have |vL - vR| above the filter's "
            f"{r['guard_px']:g} px (max_row_difference_px)")
    if share <= opts.disparity_warn_share:
        return Finding("stereo-rows", "OK", text + ("; the filters do not start landmarks from them; nothing to do"
                                                    if r["beyond_guard"] else "; nothing to do"))
    text += (f" (median {r['median_px']:.3g} px): a rectified stereo pair sees a point on the same row in both "
             "images, and the filters start no landmark from these; is the pair rectified, and are the columns "
             "uL, vL, uR, vR in that order?")
    return Finding("stereo-rows", "ERROR" if share > opts.disparity_error_share else "WARN", text)


def stereo_depth_finding(z: dict, opts: CheckOptions) -> Finding:
    """The share of the depths within the filter's depth guards: a baseline in the wrong
    unit puts them all outside, and no landmark ever starts."""
    lo, hi = z["guards_m"]
    if not z["observations"]:
        return Finding("stereo-depth", "OK", "no observation with positive disparity to triangulate; nothing to do")
    share = z["within_guards_share"]
    text = (f"the baseline {z['baseline_m']:.4g} m and focal length {z['fsu_px']:.4g} px put the observations at a "
            f"median depth of {z['median_m']:.3g} m (10-90 %: {z['p10_m']:.3g}-{z['p90_m']:.3g} m); "
            f"{100 * share:.0f} % are within the filter's depth guards ({lo:g}-{hi:g} m)")
    if share >= opts.depth_warn_share:
        return Finding("stereo-depth", "OK", text + "; nothing to do")
    text += ": no landmark can start" if share == 0 else ": the others start no landmark"
    units = {1e-3: ", millimetres stored as metres?", 1e-2: ", centimetres stored as metres?"}
    options = [f"{z['baseline_m'] * f:.4g} m (the file's x {f:g}{units.get(f, '')}) would put {100 * v:.0f} %"
               for f, v in z["baseline_factors"]]
    if options:
        text += f"; a baseline of {' or '.join(options)} within them: check the baseline's unit"
    else:
        text += "; check the baseline and the intrinsics, or the depth guards (min_depth_m, max_depth_m)"
    severity = "ERROR" if share < opts.depth_error_share else "WARN"
    return Finding("stereo-depth", severity, text)


def _duplicate_finding(d: dict) -> Finding:
    if not d["observations"]:
        return Finding("duplicate-observations", "OK",
                       "no two landmarks share all four pixels in a frame; nothing to do")
    e = d["example"]
    return Finding("duplicate-observations", "WARN",
                   f"{d['observations']} observations of {d['landmarks']} landmarks, in {d['frames']} frames, have "
                   f"the same four pixels as another landmark's in the same frame (first: frame {e['frame']}, "
                   f"landmark {e['copy']} copies landmark {e['landmark']}): two ids on one point, which the filters "
                   f"count twice, so they trust the estimate more than the images allow; keep one id per point")


#: The reprojection analyses (with 30+ track predictions), in order: each reads what the
#: earlier ones found.
CONVENTION_ANALYSES = (
    ("best-start", _analyse_best_start),
    ("moving-landmarks", _analyse_moving_landmarks),
    ("velocity-scale", _analyse_velocity_scale),
    ("velocity-association", _analyse_association),
    ("imu-camera-rotation", _analyse_rotation),
    ("time-offset", _analyse_time_offset),
    ("rotation-finding", _rotation_finding),
    ("association-findings", _association_findings),
    ("imu-camera-translation", _analyse_translation),
)

#: The analyses of :func:`check_sequence`, in order: (name, function of the run returning
#: an :class:`Analysis`).
ANALYSES = (
    ("timestamps", _analyse_timestamps),
    ("observations", _analyse_observations),
    ("imu-noise", _analyse_imu_noise),
    ("gyro-bias", _analyse_gyro_bias),
    ("track-pairs", _analyse_track_pairs),
    ("conventions", _analyse_conventions),
    ("pixel-noise", _analyse_pixel_noise),
    ("reprojection", _analyse_reprojection),
    ("tracker-artifacts", _analyse_tracker_artifacts),
)


#: chi-square (3 dof) 99 % quantile: the significance test of the rotation error.
_CHI2_3DOF_99 = 11.34


def _cluster_threshold(p: int, clusters: int, level: float = 0.99) -> float:
    """The ``level`` threshold of z² = φᵀ Σ⁻¹ φ for p parameters whose covariance Σ is a
    cluster sandwich over ``clusters`` blocks of frames (:func:`_sandwich_covariance`):
    Hotelling's T², p (G − 1) / (G − p) · F(p, G − p), which tends to χ²(p) (11.34 for 3)
    on long recordings (158 blocks: 11.9) and grows on short ones, where a sandwich of few
    blocks underestimates Σ (40-frame simulated drives, 6 blocks: 2 of 10 false rotation
    WARNs at χ²(3); 147 with the threshold). Infinite with p or fewer blocks."""
    if clusters <= p:
        return math.inf
    from scipy.stats import f as f_dist

    return p * (clusters - 1) / (clusters - p) * float(f_dist.ppf(level, p, clusters - p))
#: chi-square (2 dof) 99 % quantile: the significance test of the translation error.
_CHI2_2DOF_99 = 9.21


def _paired_z(diff: np.ndarray, landmark: np.ndarray) -> float:
    """z-score of the total of ``diff`` (per pair), with the pairs of a landmark summed first."""
    if diff.size == 0:
        return 0.0
    _, inv = np.unique(landmark, return_inverse=True)
    per = np.bincount(inv, weights=diff)
    if per.size < 2:
        return 0.0
    sd = float(np.std(per, ddof=1))
    return float(np.sum(per) / (sd * math.sqrt(per.size))) if sd > 0 else 0.0


def _fourier_shift(u: np.ndarray, shift_samples: float) -> np.ndarray:
    """The (T, k) signal ``u`` at the times ``t − shift_samples`` (in samples), by a
    band-limited (Fourier phase) shift of its mirrored extension. Unlike linear
    interpolation, this all-pass shift keeps the level of white noise unchanged, so the
    reprojection costs of different offsets compare the timing, not the smoothing."""
    if shift_samples == 0:
        return u.copy()
    T = u.shape[0]
    ext = np.concatenate([u, u[::-1]], axis=0)  # mirrored: no jump at the wrap-around
    f = np.fft.rfftfreq(ext.shape[0])
    spec = np.fft.rfft(ext, axis=0) * np.exp(-2j * np.pi * f * shift_samples)[:, None]
    return np.fft.irfft(spec, n=ext.shape[0], axis=0)[:T]


def _time_offset(pairs: _TrackPairs, ts, u, C0, x, shift: int, dt: float, scale: float, rng):
    """Time offset (s) minimizing the reprojection cost, its bootstrap standard error and the grid."""
    ub = _debiased(u, x[3:])
    C = _turned(C0, x[:3])
    grid = np.linspace(-dt, dt, 11)
    inv = pairs.groups[1]
    per = []
    for delta in grid:
        uu = _fourier_shift(ub, float(delta) / dt)
        per.append(np.bincount(inv, weights=_cauchy_cost(pairs.residuals(pairs.relative_imu(ts, uu, shift), C),
                                                          scale)))
    per = np.array(per)  # (G, L)

    def vertex(costs):
        i = int(np.argmin(costs))
        i = min(max(i, 1), len(grid) - 2)
        y0, y1, y2 = costs[i - 1], costs[i], costs[i + 1]
        den = y0 - 2 * y1 + y2
        h = grid[1] - grid[0]
        off = 0.5 * (y0 - y2) / den if den > 0 else 0.0
        return float(grid[i] + np.clip(off, -1, 1) * h)

    best = vertex(per.sum(axis=1))
    boots = []
    L = per.shape[1]
    for _ in range(50):
        idx = rng.integers(0, L, L)
        boots.append(vertex(per[:, idx].sum(axis=1)))
    se = float(np.std(boots, ddof=1)) if L > 1 else None
    return best, se, {"offsets_s": grid.tolist(), "cost": per.sum(axis=1).tolist()}
