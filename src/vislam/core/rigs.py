"""Published calibrations of known rigs, to recognize a recording's ``cam_T_imu``.

The KITTI course files store KITTI's published rotation but the translation of the
inverse transform (``imu_T_cam``'s, the camera's position in the IMU frame; see the data
README). The hand-eye test of :mod:`vislam.core.check` finds that from the tracks where
the drive turns enough; on a recording whose rotation block *is* a published calibration,
the comparison with the published translation settles it without any motion.

Each entry is cam_T_imu of the rectified left grey camera (KITTI ``image_00``),
composed from KITTI's published calibration files:
``cam_T_imu = [R_rect_00 | 0] · T_velo→cam · T_imu→velo``. ``calib_imu_to_velo`` is the
same for every KITTI date; ``R_rect_00 · T_velo→cam`` per date is the ``Tr`` of the KITTI
odometry benchmark's ``calib.txt`` (sequences 00-02: 2011_10_03; 03: 2011_09_26) or, for
2011_09_30, composed from that date's ``calib_velo_to_cam.txt`` and
``calib_cam_to_cam.txt``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["KnownRig", "KNOWN_RIGS", "match_known_rig", "swapped_translation"]

_IMU_TO_VELO_R = [[9.999976e-01, 7.553071e-04, -2.035826e-03],
                  [-7.854027e-04, 9.998898e-01, -1.482298e-02],
                  [2.024406e-03, 1.482454e-02, 9.998881e-01]]
_IMU_TO_VELO_T = [-8.086759e-01, 3.195559e-01, -7.997231e-01]

# R_rect_00 · T_velo→cam (3x4) per date
_VELO_TO_RECT = {
    "KITTI 2011_10_03": [[4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
                         [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
                         [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01]],
    "KITTI 2011_09_26": [[2.347736981471e-04, -9.999441545438e-01, -1.056347781105e-02, -2.796816941295e-03],
                         [1.044940741659e-02, 1.056535364138e-02, -9.998895741176e-01, -7.510879138296e-02],
                         [9.999453885620e-01, 1.243653783865e-04, 1.045130299567e-02, -2.721327964059e-01]],
}
_SEP30_VELO_TO_CAM_R = [[7.027555e-03, -9.999753e-01, 2.599616e-05],
                        [-2.254837e-03, -4.184312e-05, -9.999975e-01],
                        [9.999728e-01, 7.027479e-03, -2.255075e-03]]
_SEP30_VELO_TO_CAM_T = [-7.137748e-03, -7.482656e-02, -3.336324e-01]
_SEP30_R_RECT_00 = [[9.999280e-01, 8.085985e-03, -8.866797e-03],
                    [-8.123205e-03, 9.999583e-01, -4.169750e-03],
                    [8.832711e-03, 4.241477e-03, 9.999520e-01]]


def swapped_translation(cam_T_imu: np.ndarray) -> np.ndarray:
    """The translation cam_T_imu has when its stored translation is really imu_T_cam's
    (the camera's position in the IMU frame, the mix-up of the KITTI course files):
    ``−R t`` with R, t the stored rotation block and translation."""
    C = np.asarray(cam_T_imu, dtype=np.float64)
    return -C[:3, :3] @ C[:3, 3]


def _rigid(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _published() -> dict[str, np.ndarray]:
    imu_to_velo = _rigid(_IMU_TO_VELO_R, _IMU_TO_VELO_T)
    rect = {name: np.vstack([np.asarray(m), [0.0, 0.0, 0.0, 1.0]]) for name, m in _VELO_TO_RECT.items()}
    rect["KITTI 2011_09_30"] = _rigid(_SEP30_R_RECT_00, [0.0, 0.0, 0.0]) @ _rigid(_SEP30_VELO_TO_CAM_R,
                                                                                   _SEP30_VELO_TO_CAM_T)
    out = {}
    for name in sorted(rect):
        T = rect[name] @ imu_to_velo
        T.setflags(write=False)
        out[name] = T
    return out


@dataclass(frozen=True)
class KnownRig:
    """A published calibration a recording's ``cam_T_imu`` was recognized as."""

    #: e.g. "KITTI 2011_09_30"
    name: str
    #: the published cam_T_imu (4, 4)
    cam_T_imu: np.ndarray
    #: "published": the recording's translation is the published one; "swapped": it is
    #: the published imu_T_cam's (−Rᵀ t); "other": neither
    translation: str
    #: distance (m) of the recording's translation from the published one
    translation_error_m: float


#: Published cam_T_imu of the rigs :func:`match_known_rig` recognizes.
KNOWN_RIGS: dict[str, np.ndarray] = _published()


def match_known_rig(cam_T_imu, rotation_tol: float = 1e-6, translation_tol_m: float = 0.005) -> KnownRig | None:
    """The known rig whose published rotation ``cam_T_imu``'s rotation block equals (max
    absolute difference of the entries below ``rotation_tol``; the published values are
    given to 7 digits), with how its translation relates to the published one, or None."""
    C = np.asarray(cam_T_imu, dtype=np.float64)
    if C.shape != (4, 4) or not np.all(np.isfinite(C)):
        return None
    for name, P in KNOWN_RIGS.items():
        if np.max(np.abs(C[:3, :3] - P[:3, :3])) > rotation_tol:
            continue
        t, t_pub = C[:3, 3], P[:3, 3]
        err = float(np.linalg.norm(t - t_pub))
        if err <= translation_tol_m:
            kind = "published"
        elif np.linalg.norm(swapped_translation(C) - t_pub) <= translation_tol_m:  # t is imu_T_cam's
            kind = "swapped"
        else:
            kind = "other"
        return KnownRig(name, P, kind, err)
    return None
