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


def _require_finite(out: np.ndarray, what: str) -> np.ndarray:
    """Return ``out``, or raise GeometryError if any entry overflowed to inf/NaN (a point or
    a disparity so close to zero that the result is not representable)."""
    if not np.isfinite(out).all():
        raise GeometryError(f"{what}: result overflows (point too close to the camera plane z = 0)")
    return out


def _in_front(q: np.ndarray, what: str) -> np.ndarray:
    """Depths q_z of homogeneous points, after checking they are finite and positive."""
    if not np.isfinite(q).all():
        raise GeometryError(f"{what}: point coordinates must be finite")
    z = q[..., 2]
    if (~(z > 0)).any():
        raise GeometryError(f"{what}: point at or behind the camera (z <= 0)")
    return z


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
    [0, 0, -q_w/q_z, 1]]``. Requires q_z > 0 and a finite result.
    """
    q = _homogeneous(q)
    z = _in_front(q, "dpi_dq")
    out = np.zeros(q.shape[:-1] + (4, 4))
    with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported below
        inv_z = (1.0 / z)[..., None]
        out[..., _XYW, _XYW] = inv_z  # (0, 0), (1, 1), (3, 3)
        out[..., _XYW, 2] = -q[..., _XYW] * inv_z * inv_z  # (0, 2), (1, 2), (3, 2): −q_i / q_z²
    return _require_finite(out, "dpi_dq")


_XYW = np.array([0, 1, 3])  # the rows of dπ/dq with entries


#: The largest focal length or principal-point coordinate accepted (px): a million pixels
#: is beyond any camera, and keeps the stereo model's products finite (a principal point at
#: 1e200 px overflowed the filters).
MAX_INTRINSIC_PX = 1e6


def intrinsics_problem(fx: float, fy: float, cx: float, cy: float) -> str | None:
    """What is wrong with pinhole intrinsics (px), as a phrase for an error message, or
    None: focal lengths must be in (0, :data:`MAX_INTRINSIC_PX`], the principal point
    within ±:data:`MAX_INTRINSIC_PX`."""
    if not all(np.isfinite(x) for x in (fx, fy, cx, cy)):
        return f"has non-finite intrinsics (fx, fy, cx, cy) = ({fx:g}, {fy:g}, {cx:g}, {cy:g})"
    if not (0 < fx <= MAX_INTRINSIC_PX and 0 < fy <= MAX_INTRINSIC_PX):
        return f"has focal lengths {fx:g}, {fy:g} px; expected both in (0, {MAX_INTRINSIC_PX:g}] px"
    if not (abs(cx) <= MAX_INTRINSIC_PX and abs(cy) <= MAX_INTRINSIC_PX):
        return f"has principal point ({cx:g}, {cy:g}) px; expected it within ±{MAX_INTRINSIC_PX:g} px"
    return None


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
        if K.shape == (3, 3):
            problem = intrinsics_problem(K[0, 0], K[1, 1], K[0, 2], K[1, 2])
            if problem:
                raise ValueError(f"K {problem}")
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
        z = _in_front(q, "project")
        with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported below
            out = np.einsum("ij,...j->...i", self.M, q / z[..., None])
        return _require_finite(out, "project")

    def projection_jacobian(self, p_in_cam) -> np.ndarray:
        """``M dπ/dq(q)`` (..., 4, 4): derivative of the pixels with respect to homogeneous q."""
        J = dpi_dq(p_in_cam)
        with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported below
            out = self.M @ J
        return _require_finite(out, "projection_jacobian")

    def disparity_px(self, pixels) -> np.ndarray:
        """``uL - uR`` of observations (..., 4)."""
        pixels = np.asarray(pixels, dtype=np.float64)
        return pixels[..., 0] - pixels[..., 2]

    def triangulate(self, pixels) -> np.ndarray:
        """Invert the stereo model: observations (..., 4) -> points (..., 3) in the left camera.

        Raises GeometryError for zero, negative or non-finite disparity, non-finite pixels,
        and a disparity so small that the depth overflows.
        """
        pixels = np.asarray(pixels, dtype=np.float64)
        if not np.all(np.isfinite(pixels)):
            raise GeometryError("triangulate: pixel coordinates must be finite")
        with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported below
            d = self.disparity_px(pixels)
            if np.any(~(d > 0)) or np.any(~np.isfinite(d)):
                raise GeometryError("triangulate: disparity uL - uR must be finite and positive")
            z = self.fsu * self.baseline_m / d
            x = z * (pixels[..., 0] - self.cu) / self.fsu
            y = z * (pixels[..., 1] - self.cv) / self.fsv
        return _require_finite(np.stack([x, y, z], axis=-1), "triangulate")

    def triangulation_jacobian(self, pixels) -> np.ndarray:
        """Derivative of :meth:`triangulate` with respect to [uL, vL, uR, vR]: (..., 3, 4)."""
        pixels = np.asarray(pixels, dtype=np.float64)
        p = self.triangulate(pixels)
        d = self.disparity_px(pixels)
        z = p[..., 2]
        out = np.zeros(pixels.shape[:-1] + (3, 4))
        with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported below
            dz_duL = -z / d  # z = fsu b / d,  dz/dd = -z / d,  dd/duL = 1, dd/duR = -1
            a = (pixels[..., 0] - self.cu) / self.fsu
            c = (pixels[..., 1] - self.cv) / self.fsv
            out[..., 2, 0] = dz_duL
            out[..., 2, 2] = -dz_duL
            out[..., 0, 0] = dz_duL * a + z / self.fsu
            out[..., 0, 2] = -dz_duL * a
            out[..., 1, 0] = dz_duL * c
            out[..., 1, 2] = -dz_duL * c
            out[..., 1, 1] = z / self.fsv
        return _require_finite(out, "triangulation_jacobian")
