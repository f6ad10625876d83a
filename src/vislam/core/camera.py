"""The rectified stereo camera of the report.

A point ``q`` in the left camera frame (x right, y down, z forward, metres; homogeneous
``[x, y, z, 1]``) is observed as the 4-vector of pixels ``z = [uL, vL, uR, vR]``::

    z = M π(q),   π(q) = q / q_z,

    M = [[fsu, 0,   cu, 0       ],
         [0,   fsv, cv, 0       ],
         [fsu, 0,   cu, -fsu b  ],
         [0,   fsv, cv, 0       ]]

with focal lengths ``fsu, fsv`` and principal point ``(cu, cv)`` from K (pixels) and
the baseline ``b`` (metres). Inverting it (the report's landmark initialization)::

    z = fsu b / (uL - uR),   x = z (uL - cu) / fsu,   y = z (vL - cv) / fsv.

Every function is batched over leading axes. Points at or behind the camera and
observations with zero or negative disparity have no projection / triangulation:
they raise :class:`vislam.errors.GeometryError` instead of returning inf or NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vislam.errors import GeometryError

__all__ = ["StereoCamera", "stereo_matrix", "dpi_dq"]


def stereo_matrix(K, baseline_m: float) -> np.ndarray:
    """The report's 4x4 stereo calibration matrix M from intrinsics K and baseline b."""
    K = np.asarray(K, dtype=np.float64)
    fsu, fsv, cu, cv = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array(
        [
            [fsu, 0.0, cu, 0.0],
            [0.0, fsv, cv, 0.0],
            [fsu, 0.0, cu, -fsu * baseline_m],
            [0.0, fsv, cv, 0.0],
        ]
    )


def _homogeneous(q) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1] == 3:
        q = np.concatenate([q, np.ones(q.shape[:-1] + (1,))], axis=-1)
    elif q.shape[-1] != 4:
        raise ValueError(f"expected points of shape (..., 3) or (..., 4), got {q.shape}")
    return q


def dpi_dq(q) -> np.ndarray:
    """Jacobian of the projection π(q) = q / q_z for homogeneous q: (..., 4) -> (..., 4, 4).

    ``dπ/dq = (1/q_z) [[1, 0, -q_x/q_z, 0], [0, 1, -q_y/q_z, 0], [0, 0, 0, 0],
    [0, 0, -q_w/q_z, 1]]``. Requires q_z > 0.
    """
    q = _homogeneous(q)
    z = q[..., 2]
    if np.any(~(z > 0)):
        raise GeometryError("dpi_dq: point at or behind the camera (z <= 0)")
    inv_z = 1.0 / z
    out = np.zeros(q.shape[:-1] + (4, 4))
    out[..., 0, 0] = inv_z
    out[..., 1, 1] = inv_z
    out[..., 3, 3] = inv_z
    out[..., 0, 2] = -q[..., 0] * inv_z * inv_z
    out[..., 1, 2] = -q[..., 1] * inv_z * inv_z
    out[..., 3, 2] = -q[..., 3] * inv_z * inv_z
    return out


@dataclass(frozen=True)
class StereoCamera:
    """Rectified stereo pair: left intrinsics ``K`` (3x3, pixels) and ``baseline_m`` (m).

    ``M`` is the report's 4x4 stereo matrix. Image size, when known, bounds which
    points are visible (used by the simulator).
    """

    K: np.ndarray
    baseline_m: float
    image_size_px: tuple[int, int] | None = None  # (width, height)
    M: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        K = np.array(self.K, dtype=np.float64)
        K.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "baseline_m", float(self.baseline_m))
        M = stereo_matrix(K, self.baseline_m)
        M.setflags(write=False)
        object.__setattr__(self, "M", M)

    @property
    def fsu(self) -> float:
        return float(self.K[0, 0])

    @property
    def fsv(self) -> float:
        return float(self.K[1, 1])

    @property
    def cu(self) -> float:
        return float(self.K[0, 2])

    @property
    def cv(self) -> float:
        return float(self.K[1, 2])

    def project(self, p_in_cam) -> np.ndarray:
        """Pixels ``z = M π(q)`` (..., 4) of points (..., 3) or (..., 4) in the left camera frame."""
        q = _homogeneous(p_in_cam)
        z = q[..., 2]
        if np.any(~(z > 0)):
            raise GeometryError("project: point at or behind the camera (z <= 0)")
        return np.einsum("ij,...j->...i", self.M, q / z[..., None])

    def projection_jacobian(self, p_in_cam) -> np.ndarray:
        """``M dπ/dq(q)`` (..., 4, 4): derivative of the pixels with respect to homogeneous q."""
        return self.M @ dpi_dq(p_in_cam)

    def disparity_px(self, pixels) -> np.ndarray:
        """``uL - uR`` of observations (..., 4)."""
        pixels = np.asarray(pixels, dtype=np.float64)
        return pixels[..., 0] - pixels[..., 2]

    def triangulate(self, pixels) -> np.ndarray:
        """Invert the stereo model: observations (..., 4) -> points (..., 3) in the left camera.

        Raises GeometryError for zero, negative or non-finite disparity.
        """
        pixels = np.asarray(pixels, dtype=np.float64)
        d = self.disparity_px(pixels)
        if np.any(~(d > 0)) or np.any(~np.isfinite(pixels)):
            raise GeometryError("triangulate: disparity uL - uR must be finite and positive")
        z = self.fsu * self.baseline_m / d
        x = z * (pixels[..., 0] - self.cu) / self.fsu
        y = z * (pixels[..., 1] - self.cv) / self.fsv
        return np.stack([x, y, z], axis=-1)

    def triangulation_jacobian(self, pixels) -> np.ndarray:
        """Derivative of :meth:`triangulate` with respect to [uL, vL, uR, vR]: (..., 3, 4)."""
        pixels = np.asarray(pixels, dtype=np.float64)
        p = self.triangulate(pixels)
        d = self.disparity_px(pixels)
        z = p[..., 2]
        dz_duL = -z / d  # z = fsu b / d,  dz/dd = -z / d,  dd/duL = 1, dd/duR = -1
        a = (pixels[..., 0] - self.cu) / self.fsu
        c = (pixels[..., 1] - self.cv) / self.fsv
        out = np.zeros(pixels.shape[:-1] + (3, 4))
        out[..., 2, 0] = dz_duL
        out[..., 2, 2] = -dz_duL
        out[..., 0, 0] = dz_duL * a + z / self.fsu
        out[..., 0, 2] = -dz_duL * a
        out[..., 1, 0] = dz_duL * c
        out[..., 1, 2] = -dz_duL * c
        out[..., 1, 1] = z / self.fsv
        return out
