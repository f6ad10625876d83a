"""Writing a simulated drive (:class:`vislam.core.simulate.SimulatedDrive`) to a directory.

``write_simulated_drive(drive, out_dir)`` writes:

* ``sequence.npz`` — the recording in the datasets' npz format (:func:`save_sequence`),
  loadable like the real data;
* ``groundtruth.tum`` — the true ``world_T_imu`` of every frame (timestamp tx ty tz qx
  qy qz qw);
* ``groundtruth.kitti`` — the true poses of the left *camera*, by the KITTI convention
  (as the real datasets' ``groundtruth/*.txt``): ``world_T_cam(i) = cam_T_imu @
  world_T_imu(i) @ imu_T_cam`` (world = first camera frame), 12 row-major values of the
  top 3x4 per frame. ``vislam eval`` and ``vislam run --gt`` read KITTI ground truth as
  camera poses by default and convert them back with the dataset's ``cam_T_imu``;
* ``landmarks_true.npz`` — the true landmarks and the outlier flags, keys:

  ==========================  =========  =================================================
  ``ids``                     (M,)       landmark id (column j of ``features``)
  ``p_lm_in_world``           (M, 3)     true position (m); moving: at ``first_frame``
  ``is_moving``               (M,)       bool
  ``velocity_in_world``       (M, 3)     constant world velocity (m/s), zero if static
  ``first_frame``             (M,)       first frame the landmark is observed in
  ``kind``                    (M,)       index into ``kind_names`` (facade, pole, ...)
  ``kind_names``              (K,)       unicode names of the kinds
  ``vehicle_id``              (M,)       vehicle of a moving landmark, -1 if static
  ``observation_frame``       (N,)       frame of each observation (rows of the sequence)
  ``observation_landmark_id`` (N,)       landmark id of each observation
  ``observation_is_outlier``  (N,)       bool: the observation is a gross mismatch
  ``observation_true_pixels`` (N, 4)     noise-free [uL, vL, uR, vR] of the observation
  ``timestamps``              (T,)       frame times (s)
  ==========================  =========  =================================================

  A moving landmark's position at frame k is
  ``p_lm_in_world + velocity_in_world * (timestamps[k] - timestamps[first_frame])``.

Every file is written atomically and deterministically: the same drive gives the same
bytes. The dataset format stores features densely (4 x M x T doubles); a drive whose
array would exceed ``max_dense_bytes`` is refused before anything is written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vislam.core.simulate import LANDMARK_KINDS, SimulatedDrive
from vislam.errors import OutputError
from vislam.tools.dataset_io import save_sequence
from vislam.tools.npz import write_npz
from vislam.tools.trajectory_io import imu_to_camera_trajectory, write_kitti, write_tum

__all__ = ["write_simulated_drive", "landmark_truth_arrays", "SIMULATION_FILES", "DEFAULT_MAX_DENSE_BYTES"]

#: File names written by :func:`write_simulated_drive`, in writing order.
SIMULATION_FILES = ("sequence.npz", "groundtruth.tum", "groundtruth.kitti", "landmarks_true.npz")

#: Largest dense feature array (bytes) :func:`write_simulated_drive` builds by default.
DEFAULT_MAX_DENSE_BYTES = 4 * 1024**3


def landmark_truth_arrays(drive: SimulatedDrive) -> dict[str, np.ndarray]:
    """The arrays of ``landmarks_true.npz`` (see the module docstring)."""
    obs = drive.sequence.observations
    return {
        "ids": np.arange(drive.n_landmarks, dtype=np.int64),
        "p_lm_in_world": drive.p_lm_in_world,
        "is_moving": drive.landmark_is_moving,
        "velocity_in_world": drive.landmark_velocity_in_world,
        "first_frame": drive.landmark_first_frame,
        "kind": drive.landmark_kind,
        "kind_names": np.array(LANDMARK_KINDS),
        "vehicle_id": drive.landmark_vehicle_id,
        "observation_frame": obs.frame_index.astype(np.int64),
        "observation_landmark_id": obs.landmark_ids,
        "observation_is_outlier": drive.observation_is_outlier,
        "observation_true_pixels": drive.observation_true_pixels,
        "timestamps": drive.sequence.timestamps_s,
    }


def write_simulated_drive(drive: SimulatedDrive, out_dir, max_dense_bytes: int = DEFAULT_MAX_DENSE_BYTES) -> list[Path]:
    """Write ``drive`` into ``out_dir`` (created if needed); returns the paths written.

    Raises OutputError when the directory cannot be written or the dense feature array
    of ``sequence.npz`` would need more than ``max_dense_bytes``.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir}: exists and is not a directory")
    seq = drive.sequence
    dense_bytes = 32 * seq.n_landmarks * seq.n_frames
    if dense_bytes > max_dense_bytes:
        raise OutputError(
            f"{out_dir / 'sequence.npz'}: the dataset format stores features densely (4 x M x T doubles); "
            f"{seq.n_landmarks} landmarks x {seq.n_frames} frames would need {dense_bytes / 1024**3:.1f} GiB "
            f"(limit {max_dense_bytes / 1024**3:.1f} GiB); simulate fewer frames"
        )
    paths = [out_dir / name for name in SIMULATION_FILES]
    save_sequence(seq, paths[0])
    write_tum(paths[1], seq.timestamps_s, drive.world_T_imu)
    write_kitti(paths[2], imu_to_camera_trajectory(drive.world_T_imu, seq.cam_T_imu))
    write_npz(paths[3], landmark_truth_arrays(drive))
    return paths
