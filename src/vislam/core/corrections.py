"""Corrections of a recording's conventions, biases and calibration, applied to the data.

``vislam check`` (:mod:`vislam.core.check`) estimates how a recording departs from the
filter's assumptions; the estimates become :class:`~vislam.core.options.FilterOptions`
fields (:data:`~vislam.core.options.DATA_CORRECTION_FIELDS`), and
:func:`apply_corrections` turns them into a corrected :class:`Sequence` before any
estimator sees it. The data file itself is never edited.

In this order:

0. ``timestamp_scale = f``: every timestamp is multiplied by f (a recording stamped in
   milliseconds needs 0.001).
1. ``velocity_association = "current"``: the sample of frame k describes the interval
   k -> k+1. The estimators use sample k+1 for that interval (see
   :mod:`vislam.core.propagation`), so every sample moves one frame later:
   ``u'[k+1] = u[k]`` and ``u'[0] = u[0]``.
2. ``time_offset_s = δ``: the sample stamped t describes the motion at t + δ, so the
   velocity at frame time t_k is the recording's signal at t_k − δ (linear
   interpolation between samples, held constant beyond the ends).
3. ``velocity_scale = s``: every linear-velocity sample is multiplied by s; then
   ``gyro_bias_radps`` / ``velocity_bias_mps`` are subtracted from every sample.
4. ``cam_T_imu`` (a 4x4 override) replaces the recording's transform; then
   ``imu_camera_rotation_correction_deg = φ`` (rotation vector in the camera frame,
   degrees) turns its rotation block: ``R ← exp(φ) R``. The translation, the IMU origin
   in the camera frame, is kept.

With every field at its default, the input object itself is returned, and so is a
sequence these same corrections were already applied to (``Sequence.corrections``), so
that a caller and the estimators may both apply them safely. The recording's own
transform stays in ``Sequence.file_cam_T_imu`` when step 4 changes it, and
:func:`calibration_used` says which ``cam_T_imu`` a filter on the sequence uses and which
corrections made it (every estimator's :class:`~vislam.core.results.RunResult` carries it
as ``calibration``).
"""

from __future__ import annotations

import numpy as np

from vislam.core.lie import so3_exp
from vislam.core.options import DATA_CORRECTION_FIELDS, FilterOptions
from vislam.core.results import CalibrationUsed
from vislam.core.sequence import MAX_IMU_SAMPLE, MAX_TIME_STEP_S, Sequence, first_sample_beyond
from vislam.errors import ConfigError

__all__ = ["apply_corrections", "correction_values", "shift_to_current_association", "resample_velocities",
           "rotate_cam_T_imu", "calibration_used", "CALIBRATION_FIELDS"]

#: The data-correction fields that change ``cam_T_imu`` (step 4 of the module docstring).
CALIBRATION_FIELDS = ("cam_T_imu", "imu_camera_rotation_correction_deg")


def shift_to_current_association(u: np.ndarray) -> np.ndarray:
    """(T, k) samples where sample k describes k -> k+1, re-indexed for the estimators'
    convention (sample k+1 describes k -> k+1): ``out[k+1] = u[k]``, ``out[0] = u[0]``."""
    u = np.asarray(u, dtype=np.float64)
    out = np.empty_like(u)
    out[1:] = u[:-1]
    out[:1] = u[:1]
    return out


def resample_velocities(timestamps_s: np.ndarray, u: np.ndarray, time_offset_s: float) -> np.ndarray:
    """(T, k) values of the signal ``u`` (sampled at ``timestamps_s``) at the times
    ``timestamps_s − time_offset_s``: linear interpolation, constant beyond the ends."""
    t = np.asarray(timestamps_s, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    if time_offset_s == 0:
        return u.copy()
    query = t - time_offset_s
    return np.column_stack([np.interp(query, t, u[:, i]) for i in range(u.shape[1])])


def rotate_cam_T_imu(cam_T_imu: np.ndarray, rotation_vector_deg) -> np.ndarray:
    """cam_T_imu with its rotation block turned by ``exp(φ)`` on the camera side
    (φ in degrees, camera frame); the translation is kept."""
    out = np.array(cam_T_imu, dtype=np.float64)
    phi = np.radians(np.asarray(rotation_vector_deg, dtype=np.float64))
    if np.any(phi):
        out[:3, :3] = so3_exp(phi) @ out[:3, :3]
    return out


def apply_corrections(sequence: Sequence, options: FilterOptions) -> Sequence:
    """The recording as the filter should see it under ``options``' data corrections
    (see the module docstring); ``sequence`` itself when there is nothing to correct."""
    if not options.has_data_corrections:
        return sequence
    applied = correction_values(options)
    if sequence.corrections == applied:
        return sequence
    if options.timestamp_scale != 1.0:
        t = sequence.timestamps_s * options.timestamp_scale
        longest = float(np.max(np.diff(t))) if t.size > 1 else 0.0
        if longest > MAX_TIME_STEP_S:
            raise ConfigError(f"timestamp_scale {options.timestamp_scale:g} makes a frame interval of "
                              f"{longest:.3g} s, beyond {MAX_TIME_STEP_S:g} s")
        sequence = sequence.replace(timestamps_s=t)
    u = sequence.velocities()
    if options.velocity_association == "current":
        u = shift_to_current_association(u)
    if options.time_offset_s:
        duration = sequence.duration_s
        if abs(options.time_offset_s) >= duration:
            raise ConfigError(f"time_offset_s {options.time_offset_s:g} s is as long as the recording "
                              f"({duration:.3g} s) or longer: every velocity sample would be the first or the last; "
                              f"expected a camera-IMU offset (vislam check estimates it)")
        u = resample_velocities(sequence.timestamps_s, u, options.time_offset_s)
    if options.velocity_scale != 1.0:
        u = u.copy()
        u[:, :3] *= options.velocity_scale
    u = u - np.concatenate([np.asarray(options.velocity_bias_mps), np.asarray(options.gyro_bias_radps)])
    far = first_sample_beyond(u)
    if far is not None:
        k, i = far
        raise ConfigError(f"the data corrections (velocity_scale {options.velocity_scale:g}, the biases) take the "
                          f"{'linear' if i < 3 else 'angular'} velocity of frame {k} to {u[k, i]:.10g}, beyond "
                          f"±{MAX_IMU_SAMPLE:g}: not a unit the filters can integrate")
    cam_T_imu = np.array(options.cam_T_imu, dtype=np.float64) if options.cam_T_imu is not None else sequence.cam_T_imu
    cam_T_imu = rotate_cam_T_imu(cam_T_imu, options.imu_camera_rotation_correction_deg)
    recorded = sequence.recorded_cam_T_imu
    file_cam_T_imu = None if np.array_equal(cam_T_imu, recorded) else recorded
    return sequence.replace(linear_velocity_in_imu_mps=u[:, :3], angular_velocity_in_imu_radps=u[:, 3:],
                            cam_T_imu=cam_T_imu, corrections=applied, file_cam_T_imu=file_cam_T_imu)


def calibration_used(sequence: Sequence) -> CalibrationUsed:
    """The ``cam_T_imu`` a filter run on ``sequence`` uses (``sequence.cam_T_imu``), the
    recording's own, and the corrections (of ``sequence.corrections``) that turned one into
    the other, in the order they were applied."""
    corrections = []
    applied = sequence.corrections or {}
    if applied.get("cam_T_imu") is not None:
        corrections.append({"field": "cam_T_imu", "value": [list(map(float, row)) for row in applied["cam_T_imu"]],
                            "effect": "replaces the recording's cam_T_imu"})
    phi = applied.get("imu_camera_rotation_correction_deg")
    if phi is not None and any(float(x) != 0.0 for x in phi):
        corrections.append({"field": "imu_camera_rotation_correction_deg", "value": [float(x) for x in phi],
                            "effect": "turns the rotation block: R <- exp(phi) R (camera frame, degrees); the "
                                      "translation is kept"})
    return CalibrationUsed(np.array(sequence.cam_T_imu), np.array(sequence.recorded_cam_T_imu), tuple(corrections))


def correction_values(options: FilterOptions) -> dict:
    """The data-correction fields of ``options`` (plain values), as recorded in
    ``Sequence.corrections``."""
    values = options.to_dict()
    return {name: values[name] for name in DATA_CORRECTION_FIELDS}
