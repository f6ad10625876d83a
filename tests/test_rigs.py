"""Recognition of published rig calibrations (vislam.core.rigs)."""

import numpy as np
import pytest

from vislam.core.lie import so3_exp
from vislam.core.rigs import KNOWN_RIGS, match_known_rig
from vislam.core.simulate import KITTI_CAM_T_IMU


@pytest.mark.parametrize("name", sorted(KNOWN_RIGS))
def test_published_rigs_are_rigid_and_recognized_both_ways(name):
    P = KNOWN_RIGS[name]
    R = P[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)  # published to 7 digits
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-5)
    # the IMU 1.0-1.2 m behind and 0.7-0.8 m below the left camera (camera: z forward, y down)
    assert -1.2 < P[2, 3] < -1.0 and 0.7 < P[1, 3] < 0.8
    assert match_known_rig(P).translation == "published"
    swapped = P.copy()
    swapped[:3, 3] = -R.T @ P[:3, 3]  # imu_T_cam's translation stored as cam_T_imu's
    rig = match_known_rig(swapped)
    assert rig.name == name and rig.translation == "swapped"
    assert rig.translation_error_m > 2.0


def test_other_translations_and_rotations():
    C = KITTI_CAM_T_IMU.copy()
    C[:3, 3] += [0.5, 0.0, 0.0]
    assert match_known_rig(C).translation == "other"
    C = KITTI_CAM_T_IMU.copy()
    C[:3, :3] = C[:3, :3] @ so3_exp(np.array([0.0, 0.0, 1e-4]))  # 0.006° off the published rotation
    assert match_known_rig(C) is None
    assert match_known_rig(np.full((4, 4), np.nan)) is None
    assert match_known_rig(np.eye(3)) is None


def test_the_simulator_rig_is_the_published_2011_09_30_calibration():
    rig = match_known_rig(KITTI_CAM_T_IMU)
    assert rig.name == "KITTI 2011_09_30" and rig.translation == "published"
    assert rig.translation_error_m < 1e-6
