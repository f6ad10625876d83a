"""Typed options of the filter, by component, with documented units and defaults.

:class:`FilterOptions` is made of frozen groups, one per component of the estimators:

========================  =====================================  ==============================
attribute                 group                                  component
========================  =====================================  ==============================
``options.noise``         :class:`NoiseOptions`                  noise model W, V, initial pose
``options.landmarks``     :class:`LandmarkOptions`               landmark guards, initialization, chart
``options.gating``        :class:`GatingOptions`                 gate and rejection of observations
``options.update``        :class:`UpdateOptions`                 EKF variant and iterated update
``options.stalls``        :class:`StallOptions`                  repeated observations, stalled tracks
``options.imu_error``     :class:`ImuErrorOptions`               IMU-error (Gauss-Markov) state
``options.motion``        :class:`MotionOptions`                 frame of the velocity samples
``options.corrections``   :class:`DataCorrections`               corrections applied to the data
``options.smoother``      :class:`SmootherOptions`               the sliding-window smoother
``options.refinement``    :class:`RefineOptions`                 the smoother's batch refinement
========================  =====================================  ==============================

Each field carries its one-line doc, unit, type, range or choices and its *flat name* in
``dataclasses.field(metadata=...)``; one generic validator (:func:`check_value`) reads
them. Every option also has a flat name, the spelling of options files, flags and code
before the groups (``velocity_noise_mps`` is ``noise.velocity_mps``):

* ``FilterOptions(velocity_noise_mps=0.5)`` and ``options.replace(...)`` /
  ``dataclasses.replace(options, ...)`` take flat names (and whole groups);
* ``options.velocity_noise_mps`` reads the field through a read-only property;
* :meth:`FilterOptions.from_dict` takes flat keys, nested groups
  (``{"noise": {"velocity_mps": 0.5}}``) or both, and refuses unknown keys (with
  "did you mean") and invalid values with a :class:`vislam.errors.ConfigError`;
* :meth:`FilterOptions.to_dict` is flat (the shape of summary.json, suggested.yaml and
  sweep results), :meth:`FilterOptions.to_nested_dict` by group.

Noise model (the report's): motion noise ``W = diag(σ_v², σ_v², σ_v², σ_ω², σ_ω², σ_ω²)``
enters the prediction as ``τ² W`` (σ_v, σ_ω: 1σ error of one velocity sample per axis);
observation noise ``V = σ_px² I₄`` on each stereo observation ``[uL, vL, uR, vR]``. The
defaults suit a clean, GPS-aided IMU like the sparse KITTI files'; the dense files need
``velocity_noise_mps=0.5, angular_noise_radps=0.05``. What each option does and how its
default was chosen: docs/options.md.
"""

from __future__ import annotations

import dataclasses
import math
import operator
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Mapping

import numpy as np

from vislam.core.suggest import did_you_mean, unknown_names_message
from vislam.errors import ConfigError

__all__ = ["FilterOptions", "MODES", "REPEATED_POLICIES", "STALL_POLICIES", "EKF_VARIANTS", "ROBUST_PRESET",
           "VELOCITY_ASSOCIATIONS", "DATA_CORRECTION_FIELDS", "KERNELS", "LANDMARK_PARAMETRIZATIONS",
           "NoiseOptions", "LandmarkOptions", "GatingOptions", "UpdateOptions", "StallOptions", "ImuErrorOptions",
           "MotionOptions", "DataCorrections", "SmootherOptions", "RefineOptions", "OPTION_GROUPS", "FLAT_FIELDS",
           "check_value", "flatten_options", "nest_options"]

#: The three estimators of the report, and the sliding-window smoother (vislam.core.smoother).
MODES = ("localization", "mapping", "slam", "smoother")
#: Robust kernels of the smoother and of its batch refinement.
KERNELS = ("cauchy", "huber", "none")
#: Policies for observations that repeat the previous frame's pixels exactly.
REPEATED_POLICIES = ("auto", "skip", "split", "use")
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

#: Options of the robust preset (``--robust``): for scenes with moving traffic — a
#: more sensitive drift test and two frames of probation for new landmarks.
ROBUST_PRESET = {"drift_test_probability": 0.9, "probation_frames": 2}

#: Kinds of option values (metadata ``kind``) and what the validator accepts for each.
KINDS = {
    "number": "a finite number (an integer is taken as a float)",
    "integer": "an integer",
    "bool": "true or false",
    "choice": "one of the names in metadata 'choices'",
    "per_axis": "a number, or three numbers (IMU x, y, z)",
    "vector3": "three numbers (x, y, z)",
    "rigid": "a 4x4 rigid transform (4 rows of 4 numbers), or null",
}


#: Upper bound of ``max_landmarks_in_state``: a state of 10 000 landmarks holds a 7 GB covariance.
MAX_LANDMARKS_IN_STATE = 10_000


def option(default, doc: str, *, unit: str = "", kind: str = "number", range: tuple | None = None,
           open: tuple[bool, bool] = (False, False), choices: tuple | None = None, optional: bool = False,
           flat: str | None = None, note: str = ""):
    """A dataclass field of an option group with its metadata: ``doc`` (one line),
    ``unit``, ``kind`` (:data:`KINDS`), ``range`` (low, high; None for unbounded) with
    ``open`` (whether each bound is excluded), ``choices``, ``optional`` (None allowed:
    the test is off), ``flat`` (the flat name; default the field's own) and ``note``
    (appended to a range error)."""
    assert kind in KINDS, kind
    meta = {"doc": doc, "unit": unit, "kind": kind, "range": range, "open": open, "choices": choices,
            "optional": optional, "flat": flat, "note": note}
    return field(default=default, metadata=meta)


def _range_text(meta) -> str:
    low, high = meta["range"]
    low_open, high_open = meta["open"]
    if low is not None and high is not None:
        return f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {low:g}"
    return f"{'<' if high_open else '<='} {high:g}"


def _in_range(value: float, meta) -> bool:
    low, high = meta["range"]
    low_open, high_open = meta["open"]
    if low is not None and (value < low or (low_open and value == low)):
        return False
    return not (high is not None and (value > high or (high_open and value == high)))


def check_value(name: str, value, meta: Mapping[str, Any]):
    """``value`` checked against an option's metadata and normalized (three numbers as a
    tuple, a rigid transform as a tuple of rows); ConfigError naming ``name`` otherwise."""
    kind, optional = meta["kind"], meta["optional"]
    if value is None and (optional or kind == "rigid"):
        return None
    null = " or null" if optional else ""
    if kind == "choice":
        if not isinstance(value, str) or value not in meta["choices"]:
            raise ConfigError(f"{name} must be one of {', '.join(meta['choices'])}, got {value!r}")
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{name} must be true or false, got {value!r}")
        return value
    if kind == "integer":
        if isinstance(value, bool) or not isinstance(value, int) or not _in_range(value, meta):
            raise ConfigError(f"{name} must be an integer {_range_text(meta)}, got {value!r}")
        return value
    if kind == "per_axis":
        return _per_axis(name, value)
    if kind == "vector3":
        out = _three_numbers(name, value)
        if meta["range"] is not None and not all(_in_range(x, meta) for x in out):
            raise ConfigError(f"{name} must be three numbers {_range_text(meta)}, got {value!r}")
        return out
    if kind == "rigid":
        return _rigid(name, value)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number{null}, got {value!r}")
    if meta["range"] is not None and not _in_range(value, meta):
        if meta["note"]:
            raise ConfigError(f"{name} must be {_range_text(meta)} ({meta['note']}), got {value!r}")
        raise ConfigError(f"{name} must be {_range_text(meta)}{null}, got {value!r}")
    return value


class _Group:
    """Base of the option groups: the generic validation in ``__post_init__``."""

    #: What the group is about (the title of its --help section and docs table).
    TITLE: ClassVar[str] = ""

    def __post_init__(self):
        for f in fields(self):
            value = check_value(f.metadata["flat"] or f.name, getattr(self, f.name), f.metadata)
            object.__setattr__(self, f.name, value)
        self._check()

    def _check(self) -> None:
        """Checks across the group's fields (none by default)."""


#: Common ranges of option() (``**POSITIVE``): > 0, >= 0, and in (0, 1).
POSITIVE = {"range": (0, None), "open": (True, False)}
NON_NEGATIVE = {"range": (0, None)}
PROBABILITY = {"range": (0, 1), "open": (True, True)}
#: Largest 1σ of a noise or prior option, in its unit (m/s, rad/s, px, m, rad, m/s²):
#: 1e6 is no information at all, and far larger ones (1e300) overflow the squares and
#: products of the covariances. The smallest 1σ of a pixel noise: its square must keep V
#: positive-definite (1e-300 px underflows to V = 0).
MAX_STD = 1e6
MIN_PIXEL_STD = 1e-6
#: Largest |coordinate| (m) of cam_T_imu's translation: the IMU and the camera sit on one
#: vehicle; 1e300 m overflowed every projection to a non-finite state.
MAX_LEVER_ARM_M = 1e3
#: ``**STD``: a 1σ >= 0 and at most MAX_STD; ``**PIXEL_STD``: in [MIN_PIXEL_STD, MAX_STD].
STD = {"range": (0, MAX_STD)}
PIXEL_STD = {"range": (MIN_PIXEL_STD, MAX_STD)}


@dataclass(frozen=True)
class NoiseOptions(_Group):
    """The filter's noise model: motion noise W, observation noise V, initial pose."""

    TITLE: ClassVar[str] = "noise model"
    velocity_mps: float | tuple[float, float, float] = option(
        0.02, "1σ error of one linear-velocity sample per axis; one number or three (IMU x, y, z)", unit="m/s",
        kind="per_axis", flat="velocity_noise_mps")
    angular_radps: float | tuple[float, float, float] = option(
        0.0003, "1σ error of one angular-velocity sample per axis; one number or three (IMU x, y, z)",
        unit="rad/s", kind="per_axis", flat="angular_noise_radps")
    pixel_px: float = option(2.0, "1σ error of one pixel coordinate of a stereo observation (V = σ² I₄)",
                             unit="px", **PIXEL_STD, flat="pixel_noise_px",
                             note="the update needs a positive-definite V")
    initial_position_std_m: float = option(0.0, "1σ of the initial position (the world frame is the first IMU "
                                           "pose, so 0 is exact)", unit="m", **STD)
    initial_rotation_std_rad: float = option(0.0, "1σ of the initial orientation", unit="rad", **STD)


@dataclass(frozen=True)
class LandmarkOptions(_Group):
    """Which stereo points become landmarks, when, and how the state holds them."""

    TITLE: ClassVar[str] = "landmarks and initialization"
    min_disparity_px: float = option(2.0, "smallest disparity uL − uR accepted for triangulation", unit="px",
                                     **NON_NEGATIVE)
    max_depth_m: float = option(200.0, "largest triangulated depth accepted for a new landmark", unit="m",
                                **NON_NEGATIVE)
    min_depth_m: float = option(0.5, "smallest triangulated depth accepted for a new landmark", unit="m",
                                **NON_NEGATIVE)
    max_row_difference_px: float = option(3.0, "largest row difference vL − vR, absolute (rectified rows "
                                          "should agree)", unit="px", **NON_NEGATIVE)
    init_frames: int = option(1, "frames a SLAM landmark must pass the guards and a static-point test before it "
                              "enters the state (1: at first sight, the report)", unit="frames", kind="integer",
                              range=(1, None))
    probation_frames: int = option(0, "frames a new SLAM landmark updates only itself (Schmidt-Kalman consider "
                                   "update) before it updates the pose (0: off, the report)", unit="frames",
                                   kind="integer", range=(0, None))
    parametrization: str = option("inverse_depth", "chart of the SLAM landmarks in the state: anchored inverse "
                                  "depth or the report's Cartesian world position", kind="choice",
                                  choices=LANDMARK_PARAMETRIZATIONS, flat="landmark_parametrization")
    keep_all: bool = option(False, "keep every landmark in the SLAM state for the whole run (the report's "
                            "variant; by default a landmark is marginalized when its track ends)", kind="bool",
                            flat="keep_all_landmarks")
    max_in_state: int = option(1000, "most landmarks in the SLAM EKF's state (and the smoother's window) at once: a "
                               "new landmark waits for room, lowest id first (a frame's update costs the cube of its landmarks: 1000 "
                               "take seconds, 3000 a minute and gigabytes)", unit="landmarks", kind="integer",
                               range=(1, MAX_LANDMARKS_IN_STATE), flat="max_landmarks_in_state")
    motion: bool = option(False, "give every SLAM landmark a velocity with a constant-velocity prediction (the "
                          "report's proposed fix for moving landmarks; Cartesian)", kind="bool",
                          flat="landmark_motion")
    velocity_std_mps: float = option(2.0, "prior 1σ of a new landmark's velocity per axis (motion model only)",
                                     unit="m/s", **STD, flat="landmark_velocity_std_mps")
    acceleration_std_mps2: float = option(1.0, "1σ of a landmark's acceleration per axis, process noise (motion "
                                          "model only)", unit="m/s²", **STD,
                                          flat="landmark_acceleration_std_mps2")

    def _check(self) -> None:
        if self.min_depth_m >= self.max_depth_m:
            raise ConfigError("min_depth_m must be smaller than max_depth_m")


@dataclass(frozen=True)
class GatingOptions(_Group):
    """Which observations are used, and when a landmark is taken for a moving point."""

    TITLE: ClassVar[str] = "gating and rejection"
    probability: float | None = option(0.95, "chi-square gate probability of the 4-D stereo innovation; "
                                       "observations outside are not used (null: no gate)", **PROBABILITY,
                                       optional=True, flat="gating_probability")
    max_consecutive_gated: int = option(3, "a landmark gated this many frames in a row is removed and flagged "
                                        "rejected (0: never)", unit="frames", kind="integer", range=(0, None))
    drift_test_probability: float | None = option(0.99, "innovation drift test: a landmark whose whitened "
                                                  "residuals keep drifting beyond this chi-square(4) quantile is "
                                                  "rejected as moving (null: off)", **PROBABILITY, optional=True)


@dataclass(frozen=True)
class UpdateOptions(_Group):
    """The EKF's measurement update."""

    TITLE: ClassVar[str] = "update"
    ekf: str = option("oc", "oc: observability-constrained EKF (Jacobians projected so the global pose stays "
                      "unobservable); standard: the report's equations", kind="choice", choices=EKF_VARIANTS)
    iterations: int = option(4, "most iterations of the SLAM update per frame (1: the EKF; more: the iterated "
                             "EKF, not with landmark motion)", kind="integer", range=(1, None),
                             flat="update_iterations")
    iteration_tolerance: float = option(0.5, "stop iterating when the next step would move the estimate by less "
                                        "than this (0: always update_iterations)", unit="σ", **NON_NEGATIVE,
                                        flat="update_iteration_tolerance")


@dataclass(frozen=True)
class StallOptions(_Group):
    """Observations that repeat the previous frame's pixels, and the tracks they stall."""

    TITLE: ClassVar[str] = "stalled tracks"
    repeated_observations: str = option("auto", "an observation repeating its landmark's previous pixels bit for "
                                        "bit: skip it (with the remap), split the track there (a new landmark, "
                                        "in sync), or use it; auto: split in the SLAM EKF, skip elsewhere",
                                        kind="choice", choices=REPEATED_POLICIES)
    policy: str = option("remap", "remap: give each observation of a stalled track to the frame it was taken "
                         "(SLAM, with repeated_observations skip; runs stall_max_delay_frames behind); keep: "
                         "use it at the frame it arrives", kind="choice", choices=STALL_POLICIES,
                         flat="stalled_tracks")
    max_delay_frames: int = option(10, "largest lag the remap restores (larger lags are dropped); also the "
                                   "remapped filter's output delay", unit="frames", kind="integer", range=(0, None),
                                   flat="stall_max_delay_frames")


@dataclass(frozen=True)
class ImuErrorOptions(_Group):
    """The optional IMU-error state of SLAM: a Gauss-Markov error b of the velocity samples."""

    TITLE: ClassVar[str] = "IMU-error state"
    sigma_mps: float | tuple[float, float, float] = option(
        0.0, "stationary 1σ of the slowly varying error of the linear-velocity samples; one number or three "
        "(0 with sigma_radps 0: off)", unit="m/s", kind="per_axis", flat="imu_bias_sigma_mps")
    sigma_radps: float | tuple[float, float, float] = option(
        0.0, "stationary 1σ of the slowly varying error of the angular-velocity samples; one number or three",
        unit="rad/s", kind="per_axis", flat="imu_bias_sigma_radps")
    time_constant_s: float = option(5.0, "correlation time T_c of the IMU-error state (a = exp(−τ/T_c) per step)",
                                    unit="s", **POSITIVE, flat="imu_bias_time_constant_s")


@dataclass(frozen=True)
class MotionOptions(_Group):
    """How the velocity samples drive the prediction."""

    TITLE: ClassVar[str] = "motion model"
    velocity_frame: str = option("level", "frame of the linear velocities: body (the IMU frame, the report) or "
                                 "level (heading-aligned and levelled, an INS's vf/vl/vu as in KITTI)", kind="choice",
                                 choices=VELOCITY_FRAMES)
    level_jacobian: bool = option(True, "with velocity_frame level: propagate the covariance with the exact "
                                  "transition, which includes the roll and pitch dependence of the body velocity",
                                  kind="bool", flat="level_velocity_jacobian")


@dataclass(frozen=True)
class DataCorrections(_Group):
    """Corrections applied to the recording before filtering (vislam.core.corrections);
    ``vislam check`` estimates them, the defaults leave the data untouched."""

    TITLE: ClassVar[str] = "data corrections"
    gyro_bias_radps: tuple[float, float, float] = option(
        (0.0, 0.0, 0.0), "gyro bias subtracted from every angular-velocity sample (IMU x, y, z)", unit="rad/s",
        kind="vector3", range=(-MAX_STD, MAX_STD))
    velocity_bias_mps: tuple[float, float, float] = option(
        (0.0, 0.0, 0.0), "velocity bias subtracted from every linear-velocity sample (IMU x, y, z)", unit="m/s",
        kind="vector3", range=(-MAX_STD, MAX_STD))
    velocity_scale: float = option(1.0, "factor on every linear-velocity sample, before the bias (a recording in "
                                   "km/h needs 1/3.6)", range=(0, 1e3), open=(True, False))
    timestamp_scale: float = option(1.0, "factor that turns the recording's timestamps into seconds (0.001 for "
                                    "milliseconds)", range=(1e-12, 1e6))
    imu_camera_rotation_correction_deg: tuple[float, float, float] = option(
        (0.0, 0.0, 0.0), "rotation vector φ in the camera frame: cam_T_imu's rotation becomes exp(φ) R, its "
        "translation is kept", unit="deg", kind="vector3", range=(-360.0, 360.0))
    cam_T_imu: tuple | None = option(None, "4x4 rigid transform (rows) replacing the recording's cam_T_imu, or "
                                     "null to keep it (the rotation correction applies on top)", kind="rigid")
    velocity_association: str = option("next", "which velocity sample describes the interval k -> k+1: next "
                                        "(sample k+1, KITTI) or current (sample k)", kind="choice",
                                        choices=VELOCITY_ASSOCIATIONS)
    time_offset_s: float = option(0.0, "camera-IMU time offset: the sample stamped t describes the motion at "
                                  "t + offset (the velocities are resampled at the frame times)", unit="s")


@dataclass(frozen=True)
class SmootherOptions(_Group):
    """The sliding-window smoother (mode "smoother", vislam.core.smoother)."""

    TITLE: ClassVar[str] = "smoother"
    window_s: float = option(3.0, "length of the fixed-lag window: older poses and landmarks not seen for this "
                             "long are marginalized", unit="s", **POSITIVE,
                             flat="smoother_window_s")
    pixel_noise_px: float | None = option(1.0, "1σ of one pixel coordinate in the smoother's stereo factors "
                                          "(null: pixel_noise_px)", unit="px", **PIXEL_STD,
                                          optional=True, flat="smoother_pixel_noise_px")
    kernel: str = option("cauchy", "robust kernel of the stereo factors", kind="choice", choices=KERNELS,
                         flat="smoother_kernel")
    kernel_scale: float = option(2.0, "scale of the kernel in units of the whitened error", unit="σ",
                                 **POSITIVE, flat="smoother_kernel_scale")
    relinearize_threshold: float = option(0.01, "iSAM2 relinearization threshold (norm of a variable's tangent "
                                          "update)", **NON_NEGATIVE, flat="smoother_relinearize_threshold")
    landmark_prior_m: float = option(30.0, "1σ of the weak position prior on each new landmark, around its "
                                     "triangulation", unit="m", range=(0, MAX_STD), open=(True, False),
                                     flat="smoother_landmark_prior_m")
    outlier_sigma: float = option(4.0, "an observation whose whitened error exceeds this after its frame's update "
                                  "is removed, counted as gated (0: no check)", unit="σ", **NON_NEGATIVE,
                                  flat="smoother_outlier_sigma")
    drift_ratio: float | None = option(8.0, "drift test: a landmark whose residual trend exceeds this many times "
                                       "the frame's median (and moves faster than drift_min_speed) is rejected "
                                       "(null: off)", range=(1, None), open=(True, False), optional=True,
                                       flat="smoother_drift_ratio")
    drift_min_speed_mps: float = option(2.0, "apparent speed below which the drift test does not take a trend for "
                                        "motion", unit="m/s", **NON_NEGATIVE,
                                        flat="smoother_drift_min_speed_mps")
    pose_covariance: bool = option(False, "compute the newest pose's marginal covariance every frame (costs as "
                                   "much as the update; otherwise pose_covariance is None)", kind="bool",
                                   flat="smoother_pose_covariance")


@dataclass(frozen=True)
class RefineOptions(_Group):
    """The batch Levenberg-Marquardt refinement after the smoother (``vislam run --refine``)."""

    TITLE: ClassVar[str] = "batch refinement"
    enabled: bool = option(False, "after the smoother, a batch pass over the whole drive from its final estimate",
                           kind="bool", flat="refine")
    kernel: str = option("huber", "robust kernel of the refinement's stereo factors", kind="choice",
                         choices=KERNELS, flat="refine_kernel")
    kernel_scale: float = option(1.0, "scale of the kernel in units of the whitened error", unit="σ",
                                 **POSITIVE, flat="refine_kernel_scale")
    outlier_px: float = option(6.0, "second pass without the stereo factors whose reprojection error after the "
                               "first exceeds this", unit="px", **POSITIVE,
                               flat="refine_outlier_px")
    max_iterations: int = option(100, "iteration limit of each Levenberg-Marquardt pass", kind="integer",
                                 range=(1, None), flat="refine_max_iterations")


#: Attribute of FilterOptions -> its group class, in the order of the documentation.
OPTION_GROUPS: dict[str, type] = {
    "noise": NoiseOptions, "landmarks": LandmarkOptions, "gating": GatingOptions, "update": UpdateOptions,
    "stalls": StallOptions, "imu_error": ImuErrorOptions, "motion": MotionOptions,
    "corrections": DataCorrections, "smoother": SmootherOptions, "refinement": RefineOptions,
}

#: Flat name -> (group, field name in the group), in the order of the groups.
FLAT_FIELDS: dict[str, tuple[str, str]] = {
    (f.metadata["flat"] or f.name): (group, f.name) for group, cls in OPTION_GROUPS.items() for f in fields(cls)
}
#: (group, field) -> the field (with its metadata), keyed by flat name.
_FIELD_OF = {flat: {f.name: f for f in fields(OPTION_GROUPS[g])}[n] for flat, (g, n) in FLAT_FIELDS.items()}
assert len(FLAT_FIELDS) == sum(len(fields(c)) for c in OPTION_GROUPS.values()), "a flat name is used twice"
assert not set(FLAT_FIELDS) & set(OPTION_GROUPS), "a flat name is a group's name"


def _group_fields(group: str) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in fields(OPTION_GROUPS[group])}


def flatten_options(values: Mapping[str, Any], source: str = "options") -> dict[str, Any]:
    """A mapping of options with nested groups (``{"noise": {"velocity_mps": 0.5}}``,
    a ``[noise]`` TOML table) turned flat (``{"velocity_noise_mps": 0.5}``); flat keys
    pass as they are. A group key whose value is not a mapping, an unknown key inside a
    group (with "did you mean"), an unknown table, or an option given twice (flat and
    nested) is a ConfigError naming ``source``. Other unknown flat keys are left to
    :meth:`FilterOptions.from_dict`."""
    out: dict[str, Any] = {}
    nested_from: dict[str, str] = {}
    for key, value in values.items():
        if key in OPTION_GROUPS:
            if not isinstance(value, Mapping):
                raise ConfigError(f"{source}: {key!r} is a group of options and needs a mapping (table) of its "
                                  f"fields, got {type(value).__name__}")
            known = _group_fields(key)
            unknown = [k for k in value if k not in known]
            if unknown:
                raise ConfigError(f"{source}: group {key!r}: {unknown_names_message('option(s)', unknown, known)}")
            for name, v in value.items():
                f = known[name]
                flat = f.metadata["flat"] or f.name
                if flat in values:
                    raise ConfigError(f"{source}: option {key}.{name} is given twice (also as {flat!r})")
                out[flat] = v
                nested_from[flat] = f"{key}.{name}"
        elif isinstance(value, Mapping):
            hint = did_you_mean(key, OPTION_GROUPS) if isinstance(key, str) else ""
            groups = ", ".join(OPTION_GROUPS)
            raise ConfigError(f"{source}: option {key!r} is a table/mapping but not a group of options "
                              f"({hint or 'groups: ' + groups}); a file is a mapping of option names to values, "
                              f"or of groups to their options")
        else:
            out[key] = value
    return out


def nest_options(flat: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """A flat mapping of option names (all known) as nested groups, in group order."""
    out: dict[str, dict[str, Any]] = {}
    for key, value in flat.items():
        group, name = FLAT_FIELDS[key]
        out.setdefault(group, {})[name] = value
    return {g: out[g] for g in OPTION_GROUPS if g in out}


def _chi2_4_quantile(p: float | None) -> float:
    """The p-quantile of χ² with 4 degrees of freedom (the gate of a stereo observation).

    Its survival function is closed-form, Q(x) = e^(−x/2) (1 + x/2): with y = x/2 the
    quantile solves y − log(1 + y) = −log(1 − p), increasing and convex in y > 0, so
    Newton's method from any y > 0 converges (monotonically after the first step) — to
    rounding, as scipy.special.chdtri(4, 1 − p) (without importing scipy.special, 40 ms)."""
    if p is None:
        return math.inf
    if p >= 1.0:
        return math.inf
    c = -math.log1p(-p)
    if c <= 0.0:
        return 0.0
    y = c + math.log1p(c) + math.sqrt(2.0 * c)  # right of the root, or its first step is
    for _ in range(100):
        step = (y - math.log1p(y) - c) * (1.0 + y) / y  # h / h',  h' = y / (1 + y)
        y -= step
        if abs(step) <= 4e-16 * y:
            break
    return 2.0 * y


def _axis_array(value) -> np.ndarray:
    """A PER_AXIS_FIELDS value (a number or three) as a (3,) array (a copy)."""
    return np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()


@dataclass(frozen=True, init=False)
class FilterOptions:
    """Noise, initialization and robustness parameters of the estimators, by component.

    Build it with flat names (``FilterOptions(velocity_noise_mps=0.5)``), with groups
    (``FilterOptions(noise=NoiseOptions(velocity_mps=0.5))``) or both (flat names apply on
    top of the groups). Every flat name reads as an attribute (``options.pixel_noise_px``
    is ``options.noise.pixel_px``). Fields, units and defaults: the group classes and
    docs/options.md.
    """

    noise: NoiseOptions = field(default_factory=NoiseOptions)
    landmarks: LandmarkOptions = field(default_factory=LandmarkOptions)
    gating: GatingOptions = field(default_factory=GatingOptions)
    update: UpdateOptions = field(default_factory=UpdateOptions)
    stalls: StallOptions = field(default_factory=StallOptions)
    imu_error: ImuErrorOptions = field(default_factory=ImuErrorOptions)
    motion: MotionOptions = field(default_factory=MotionOptions)
    corrections: DataCorrections = field(default_factory=DataCorrections)
    smoother: SmootherOptions = field(default_factory=SmootherOptions)
    refinement: RefineOptions = field(default_factory=RefineOptions)

    def __init__(self, **values):
        changes: dict[str, dict[str, Any]] = {}
        groups: dict[str, Any] = {}
        for key, value in values.items():
            if key in OPTION_GROUPS:
                cls = OPTION_GROUPS[key]
                if isinstance(value, Mapping):
                    value = _build_group(key, value)
                elif not isinstance(value, cls):
                    raise ConfigError(f"{key} must be a {cls.__name__} (or a mapping of its fields), got "
                                      f"{type(value).__name__}")
                groups[key] = value
            elif key in FLAT_FIELDS:
                group, name = FLAT_FIELDS[key]
                changes.setdefault(group, {})[name] = value
            else:
                hint = did_you_mean(key, [*FLAT_FIELDS, *OPTION_GROUPS])
                raise TypeError(f"FilterOptions got an unexpected keyword argument {key!r}" + (f"; {hint}" if hint
                                                                                                else ""))
        for group, cls in OPTION_GROUPS.items():
            value = groups.get(group)
            if group in changes:
                value = dataclasses.replace(value, **changes[group]) if value is not None else cls(**changes[group])
            object.__setattr__(self, group, value if value is not None else _DEFAULT_GROUPS[group])

    # --- derived values ------------------------------------------------------------------
    @property
    def remaps_stalled_tracks(self) -> bool:
        """Whether SLAM runs the stalled-track remap (see :attr:`stalled_tracks`)."""
        return self.stalls.policy == "remap" and self.repeated_policy("slam") == "skip"

    def repeated_policy(self, estimator: str) -> str:
        """``repeated_observations`` as the given estimator ("slam": the SLAM EKF,
        "smoother", "mapping") applies it: "auto" is "split" in the SLAM EKF — a restarted
        track is a new point in sync, and the remap's lag model, exact only at constant
        motion, biases the EKF in turns (docs/data.md, the lever arm) — and "skip" (with
        the remap) in the smoother, whose robust kernel keeps the long tracks' benefit."""
        value = self.stalls.repeated_observations
        if value != "auto":
            return value
        return "split" if estimator == "slam" else "skip"

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
        return np.concatenate([_axis_array(self.imu_error.sigma_mps), _axis_array(self.imu_error.sigma_radps)])

    @property
    def velocity_noise_per_axis(self) -> np.ndarray:
        """(3,) σ_v per IMU axis (m/s)."""
        return _axis_array(self.noise.velocity_mps)

    @property
    def angular_noise_per_axis(self) -> np.ndarray:
        """(3,) σ_ω per IMU axis (rad/s)."""
        return _axis_array(self.noise.angular_radps)

    @property
    def has_data_corrections(self) -> bool:
        """True when some option changes the data (see vislam.core.corrections)."""
        return self.corrections != _DEFAULT_GROUPS["corrections"]

    @property
    def V(self) -> np.ndarray:
        """4x4 observation noise covariance of one stereo observation."""
        return np.eye(4) * self.noise.pixel_px**2

    @property
    def initial_pose_covariance(self) -> np.ndarray:
        return np.diag([self.noise.initial_position_std_m**2] * 3 + [self.noise.initial_rotation_std_rad**2] * 3)

    @property
    def gate_threshold(self) -> float:
        """Chi-square(4) quantile for :attr:`gating_probability` (inf when gating is off)."""
        return _chi2_4_quantile(self.gating.probability)

    @property
    def drift_threshold(self) -> float:
        """Chi-square(4) quantile for :attr:`drift_test_probability` (inf when off)."""
        return _chi2_4_quantile(self.gating.drift_test_probability)

    # --- (de)serialization ------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Flat plain values (tuples as lists), safe for JSON and YAML: the shape of
        summary.json's ``options``, suggested.yaml and sweep results."""
        return {flat: _as_lists(getattr(getattr(self, g), n)) for flat, (g, n) in FLAT_FIELDS.items()}

    def to_nested_dict(self) -> dict[str, dict[str, Any]]:
        """Plain values by group (``{"noise": {"velocity_mps": ...}, ...}``)."""
        return nest_options(self.to_dict())

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], source: str = "options") -> "FilterOptions":
        """Build from a mapping of flat names, of groups to their fields, or both; unknown
        keys and bad values raise ConfigError naming ``source``."""
        if not isinstance(values, Mapping):
            raise ConfigError(f"{source}: expected a mapping of option names to values, got {type(values).__name__}")
        values = flatten_options(values, source)
        unknown = sorted((k for k in values if k not in FLAT_FIELDS), key=repr)
        if unknown:
            raise ConfigError(f"{source}: {_unknown_message(unknown)}")
        clean = {}
        for key, value in values.items():
            kind = _FIELD_OF[key].metadata["kind"]
            if kind in ("number", "per_axis") and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if kind in ("per_axis", "vector3", "rigid") and isinstance(value, list):
                value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
            clean[key] = value
        try:
            return cls(**clean)
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}") from None

    def replace(self, **changes) -> "FilterOptions":
        """A copy with ``changes`` (flat names or groups), validated."""
        return dataclasses.replace(self, **changes)


def _unknown_message(unknown: list) -> str:
    """"unknown option(s) ..." with "did you mean"; a field's name in its group given at
    the top level is pointed to its flat name and group."""
    for key in unknown:
        places = [(flat, g) for flat, (g, n) in FLAT_FIELDS.items() if n == key and flat != key]
        if len(unknown) == 1 and places:
            where = " or ".join(f"{flat!r} (or {key!r} in group {g!r})" for flat, g in places)
            return f"unknown option {key!r}; at the top level it is {where}"
    return unknown_names_message("option(s)", unknown, [*FLAT_FIELDS, *OPTION_GROUPS])


def _build_group(group: str, values: Mapping[str, Any]):
    known = _group_fields(group)
    unknown = [k for k in values if k not in known]
    if unknown:
        raise ConfigError(f"group {group!r}: {unknown_names_message('option(s)', unknown, known)}")
    return OPTION_GROUPS[group](**values)


def _flat_property(flat: str, group: str, name: str) -> property:
    f = _FIELD_OF[flat]
    unit = f" ({f.metadata['unit']})" if f.metadata["unit"] else ""
    return property(operator.attrgetter(f"{group}.{name}"),
                    doc=f"{f.metadata['doc']}{unit}; default {f.default!r}. Read-only: ``{group}.{name}``.")


for _flat, (_group, _name) in FLAT_FIELDS.items():
    setattr(FilterOptions, _flat, _flat_property(_flat, _group, _name))
del _flat, _group, _name



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
    """A 1σ in [0, MAX_STD] stays a number; three of them become a tuple."""
    if isinstance(value, (list, tuple, np.ndarray)):
        out = _three_numbers(name, value)
        if min(out) < 0 or max(out) > MAX_STD:
            raise ConfigError(f"{name} must be in [0, {MAX_STD:g}] on every axis, got {value!r}")
        return out
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number or three finite numbers (x, y, z), got {value!r}")
    if value < 0:
        raise ConfigError(f"{name} must be >= 0, got {value!r}")
    if value > MAX_STD:
        raise ConfigError(f"{name} must be at most {MAX_STD:g} (no information at all; larger ones overflow the "
                          f"covariances), got {value!r}")
    return value


def _rigid(name: str, value):
    if value is None:
        return None
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a 4x4 matrix (4 rows of 4 numbers) or null, got {value!r}") from None
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{name} must be a 4x4 matrix of finite numbers or null, got shape {a.shape}")
    R = a[:3, :3]
    if (not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0
            or not np.allclose(a[3], [0.0, 0.0, 0.0, 1.0])):
        raise ConfigError(f"{name} must be a rigid transform: a rotation block (orthonormal, det +1) and last "
                          "row 0 0 0 1")
    if np.abs(a[:3, 3]).max() > MAX_LEVER_ARM_M:
        raise ConfigError(f"{name}'s translation must be within ±{MAX_LEVER_ARM_M:g} m (an IMU-camera lever arm), "
                          f"got {a[:3, 3].tolist()}")
    return tuple(tuple(float(x) for x in row) for row in a)


#: The groups with their defaults (validated once).
_DEFAULT_GROUPS = {group: cls() for group, cls in OPTION_GROUPS.items()}


def _default_text(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return "[" + ", ".join(_default_text(v) for v in value) + "]"
    return repr(value) if isinstance(value, float) else str(value)


def reference_markdown() -> str:
    """The options' reference tables (Markdown, one per group) from the fields' metadata:
    the block between the markers of docs/options.md (tests/test_options_groups.py
    checks that the page holds exactly this)."""
    lines = []
    for group, cls in OPTION_GROUPS.items():
        lines += [f"### `{group}`: {cls.TITLE}", "", " ".join(cls.__doc__.split()), "",
                  "| flat name | in the group | unit | default | what it does |", "|---|---|---|---|---|"]
        for f in fields(cls):
            m = f.metadata
            what = m["doc"].replace("|", "\\|")
            if m["kind"] == "choice":
                what += f" ({' / '.join(m['choices'])})"
            default = _default_text(f.default)
            lines.append(f"| `{m['flat'] or f.name}` | `{f.name}` | {m['unit'] or '–'} | `{default}` | {what} |")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"
