"""The in-memory recording every estimator consumes: :class:`Sequence`.

A sequence has T frames. Velocities are IMU-frame body velocities sampled at the frame
timestamps. Stereo features are stored sparsely, frame by frame (compressed rows), so
that memory grows with the number of observations, not with landmarks x frames;
:meth:`StereoObservations.dense` rebuilds the dataset's 4 x M x T array (-1 where a
landmark is not seen) and :attr:`StereoObservations.observed_mask` the explicit M x T mask.

Landmark ids are the column indices ``j`` of the dataset's feature array.

All arrays are read-only: a Sequence is immutable once built.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from vislam.core.camera import StereoCamera
from vislam.core.options import MAX_LEVER_ARM_M
from vislam.errors import SequenceError

__all__ = ["StereoObservations", "Sequence", "Frame", "Calibration", "MISSING_PIXEL", "frozen_array", "RepeatMotion",
           "imu_dropouts", "IMU_DROPOUT_MIN_SAMPLES", "imu_spikes", "imu_spike_mask", "frame_times_not_seconds",
           "true_runs",
           "SequenceError", "rigid_transform_problem",
           "repeat_decision", "predicted_flow_px", "REPEAT_MIN_PREDICTED_FLOW_PX"]

#: Value of all four pixel coordinates where a landmark is not observed (dataset format).
MISSING_PIXEL = -1.0


#: Tolerance of the rotation block of an in-memory ``cam_T_imu`` (|RᵀR − I|, |det R − 1|,
#: last row): looser than the loader's, it refuses what is not a rigid transform at all
#: (a scaled rotation, NaN), not rounding.
_RIGID_TOL = 1e-4


def rigid_transform_problem(T, name: str = "cam_T_imu") -> str | None:
    """What makes ``T`` unfit as the IMU-camera transform (not 4x4, not finite, not rigid,
    a translation beyond ±:data:`MAX_LEVER_ARM_M`), or None."""
    T = np.asarray(T)
    if T.shape != (4, 4):
        return f"{name} must be 4x4, got shape {T.shape}"
    if not np.issubdtype(T.dtype, np.number) or np.iscomplexobj(T) or not np.all(np.isfinite(T)):
        return f"{name} must be a finite 4x4 rigid transform, got {np.asarray(T).tolist()}"
    T = T.astype(np.float64)
    R = T[:3, :3]
    with np.errstate(all="ignore"):  # huge entries: still "not rigid"
        orth = float(np.max(np.abs(R.T @ R - np.eye(3))))
        det = float(np.linalg.det(R))
    if not (orth <= _RIGID_TOL and abs(det - 1.0) <= _RIGID_TOL
            and np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0])) <= _RIGID_TOL):
        return (f"{name} is not a rigid transform (max |RᵀR - I| = {orth:.3g}, det R = {det:.6g}, last row "
                f"{T[3].tolist()}); expected a rotation block and last row [0, 0, 0, 1]")
    if np.abs(T[:3, 3]).max() > MAX_LEVER_ARM_M:
        return f"{name} has translation {T[:3, 3].tolist()} (m); expected an IMU-camera lever arm within " \
               f"±{MAX_LEVER_ARM_M:g} m"
    return None


#: The largest pixel coordinate accepted in an observation (absolute, px): far beyond any
#: image, and small enough that products of pixels stay finite (1e300 overflowed them).
MAX_PIXEL_COORD = 1e6


#: A camera's frame interval (s): outside it, time stamps are likely not in seconds
#: (``vislam check``'s ``frame_interval_s``, and a warning of every run).
CAMERA_FRAME_INTERVAL_S = (0.005, 1.0)
#: Units time stamps may have been recorded in by mistake: (seconds per unit, name).
TIMESTAMP_UNITS = ((1e-3, "milliseconds"), (1e-6, "microseconds"), (1e-9, "nanoseconds"))


def timestamp_unit_guess(dt: float, frame_interval_s: tuple[float, float] = CAMERA_FRAME_INTERVAL_S):
    """(seconds per unit, name) of the first of :data:`TIMESTAMP_UNITS` that brings a
    median frame interval ``dt`` (in the recording's unit) inside ``frame_interval_s``,
    or None."""
    lo, hi = frame_interval_s
    return next(((factor, name) for factor, name in TIMESTAMP_UNITS if lo <= dt * factor <= hi), None)


def frame_times_not_seconds(timestamps_s) -> tuple[float, tuple | None] | None:
    """(median frame interval, :func:`timestamp_unit_guess` of it) when the frame times are
    not a camera's in seconds (outside :data:`CAMERA_FRAME_INTERVAL_S`), else None."""
    t = np.asarray(timestamps_s, dtype=np.float64)
    if t.size < 2:
        return None
    interval = float(np.median(np.diff(t)))
    lo, hi = CAMERA_FRAME_INTERVAL_S
    return None if lo <= interval <= hi else (interval, timestamp_unit_guess(interval))


#: The largest IMU sample component accepted at all (m/s and rad/s): far beyond any unit
#: mistake worth integrating (300 m/s in mm/s is 3e5), and small enough that the filters'
#: squares and products of samples stay finite (a 1e200 sample overflowed them). Loaders
#: and ``predict`` refuse a sample beyond it; :data:`IMU_SAMPLE_LIMITS` only warn.
MAX_IMU_SAMPLE = 1e9

def first_sample_beyond(samples: np.ndarray) -> tuple[int, int] | None:
    """(frame, column) of the first IMU sample of ``samples`` (T, k) beyond
    ±:data:`MAX_IMU_SAMPLE`, or None (NaN is not counted: no velocities)."""
    far = np.abs(samples) > MAX_IMU_SAMPLE
    if not far.any():
        return None
    k, i = np.argwhere(far)[0]
    return int(k), int(i)


def first_pixel_row_beyond(pixels: np.ndarray) -> int | None:
    """Row of the first observation of ``pixels`` (n, 4) not finite and within
    ±:data:`MAX_PIXEL_COORD`, or None."""
    ok = np.abs(pixels) <= MAX_PIXEL_COORD  # NaN fails too
    if ok.all():
        return None
    return int(np.flatnonzero(~ok.all(axis=1))[0])


#: The longest frame interval accepted (s, about 32 years): time stamps in nanoseconds
#: (1e8 per frame at 10 Hz) still load, so that ``vislam check`` can name their unit, and
#: the prediction's τ·u and τ²·W stay finite (a 1e290 s interval overflowed them).
MAX_TIME_STEP_S = 1e9

#: IMU samples beyond these are not a vehicle's motion (speed of sound; a MEMS gyro's
#: usual full scale, 2000 deg/s): a unit mistake or corrupt samples (:func:`imu_sample_warnings`).
IMU_SAMPLE_LIMITS = {"speed_mps": 343.0, "turn_rate_radps": 35.0}


def imu_samples_beyond_limits(linear_velocity_mps: np.ndarray, angular_velocity_radps: np.ndarray) -> list[str]:
    """For (T, 3) velocity samples beyond :data:`IMU_SAMPLE_LIMITS`: one phrase per kind
    (how many, the largest and its frame); empty when every sample is within."""
    out = []
    for name, what, unit, samples in (("speed_mps", "speed", "m/s", linear_velocity_mps),
                                      ("turn_rate_radps", "turn rate", "rad/s", angular_velocity_radps)):
        norm = np.linalg.norm(np.asarray(samples, dtype=np.float64), axis=-1)
        limit = IMU_SAMPLE_LIMITS[name]
        over = np.flatnonzero(~(norm <= limit))
        if over.size:
            worst = int(over[np.argmax(np.nan_to_num(norm[over], nan=np.inf))])
            out.append(f"{over.size} IMU sample(s) with a {what} beyond {limit:g} {unit} (largest {norm[worst]:.3g} "
                       f"{unit}, frame {worst})")
    return out


#: Consecutive IMU samples exactly 0 in all six channels, or exactly the sample before them,
#: this many or more: no sensor reads that (its noise alone moves the last digits), a dropout
#: filled with zeros or a held last value does (:func:`imu_dropouts`). The shared files
#: have not one exact zero or exact repeat.
IMU_DROPOUT_MIN_SAMPLES = 10


def true_runs(mask: np.ndarray, min_length: int = 1) -> list[tuple[int, int]]:
    """(first, last) index of each run of True in ``mask`` at least ``min_length`` long."""
    edges = np.flatnonzero(np.diff(np.r_[0, np.asarray(mask, dtype=np.int8), 0]))
    return [(int(a), int(b) - 1) for a, b in zip(edges[0::2], edges[1::2]) if b - a >= min_length]


def imu_dropouts(linear_velocity_mps: np.ndarray, angular_velocity_radps: np.ndarray,
                 min_samples: int = IMU_DROPOUT_MIN_SAMPLES) -> list[str]:
    """Stretches of at least ``min_samples`` IMU samples exactly 0 in all six channels, or
    exactly the sample before them (a dropout filled with zeros, a sensor that held its last
    value): one phrase per kind (how many stretches, the first ones' samples); empty when
    none. A recording whose samples are all 0 is one stretch."""
    u = np.hstack([np.asarray(linear_velocity_mps, dtype=np.float64).reshape(-1, 3),
                   np.asarray(angular_velocity_radps, dtype=np.float64).reshape(-1, 3)])
    zero = np.all(u == 0.0, axis=1)
    held = np.r_[False, np.all(u[1:] == u[:-1], axis=1)] & ~zero
    out = []
    for mask, what in ((zero, "exactly 0 in all six channels (a dropout filled with zeros?)"),
                       (held, "exactly the sample before them in all six channels (a sensor that held its last "
                              "value?)")):
        runs = true_runs(mask, min_samples)
        if runs:
            listed = ", ".join(f"{a}-{b}" for a, b in runs[:3]) + (", ..." if len(runs) > 3 else "")
            out.append(f"{len(runs)} stretch(es) of {min_samples} or more IMU samples {what}: frames {listed}")
    return out


#: An isolated IMU spike (:func:`imu_spikes`): a sample this many robust standard
#: deviations (1.4826 MAD) of the recording's own sample-to-neighbours differences away
#: from the mean of its two neighbours, and at least IMU_SPIKE_MIN_JUMP from it, while the
#: neighbours agree. The shared files' largest such deviation is 15.5 (a clean drive's
#: heavy tails) and 4.3 on the noisy ones; a 50 m/s spike in sparse 0027 is 7500.
IMU_SPIKE_Z = 50.0
#: The smallest deviation a spike has (m/s, rad/s): about 1 g and 6 deg/s² over 0.1 s.
IMU_SPIKE_MIN_JUMP = (1.0, 0.1)


def imu_spike_mask(linear_velocity_mps: np.ndarray, angular_velocity_radps: np.ndarray) -> np.ndarray:
    """(T,) True at the isolated spikes of :func:`imu_spikes` (any of the six channels;
    not those beyond :data:`IMU_SAMPLE_LIMITS`, which :func:`imu_samples_beyond_limits` names)."""
    out = np.zeros(np.asarray(linear_velocity_mps).reshape(-1, 3).shape[0], dtype=bool)
    if out.size < 5:
        return out
    for samples, floor in ((linear_velocity_mps, IMU_SPIKE_MIN_JUMP[0]), (angular_velocity_radps, IMU_SPIKE_MIN_JUMP[1])):
        u = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            r = u[1:-1] - 0.5 * (u[:-2] + u[2:])  # the sample against the mean of its neighbours
            gap = np.abs(u[2:] - u[:-2])  # the neighbours against each other
            med = np.nanmedian(r, axis=0)
            scale = 1.4826 * np.nanmedian(np.abs(r - med), axis=0)
            dev = np.abs(r - med)
            spike = (dev > IMU_SPIKE_Z * scale) & (dev > floor) & (gap < 0.5 * dev)
        out[1:-1] |= np.any(spike, axis=1)
    for samples, name in ((linear_velocity_mps, "speed_mps"), (angular_velocity_radps, "turn_rate_radps")):
        out &= np.linalg.norm(np.asarray(samples, dtype=np.float64).reshape(-1, 3), axis=1) <= IMU_SAMPLE_LIMITS[name]
    return out


def imu_spikes(linear_velocity_mps: np.ndarray, angular_velocity_radps: np.ndarray) -> list[str]:
    """Isolated spikes of the IMU samples: a sample far from both of its neighbours, which
    agree with each other (:data:`IMU_SPIKE_Z`): a glitch, no vehicle's motion. One phrase
    (how many, the first frames), or none."""
    k = np.flatnonzero(imu_spike_mask(linear_velocity_mps, angular_velocity_radps))
    if k.size == 0:
        return []
    listed = ", ".join(str(int(i)) for i in k[:5]) + (", ..." if k.size > 5 else "")
    return [f"{k.size} isolated IMU sample(s) far from both of their neighbours, which agree (frames {listed})"]


def imu_sample_warnings(linear_velocity_mps: np.ndarray, angular_velocity_radps: np.ndarray) -> list[str]:
    """Warnings (one line each) of a run for the samples of :func:`imu_samples_beyond_limits`
    and :func:`imu_dropouts`: the filters integrate them as they are."""
    return [f"{phrase}: not a vehicle's motion — another unit, or corrupt samples; the filters integrate them as "
            f"they are (`vislam check DATA` measures the units)"
            for phrase in imu_samples_beyond_limits(linear_velocity_mps, angular_velocity_radps)
            + imu_spikes(linear_velocity_mps, angular_velocity_radps)] + [
        f"{phrase}: the filters integrate them as they are, so the trajectory there follows them, not the "
        f"vehicle (`vislam check DATA`)" for phrase in imu_dropouts(linear_velocity_mps, angular_velocity_radps)]


def frozen_array(a, dtype=None) -> np.ndarray:
    """A read-only copy of ``a`` (optionally converted to ``dtype``)."""
    a = np.array(a, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class StereoObservations:
    """Stereo feature observations, sorted by frame.

    Attributes:
        frame_offsets: (T + 1,) int64; observations of frame t are rows
            ``frame_offsets[t]:frame_offsets[t + 1]``.
        landmark_ids: (N,) int64 landmark id (dataset column j) of each observation;
            strictly increasing within a frame.
        pixels: (N, 4) float64 ``[uL, vL, uR, vR]`` in pixels of the rectified images.
        n_landmarks: M, the number of landmark ids (``landmark_ids < M``).
    """

    frame_offsets: np.ndarray
    landmark_ids: np.ndarray
    pixels: np.ndarray
    n_landmarks: int

    def __post_init__(self):
        object.__setattr__(self, "frame_offsets", frozen_array(self.frame_offsets, np.int64))
        object.__setattr__(self, "landmark_ids", frozen_array(self.landmark_ids, np.int64))
        object.__setattr__(self, "pixels", frozen_array(np.reshape(self.pixels, (-1, 4)), np.float64))
        object.__setattr__(self, "n_landmarks", int(self.n_landmarks))
        n = self.landmark_ids.shape[0]
        if self.frame_offsets.ndim != 1 or self.frame_offsets.size < 1:
            raise SequenceError("frame_offsets must be a non-empty 1-D array")
        if self.frame_offsets[0] != 0 or self.frame_offsets[-1] != n or np.any(np.diff(self.frame_offsets) < 0):
            raise SequenceError("frame_offsets must start at 0, be non-decreasing and end at len(landmark_ids)")
        if self.pixels.shape[0] != n:
            raise SequenceError("pixels and landmark_ids differ in length")
        row = first_pixel_row_beyond(self.pixels)
        if row is not None:
            raise SequenceError(f"pixels must be finite and within ±{MAX_PIXEL_COORD:g}; observation {row} has "
                                f"{self.pixels[row].tolist()}")
        if n and (self.landmark_ids.min() < 0 or self.landmark_ids.max() >= self.n_landmarks):
            raise SequenceError("landmark_ids out of range [0, n_landmarks)")
        if n > 1:
            same_frame = np.ones(n - 1, dtype=bool)
            inner = self.frame_offsets[1:-1]
            same_frame[inner[(inner > 0) & (inner < n)] - 1] = False
            if np.any(same_frame & (np.diff(self.landmark_ids) <= 0)):
                raise SequenceError("landmark_ids must be strictly increasing within each frame")

    @property
    def n_frames(self) -> int:
        return self.frame_offsets.shape[0] - 1

    @property
    def n_observations(self) -> int:
        return self.landmark_ids.shape[0]

    def frame(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(landmark_ids (n,), pixels (n, 4)) observed at frame ``t``; read-only views."""
        a, b = self.frame_offsets[t], self.frame_offsets[t + 1]
        return self.landmark_ids[a:b], self.pixels[a:b]

    @cached_property
    def frame_index(self) -> np.ndarray:
        """(N,) frame index of every observation."""
        out = np.repeat(np.arange(self.n_frames), np.diff(self.frame_offsets))
        out.setflags(write=False)
        return out

    def counts_per_frame(self) -> np.ndarray:
        """(T,) number of observations in each frame."""
        return np.diff(self.frame_offsets)

    def duplicate_mask(self) -> np.ndarray:
        """(N,) bool: the observation has the same four pixels as an observation of a
        lower landmark id in the same frame — two ids on one point (a tracker that started
        a second track on a corner it already follows, or a file with copied columns).
        The filters would count that point twice."""
        n = self.n_observations
        out = np.zeros(n, dtype=bool)
        if n < 2:
            return out
        p = self.pixels
        # by frame, then pixels, then id (ids increase within a frame: the first of a group is the lowest)
        order = np.lexsort((np.arange(n), p[:, 3], p[:, 2], p[:, 1], p[:, 0], self.frame_index))
        same = (self.frame_index[order[1:]] == self.frame_index[order[:-1]]) & np.all(
            p[order[1:]] == p[order[:-1]], axis=1)
        out[order[1:][same]] = True
        return out

    @cached_property
    def observed_mask(self) -> np.ndarray:
        """(M, T) bool: True where landmark j is observed at frame t."""
        mask = np.zeros((self.n_landmarks, self.n_frames), dtype=bool)
        mask[self.landmark_ids, self.frame_index] = True
        mask.setflags(write=False)
        return mask

    def dense(self) -> np.ndarray:
        """The dataset layout: (4, M, T) float64, ``-1`` where not observed (allocates 32·M·T bytes)."""
        out = np.full((4, self.n_landmarks, self.n_frames), MISSING_PIXEL)
        out[:, self.landmark_ids, self.frame_index] = self.pixels.T
        return out

    @classmethod
    def from_dense(cls, features) -> "StereoObservations":
        """Build from a (4, M, T) array with -1 (all four coordinates) where not observed."""
        features = np.asarray(features, dtype=np.float64)
        if features.ndim != 3 or features.shape[0] != 4:
            raise SequenceError(f"features must have shape (4, M, T), got {features.shape}")
        _, m, t = features.shape
        missing = features == MISSING_PIXEL
        observed = ~missing.all(axis=0)  # (M, T)
        partial = observed & missing.any(axis=0)
        if partial.any():  # the dataset format marks an unobserved cell with -1 in all four
            j, k = (int(i) for i in np.argwhere(partial)[0])
            raise SequenceError(f"features: landmark {j} at frame {k} has [uL, vL, uR, vR] = "
                                f"{features[:, j, k].tolist()}; expected four pixels or -1 in all four (not observed)")
        frame_idx, lm_idx = np.nonzero(observed.T)  # sorted by frame, then landmark
        pixels = features[:, lm_idx, frame_idx].T
        offsets = np.zeros(t + 1, dtype=np.int64)
        np.cumsum(np.bincount(frame_idx, minlength=t), out=offsets[1:])
        return cls(offsets, lm_idx, pixels, m)

    def previous_index(self) -> np.ndarray:
        """(N,) row of the same landmark's observation in the previous frame, or -1."""
        n = self.n_observations
        out = np.full(n, -1, dtype=np.int64)
        if n < 2:
            return out
        order = np.lexsort((self.frame_index, self.landmark_ids))  # by landmark, then frame
        ids = self.landmark_ids[order]
        frames = self.frame_index[order]
        follows = (ids[1:] == ids[:-1]) & (frames[1:] == frames[:-1] + 1)
        out[order[1:][follows]] = order[:-1][follows]
        return out

    def repeated_mask(self, motion: "RepeatMotion | None" = None) -> np.ndarray:
        """(N,) True for an observation that repeats the same landmark's observation in
        the previous frame — a tracker artifact, not a measurement: the KITTI feature
        files repeat every live track's previous pixels at the frames where new features
        are detected (5-12 % of their observations), while the vehicle moves on.

        The decision (:func:`repeat_decision`, the same rule as the estimators' online
        detectors) survives integer-quantized pixels: four bit-identical pixels with a
        fractional part are a repeat (a sub-pixel tracker never reproduces a position);
        bit-identical integer pixels count only at a frame where every continuing track
        repeats at once and either new tracks start there (the re-detection) or, with
        ``motion`` (:meth:`Sequence.repeat_motion`), the odometry moves the tracks by at
        least :data:`REPEAT_MIN_PREDICTED_FLOW_PX` while they moved the step before.
        """
        return self.repeat_evidence(motion)[0]

    def repeat_evidence(self, motion: "RepeatMotion | None" = None) -> tuple[np.ndarray, dict]:
        """(:meth:`repeated_mask`, counts of the evidence): ``frames_fractional`` (stall
        frames with bit-identical fractional pixels), ``frames_new_tracks`` and
        ``frames_odometry`` (integer-pixel stall frames by each evidence),
        ``integer_coincidences`` (bit-identical integer observations not counted)."""
        n = self.n_observations
        out = np.zeros(n, dtype=bool)
        counts = {"frames_fractional": 0, "frames_new_tracks": 0, "frames_odometry": 0, "integer_coincidences": 0}
        if n < 2:
            return out, counts
        prev = self.previous_index()
        cont = prev >= 0
        equal = np.zeros(n, dtype=bool)
        equal[cont] = np.all(self.pixels[cont] == self.pixels[prev[cont]], axis=1)
        if not equal.any():
            return out, counts
        flow = np.full(n, np.nan)
        flow[cont] = np.hypot(*(self.pixels[cont, :2] - self.pixels[prev[cont], :2]).T)
        off = self.frame_offsets
        prev_flow = np.nan
        for t in range(self.n_frames):
            a, b = off[t], off[t + 1]
            f = flow[a:b]
            if equal[a:b].any():
                c = cont[a:b]
                rep, how = repeat_decision(self.pixels[a:b][c], equal[a:b][c], int(np.count_nonzero(~c)), prev_flow,
                                           None if motion is None else motion.at(t))
                out[np.flatnonzero(c) + a] = rep
                if how:
                    counts[how] += 1
                counts["integer_coincidences"] += int(np.count_nonzero(equal[a:b][c] & ~rep))
            f = f[np.isfinite(f)]
            prev_flow = float(np.median(f)) if f.size else np.nan
        return out, counts

    def track_lengths(self) -> np.ndarray:
        """(M,) number of frames in which each landmark is observed."""
        return np.bincount(self.landmark_ids, minlength=self.n_landmarks)


#: Integer-pixel repeats count without new tracks only if the odometry moves some
#: continuing track by at least this much (px) over the frame interval (and the tracks
#: moved at least 1 px the step before). On the six shared files rounded to integers
#: (benchmarks/quantized_repeats.py) the stall frames predict at least 1.46 px (sparse
#: 0020; those below 2 px start new tracks), the frames where every track repeats by
#: coincidence (a stopped car, one far track) at most 1.24 px or had no motion before.
REPEAT_MIN_PREDICTED_FLOW_PX = 2.0
#: ... the previous step's median track motion (px) that goes with it.
REPEAT_MIN_PREVIOUS_FLOW_PX = 1.0


@dataclass(frozen=True)
class RepeatMotion:
    """What the repeat rule needs of the odometry: per frame t, the interval τ (s) and
    the speed |v| (m/s) and turn rate |ω| (rad/s) of frame t's sample, and the camera."""

    tau_s: np.ndarray
    speed_mps: np.ndarray
    rate_radps: np.ndarray
    camera: StereoCamera

    def at(self, t: int):
        if t == 0:
            return None
        return (float(self.tau_s[t]), float(self.speed_mps[t]), float(self.rate_radps[t]), self.camera)


def predicted_flow_px(pixels: np.ndarray, motion) -> np.ndarray:
    """Rough pixel motion of stereo observations ``pixels`` (n, 4) over one interval of
    ``motion`` = (τ, |v|, |ω|, camera): the radial flow of a forward translation plus the
    flow of the turn, r |v| τ / z + fsu |ω| τ (z from the disparity; none behind)."""
    tau, speed, rate, cam = motion
    d = pixels[:, 0] - pixels[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.where(d > 0, d / (cam.fsu * cam.baseline_m), 0.0)
    r = np.hypot(pixels[:, 0] - cam.cu, pixels[:, 1] - cam.cv)
    return r * speed * tau * inv_z + cam.fsu * rate * tau


def repeat_decision(pixels: np.ndarray, equal: np.ndarray, n_new: int, previous_flow_px: float,
                    motion=None) -> tuple[np.ndarray, str | None]:
    """Which of one frame's *continuing* observations (``pixels`` (n, 4), ``equal``: all
    four bit-identical to the previous frame's) are repeats, and the evidence ("frames_fractional",
    "frames_new_tracks", "frames_odometry" or None). ``n_new``: tracks starting in the frame;
    ``previous_flow_px``: median motion of the tracks the step before (NaN: unknown);
    ``motion``: (τ, |v|, |ω|, camera) of the interval, or None. See
    :meth:`StereoObservations.repeated_mask`."""
    if not equal.any():
        return equal, None
    fractional = np.any(pixels != np.round(pixels), axis=1)
    if np.any(equal & fractional):
        return equal, "frames_fractional"  # bit-identical sub-pixel values: no coincidence
    if not equal.all():  # integer pixels, some continuing tracks moved: coincidences of rounding
        return np.zeros_like(equal), None
    if n_new > 0:
        return equal, "frames_new_tracks"
    if motion is not None and previous_flow_px >= REPEAT_MIN_PREVIOUS_FLOW_PX and \
            float(np.max(predicted_flow_px(pixels, motion))) >= REPEAT_MIN_PREDICTED_FLOW_PX:
        return equal, "frames_odometry"
    return np.zeros_like(equal), None


@dataclass(frozen=True, eq=False)
class Calibration:
    """What a filter needs to know about the sensors: the stereo camera and ``cam_T_imu``
    (maps IMU coordinates into the left camera frame)."""

    camera: StereoCamera
    cam_T_imu: np.ndarray

    def __post_init__(self):
        if not isinstance(self.camera, StereoCamera):
            raise SequenceError(f"Calibration: camera must be a StereoCamera, got {type(self.camera).__name__}")
        problem = rigid_transform_problem(self.cam_T_imu)
        if problem:
            raise SequenceError(f"Calibration: {problem}")
        object.__setattr__(self, "cam_T_imu", frozen_array(self.cam_T_imu, np.float64))


@dataclass(frozen=True, eq=False)
class Frame:
    """One frame of a recording, as a robot (or a ROS node) delivers it.

    Attributes:
        index: frame number t (0 for the first frame).
        timestamp_s: time of the frame (s).
        dt_s: time since the previous frame, τ = t_t − t_{t−1} (s); 0 for the first frame.
        linear_velocity_mps: (3,) IMU-frame linear velocity sample of this frame (m/s).
        angular_velocity_radps: (3,) IMU-frame angular velocity sample (rad/s).
            By the velocity association of the KITTI files (see
            :mod:`vislam.core.propagation`), the sample of frame t is the twist over the
            interval from frame t−1 to frame t: ``step`` predicts with it over ``dt_s``.
        landmark_ids: (n,) int64 ids of the landmarks observed, strictly increasing.
        pixels: (n, 4) ``[uL, vL, uR, vR]`` of each observation (px).
    """

    index: int
    timestamp_s: float
    dt_s: float
    linear_velocity_mps: np.ndarray
    angular_velocity_radps: np.ndarray
    landmark_ids: np.ndarray
    pixels: np.ndarray

    @property
    def n_observations(self) -> int:
        return int(self.landmark_ids.shape[0])


@dataclass(frozen=True, eq=False)
class Sequence:
    """A stereo visual-inertial recording.

    Attributes:
        name: human-readable name (usually the file stem, e.g. ``"0027"``).
        timestamps_s: (T,) frame times in seconds, strictly increasing.
        linear_velocity_in_imu_mps: (T, 3) linear velocity of the IMU in its own frame, m/s.
        angular_velocity_in_imu_radps: (T, 3) angular velocity of the IMU in its own frame, rad/s.
        observations: stereo features, see :class:`StereoObservations`.
        camera: stereo calibration (K in pixels, baseline in metres, the report's M).
        cam_T_imu: (4, 4) maps IMU coordinates into the left camera frame.
        source: where the data came from (a path, or ``"simulator"``), for messages.
        corrections: the data corrections already applied to it (a mapping of
            FilterOptions fields, see :func:`vislam.core.corrections.apply_corrections`),
            or None for the data as recorded.
        file_cam_T_imu: (4, 4) the recording's own ``cam_T_imu`` when corrections
            replaced it (a ``cam_T_imu`` override, a rotation correction), else None:
            ``cam_T_imu`` is the recording's (see :attr:`recorded_cam_T_imu`).

    The constructor holds the loader's rules (:class:`SequenceError` otherwise): at
    least one frame, times finite and strictly increasing with no interval beyond
    :data:`MAX_TIME_STEP_S`, velocities (T, 3) within ±:data:`MAX_IMU_SAMPLE` (NaN: none
    recorded), ``cam_T_imu`` a finite rigid transform (:func:`rigid_transform_problem`).
    """

    name: str
    timestamps_s: np.ndarray
    linear_velocity_in_imu_mps: np.ndarray
    angular_velocity_in_imu_radps: np.ndarray
    observations: StereoObservations
    camera: StereoCamera
    cam_T_imu: np.ndarray
    source: str = ""
    corrections: dict | None = None
    file_cam_T_imu: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "timestamps_s", frozen_array(np.ravel(self.timestamps_s), np.float64))
        object.__setattr__(self, "linear_velocity_in_imu_mps", frozen_array(self.linear_velocity_in_imu_mps, np.float64))
        object.__setattr__(
            self, "angular_velocity_in_imu_radps", frozen_array(self.angular_velocity_in_imu_radps, np.float64)
        )
        object.__setattr__(self, "cam_T_imu", frozen_array(self.cam_T_imu, np.float64))
        t = self.timestamps_s.shape[0]
        self._check_timestamps()
        for name in ("linear_velocity_in_imu_mps", "angular_velocity_in_imu_radps"):
            if getattr(self, name).shape != (t, 3):
                raise SequenceError(f"{name} must have shape ({t}, 3), got {getattr(self, name).shape}")
            far = first_sample_beyond(getattr(self, name))  # NaN (no velocities) is not refused here
            if far is not None:
                k, i = far
                raise SequenceError(f"{name} has {getattr(self, name)[k, i]:.3g} at frame {k}; expected samples "
                                 f"within ±{MAX_IMU_SAMPLE:g}")
        if self.observations.n_frames != t:
            raise SequenceError(f"observations cover {self.observations.n_frames} frames, timestamps {t}")
        if not isinstance(self.camera, StereoCamera):
            raise SequenceError(f"{self._where}camera must be a StereoCamera, got {type(self.camera).__name__}")
        problem = rigid_transform_problem(self.cam_T_imu)
        if problem:
            raise SequenceError(f"{self._where}{problem}")
        if self.file_cam_T_imu is not None:
            object.__setattr__(self, "file_cam_T_imu", frozen_array(self.file_cam_T_imu, np.float64))
            if self.file_cam_T_imu.shape != (4, 4):
                raise SequenceError("file_cam_T_imu must be 4x4")

    @property
    def _where(self) -> str:
        """``"SOURCE: "`` for messages (the file, or the name of an in-memory recording)."""
        where = self.source or self.name
        return f"{where}: " if where else ""

    def _check_timestamps(self) -> None:
        """At least one frame; times finite and strictly increasing, no interval beyond
        :data:`MAX_TIME_STEP_S` (the loader's rules; a NaN or a step back reached the
        filters as a bad ``predict`` argument)."""
        t = self.timestamps_s
        where = self._where
        if t.shape[0] == 0:
            raise SequenceError(f"{where}timestamps_s is empty; a recording needs at least one frame")
        bad = ~np.isfinite(t)
        if bad.any():
            i = int(np.argmax(bad))
            raise SequenceError(f"{where}timestamps_s has {t[i]} at frame {i}; expected finite seconds")
        with np.errstate(over="ignore", invalid="ignore"):
            step = np.diff(t)
        bad = ~(step > 0)
        if bad.any():
            i = int(np.argmax(bad)) + 1
            raise SequenceError(f"{where}timestamps_s is not strictly increasing at frame {i} ({float(t[i])!r} after "
                                f"{float(t[i - 1])!r}); expected strictly increasing times (s)")
        long = step > MAX_TIME_STEP_S
        if long.any():
            i = int(np.argmax(long)) + 1
            raise SequenceError(f"{where}timestamps_s has a frame interval of {float(step[i - 1]):.3g} s at frame {i}; "
                                f"expected at most {MAX_TIME_STEP_S:g} s")

    @property
    def n_frames(self) -> int:
        return self.timestamps_s.shape[0]

    @property
    def n_landmarks(self) -> int:
        return self.observations.n_landmarks

    @property
    def duration_s(self) -> float:
        return float(self.timestamps_s[-1] - self.timestamps_s[0]) if self.n_frames > 1 else 0.0

    @cached_property
    def imu_T_cam(self) -> np.ndarray:
        from vislam.core.lie import se3_inverse

        out = se3_inverse(self.cam_T_imu)
        out.setflags(write=False)
        return out

    @property
    def recorded_cam_T_imu(self) -> np.ndarray:
        """The recording's own ``cam_T_imu`` (the data file's), before any correction."""
        return self.file_cam_T_imu if self.file_cam_T_imu is not None else self.cam_T_imu

    @property
    def calibration(self) -> Calibration:
        """The sensors' calibration, for the filters' constructors."""
        return Calibration(self.camera, self.cam_T_imu)

    def frame(self, t: int) -> Frame:
        """Frame ``t`` (its arrays are read-only views into the sequence)."""
        if not 0 <= t < self.n_frames:
            raise IndexError(f"frame {t} out of range [0, {self.n_frames})")
        ids, pixels = self.observations.frame(t)
        dt = float(self.timestamps_s[t] - self.timestamps_s[t - 1]) if t > 0 else 0.0
        return Frame(t, float(self.timestamps_s[t]), dt, self.linear_velocity_in_imu_mps[t],
                     self.angular_velocity_in_imu_radps[t], ids, pixels)

    def frames(self, start: int = 0, stop: int | None = None):
        """Iterate over the frames ``start .. stop − 1`` in order (:class:`Frame`)."""
        stop = self.n_frames if stop is None else min(stop, self.n_frames)
        for t in range(start, stop):
            yield self.frame(t)

    def velocities(self) -> np.ndarray:
        """(T, 6) twists u_t = (v_t, ω_t) in the report's order."""
        return np.concatenate([self.linear_velocity_in_imu_mps, self.angular_velocity_in_imu_radps], axis=1)

    def repeat_motion(self) -> RepeatMotion:
        """The odometry the repeat rule uses (:meth:`StereoObservations.repeated_mask`)."""
        tau = np.r_[0.0, np.diff(self.timestamps_s)]
        return RepeatMotion(tau, np.linalg.norm(self.linear_velocity_in_imu_mps, axis=1),
                            np.linalg.norm(self.angular_velocity_in_imu_radps, axis=1), self.camera)

    def repeated_mask(self) -> np.ndarray:
        """:meth:`StereoObservations.repeated_mask` with this sequence's odometry."""
        return self.observations.repeated_mask(self.repeat_motion())

    def replace(self, **changes) -> "Sequence":
        """A copy with some fields replaced (the original is unchanged)."""
        from dataclasses import replace

        return replace(self, **changes)
