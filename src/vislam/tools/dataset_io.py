"""Reading and writing datasets in the report's npz format.

(Loader under construction: see ``load_sequence``.)
"""

from __future__ import annotations

import numpy as np

from vislam.core.sequence import Sequence
from vislam.tools.npz import write_npz

__all__ = ["load_sequence", "save_sequence"]


def save_sequence(sequence: Sequence, path, compress: bool = True) -> None:
    """Write ``sequence`` as an npz in the report's key convention (atomically).

    Keys: time_stamps (1, T), features (4, M, T) with -1 where unobserved,
    linear_velocity / rotational_velocity (3, T), K (3, 3), b (), cam_T_imu (4, 4).
    """
    arrays = {
        "time_stamps": sequence.timestamps_s[None, :],
        "features": sequence.observations.dense(),
        "linear_velocity": sequence.linear_velocity_in_imu_mps.T,
        "rotational_velocity": sequence.angular_velocity_in_imu_radps.T,
        "K": sequence.camera.K,
        "b": np.array(sequence.camera.baseline_m),
        "cam_T_imu": sequence.cam_T_imu,
    }
    write_npz(path, arrays, compress=compress)


def load_sequence(path) -> Sequence:
    raise NotImplementedError
