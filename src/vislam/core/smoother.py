"""A sliding-window (fixed-lag) smoother over the EKF's measurements, on GTSAM.

:class:`SmootherFilter` has the stepwise API of :mod:`vislam.core.filters` (``predict``,
``update``, ``step``, read access, ``finish``), so :func:`vislam.core.estimators.drive`
runs it like any EKF. Its factor graph, per frame k:

* a pose ``X(k) = world_T_imu[k]`` (GTSAM's Pose3, tangent (ω, v), right perturbation);
* the motion model ``world_T_imu[k] = world_T_imu[k−1] · exp(τ_k u_k)`` with covariance
  ``τ_k² W`` (W reordered to (ω, v)): with levelled velocities (``velocity_frame``
  "level", the default) a :func:`level_odometry_error` factor — the gyro's rotation
  between the poses and the displacement compared in the level frame of pose k−1, so
  it does not hold the roll and pitch of the moment it was created — and with
  body-frame velocities a ``BetweenFactorPose3``; the first pose has a prior at the
  identity (the world frame);
* each stereo observation ``[uL, vL, uR, vR]`` as a ``GenericStereoFactor3D`` on
  ``StereoPoint2(uL, uR, (vL+vR)/2)`` with σ = ``smoother_pixel_noise_px`` (σ/√2 on the row), the
  IMU-to-camera transform as ``body_P_sensor`` and a robust kernel
  (``smoother_kernel``, ``smoother_kernel_scale`` in σ);
* a new landmark from the EKF's initialization guards and the stereo model's inverse,
  with a weak prior (``smoother_landmark_prior_m``) around the triangulation — it keeps
  a landmark determined when its projections lose their Jacobian (behind the camera).

``gtsam.IncrementalFixedLagSmoother`` (iSAM2, one Gauss-Newton step per frame,
relinearization threshold ``smoother_relinearize_threshold``) keeps the poses of the
last ``smoother_window_s`` seconds and the landmarks observed in that time and
marginalizes the rest. What leaves the window is final: each pose's estimate when it
leaves (:meth:`SmootherFilter.final_trajectory`), each landmark's estimate and 3x3
covariance into the map (the covariance given the poses: the information of its own
factors — GTSAM's marginal of a landmark deep in the Bayes tree costs ~50 ms). ``step``
gives the online estimate of the current pose (read by ``drive`` frame by frame, kept
as ``result.extra["online_world_T_imu"]``); the result's trajectory is the final one.
With ``smoother_pose_covariance`` the marginal covariance of the newest pose is computed
every frame (``pose_covariance``; as costly as the update, so off by default).

Stalled tracks (``stalled_tracks``): at the feature files' re-detection frames the
continuing tracks repeat their previous pixels, and from then on they are one frame
late. The repeat is dropped (``RepeatDetector``) and, with "remap", an observation at
frame k of a track that has stalled L times since it began is attached to pose k − L
(the stall count is kept per id from the track's first observation, guards or not).
With ``repeated_observations: split`` a repeat ends its track instead and starts a new
landmark of the same id, in sync ("auto", the default, is "skip" with the remap here).

Outliers: besides the kernel, the observations of frame t are checked after the update
of frame t + 1; those whose whitened error exceeds ``smoother_outlier_sigma`` are
removed with the next update (gated); a landmark gated ``max_consecutive_gated`` times
in a row is rejected (no further factors; flagged in the map). An observation whose
remapped pose has left the window is dropped (counted as gated).

Moving landmarks (``smoother_drift_ratio``, ``smoother_drift_min_speed_mps``): after
the same update, the landmarks observed in frame t get a drift test over their
observations in the window (:meth:`SmootherFilter._drift_test`): a point on a moving
vehicle, fitted as static, leaves residuals with a one-signed trend in time. One whose
trend statistic exceeds ``smoother_drift_ratio`` times the median of the frame's tested
landmarks and whose apparent speed exceeds ``smoother_drift_min_speed_mps`` is rejected
and all its factors still in the window are removed (counted in ``landmarks_moving``).

:func:`refine` (``--refine``): batch Levenberg–Marquardt over every factor of the drive
from the smoother's final estimate, robust (``refine_kernel``), then a second pass
without the stereo factors whose reprojection error exceeds ``refine_outlier_px``.

Covariances are returned in the EKF's convention: for T = world_T_imu with right
perturbation ξ = (ω, v), imu_T_world = T⁻¹ has left perturbation −ξ — the same
covariance with the blocks reordered to (v, ω).
"""

from __future__ import annotations

import logging
import math
import re
import time

import numpy as np

from vislam.core.bookkeeping import MapBuilder, RepeatDetector, admitted_count, sorted_positions
from vislam.core.contract import FrameStats, FrameStatsCounter, LandmarkEstimates, StepwiseFilter
from vislam.core.contract import checked_dt as _check_dt
from vislam.core.contract import checked_frame as _frame
from vislam.core.contract import checked_observations as _observations
from vislam.core.contract import twist as _twist
from vislam.core.lie import se3_inverse
from vislam.core.propagation import body_to_level, body_twist
from vislam.core.options import FilterOptions
from vislam.core.results import LANDMARK_OK, LANDMARK_REJECTED, LandmarkMap, RunStats
from vislam.core.sequence import Calibration, Frame
from vislam.core.updaters import StereoModel, initialization_guard, mapping_initialize
from vislam.errors import ConfigError, EstimationError

logger = logging.getLogger(__name__)

__all__ = ["SmootherFilter", "run_smoother", "refine", "to_ekf_covariance"]

#: Fewest landmarks tested in a frame for the drift test's median (else no test).
_MIN_DRIFT_POPULATION = 10

#: GTSAM's Symbol keys: the character in the top 8 bits, the index below (gtsam.symbol).
_X_BASE, _L_BASE = ord("x") << 56, ord("l") << 56

#: (v, ω) <-> (ω, v): the same permutation both ways.
_PERM = np.array([3, 4, 5, 0, 1, 2])


def to_ekf_covariance(cov_gtsam: np.ndarray) -> np.ndarray:
    """GTSAM Pose3 marginal (right perturbation of world_T_imu, (ω, v)) -> the EKF's
    (left perturbation of imu_T_world, (v, ω)): the sign flip leaves Σ unchanged, the
    blocks swap."""
    cov = np.asarray(cov_gtsam, dtype=np.float64)
    return cov[np.ix_(_PERM, _PERM)]


def _gtsam():
    try:
        import gtsam
    except ImportError as exc:  # pragma: no cover - gtsam is a dependency
        raise ConfigError("mode smoother needs the gtsam package (pip install gtsam)") from exc
    return gtsam


_GTSAM_KEY = re.compile(r"variable \d+ \(Symbol: ([xl])(\d+)\)")


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line (GTSAM's span several, with blank lines), with
    GTSAM's keys named as the smoother's variables (``x151`` the pose of frame 151,
    ``l7`` landmark key 7) and without its pointers to its documentation."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    text = _GTSAM_KEY.sub(lambda m: f"variable {m[1]}{m[2]} ({'the pose of frame' if m[1] == 'x' else 'landmark'} "
                          f"{m[2]})", text)
    cut = text.find(" See the GTSAM")
    return (text[:cut] if cut > 0 else text).rstrip(". ")


def _rigid(T: np.ndarray) -> np.ndarray:
    """T with its rotation projected onto SO(3) (recorded transforms are rigid to ~1e-7)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = R
    out[3] = (0, 0, 0, 1)
    return out


def _kernel(gtsam, name: str, scale: float, base):
    if name == "none":
        return base
    est = gtsam.noiseModel.mEstimator
    m = est.Cauchy.Create(scale) if name == "cauchy" else est.Huber.Create(scale)
    return gtsam.noiseModel.Robust.Create(m, base)


def level_odometry_error(world_T_i: np.ndarray, world_T_j: np.ndarray, delta_R: np.ndarray, d_level: np.ndarray,
                         jacobians: bool = False):
    """Error of the levelled motion model between two poses, in GTSAM's (ω, v) order::

        e_ω = Log(ΔRᵀ · R_iᵀ R_j)                (the gyro's rotation over the step)
        e_v = Rz(ψ_i)ᵀ (t_j − t_i) − d_level     (the displacement in the level frame of pose i)

    with world_T_i = (R_i, t_i), ψ_i the heading of pose i's x axis in the world's
    horizontal plane, ΔR = exp(τ ω) and d_level the step's displacement in the level
    frame (τ v_level and the turn's curvature). The displacement is compared in the
    level frame, not in the body frame, so the factor says nothing about the poses'
    roll and pitch through the translation: a ``BetweenFactorPose3`` with the levelled
    velocity turned into the body frame at creation would hold the pitch estimated
    then (measured: the smoother climbed ~50 m on dense 0034).

    With ``jacobians``: also (H_i, H_j), the 6x6 derivatives with respect to GTSAM's
    right perturbations (ω, v) of each pose (R → R exp(ω^), t → t + R v), tested
    against finite differences."""
    out = _level_odometry(np.asarray(world_T_i, dtype=np.float64).tolist(),
                          np.asarray(world_T_j, dtype=np.float64).tolist(),
                          np.asarray(delta_R, dtype=np.float64).tolist(),
                          np.asarray(d_level, dtype=np.float64).tolist(), jacobians)
    return out if jacobians else out[0]


def _level_odometry(Ti: list, Tj: list, dR: list, dl: list, jacobians: bool):
    """:func:`level_odometry_error` on nested lists (the rows of the 4x4 poses and of ΔR;
    d_level): (e, H_i, H_j), the Jacobians None without ``jacobians``. Scalar arithmetic
    on Python floats on purpose: GTSAM calls it back ~30 times a frame (the iSAM2 batch
    step relinearizes every odometry factor of the window), where numpy's per-call
    overhead on 3x3 blocks cost 3x more than the arithmetic."""
    (a00, a01, a02, ti0), (a10, a11, a12, ti1), (a20, a21, a22, ti2) = Ti[0], Ti[1], Ti[2]
    (b00, b01, b02, tj0), (b10, b11, b12, tj1), (b20, b21, b22, tj2) = Tj[0], Tj[1], Tj[2]
    # R_ij = R_iᵀ R_j
    q00, q01, q02 = a00 * b00 + a10 * b10 + a20 * b20, a00 * b01 + a10 * b11 + a20 * b21, a00 * b02 + a10 * b12 + a20 * b22
    q10, q11, q12 = a01 * b00 + a11 * b10 + a21 * b20, a01 * b01 + a11 * b11 + a21 * b21, a01 * b02 + a11 * b12 + a21 * b22
    q20, q21, q22 = a02 * b00 + a12 * b10 + a22 * b20, a02 * b01 + a12 * b11 + a22 * b21, a02 * b02 + a12 * b12 + a22 * b22
    (d00, d01, d02), (d10, d11, d12), (d20, d21, d22) = dR
    Rot3 = _gtsam().Rot3  # its Logmap and LogmapDerivative: 100x faster than scipy's for one matrix
    e_r = Rot3.Logmap(Rot3(  # ΔRᵀ R_ij
        d00 * q00 + d10 * q10 + d20 * q20, d00 * q01 + d10 * q11 + d20 * q21, d00 * q02 + d10 * q12 + d20 * q22,
        d01 * q00 + d11 * q10 + d21 * q20, d01 * q01 + d11 * q11 + d21 * q21, d01 * q02 + d11 * q12 + d21 * q22,
        d02 * q00 + d12 * q10 + d22 * q20, d02 * q01 + d12 * q11 + d22 * q21, d02 * q02 + d12 * q12 + d22 * q22))
    n2 = a00 * a00 + a10 * a10  # the heading ψ: x axis of the body in the world
    n = math.sqrt(n2)
    c, s = a00 / n, a10 / n  # cos ψ, sin ψ
    x, y, z = tj0 - ti0, tj1 - ti1, tj2 - ti2
    er0, er1, er2 = e_r.tolist()
    e = np.array([er0, er1, er2, c * x + s * y - dl[0], -s * x + c * y - dl[1], z - dl[2]])  # Rz(ψ)ᵀ d − d_level
    if not jacobians:
        return e, None, None
    (j00, j01, j02), (j10, j11, j12), (j20, j21, j22) = Rot3.LogmapDerivative(e_r).tolist()  # Jr⁻¹(φ)
    # ψ under R_i exp(ω^): the first column moves by R_i (ω × e_x) = −R_i [e_x]× ω, so
    # d(c0, c1)/dω = [[0, −R02, R01], [0, −R12, R11]] and dψ = (c0 dc1 − c1 dc0) / (c0² + c1²)
    dpsi_y = (a10 * a02 - a00 * a12) / n2
    dpsi_z = (a00 * a11 - a10 * a01) / n2
    g0, g1 = -s * x + c * y, -c * x - s * y  # (d Rz(ψ)ᵀ / dψ) d, its z row is 0
    H_i = np.array([  # ΔRᵀR_iᵀR_j → (…) exp(−R_ijᵀ ω_i): −Jr⁻¹ R_ijᵀ; t_i + R_i v_i: −Rz(ψ)ᵀ R_i
        -(j00 * q00 + j01 * q01 + j02 * q02), -(j00 * q10 + j01 * q11 + j02 * q12), -(j00 * q20 + j01 * q21 + j02 * q22),
        0.0, 0.0, 0.0,
        -(j10 * q00 + j11 * q01 + j12 * q02), -(j10 * q10 + j11 * q11 + j12 * q12), -(j10 * q20 + j11 * q21 + j12 * q22),
        0.0, 0.0, 0.0,
        -(j20 * q00 + j21 * q01 + j22 * q02), -(j20 * q10 + j21 * q11 + j22 * q12), -(j20 * q20 + j21 * q21 + j22 * q22),
        0.0, 0.0, 0.0,
        0.0, g0 * dpsi_y, g0 * dpsi_z, -(c * a00 + s * a10), -(c * a01 + s * a11), -(c * a02 + s * a12),
        0.0, g1 * dpsi_y, g1 * dpsi_z, s * a00 - c * a10, s * a01 - c * a11, s * a02 - c * a12,
        0.0, 0.0, 0.0, -a20, -a21, -a22]).reshape(6, 6)
    H_j = np.array([  # (…) exp(ω_j): Jr⁻¹; t_j + R_j v_j: Rz(ψ)ᵀ R_j
        j00, j01, j02, 0.0, 0.0, 0.0,
        j10, j11, j12, 0.0, 0.0, 0.0,
        j20, j21, j22, 0.0, 0.0, 0.0,
        0.0, 0.0, 0.0, c * b00 + s * b10, c * b01 + s * b11, c * b02 + s * b12,
        0.0, 0.0, 0.0, c * b10 - s * b00, c * b11 - s * b01, c * b12 - s * b02,
        0.0, 0.0, 0.0, b20, b21, b22]).reshape(6, 6)
    return e, H_i, H_j


def _level_odometry_factor(g, key_i: int, key_j: int, delta_R: np.ndarray, d_level: np.ndarray, noise):
    """A ``gtsam.CustomFactor`` of :func:`level_odometry_error`. It keeps its last
    linearization: the iSAM2 batch step relinearizes every factor of the window each
    frame, and a third of the time neither pose has moved since (the relinearization
    threshold), so the same error and Jacobians are handed back without recomputing them."""
    dR, dl = delta_R.tolist(), d_level.tolist()
    last: list = [None, None, None]  # rows of T_i, rows of T_j, (e, H_i, H_j)

    def error(_factor, values, H):
        Ti = values.atPose3(key_i).matrix().tolist()
        Tj = values.atPose3(key_j).matrix().tolist()
        if H is None:
            return _level_odometry(Ti, Tj, dR, dl, False)[0]
        if Ti == last[0] and Tj == last[1]:
            out = last[2]
        else:
            out = _level_odometry(Ti, Tj, dR, dl, True)
            last[:] = Ti, Tj, out
        H[0] = out[1]
        H[1] = out[2]
        return out[0]

    return g.CustomFactor(noise, [key_i, key_j], error)


class _Landmark:
    """A landmark in the smoother (its track may have ended: it stays until marginalized)."""

    __slots__ = ("key", "id", "nobs", "ngated", "first", "last", "consecutive", "rejected", "stamp", "obs")

    def __init__(self, key: int, lm_id: int, t: int, stamp: float):
        self.key, self.id = key, lm_id
        self.obs: list = []  # (frame of the pose, pixels) of the observations kept
        self.nobs, self.ngated, self.first, self.last = 1, 0, t, t
        self.consecutive, self.rejected, self.stamp = 0, False, stamp


class _NewFactors:
    """What one frame adds to the window: the factor graph, initial values and time
    stamps of the update, and its stereo factors' entries (their graph positions become
    the smoother's factor indices after the update) and ``added`` (landmark, pose frame,
    pixels, entry) of the observations of landmarks already in the window."""

    __slots__ = ("graph", "values", "stamps", "entries", "added")

    def __init__(self, graph, values, stamps: dict):
        self.graph, self.values, self.stamps = graph, values, stamps
        self.entries: list = []
        self.added: list = []


class SmootherFilter(StepwiseFilter):
    """Fixed-lag smoother with the stepwise API of the EKFs (see the module docstring).

    ``calibration``: ``sequence.calibration`` (camera and cam_T_imu); ``options``: a
    :class:`FilterOptions` (motion and pixel noise, guards, ``stalled_tracks``,
    ``smoother_*``, ``refine_*``).
    """

    mode = "smoother"

    def __init__(self, calibration: Calibration, options: FilterOptions | None = None):
        gtsam = self._g = _gtsam()
        self._init_history()  # and the diagnostics: failed, drift_log, timings
        self.calibration = calibration
        self.options = opts = options or FilterOptions()
        cam = calibration.camera
        self._model = StereoModel(cam, calibration.cam_T_imu)
        self._V = opts.V
        self._K = gtsam.Cal3_S2Stereo(cam.fsu, cam.fsv, 0.0, cam.cu, cam.cv, cam.baseline_m)
        self._body_P_sensor = gtsam.Pose3(_rigid(self._model.imu_T_cam))
        s = opts.pixel_noise_px if opts.smoother_pixel_noise_px is None else opts.smoother_pixel_noise_px
        self._sigmas = np.array([s, s, s / np.sqrt(2.0)])
        base = gtsam.noiseModel.Diagonal.Sigmas(self._sigmas)
        self._stereo_noise = _kernel(gtsam, opts.smoother_kernel, opts.smoother_kernel_scale, base)
        self._stereo_base = base
        self._lm_prior = gtsam.noiseModel.Isotropic.Sigma(3, opts.smoother_landmark_prior_m)
        W = opts.W
        self._W_gtsam = W[np.ix_(_PERM, _PERM)]
        sp = max(opts.initial_position_std_m, 1e-6)
        sr = max(opts.initial_rotation_std_rad, 1e-6)
        self._pose_prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([sr, sr, sr, sp, sp, sp]))
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(opts.smoother_relinearize_threshold)
        params.relinearizeSkip = 1
        # removed and marginalized factors' slots are reused: without it iSAM2's factor array
        # grows by every factor of the drive (~50 000 slots on a dense file), and its batch
        # step, taken every frame here, walks and copies them all (dense 0034: ~25 % of a frame)
        params.findUnusedFactorSlots = True
        self._window = float(opts.smoother_window_s)
        self._smoother = gtsam.IncrementalFixedLagSmoother(self._window, params)
        # "split": a repeat ends its track and starts a new one, in sync (no remap)
        repeated = opts.repeated_policy("smoother")
        self._split = repeated == "split"
        self._remap = opts.stalled_tracks == "remap" and repeated == "skip"

        self.stats = RunStats()
        self._delta = FrameStatsCounter(self.stats)
        self._repeated = RepeatDetector(repeated != "use", self.stats, calibration.camera)
        self._builder = MapBuilder()
        self.frame_index = -1
        self.last_frame_stats = FrameStats(frame=-1)
        self._time = 0.0  # seconds since the first frame
        self._pending_odometry = None  # (τ, u) of the next frame
        # window contents
        self._pose_stamp: dict[int, float] = {}  # frame -> timestamp, poses in the window
        self._pose_value: dict[int, np.ndarray] = {}  # frame -> world_T_imu estimate (latest)
        self._landmarks: dict[int, _Landmark] = {}  # key -> landmark in the window
        self._tracks: dict[int, int] = {}  # dataset id -> key of its track in progress
        self._rejected_ids: set[int] = set()  # ids of rejected tracks still in view
        self._prev_ids = np.zeros(0, dtype=np.int64)  # ids of the previous frame (every observation)
        self._prev_lag = np.zeros(0, dtype=np.int64)  # their stall counts
        self._next_key = 0
        self._current = np.eye(4)
        self._current_cov = None
        # final values
        self._final_pose: dict[int, np.ndarray] = {}
        self._final_cursor = 0  # the next frame pop_final_poses hands out
        self._online_cov: dict[int, np.ndarray] = {}  # marginal of each pose when it was the newest
        self._final_lm: dict[int, np.ndarray] = {}  # key -> p (for refine)
        # every factor of the drive, for refine
        self._odometry_factors: list = []
        self._prior_factors: list = []
        self._stereo_factors: list = []  # GenericStereoFactor3D (the smoother's noise model)
        self._stereo_pix = np.zeros((1024, 4))  # their pixels [uL, vL, uR, vR], row = index in _stereo_factors
        self._stereo_removed: set[int] = set()
        self._to_remove: list[int] = []  # smoother factor indices to remove with the next update
        self._unchecked: tuple = (-1, [])  # (frame, observations, factor indices) not yet checked
        self._drift_gate = np.inf if opts.smoother_drift_ratio is None else float(opts.smoother_drift_ratio)
        self._fresh: set[int] = set()  # frames whose _pose_value is from the latest update
        self.diagnostics.timings = {"marginals_s": 0.0, "update_s": 0.0}

    # --- read access ----------------------------------------------------------------
    @property
    def world_T_imu(self) -> np.ndarray:
        """(4, 4) online estimate of the current IMU pose."""
        return self._current.copy()

    @property
    def imu_T_world(self) -> np.ndarray:
        return se3_inverse(self._current)

    @property
    def pose_covariance(self) -> np.ndarray | None:
        """(6, 6) marginal covariance of the current pose (EKF convention: left
        perturbation of imu_T_world, (v, ω))."""
        return None if self._current_cov is None else self._current_cov.copy()

    @property
    def live_landmark_ids(self) -> np.ndarray:
        """Ids of the landmarks in the window (not rejected)."""
        ids = [lm.id for lm in self._landmarks.values() if not lm.rejected]
        return np.array(sorted(ids), dtype=np.int64)

    @property
    def live_p_lm_in_world(self) -> np.ndarray:
        lms = sorted((lm for lm in self._landmarks.values() if not lm.rejected), key=lambda lm: lm.id)
        if not lms:
            return np.zeros((0, 3))
        return np.array([self._smoother.calculateEstimatePoint3(self._L(lm.key)) for lm in lms])

    def landmark_estimates(self) -> LandmarkEstimates:
        """The landmarks in the window (not rejected) as world points; their covariances
        are NaN (computed only when a landmark leaves the window)."""
        ids = self.live_landmark_ids
        return LandmarkEstimates(ids, self.live_p_lm_in_world, np.full((ids.size, 3, 3), np.nan))

    def frozen_map(self) -> LandmarkMap:
        """The landmarks marginalized so far (a copy)."""
        return self._builder.snapshot()

    def final_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """After :meth:`finish`: ((T, 4, 4) final world_T_imu of every frame processed —
        each pose's value when it left the window or at the end — and (T, 6, 6) the
        marginal covariance of each pose when it was the newest (the online one, EKF
        convention; the smoothed pose is at least as certain), or None without
        ``smoother_pose_covariance``)."""
        n = self.frame_index + 1
        poses = np.array([self._final_pose.get(k, np.full((4, 4), np.nan)) for k in range(n)]).reshape(n, 4, 4)
        if not self.options.smoother_pose_covariance:
            return poses, None
        covs = np.array([self._online_cov.get(k, np.full((6, 6), np.nan)) for k in range(n)]).reshape(n, 6, 6)
        return poses, covs

    def pop_final_poses(self) -> list:
        """``[(t, world_T_imu (4, 4)), ...]``: the poses that became final since the last
        call (they left the window, or :meth:`finish` froze the window), in frame order —
        the values :meth:`final_trajectory` returns. Unlike the EKFs' it does not take
        the frames of :meth:`pop_processed`, which hands out the online estimates."""
        out = []
        while self._final_cursor in self._final_pose:
            out.append((self._final_cursor, self._final_pose[self._final_cursor].copy()))
            self._final_cursor += 1
        return out

    # --- keys -------------------------------------------------------------------------
    def _X(self, k: int) -> int:
        return _X_BASE + k  # gtsam.symbol("x", k), without a call into GTSAM (~300 keys a frame)

    def _L(self, key: int) -> int:
        return _L_BASE + key  # gtsam.symbol("l", key)

    # --- the frame --------------------------------------------------------------------
    def step(self, frame: Frame) -> FrameStats:
        """:meth:`predict` with the frame's velocity sample (not for the first frame), then :meth:`update`."""
        _frame(frame)
        if self.frame_index >= 0:
            self.predict(frame.dt_s, frame.linear_velocity_mps, frame.angular_velocity_radps)
        return self.update(frame.landmark_ids, frame.pixels)

    def predict(self, dt_s: float, linear_velocity, angular_velocity) -> None:
        """Odometry of the interval ending at the next frame: the next :meth:`update`
        adds the pose ``X(k) = X(k−1) · exp(τ u)`` with covariance τ² W."""
        self._require_healthy()
        tau = _check_dt(dt_s)
        self._pending_odometry = (tau, _twist(linear_velocity, angular_velocity))
        self._repeated.set_motion(tau, linear_velocity, angular_velocity)

    def update(self, ids, pixels) -> FrameStats:
        """Add the frame's pose and observations, update the window, marginalize what
        leaves it. Raises EstimationError on a numerical failure (the smoother stops)."""
        self._require_healthy()
        ids_seen, z = _observations(ids, pixels)
        if self.frame_index >= 0 and self._pending_odometry is None:
            raise ConfigError("update: call predict (the odometry of the interval) before each frame but the first")
        self.frame_index += 1
        t = self.frame_index
        self.stats.frames += 1
        self.stats.observations_total += ids_seen.size
        self._delta.begin()
        try:
            self._frame(t, ids_seen, z)
        except EstimationError as exc:
            self.diagnostics.failed = str(exc)
            raise
        except RuntimeError as exc:  # gtsam: indeterminate system, cheirality, ... (messages of several lines)
            self.diagnostics.failed = f"numerical failure at frame {t}: {_one_line(exc)}"
            raise EstimationError(self.diagnostics.failed, frame=t) from exc
        except Exception as exc:  # noqa: BLE001 - any other failure inside GTSAM or here: one line, a partial result
            self.diagnostics.failed = f"failure at frame {t}: {type(exc).__name__}: {_one_line(exc)}"
            raise EstimationError(self.diagnostics.failed, frame=t) from exc
        self.stats.frames_processed += 1
        n_live = sum(1 for lm in self._landmarks.values() if not lm.rejected)
        self.stats.max_state_landmarks = max(self.stats.max_state_landmarks, len(self._landmarks))
        self.last_frame_stats = self._delta.end(t, ids_seen.size, n_live, 0.0, 0)
        self._record(self.last_frame_stats)  # the online estimate; drive() swaps in final_trajectory()
        return self.last_frame_stats

    def _frame(self, t: int, ids_seen: np.ndarray, z: np.ndarray) -> None:
        """One frame, in the EKF's order of steps (see :meth:`vislam.core.filters.SlamFilter.update`)."""
        g = self._g
        new = _NewFactors(g.NonlinearFactorGraph(), g.Values(), {})
        X = self._X(t)
        self._predict_pose(t, new)  # the motion model (the EKF's predict)
        now = self._time
        cutoff = now - self._window
        rep, lag = self._select(ids_seen, z, t)  # repeats, stall counts, tracks (its _select)
        pending = self._add_observations(t, ids_seen, z, rep, lag, now, cutoff, new)  # in the window (_update_live)
        if pending[0]:
            self._initialize_new(t, *pending, now, new)  # new landmarks (its _initialize_new)
        # what leaves the window in this update (its _marginalize_ended): final values and marginals first
        self._marginalize(cutoff)
        self._update_window(t, X, new)
        # gate and reject (its _reject): the previous frame's observations, whose poses and
        # landmarks have had two updates now; those that fail are removed with the next update
        previous, self._unchecked = self._unchecked, (t, new.added)
        self._check_outliers(*previous)

    def _predict_pose(self, t: int, new: "_NewFactors") -> None:
        """Step 1: the pose X(t) with its factor: the prior at the identity for the first
        frame, else the motion model from X(t−1) with the pending odometry (its initial
        value the latest estimate moved by it)."""
        g = self._g
        X = self._X(t)
        if t == 0:
            pose = np.eye(4)
            f = g.PriorFactorPose3(X, g.Pose3(pose), self._pose_prior)
            self._prior_factors.append(f)
        else:
            tau, u_rec = self._pending_odometry
            # the linear velocity in the body frame of the latest estimate (the initial value)
            imu_T_world = se3_inverse(self._current)
            u = body_twist(u_rec, imu_T_world, self.options.velocity_frame)
            xi = np.concatenate([u[3:], u[:3]]) * tau  # (ω, v) τ
            step = g.Pose3.Expmap(xi)
            pose = self._current @ step.matrix()
            if tau > self._window:
                # a time gap longer than the window: everything before it leaves the window
                # now, and the held velocity sample over it is a guess; the smoother starts
                # again from the dead-reckoned pose, held as the first one is (an odometry
                # factor over kilometres couples the heading to the position so strongly that
                # GTSAM found the system indeterminate: seen from gaps of ~400 s)
                f = g.PriorFactorPose3(X, g.Pose3(pose), self._pose_prior)
                self._prior_factors.append(f)
                self.diagnostics.restarts.append(t)
            else:
                cov = tau * tau * self._W_gtsam + 1e-12 * np.eye(6)
                noise = g.noiseModel.Gaussian.Covariance(cov)
                if self.options.velocity_frame == "level":
                    # the step's displacement back in the level frame: τ v_level plus the turn's
                    # curvature (roll and pitch enter only this second-order term)
                    d_level = body_to_level(imu_T_world, step.translation())
                    f = _level_odometry_factor(g, self._X(t - 1), X, step.rotation().matrix(), d_level, noise)
                else:
                    f = g.BetweenFactorPose3(self._X(t - 1), X, step, noise)
                self._odometry_factors.append((t, f))
            self._time += tau
        self._pending_odometry = None
        new.graph.add(f)
        new.values.insert(X, g.Pose3(pose))
        new.stamps[X] = self._time
        self._pose_stamp[t] = self._time
        self._pose_value[t] = pose

    def _select(self, ids_seen: np.ndarray, z: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Step 2: the frame's exact repeats and each observation's stall count (the
        remap attaches it to pose t − lag); tracks not seen end, rejected ones out of view
        are forgotten. Returns (repeat mask, lag)."""
        rep = self._repeated(t, ids_seen, z)
        if self._split and rep.any():
            for i in ids_seen[rep].tolist():
                self._tracks.pop(i, None)  # the track ends; the repeat starts a new one
            rep = np.zeros_like(rep)
        pos, hit = sorted_positions(ids_seen, self._prev_ids)
        lag = np.where(hit, self._prev_lag[pos] if self._prev_ids.size else 0, 0)
        if self._remap:
            lag = lag + rep
        self._prev_ids, self._prev_lag = ids_seen, lag
        ended = set(self._tracks) - set(ids_seen.tolist())
        for i in ended:
            del self._tracks[i]
        self._rejected_ids &= set(ids_seen.tolist())
        return rep, lag

    def _add_observations(self, t: int, ids_seen: np.ndarray, z: np.ndarray, rep: np.ndarray, lag: np.ndarray,
                          now: float, cutoff: float, new: "_NewFactors") -> tuple[list, list, list]:
        """Step 3: a stereo factor for each observation of a landmark in the window (not
        a repeat, not rejected, its remapped pose still in the window). Returns (ids,
        pixels, pose frames) of the observations of new tracks."""
        new_ids, new_z, new_frame = [], [], []
        for i in np.flatnonzero(~rep):
            lm_id = int(ids_seen[i])
            if lm_id in self._rejected_ids:
                continue
            k = t - int(lag[i])
            if k not in self._pose_stamp or self._pose_stamp[k] < cutoff:
                self.stats.observations_gated += 1  # its pose has left the window
                continue
            key = self._tracks.get(lm_id)
            if key is None:
                new_ids.append(lm_id)
                new_z.append(z[i])
                new_frame.append(k)
                continue
            lm = self._landmarks[key]
            lm.stamp = now
            new.stamps[self._L(key)] = now
            entry = [k, len(self._stereo_factors), new.graph.size(), z[i], False]
            lm.obs.append(entry)
            new.entries.append(entry)
            new.added.append((lm, k, z[i], entry))
            new.graph.add(self._stereo(z[i], k, key))
        return new_ids, new_z, new_frame

    def _initialize_new(self, t: int, new_ids: list, new_z: list, new_frame: list, now: float,
                        new: "_NewFactors") -> None:
        """Step 6: new landmarks from the EKF's initialization guards and the stereo
        model's inverse at their pose's latest estimate, each with a weak prior and its
        first stereo factor."""
        g = self._g
        new_z = np.array(new_z)
        good = initialization_guard(self.calibration.camera, new_z, self.options)
        self.stats.observations_not_initialized += int((~good).sum())
        candidates = np.flatnonzero(good)  # in id order (ids_seen is sorted)
        room = max(self.options.max_landmarks_in_state - len(self._landmarks), 0)
        good[candidates[admitted_count(candidates.size, room, self.stats):]] = False  # a full window: the rest wait
        new_frame = np.array(new_frame)
        for k in np.unique(new_frame[good]):
            sel = np.flatnonzero(good & (new_frame == k))
            p_w, _ = mapping_initialize(self._model, se3_inverse(self._pose_value[int(k)]), new_z[sel], self._V)
            for j, p in zip(sel, p_w):
                key = self._next_key
                self._next_key += 1
                lm = _Landmark(key, new_ids[j], t, now)
                self._landmarks[key] = lm
                self._tracks[new_ids[j]] = key
                L = self._L(key)
                new.values.insert(L, p)
                new.stamps[L] = now
                prior = g.PriorFactorPoint3(L, p, self._lm_prior)
                self._prior_factors.append(prior)
                new.graph.add(prior)
                entry = [int(k), len(self._stereo_factors), new.graph.size(), new_z[j], True]
                lm.obs.append(entry)
                new.entries.append(entry)
                new.graph.add(self._stereo(new_z[j], int(k), key))
                self.stats.landmarks_initialized += 1
                self.stats.observations_used += 1

    def _update_window(self, t: int, X: int, new: "_NewFactors") -> None:
        """The window's update with the frame's factors (and the removal of those gated
        after the previous frame): the newest pose's estimate (and marginal), and the
        smoother's index of every stereo factor added."""
        tic = time.perf_counter()
        remove, self._to_remove = self._to_remove, []
        self._smoother.update(new.graph, new.values, new.stamps, remove)
        n_new = new.graph.size()
        factor_index = list(self._smoother.getISAM2Result().getNewFactorsIndices())
        self._current = self._smoother.calculateEstimatePose3(X).matrix()
        self._pose_value[t] = self._current
        self._fresh = {t}
        self.diagnostics.timings["update_s"] += time.perf_counter() - tic
        if self.options.smoother_pose_covariance:
            tic = time.perf_counter()
            self._current_cov = self._online_cov[t] = to_ekf_covariance(self._smoother.marginalCovariance(X))
            self.diagnostics.timings["marginals_s"] += time.perf_counter() - tic
        if len(factor_index) != n_new:  # pragma: no cover - gtsam contract
            raise EstimationError(f"gtsam returned {len(factor_index)} factor indices for {n_new} factors", frame=t)
        # graph order: the pose factor, the stereo factors of `added`, then (prior, stereo) per new landmark
        for entry in new.entries:
            entry[2] = int(factor_index[entry[2]])

    def _stereo(self, pix: np.ndarray, k: int, key: int):
        """The stereo factor of an observation (under the smoother's kernel; also kept,
        in ``_stereo_factors``, for refine, which swaps the noise model)."""
        g = self._g
        meas = g.StereoPoint2(float(pix[0]), float(pix[2]), 0.5 * float(pix[1] + pix[3]))
        f = g.GenericStereoFactor3D(meas, self._stereo_noise, _X_BASE + k, _L_BASE + key, self._K, self._body_P_sensor)
        i = len(self._stereo_factors)
        if i == self._stereo_pix.shape[0]:
            self._stereo_pix = np.concatenate([self._stereo_pix, np.zeros_like(self._stereo_pix)])
        self._stereo_pix[i] = pix
        self._stereo_factors.append(f)
        return f

    def _check_outliers(self, t: int, added: list) -> None:
        """Whitened errors of frame t's observations of existing landmarks after the
        update of frame t + 1: those beyond ``smoother_outlier_sigma`` are removed
        (gated) with the next update. (Right after their own update the newest pose has
        had one Gauss-Newton step only: on the simulator, checking then gated good
        observations and doubled the error.)"""
        # observations whose pose or landmark has left the window since are final: used
        added = [a for a in added if a[3][2] >= 0]  # not removed with a rejected landmark
        live = [a[1] in self._pose_stamp and a[0].key in self._landmarks for a in added]
        for a, ok in zip(added, live):
            if not ok:
                self._accept(a[0], t)
        added = [a for a, ok in zip(added, live) if ok]
        if not added:
            return
        opts = self.options
        n_added = len(added)
        frames = np.array([a[1] for a in added], dtype=np.int64)
        uniq, inv = np.unique(frames, return_inverse=True)
        for k in uniq.tolist():
            self._pose_value[k] = self._smoother.calculateEstimatePose3(self._X(k)).matrix()
            self._fresh.add(k)
        poses = np.array([self._pose_value[k] for k in uniq.tolist()])
        p = np.array([self._smoother.calculateEstimatePoint3(self._L(a[0].key)) for a in added]).reshape(n_added, 3)
        err = self._whitened_norms(poses[inv], p, self._stereo_pix[np.array([a[3][1] for a in added], dtype=np.int64)])
        limit = opts.smoother_outlier_sigma if opts.smoother_outlier_sigma > 0 else np.inf
        bad = err > limit
        remove = []
        for j, (lm, k, pix, entry) in enumerate(added):
            if entry[2] < 0:  # removed meanwhile with its landmark
                continue
            if bad[j]:
                lm.ngated += 1
                lm.consecutive += 1
                self.stats.observations_gated += 1
                self._remove_factors(lm, [entry], remove)
                if opts.max_consecutive_gated and lm.consecutive >= opts.max_consecutive_gated and not lm.rejected:
                    # rejected: no further factors. Its earlier factors stay (under the
                    # kernel): removing them too took dense 0027 from 2.6 to 4.7 m ATE.
                    lm.rejected = True
                    self.stats.landmarks_rejected += 1
                    if self._tracks.get(lm.id) == lm.key:
                        del self._tracks[lm.id]
                        self._rejected_ids.add(lm.id)
            else:
                entry[4] = True
                self._accept(lm, t)
        if self._drift_gate < np.inf:
            self._drift_test([a[0] for a in added], {a[0].key: p[j] for j, a in enumerate(added)}, remove)
        self._to_remove = remove  # with the next update (the landmark stays in the window until then)

    def _drift_test(self, lms: list, points: dict, remove: list) -> None:
        """Drift test of the landmarks observed in the frame just checked (``points``: key
        -> current estimate), the smoother's counterpart of the EKF's drift test. A
        static point fits its observations in the window without a trend; a point on a
        moving vehicle, fitted as static, leaves residuals that drift one way. For each
        landmark with at least three checked, kept observations in the window, at the
        current estimate:

        * the trend statistic ‖Σ s_i r_i‖² / Σ s_i² of its whitened residuals r_i
          (uL, uR, v) regressed on the frame number (s_i = k_i − mean k), compared with
          the median over the landmarks tested in this frame (at least
          ``_MIN_DRIFT_POPULATION`` of them): beyond ``smoother_drift_ratio`` times the
          median it drifts. Relative, not a chi-square quantile: σ is not the
          features' true scatter, and on real data static points trend too;
        * its apparent speed: one Gauss-Newton step of the point as moving at constant
          velocity over the observations' timestamps; a trend below
          ``smoother_drift_min_speed_mps`` is not taken for motion (on dense 0027 the
          static points that trend do so at ~0.4 m/s, the simulator's vehicles at 3–15).

        A landmark that fails both is rejected and all its factors still in the window
        are removed with the next update: they have been pulling the poses."""
        todo = self._drift_candidates(lms)
        if len(todo) < _MIN_DRIFT_POPULATION:
            return
        n = len(todo)
        owner = np.array([j for j, (_, obs) in enumerate(todo) for _ in obs], dtype=np.int64)  # sorted
        frames = np.array([e[0] for _, obs in todo for e in obs], dtype=np.int64)
        pix = self._stereo_pix[np.array([e[1] for _, obs in todo for e in obs], dtype=np.int64)]
        uniq, inv = np.unique(frames, return_inverse=True)
        for k in uniq.tolist():
            if k not in self._fresh:
                self._pose_value[k] = self._smoother.calculateEstimatePose3(self._X(k)).matrix()
                self._fresh.add(k)
        # camera from world of each observation: inverted once per pose, not per observation
        cam_T_world = self._cam_T_world(np.array([self._pose_value[k] for k in uniq.tolist()]))
        ts = np.array([self._pose_stamp[k] for k in uniq.tolist()])[inv]
        cam_T_world = cam_T_world[inv]
        p = np.array([points[lm.key] for lm, _ in todo]).reshape(n, 3)[owner]
        r, front = self._camera_residuals(cam_T_world, p, pix)
        r = np.where(front[:, None], r, 0.0)
        w = front.astype(np.float64)
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        cnt = np.add.reduceat(w, starts)
        mean_k = np.add.reduceat(w * frames, starts) / np.maximum(cnt, 1)
        s = (frames - mean_k[owner]) * w
        ss = np.add.reduceat(s * s, starts)
        S = np.add.reduceat(s[:, None] * r, starts)
        stat = np.einsum("ki,ki->k", S, S) / np.maximum(ss, 1e-12)
        valid = (cnt >= 3) & (ss > 0)
        if np.count_nonzero(valid) < _MIN_DRIFT_POPULATION:
            return
        typical = float(np.median(stat[valid]))
        moving = valid & (stat > self._drift_gate * max(typical, 1e-12))
        speed = np.zeros(n)
        drift_log = self.diagnostics.drift_log
        if np.any(moving):  # the speed of the trending ones (of all of them for the log)
            rows = np.ones(owner.size, dtype=bool) if drift_log is not None else moving[owner]
            sub = owner[rows]
            first = np.flatnonzero(np.r_[True, sub[1:] != sub[:-1]])
            speed[sub[first]] = self._apparent_speed(cam_T_world[rows], p[rows], ts[rows], r[rows], front[rows], first)
            moving &= speed > self.options.smoother_drift_min_speed_mps
        if drift_log is not None:
            drift_log.extend(zip([lm.id for lm, _ in todo], cnt.tolist(), (stat / max(typical, 1e-12)).tolist(),
                                 speed.tolist(), [self.frame_index] * n))
        for j in np.flatnonzero(moving).tolist():
            self._reject_moving(todo[j][0], remove)

    def _drift_candidates(self, lms: list) -> list:
        """(landmark, its checked, kept observations in the window) of the distinct,
        not rejected landmarks of ``lms`` with at least three of them."""
        seen, todo = set(), []
        for lm in lms:
            if lm.rejected or lm.key in seen:
                continue
            seen.add(lm.key)
            obs = [e for e in lm.obs if e[4] and e[2] >= 0 and e[0] in self._pose_stamp]
            if len(obs) >= 3:
                todo.append((lm, obs))
        return todo

    def _reject_moving(self, lm: _Landmark, remove: list) -> None:
        """A landmark the drift test found moving: rejected, its factors in the window
        removed with the next update, its track (if in progress) ended."""
        lm.rejected = True
        self.stats.landmarks_rejected += 1
        self.stats.landmarks_moving += 1
        self._remove_factors(lm, list(lm.obs), remove)
        if self._tracks.get(lm.id) == lm.key:
            del self._tracks[lm.id]
            self._rejected_ids.add(lm.id)

    def _apparent_speed(self, cam_T_world, p, ts, r, front, starts) -> np.ndarray:
        """(n,) speed (m/s) of n landmarks taken as points moving at constant velocity:
        one Gauss-Newton step from their static estimate for (δp, v) with
        p(t_i) = p + δp + v (t_i − t̄), over observations at times ``ts`` (N,) from
        camera poses ``cam_T_world`` (N, 4, 4) of points ``p`` (N, 3) with whitened
        residuals ``r`` (N, 3), grouped by landmark (``starts``: first row of each)."""
        R = cam_T_world[:, :3, :3]
        q = np.einsum("kij,kj->ki", R, p) + cam_T_world[:, :3, 3]
        q[:, 2] = np.where(front, q[:, 2], 1.0)
        J = self._whitened_point_jacobians(R, q) * front[:, None, None]
        w = front.astype(np.float64)
        cnt = np.add.reduceat(w, starts)
        tmean = np.add.reduceat(w * ts, starts) / np.maximum(cnt, 1)
        owner = np.repeat(np.arange(starts.size), np.diff(np.r_[starts, ts.size]))
        sv = (ts - tmean[owner]) * w
        JtJ = np.swapaxes(J, 1, 2) @ J
        Jtr = np.einsum("kji,kj->ki", J, r)
        M = np.empty((ts.size, 6, 6))
        M[:, :3, :3] = JtJ
        M[:, :3, 3:] = M[:, 3:, :3] = JtJ * sv[:, None, None]
        M[:, 3:, 3:] = JtJ * (sv * sv)[:, None, None]
        A = np.add.reduceat(M, starts, axis=0)
        b = -np.add.reduceat(np.concatenate([Jtr, Jtr * sv[:, None]], axis=1), starts, axis=0)
        A[:, :3, :3] += np.eye(3) / self.options.smoother_landmark_prior_m**2
        A += 1e-9 * np.eye(6)
        sol = np.linalg.solve(A, b[:, :, None])[:, :, 0]
        return np.linalg.norm(sol[:, 3:], axis=1)

    def _whitened_point_jacobians(self, R: np.ndarray, q: np.ndarray) -> np.ndarray:
        """(n, 3, 3) whitened d(uL, uR, v)/dp of stereo observations of world points p
        seen at camera coordinates ``q`` (n, 3; depth > 0) through camera-from-world
        rotations ``R`` (n, 3, 3)."""
        cam = self.calibration.camera
        x, y, zc = q[:, 0], q[:, 1], q[:, 2]
        J = np.zeros((q.shape[0], 3, 3))  # d(uL, uR, v)/dq
        J[:, 0, 0] = J[:, 1, 0] = cam.fsu / zc
        J[:, 0, 2] = -cam.fsu * x / zc**2
        J[:, 1, 2] = -cam.fsu * (x - cam.baseline_m) / zc**2
        J[:, 2, 1] = cam.fsv / zc
        J[:, 2, 2] = -cam.fsv * y / zc**2
        return (J @ R) / self._sigmas[None, :, None]

    def _remove_factors(self, lm: _Landmark, entries: list, remove: list) -> None:
        """Schedule the removal of stereo factors of ``lm`` (those whose pose is still in
        the window; the others were marginalized) and leave them out of refine."""
        for entry in entries:
            if entry[2] >= 0 and entry[0] in self._pose_stamp:
                remove.append(entry[2])
                self._stereo_removed.add(entry[1])
                entry[2] = -1
        lm.obs = [e for e in lm.obs if e[2] >= 0 or e[0] not in self._pose_stamp]

    def _accept(self, lm: _Landmark, t: int) -> None:
        lm.nobs += 1
        lm.last = max(lm.last, t)
        lm.consecutive = 0
        self.stats.observations_used += 1

    def _whitened_norms(self, world_T_imu: np.ndarray, p: np.ndarray, pix: np.ndarray) -> np.ndarray:
        """(n,) norms of the whitened (uL, uR, v) errors of observations ``pix`` (n, 4) of
        landmarks ``p`` (n, 3) from poses (n, 4, 4); inf behind the camera."""
        r, front = self._whitened_residuals(world_T_imu, p, pix)
        return np.where(front, np.sqrt(np.einsum("ki,ki->k", r, r)), np.inf)

    def _cam_T_world(self, world_T_imu: np.ndarray) -> np.ndarray:
        """(n, 4, 4) left camera from world of IMU poses world_T_imu (n, 4, 4)."""
        return self._model.cam_T_imu @ se3_inverse(world_T_imu)

    def _whitened_residuals(self, world_T_imu: np.ndarray, p: np.ndarray, pix: np.ndarray):
        """((n, 3) whitened (uL, uR, v) errors, prediction − measurement, of observations
        ``pix`` (n, 4) of landmarks ``p`` (n, 3) from poses (n, 4, 4); (n,) in front of
        the camera)."""
        return self._camera_residuals(self._cam_T_world(world_T_imu), p, pix)

    def _camera_residuals(self, cam_T_world: np.ndarray, p: np.ndarray, pix: np.ndarray):
        """:meth:`_whitened_residuals` from camera poses ``cam_T_world`` (n, 4, 4)."""
        q = np.einsum("kij,kj->ki", cam_T_world[:, :3, :3], p) + cam_T_world[:, :3, 3]
        cam = self.calibration.camera
        front = q[:, 2] > 1e-6
        z = np.where(front, q[:, 2], 1.0)
        pred = np.stack([cam.fsu * q[:, 0] / z + cam.cu, cam.fsu * (q[:, 0] - cam.baseline_m) / z + cam.cu,
                         cam.fsv * q[:, 1] / z + cam.cv], axis=1)
        meas = np.stack([pix[:, 0], pix[:, 2], 0.5 * (pix[:, 1] + pix[:, 3])], axis=1)
        return (pred - meas) / self._sigmas, front

    def _marginalize(self, cutoff: float) -> None:
        """Freeze the poses and landmarks whose timestamp is before ``cutoff`` (they leave
        the window in the coming update: GTSAM marginalizes keys with stamp < now − lag)."""
        tic = time.perf_counter()
        for k in [k for k, s in self._pose_stamp.items() if s < cutoff]:
            self._freeze_pose(k)
        gone = [lm for lm in self._landmarks.values() if lm.stamp < cutoff]
        self._freeze_landmarks(gone)
        self.diagnostics.timings["marginals_s"] += time.perf_counter() - tic

    def _freeze_pose(self, k: int) -> None:
        """Pose k leaves the window: its current estimate is final (its covariance is
        the marginal computed when it was the newest pose)."""
        self._final_pose[k] = self._smoother.calculateEstimatePose3(self._X(k)).matrix()
        del self._pose_stamp[k]
        self._pose_value.pop(k, None)

    def _pose_estimate(self, k: int) -> np.ndarray:
        pose = self._final_pose.get(k)
        return self._pose_value[k] if pose is None else pose

    def _landmark_covariances(self, lms: list, p: np.ndarray) -> np.ndarray:
        """(n, 3, 3) covariances of landmarks given the poses of their observations: the
        inverse of the information of their kept stereo factors (whitened Jacobians of
        (uL, uR, v) at the estimate) plus their prior. The pose uncertainty is not
        included (conditional, not marginal: GTSAM's marginals of landmarks deep in the
        Bayes tree cost ~50 ms each)."""
        n = len(lms)
        info = np.broadcast_to(np.eye(3) / self.options.smoother_landmark_prior_m**2, (n, 3, 3)).copy()
        owner = np.array([j for j, lm in enumerate(lms) for _ in lm.obs], dtype=np.int64)
        if owner.size == 0:
            return np.linalg.inv(info)
        frames = np.array([e[0] for lm in lms for e in lm.obs], dtype=np.int64)
        uniq, inv = np.unique(frames, return_inverse=True)
        cam_T_world = self._model.cam_T_imu @ se3_inverse(np.array([self._pose_estimate(int(k)) for k in uniq]))
        R = cam_T_world[inv, :3, :3]
        q = np.einsum("kij,kj->ki", R, p[owner]) + cam_T_world[inv, :3, 3]
        ok = q[:, 2] > 1e-6
        J = self._whitened_point_jacobians(R[ok], q[ok])
        np.add.at(info, owner[ok], np.swapaxes(J, 1, 2) @ J)
        return np.linalg.inv(info)

    def _freeze_landmarks(self, lms) -> None:
        if not lms:
            return
        n = len(lms)
        p = np.array([self._smoother.calculateEstimatePoint3(self._L(lm.key)) for lm in lms]).reshape(n, 3)
        cov = self._landmark_covariances(lms, p)
        for j, lm in enumerate(lms):
            self._final_lm[lm.key] = p[j]
            del self._landmarks[lm.key]
            if self._tracks.get(lm.id) == lm.key:
                # its track goes on (a time gap longer than the window): a later observation
                # starts a new landmark of the same id (the map's next "track" of that id)
                del self._tracks[lm.id]
        ids = np.array([lm.id for lm in lms], dtype=np.int64)
        status = np.array([LANDMARK_REJECTED if lm.rejected else LANDMARK_OK for lm in lms], dtype=np.uint8)
        cols = {name: np.array([getattr(lm, name) for lm in lms], dtype=np.int64)
                for name in ("nobs", "ngated", "first", "last")}
        for st in (LANDMARK_OK, LANDMARK_REJECTED):
            m = status == st
            if np.any(m):
                self._builder.add(ids[m], p[m], cov[m], cols["nobs"][m], cols["ngated"][m], cols["first"][m],
                                  cols["last"][m], st)

    def _require_healthy(self) -> None:
        if self.diagnostics.failed is not None:
            raise EstimationError(f"the smoother stopped earlier ({self.diagnostics.failed}); start a new one")

    def finish(self) -> LandmarkMap:
        """Freeze every pose and landmark still in the window (their current estimates
        and marginals) and return the whole map."""
        tic = time.perf_counter()
        healthy = self.diagnostics.failed is None
        t_last, unchecked = self._unchecked
        for a in unchecked:  # the last frame's observations: no later update to check them by
            if a[3][2] >= 0:
                self._accept(a[0], t_last)
        self._unchecked = (-1, [])
        for k in list(self._pose_stamp):
            if healthy:
                self._freeze_pose(k)
            else:
                self._final_pose[k] = self._pose_value.get(k, np.full((4, 4), np.nan))
                del self._pose_stamp[k]
        if healthy:
            self._freeze_landmarks(list(self._landmarks.values()))
        self.diagnostics.timings["marginals_s"] += time.perf_counter() - tic
        return self._builder.build()

    # --- refinement -------------------------------------------------------------------
    def refine(self) -> tuple[np.ndarray, dict]:
        """Batch Levenberg–Marquardt over every factor of the drive, from the final
        estimate (after :meth:`finish`): see :func:`refine`. Returns ((T, 4, 4) refined
        world_T_imu, info)."""
        return refine(self)


def refine(smoother: SmootherFilter) -> tuple[np.ndarray, dict]:
    """Batch Levenberg–Marquardt over the whole drive, initialized from the smoother's
    final poses and landmarks: pass 1 with every factor under ``refine_kernel``; pass 2
    without the stereo factors whose reprojection error after pass 1 exceeds
    ``refine_outlier_px`` (largest StereoPoint2 coordinate error). Factors removed online
    (gated) are left out. Returns ((T, 4, 4) world_T_imu, info)."""
    g, opts = smoother._g, smoother.options
    poses, _ = smoother.final_trajectory()
    n = poses.shape[0]
    if not np.all(np.isfinite(poses)):
        raise EstimationError("refine: the smoother's trajectory is incomplete")
    values = g.Values()
    for k in range(n):
        values.insert(smoother._X(k), g.Pose3(poses[k]))
    for key, p in smoother._final_lm.items():
        values.insert(smoother._L(key), p)
    base_graph = g.NonlinearFactorGraph()
    for t, f in smoother._odometry_factors:
        if t < n:  # (a failed frame's factor is not in the trajectory)
            base_graph.add(f)
    for f in smoother._prior_factors:
        base_graph.add(f)
    robust = _kernel(g, opts.refine_kernel, opts.refine_kernel_scale, smoother._stereo_base)
    stereo = [f for i, f in enumerate(smoother._stereo_factors) if i not in smoother._stereo_removed]

    def solve(factors, initial):
        graph = g.NonlinearFactorGraph(base_graph)
        for f in factors:
            graph.add(f.cloneWithNewNoiseModel(robust))  # the smoother's factors carry its kernel
        params = g.LevenbergMarquardtParams()
        params.setMaxIterations(opts.refine_max_iterations)
        try:
            opt = g.LevenbergMarquardtOptimizer(graph, initial, params)
            out = opt.optimize()
        except RuntimeError as exc:
            raise EstimationError(f"refine: numerical failure: {_one_line(exc)}") from exc
        return out, opt.iterations()

    tic = time.perf_counter()
    first, it1 = solve(stereo, values)
    keep = []
    for f in stereo:
        e = np.abs(np.asarray(f.unwhitenedError(first)))
        keep.append(bool(np.all(e <= opts.refine_outlier_px)))
    kept = [f for f, k in zip(stereo, keep) if k]
    second, it2 = solve(kept, first)
    out = np.array([second.atPose3(smoother._X(k)).matrix() for k in range(n)])
    info = {"refine_seconds": time.perf_counter() - tic, "refine_iterations": [int(it1), int(it2)],
            "refine_stereo_factors": len(stereo), "refine_stereo_factors_dropped": len(stereo) - len(kept)}
    return out, info


def run_smoother(sequence, options: FilterOptions | None = None, progress=None, on_frame=None):
    """The smoother over a whole sequence (``drive``), then, with ``options.refine``, the
    batch refinement. Result: trajectory = final smoothed (or refined) poses;
    ``extra["online_world_T_imu"]`` the online estimates; with refine
    ``extra["smoother_world_T_imu"]`` the smoother's; ``extra["timing"]`` seconds of the
    smoother (update, marginals) and of refine."""
    from vislam.core.estimators import drive

    options = options or FilterOptions()
    filt = SmootherFilter(sequence.calibration, options)
    result = drive(filt, sequence, progress, on_frame)
    timings = filt.diagnostics.timings
    timing = {"smoother_seconds": float(result.stats.filter_seconds), "smoother_update_seconds": timings["update_s"],
              "smoother_marginals_seconds": timings["marginals_s"]}
    if options.refine and not result.partial:
        text = f"refining the whole drive ({result.stats.frames_processed} poses, batch Levenberg-Marquardt)"
        logger.info(text)
        phase = getattr(progress, "phase", None)  # a progress bar that can say what it waits for
        if phase is not None:
            phase(text)
        try:
            refined, info = filt.refine()
        except EstimationError as exc:  # the smoother's result stands, marked partial (not refined)
            result.partial, result.error = True, f"{exc} (the smoother's trajectory is kept, not refined)"
        else:
            result.extra["smoother_world_T_imu"] = result.world_T_imu
            result.world_T_imu = refined
            timing.update(info)
    result.extra["timing"] = timing
    return result
