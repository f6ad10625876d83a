"""Typed options of the filter, with documented defaults and units.

:class:`FilterOptions` holds every noise and initialization parameter of the three
estimators. It can be built from a mapping (e.g. a parsed YAML/TOML file, see
:mod:`vislam.tools.config`) with :meth:`FilterOptions.from_dict`, which refuses unknown
keys and invalid values with a :class:`vislam.errors.ConfigError`.

Noise model (the report's):

* motion noise ``W = diag(σ_v², σ_v², σ_v², σ_ω², σ_ω², σ_ω²)`` enters the prediction as
  ``τ² W``: σ_v and σ_ω are the 1σ errors of one velocity *sample*, per axis, so the
  pose error added per step is τ·σ (m and rad);
* observation noise ``V = σ_px² I₄`` on each stereo observation ``[uL, vL, uR, vR]``.

The defaults suit a clean, GPS-aided IMU like the sparse KITTI datasets'. For the dense
datasets, whose velocities carry added white noise of about 0.5 m/s and 0.05 rad/s per
axis and sample, pass ``velocity_noise_mps=0.5, angular_noise_radps=0.05``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np

from vislam.core.suggest import unknown_names_message
from vislam.errors import ConfigError

__all__ = ["FilterOptions", "MODES", "REPEATED_POLICIES", "STALL_POLICIES", "EKF_VARIANTS", "ROBUST_PRESET",
           "VELOCITY_ASSOCIATIONS", "DATA_CORRECTION_FIELDS", "KERNELS", "LANDMARK_PARAMETRIZATIONS"]

#: The three estimators of the report, and the sliding-window smoother (vislam.core.smoother).
MODES = ("localization", "mapping", "slam", "smoother")
#: Robust kernels of the smoother and of its batch refinement.
KERNELS = ("cauchy", "huber", "none")
#: Policies for observations that repeat the previous frame's pixels exactly.
REPEATED_POLICIES = ("skip", "split", "use")
#: Policies for stalled tracks.
STALL_POLICIES = ("remap", "keep")
#: EKF variants.
EKF_VARIANTS = ("oc", "standard")
#: Charts of the SLAM landmarks (see vislam.core.state).
LANDMARK_PARAMETRIZATIONS = ("inverse_depth", "cartesian")
#: Which velocity sample describes the interval between frames k and k+1: "next" (the
#: sample of frame k+1, the KITTI convention and the default) or "current" (sample k).
VELOCITY_ASSOCIATIONS = ("next", "current")
#: The frame the linear velocities are expressed in: "body" (the IMU frame, the
#: report's model) or "level" (heading-aligned and levelled: x forward and y left in the
#: horizontal plane, z up — an INS's vf/vl/vu, as in KITTI's OXTS data).
VELOCITY_FRAMES = ("body", "level")
#: Options that change the data before filtering (see vislam.core.corrections).
DATA_CORRECTION_FIELDS = ("gyro_bias_radps", "velocity_bias_mps", "imu_camera_rotation_correction_deg", "cam_T_imu",
                          "velocity_association", "time_offset_s", "velocity_scale", "timestamp_scale")
#: Options that are a number or three numbers (per IMU axis x, y, z).
PER_AXIS_FIELDS = ("velocity_noise_mps", "angular_noise_radps", "imu_bias_sigma_mps", "imu_bias_sigma_radps")
#: Options that are exactly three numbers.
VECTOR_FIELDS = ("gyro_bias_radps", "velocity_bias_mps", "imu_camera_rotation_correction_deg")


def _chi2_4_quantile(p: float | None) -> float:
    if p is None:
        return math.inf
    from scipy.special import chdtri  # inverse survival function of chi-square

    return float(chdtri(4, 1.0 - p))


#: Options of the robust preset (``--robust``): for scenes with moving traffic — a
#: more sensitive drift test and two frames of probation for new landmarks.
ROBUST_PRESET = {"drift_test_probability": 0.9, "probation_frames": 2}


def _axis_array(value) -> np.ndarray:
    """A PER_AXIS_FIELDS value (a number or three) as a (3,) array (a copy)."""
    return np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()


@dataclass(frozen=True)
class FilterOptions:
    """Noise, initialization and robustness parameters (units in each name)."""

    #: 1σ error of one linear-velocity sample, per axis (m/s). Motion noise W, linear part.
    #: One number for all three axes, or three numbers (IMU x, y, z). Default: a GPS-aided inertial system like KITTI's OXTS RT3003 (velocity accuracy
    #: 0.05 km/h ≈ 0.014 m/s RMS).
    velocity_noise_mps: float | tuple[float, float, float] = 0.02
    #: 1σ error of one angular-velocity sample, per axis (rad/s). Motion noise W, angular
    #: part; one number or three (IMU x, y, z). Default: the RT3003 gyro's angle random walk 0.2°/√h is 1.8e-4 rad/s per
    #: 10 Hz sample; rounded up.
    angular_noise_radps: float | tuple[float, float, float] = 0.0003
    #: 1σ error of one pixel coordinate of a stereo observation (px). V = σ² I₄. The
    #: KITTI features scatter by ~1.5 px around their ground-truth projections; the
    #: default adds margin for the linearization of distant landmarks.
    pixel_noise_px: float = 2.0
    #: 1σ of the initial position (m). The world frame is the first IMU pose, so 0 is exact.
    initial_position_std_m: float = 0.0
    #: 1σ of the initial orientation (rad).
    initial_rotation_std_rad: float = 0.0

    # --- landmark initialization (guards) -------------------------------------------
    #: Smallest disparity uL − uR (px) accepted for triangulation.
    min_disparity_px: float = 2.0
    #: Largest triangulated depth (m) accepted for a new landmark. A limit on the *noisy*
    #: depth lets a point from beyond it in only when the noise brings it closer (a depth
    #: bias the filter does not model); it also refuses far, low-disparity outliers.
    #: Measured (Cartesian OC-EKF, levelled velocities, SLAM with 0.5 / 0.05 noise; ATE /
    #: KITTI t) on dense 0027 as shared, with 5 % injected gross outliers (seeds 1, 2) and
    #: on four fresh noise draws (sparse 0027's velocities + white noise of the dense
    #: files' level, dense 0027's features): mean over the seven runs 60 m 4.72 m /
    #: 2.75 %, 100 m 3.62 m / 2.92 %, 200 m 3.59 m / 2.82 % (clean as shared: 4.82 / 2.75,
    #: 2.72 / 2.56, 2.79 / 2.44; worst run 5.75, 5.22, 5.45 m). Sparse 0020 / 0027 the same
    #: for all; simulator pose NEES 24 -> 14 from 60 to 200 m (8 x 150 frames). The 2 px
    #: disparity guard stops at about 190 m on KITTI, so 200 m leaves depth to it.
    #: Rerun: ``PYTHONPATH=src python benchmarks/noise_draws.py --depths 60,100,200``.
    max_depth_m: float = 200.0
    #: Smallest triangulated depth (m) accepted for a new landmark.
    min_depth_m: float = 0.5
    #: Largest |vL − vR| (px) accepted (rectified images should agree on the row).
    max_row_difference_px: float = 3.0
    #: A SLAM landmark enters the state once it has passed the guards in this many
    #: consecutive frames and its first and latest observations agree with a static
    #: point (chi-square gate, accounting for triangulation, pixel and IMU noise); the
    #: latest observation initializes it. 1 initializes at first sight (the report).
    #: Points on moving vehicles and mismatched tracks fail the check: after two failures
    #: the landmark is rejected.
    init_frames: int = 1
    #: A new SLAM landmark's first updates refine only the landmark itself, treating the
    #: pose as known with its uncertainty (Schmidt-Kalman "consider" update), for this
    #: many frames; after that it updates pose and landmarks jointly. Points on moving
    #: vehicles drift away from their static prediction during this probation and are
    #: gated out before they can pull the pose. 0 disables probation (the report).
    probation_frames: int = 0

    #: What to do with an observation whose four pixels repeat the same landmark's
    #: previous observation bit for bit (a tracker artifact of the KITTI feature files,
    #: see StereoObservations.repeated_mask): "skip" ignores it and the track goes on;
    #: "split" ends the track there and starts a new one from it (after such a repeat the
    #: tracker follows the point found at the stale pixel, usually a neighbour of the
    #: original); "use" takes it as a measurement.
    repeated_observations: str = "skip"
    #: Stalled tracks (see :mod:`vislam.core.stalls`): after each exact repeat a track's
    #: pixels behave as if taken one frame earlier. "remap" (SLAM) drops the repeat and
    #: gives each observation at frame k to frame k − (repeats so far in its track),
    #: online, by running the filter ``stall_max_delay_frames`` frames behind the newest
    #: frame (the current pose is then predicted forward with the IMU samples received
    #: since). "keep" uses every observation at the frame it arrives (needs no delay).
    #: The remap applies with ``repeated_observations: skip`` only ("split" and "use"
    #: decide themselves what a repeat means).
    #: Measured on dense 0027 (the only noisy drive with ground truth): KITTI
    #: t-error 4.01 % -> 2.73 %, ATE 4.67 -> 4.96 m; sparse files unchanged.
    stalled_tracks: str = "remap"
    #: Largest lag (frames) the remap can restore; observations lagging more are dropped
    #: (dense files: 0.3 % of observations at 10, sparse: 6 %). Also the output delay of
    #: the remapped filter.
    stall_max_delay_frames: int = 10

    # --- gating ------------------------------------------------------------------------
    #: Chi-square gate probability for the 4-D stereo innovation (0 < p < 1), or None to
    #: disable gating. Observations outside the gate are not used.
    gating_probability: float | None = 0.95
    #: A landmark whose observations fail the gate this many frames in a row is removed
    #: from the state and kept in the map flagged as rejected (0 disables rejection).
    max_consecutive_gated: int = 3
    #: Innovation drift test (probability, or None to disable). After each update, what
    #: a landmark's observation says beyond the frame's consensus pose correction is
    #: whitened with its conditional covariance (updaters.conditional_residual_model);
    #: for a static landmark these residuals are white, so their running sum over k
    #: updates divided by √k is N(0, I₄). When its squared norm exceeds the chi-square(4)
    #: quantile, the landmark is taken for a point on a moving object and rejected. It
    #: catches vehicles whose motion hides, frame by frame, inside the gate.
    drift_test_probability: float | None = 0.99

    # --- landmark motion model (the report's proposed fix for moving landmarks) --------
    #: Give every SLAM landmark a velocity with a constant-velocity prediction step, so
    #: a moving point can be tracked instead of corrupting the pose. Off by default.
    landmark_motion: bool = False
    #: Prior 1σ of a new landmark's velocity per axis (m/s), motion model only.
    landmark_velocity_std_mps: float = 2.0
    #: Process noise: 1σ of a landmark's acceleration per axis (m/s²), motion model only.
    landmark_acceleration_std_mps2: float = 1.0

    # --- filter variant ----------------------------------------------------------------
    #: "oc" (default): the observability-constrained EKF — measurement Jacobians are
    #: projected so the unobservable global pose stays unobservable (no spurious
    #: information from re-linearization), see updaters.oc_project. "standard": the
    #: report's EKF equations exactly.
    ekf: str = "oc"

    #: Chart of the SLAM landmarks in the state: "inverse_depth" — anchored inverse depth
    #: (α, β, ρ) = (x/z, y/z, 1/z) in the left camera frame of the frame that initialized
    #: the landmark, exact for a stereo observation at initialization and well behaved for
    #: distant points — or "cartesian" (the report's position in the world). Maps and
    #: outputs are Cartesian either way. With landmark_motion the landmarks are Cartesian.
    #: Measured (OC-EKF): with max_depth_m 60 inverse depth is better (dense 0027 ATE
    #: 4.38 against 4.96 m; simulator pose NEES 17 against 24, 8 x 150 frames); with
    #: max_depth_m 200 the Cartesian chart is (dense 0027 2.48 against 3.71 m; NEES 14
    #: against 20); sparse files equal either way. Inverse depth with update_iterations 3
    #: and max_depth_m 200 is the consistent configuration (see update_iterations).
    #: Default "inverse_depth" since 2026-11-30 (with the adaptive iterated update, see
    #: update_iteration_tolerance, and level_velocity_jacobian): the consistent filter.
    landmark_parametrization: str = "inverse_depth"

    #: Iterations of the SLAM update per frame: 1 is the EKF (linearized once, at the
    #: prior); n > 1 the iterated EKF, which re-linearizes the frame's joint update at the
    #: updated estimate n − 1 more times (each iteration costs about one update). With
    #: landmark_parametrization "inverse_depth", 3 iterations and max_depth_m 200 the
    #: filter is consistent on the simulator with the dense files' IMU noise (vislam
    #: consistency --runs 20: pose NEES 8.08, landmark NEES 3.72) but over dense 0027 and
    #: six variants (benchmarks/noise_draws.py) mean ATE 4.05 m / KITTI t 2.93 % against
    #: the defaults' 3.59 m / 2.82 %, at 2.5x the filter time. With Cartesian landmarks
    #: iterating makes the NEES worse (3 iterations: 22 against 14, 8 x 150 frames): the
    #: Cartesian landmark prior is a linearized, skewed triangulation, and converging on
    #: it converges on its error. See update_iteration_tolerance for the adaptive form.
    #: Default 4 (a maximum, with update_iteration_tolerance 0.5) since 2026-11-30.
    #: With landmark_motion (Cartesian landmarks with a velocity) the update is not iterated.
    update_iterations: int = 4
    #: With update_iterations > 1: stop iterating once the next re-linearization would
    #: move the estimate by less than this many standard deviations (pose, and each
    #: observed landmark, marginally; the step predicted to first order with the last
    #: gain, see updaters.slam_update_iterated), so update_iterations is a maximum. 0
    #: always does update_iterations updates.
    #: Measured with inverse depth, update_iterations 4 and 0.5: simulator pose NEES 8.14,
    #: landmark NEES 3.68 (vislam consistency --runs 20; on 8 x 150 frames 7.5, with 0.2
    #: 7.6, 3 fixed iterations 7.5), where frames iterate (0.5 px against a prior several
    #: px wide); on the KITTI files (2 px) 1.00-1.01 updates per frame, so the real-data
    #: results are inverse depth's with one update: dense 0027 and six variants mean ATE 3.66 m /
    #: KITTI t 2.75 % (defaults 3.59 / 2.82; eight more variants 3.94 / 2.92 against
    #: 4.06 / 3.00), dense 0027 as shared 3.43 m / 2.58 % (defaults 2.79 / 2.44), sparse
    #: 0020/0027 2.13 / 1.93 m (the same), at about 1.3-1.5x the defaults' filter time.
    #: Default 0.5 since 2026-11-30 (with inverse depth, 4 iterations at most and
    #: level_velocity_jacobian; measurements of that combination in the README's
    #: consistency section).
    update_iteration_tolerance: float = 0.5

    # --- IMU-error state (SLAM; see vislam.core.propagation) ----------------------------
    #: Stationary 1σ of the slowly varying error b_v of the recorded linear-velocity
    #: samples (m/s; one number or three, per axis of the frame the samples are given in,
    #: see velocity_frame). With this or imu_bias_sigma_radps > 0 the SLAM filter
    #: estimates b = (b_v, b_ω), a first-order Gauss-Markov process (u_meas = u_true + b +
    #: w; b_{k+1} = a b_k + η, a = exp(−τ/T_c), η ~ N(0, (1 − a²) σ_b²)), jointly with the
    #: pose and landmarks; the prediction uses u_meas − b̂. The white part stays
    #: velocity_noise_mps. On top of velocity_bias_mps/gyro_bias_radps (constant data
    #: corrections). Default 0 (with imu_bias_sigma_radps 0): off, the filter without it.
    #: Localization, mapping and the smoother ignore it.
    imu_bias_sigma_mps: float | tuple[float, float, float] = 0.0
    #: Stationary 1σ of the slowly varying error b_ω of the angular-velocity samples
    #: (rad/s; one number or three, IMU axes). See imu_bias_sigma_mps. Default 0.
    imu_bias_sigma_radps: float | tuple[float, float, float] = 0.0
    #: Correlation time T_c of the IMU-error state (s, > 0): a = exp(−τ/T_c) per step. A
    #: long T_c makes b nearly a constant bias. Default 5 s.
    imu_bias_time_constant_s: float = 5.0

    # --- state management ------------------------------------------------------------
    #: Keep every landmark in the SLAM state for the whole run (the report's variant;
    #: cost grows with the map). By default a landmark is marginalized when its track ends.
    keep_all_landmarks: bool = False

    # --- data corrections (applied to the recording by vislam.core.corrections) ----------
    # ``vislam check`` estimates these; all defaults leave the data untouched.
    #: Gyro bias (rad/s, IMU x, y, z), subtracted from every angular-velocity sample.
    gyro_bias_radps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: Velocity bias (m/s, IMU x, y, z), subtracted from every linear-velocity sample.
    velocity_bias_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: Factor on every linear-velocity sample (before the bias is subtracted): the
    #: recorded value times this is the speed in m/s. A recording in km/h needs 1/3.6
    #: (0.2778), one in mph 0.44704, a wheel odometry that reads 5 % fast 1/1.05.
    velocity_scale: float = 1.0
    #: Factor that turns the recording's timestamps into seconds (0.001 for a recording
    #: stamped in milliseconds, 1e-9 in nanoseconds).
    timestamp_scale: float = 1.0
    #: Correction of the IMU-camera rotation: a rotation vector in the camera frame
    #: (degrees; axis times angle). The rotation block of cam_T_imu becomes
    #: ``exp(φ) @ R``; its translation (the IMU origin in the camera frame) is kept.
    imu_camera_rotation_correction_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: Replace the recording's cam_T_imu by this 4x4 rigid transform (rows), or None to
    #: keep it. The rotation correction above applies on top of it.
    cam_T_imu: tuple | None = None
    #: Which velocity sample describes the interval k -> k+1, see VELOCITY_ASSOCIATIONS.
    velocity_association: str = "next"
    #: Camera-IMU time offset (s): the velocity sample stamped t describes the motion at
    #: t + time_offset_s. The velocities are resampled (linear interpolation) at the
    #: frame times before use.
    time_offset_s: float = 0.0
    #: The frame of the linear velocities, see VELOCITY_FRAMES. With "level" each sample
    #: is turned into the body frame with the current estimate's roll and pitch (the
    #: world z axis, i.e. the first IMU frame's, taken as up) before the prediction, so
    #: the vertical motion comes from the velocities' own z and an attitude error no
    #: longer tilts the forward motion up or down.
    velocity_frame: str = "level"
    #: With velocity_frame "level": propagate the covariance with the exact transition,
    #: which includes that the body velocity depends on the estimated roll and pitch
    #: (F = Ad(exp(−τ û)) − τ J_l ∂u/∂δ, see propagation.body_twist_jacobian); false
    #: keeps F = Ad(exp(−τ û)), as if the body velocity were measured. Measured: IMU-only
    #: localization NEES on the simulator 6.41 -> 5.91 (50 x 100 frames; 6 is exact);
    #: SLAM NEES unchanged; SLAM on dense 0027 and six noise draws/outlier variants
    #: (benchmarks/noise_draws.py, 7 runs) mean ATE 3.59 -> 3.09 m, KITTI t 2.82 ->
    #: 2.90 % (as shared 2.79 -> 3.15 m, 2.44 -> 2.77 %); sparse 0020/0027 ATE the same,
    #: KITTI t 2.19 -> 2.02 % and 2.14 -> 2.11 %.
    #: Default true since 2026-11-30: it is the exact transition.
    level_velocity_jacobian: bool = True

    # --- sliding-window smoother (mode "smoother", vislam.core.smoother) ---------------
    #: Length of the fixed-lag window (s): poses older than this, and landmarks not
    #: observed for this long, are marginalized. 3 s = 30 frames at 10 Hz.
    smoother_window_s: float = 3.0
    #: 1σ of one pixel coordinate in the smoother's stereo factors (px), or None for
    #: pixel_noise_px. The smoother relinearizes, so it needs none of the margin for
    #: linearization error that the EKF's pixel_noise_px default carries; the KITTI
    #: features scatter by ~1.5 px around their ground-truth projections.
    smoother_pixel_noise_px: float | None = 1.0
    #: Robust kernel of the stereo factors: "cauchy" (default), "huber" or "none".
    smoother_kernel: str = "cauchy"
    #: Scale of the kernel in units of the whitened error (σ = smoother_pixel_noise_px).
    #: Chosen with σ = 1 px on dense 0027 (ATE 4.4 / 3.0 / 2.7 m for scales 1 / 2 / 3)
    #: and the simulator with 10 % moving landmarks, where 3 lets the moving points pull
    #: the poses (ATE 0.115 against 0.050 m for 2).
    smoother_kernel_scale: float = 2.0
    #: iSAM2 relinearization threshold (norm of a variable's tangent update). 0.01
    #: rather than GTSAM's usual 0.1 or the prototype's 0.05: dense 0027 2.6 m against
    #: 2.8 m ATE, the simulator 0.028 against 0.034 m, for ~15 % more time per frame.
    smoother_relinearize_threshold: float = 0.01
    #: 1σ of the weak position prior on each new landmark (m), around its triangulation.
    smoother_landmark_prior_m: float = 30.0
    #: An observation whose whitened error (norm, in σ) exceeds this after the update of
    #: its frame is removed from the smoother (counted as gated); a landmark gated
    #: max_consecutive_gated times in a row is rejected. 0 disables the check. 4 rather
    #: than 6: on the simulator with 10 % moving landmarks and 2 % outliers (300 frames,
    #: seed 0) ATE 0.0031 against 0.0039 m (the clean drive: 0.0021 m); dense 0027
    #: 2.76 m / 1.46 % against 2.59 m / 1.50 %.
    smoother_outlier_sigma: float = 4.0
    #: Drift test of the smoother (a ratio, or None to disable; SmootherFilter._drift_test):
    #: after each update, each landmark observed in the frame checked has its whitened
    #: residuals over the window regressed on time; a point on a moving vehicle, fitted
    #: as static, drifts one way. A landmark whose trend statistic exceeds this many
    #: times the median of the landmarks tested in the same frame, and whose apparent
    #: speed exceeds smoother_drift_min_speed_mps, is rejected and its factors in the
    #: window removed. Relative to the median rather than a chi-square quantile: σ is not
    #: the features' true scatter (0.5 px on the simulator, ~1.5 px on KITTI) and on real
    #: data static points trend too (dense 0027: 1 % of the tests beyond 27 times the
    #: median; the simulator: static points 6 times, half the tests of moving ones 21).
    #: 8 on the simulator's 600-frame drives, seeds 0-4, with 10 % moving landmarks and
    #: 2 % outliers: ATE 1.04-1.49x the clean drive's (6: 0.86-1.68x, off: 0.98-2.27x);
    #: dense 0027 2.43 m / 1.56 % (6: 2.34 m / 1.53 %, off: 2.15 m / 1.49 %).
    smoother_drift_ratio: float | None = 8.0
    #: Apparent speed (m/s) below which the drift test does not take a trend for motion
    #: (the point fitted as moving at constant velocity over its observations). Dense
    #: 0027's trending static points: median 0.4 m/s, 90 % under 2.4; the simulator's
    #: vehicles: 90 % of the tests above 2.6 m/s.
    smoother_drift_min_speed_mps: float = 2.0
    #: Compute the marginal covariance of the newest pose every frame (the result's
    #: pose_covariance, EKF convention). Off by default: GTSAM's marginal of the newest
    #: pose costs as much as the update itself (dense 0027: 72 s of marginals against
    #: 64 s of updates), which breaks real time; without it pose_covariance is None.
    smoother_pose_covariance: bool = False

    # --- batch refinement (mode "smoother" with refine) ----------------------------------
    #: After the smoother, a batch Levenberg-Marquardt pass over the whole drive from the
    #: smoother's final estimate (``vislam run --refine``).
    refine: bool = False
    #: Robust kernel of the refinement's stereo factors.
    refine_kernel: str = "huber"
    #: Scale of the refinement's kernel, in units of the whitened error.
    refine_kernel_scale: float = 1.0
    #: Second pass without the stereo factors whose reprojection error after the first
    #: pass exceeds this (px; largest of the three StereoPoint2 coordinates).
    refine_outlier_px: float = 6.0
    #: Iteration limit of each Levenberg-Marquardt pass.
    refine_max_iterations: int = 100

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in PER_AXIS_FIELDS:
                object.__setattr__(self, f.name, _per_axis(f.name, value))
            elif f.name in VECTOR_FIELDS:
                object.__setattr__(self, f.name, _three_numbers(f.name, value))
            elif f.name == "cam_T_imu":
                object.__setattr__(self, f.name, _rigid_or_none(value))
            elif f.name == "velocity_association":
                if value not in VELOCITY_ASSOCIATIONS:
                    raise ConfigError(f"velocity_association must be one of {', '.join(VELOCITY_ASSOCIATIONS)}, "
                                      f"got {value!r}")
            elif f.name in ("velocity_scale", "timestamp_scale"):
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                        or value <= 0:
                    raise ConfigError(f"{f.name} must be a number > 0, got {value!r}")
            elif f.name == "time_offset_s":
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                    raise ConfigError(f"time_offset_s must be a finite number (s), got {value!r}")
            elif f.name in ("gating_probability", "drift_test_probability"):
                if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                          or not 0.0 < value < 1.0):
                    raise ConfigError(f"{f.name} must be in (0, 1) or null, got {value!r}")
            elif f.name == "smoother_drift_ratio":
                if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                          or not math.isfinite(value) or value <= 1.0):
                    raise ConfigError(f"{f.name} must be a number > 1 or null, got {value!r}")
            elif f.name == "repeated_observations":
                if value not in REPEATED_POLICIES:
                    raise ConfigError(f"repeated_observations must be one of {', '.join(REPEATED_POLICIES)}, got {value!r}")
            elif f.name == "velocity_frame":
                if value not in VELOCITY_FRAMES:
                    raise ConfigError(f"velocity_frame must be one of {', '.join(VELOCITY_FRAMES)}, got {value!r}")
            elif f.name == "stalled_tracks":
                if value not in STALL_POLICIES:
                    raise ConfigError(f"stalled_tracks must be one of {', '.join(STALL_POLICIES)}, got {value!r}")
            elif f.name == "smoother_pixel_noise_px":
                if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                          or not math.isfinite(value) or value <= 0):
                    raise ConfigError(f"smoother_pixel_noise_px must be a number > 0 (px) or null, got {value!r}")
            elif f.name in ("smoother_kernel", "refine_kernel"):
                if value not in KERNELS:
                    raise ConfigError(f"{f.name} must be one of {', '.join(KERNELS)}, got {value!r}")
            elif f.name == "landmark_parametrization":
                if value not in LANDMARK_PARAMETRIZATIONS:
                    raise ConfigError(f"landmark_parametrization must be one of "
                                      f"{', '.join(LANDMARK_PARAMETRIZATIONS)}, got {value!r}")
            elif f.name == "ekf":
                if value not in EKF_VARIANTS:
                    raise ConfigError(f"ekf must be one of {', '.join(EKF_VARIANTS)}, got {value!r}")
            elif isinstance(f.default, bool):
                if not isinstance(value, bool):
                    raise ConfigError(f"{f.name} must be true or false, got {value!r}")
            elif f.name in ("max_consecutive_gated", "init_frames", "probation_frames", "stall_max_delay_frames",
                            "refine_max_iterations", "update_iterations"):
                low = 1 if f.name in ("init_frames", "refine_max_iterations", "update_iterations") else 0
                if isinstance(value, bool) or not isinstance(value, int) or value < low:
                    raise ConfigError(f"{f.name} must be an integer >= {low}, got {value!r}")
            else:
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                    raise ConfigError(f"{f.name} must be a finite number, got {value!r}")
                if value < 0:
                    raise ConfigError(f"{f.name} must be >= 0, got {value!r}")
        if self.pixel_noise_px <= 0:
            raise ConfigError("pixel_noise_px must be > 0 (the update needs a positive-definite V)")
        for name in ("imu_bias_time_constant_s", "smoother_window_s", "smoother_kernel_scale",
                     "smoother_landmark_prior_m", "refine_kernel_scale", "refine_outlier_px"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if self.min_depth_m >= self.max_depth_m:
            raise ConfigError("min_depth_m must be smaller than max_depth_m")

    # --- derived matrices ----------------------------------------------------------------
    @property
    def remaps_stalled_tracks(self) -> bool:
        """Whether SLAM runs the stalled-track remap (see :attr:`stalled_tracks`)."""
        return self.stalled_tracks == "remap" and self.repeated_observations == "skip"

    @property
    def W(self) -> np.ndarray:
        """6x6 motion noise covariance of one velocity sample, (v, ω) order."""
        return np.diag(np.concatenate([self.velocity_noise_per_axis, self.angular_noise_per_axis]) ** 2)

    @property
    def imu_bias_enabled(self) -> bool:
        """Whether the SLAM filter carries the IMU-error state (some σ_b > 0)."""
        return bool(np.any(self.imu_bias_sigma > 0))

    @property
    def imu_bias_sigma(self) -> np.ndarray:
        """(6,) stationary σ of b = (b_v, b_ω) (m/s ×3, rad/s ×3)."""
        return np.concatenate([_axis_array(self.imu_bias_sigma_mps), _axis_array(self.imu_bias_sigma_radps)])

    @property
    def velocity_noise_per_axis(self) -> np.ndarray:
        """(3,) σ_v per IMU axis (m/s)."""
        return _axis_array(self.velocity_noise_mps)

    @property
    def angular_noise_per_axis(self) -> np.ndarray:
        """(3,) σ_ω per IMU axis (rad/s)."""
        return _axis_array(self.angular_noise_radps)

    @property
    def has_data_corrections(self) -> bool:
        """True when some option changes the data (see vislam.core.corrections)."""
        defaults = FilterOptions.__dataclass_fields__
        return any(getattr(self, name) != defaults[name].default for name in DATA_CORRECTION_FIELDS)

    @property
    def V(self) -> np.ndarray:
        """4x4 observation noise covariance of one stereo observation."""
        return np.eye(4) * self.pixel_noise_px**2

    @property
    def initial_pose_covariance(self) -> np.ndarray:
        return np.diag([self.initial_position_std_m**2] * 3 + [self.initial_rotation_std_rad**2] * 3)

    @property
    def gate_threshold(self) -> float:
        """Chi-square(4) quantile for :attr:`gating_probability` (inf when gating is off)."""
        return _chi2_4_quantile(self.gating_probability)

    @property
    def drift_threshold(self) -> float:
        """Chi-square(4) quantile for :attr:`drift_test_probability` (inf when off)."""
        return _chi2_4_quantile(self.drift_test_probability)

    # --- (de)serialization ------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain values (tuples as lists), safe for JSON and YAML."""
        return {k: _as_lists(v) for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], source: str = "options") -> "FilterOptions":
        """Build from a mapping; unknown keys and bad values raise ConfigError naming ``source``."""
        if not isinstance(values, Mapping):
            raise ConfigError(f"{source}: expected a mapping of option names to values, got {type(values).__name__}")
        known = {f.name: f for f in fields(cls)}
        unknown = sorted((k for k in values if k not in known), key=repr)
        if unknown:
            raise ConfigError(f"{source}: {unknown_names_message('option(s)', unknown, known)}")
        clean = {}
        for key, value in values.items():
            default = getattr(cls, key)
            if key == "smoother_pixel_noise_px":
                default = 1.0  # a float (null allowed)
            if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if key in PER_AXIS_FIELDS + VECTOR_FIELDS + ("cam_T_imu",) and isinstance(value, list):
                value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
            clean[key] = value
        try:
            return cls(**clean)
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}") from None

    def replace(self, **changes) -> "FilterOptions":
        return dataclasses.replace(self, **changes)


def _as_lists(value):
    if isinstance(value, tuple):
        return [_as_lists(v) for v in value]
    return value


def _number(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value):
        raise ConfigError(f"{name} must be finite numbers, got {value!r}")
    return float(value)


def _three_numbers(name: str, value) -> tuple[float, float, float]:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 3:
        raise ConfigError(f"{name} must be three numbers (x, y, z), got {value!r}")
    return tuple(_number(name, v) for v in value)


def _per_axis(name: str, value):
    """A number >= 0 stays a number; three numbers >= 0 become a tuple."""
    if isinstance(value, (list, tuple, np.ndarray)):
        out = _three_numbers(name, value)
        if min(out) < 0:
            raise ConfigError(f"{name} must be >= 0 on every axis, got {value!r}")
        return out
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number or three finite numbers (x, y, z), got {value!r}")
    if value < 0:
        raise ConfigError(f"{name} must be >= 0, got {value!r}")
    return value


def _rigid_or_none(value):
    if value is None:
        return None
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"cam_T_imu must be a 4x4 matrix (4 rows of 4 numbers) or null, got {value!r}") from None
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise ConfigError(f"cam_T_imu must be a 4x4 matrix of finite numbers or null, got shape {a.shape}")
    R = a[:3, :3]
    if (not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0
            or not np.allclose(a[3], [0.0, 0.0, 0.0, 1.0])):
        raise ConfigError("cam_T_imu must be a rigid transform: a rotation block (orthonormal, det +1) and last "
                          "row 0 0 0 1")
    return tuple(tuple(float(x) for x in row) for row in a)
