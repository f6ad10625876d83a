"""SO(3) and SE(3) on numpy, batched over leading axes.

Conventions (stated once, used everywhere in vislam)
-----------------------------------------------------
* A pose ``a_T_b`` is a 4x4 homogeneous matrix that maps coordinates in frame ``b``
  into frame ``a``: ``p_in_a = a_T_b @ p_in_b``. Arrays of poses have shape
  ``(..., 4, 4)``; every function here accepts any number of leading axes.
* A tangent vector (twist) of se(3) is ordered **(v, ω)**: ``xi = [v_x, v_y, v_z,
  ω_x, ω_y, ω_z]``, linear part first, as in the report.
* ``hat(xi)`` is the 4x4 matrix ``[[ω^, v], [0, 0]]``; ``exp(xi) = expm(hat(xi))``.
* The adjoint satisfies ``T @ exp(xi) @ inv(T) = exp(adjoint(T) @ xi)`` and, in the
  (v, ω) order, is ``[[R, p^ R], [0, R]]``.
* ``curly_hat(xi)`` (the report's ``ad``, written u-curly-hat) is ``[[ω^, v^], [0, ω^]]``
  and satisfies ``expm(curly_hat(xi)) = adjoint(exp(xi))``.
* ``odot(p)`` for a homogeneous point ``p = [s, λ]`` is the 4x6 matrix
  ``[[λ I, -s^], [0, 0]]`` with ``hat(xi) @ p = odot(p) @ xi``.

Perturbation side. The filter (``vislam.core.state``) follows the report: its pose
variable is the *inverse* IMU pose ``imu_T_world`` and it is perturbed on the **left**,
``imu_T_world = exp(δ) @ mean``, with δ ~ N(0, Σ), Σ 6x6 in the (v, ω) order above.
The functions in this module are convention-free group operations; the perturbation
side only matters for Jacobians, which the callers document.

Small angles. Closed forms divide by powers of the rotation angle θ; below
``SMALL_ANGLE`` a Taylor series is used instead, so exp/log/Jacobians are accurate to
machine precision for every θ including exactly zero.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "SMALL_ANGLE",
    "so3_hat",
    "so3_vee",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "so3_left_jacobian_inverse",
    "se3_left_jacobian",
    "se3_hat",
    "se3_vee",
    "se3_exp",
    "se3_log",
    "se3_inverse",
    "se3_adjoint",
    "se3_curly_hat",
    "se3_odot",
    "make_pose",
    "is_rigid_transform",
    "quaternion_from_rotation",
    "rotation_from_quaternion",
]

#: Below this rotation angle (rad) the Taylor branches are used.
SMALL_ANGLE = 1e-2


def _as_float(x) -> np.ndarray:
    if type(x) is np.ndarray and x.dtype == np.float64:  # the filters' own arrays: no conversion
        return x
    return np.asarray(x, dtype=np.float64)


# identities for the one-element paths (np.eye costs a few microseconds a call there)
_EYE3 = np.eye(3)
_EYE3.setflags(write=False)
_EYE4 = np.eye(4)
_EYE4.setflags(write=False)


# ----------------------------------------------------------------------------- SO(3)


def so3_hat(phi) -> np.ndarray:
    """(..., 3) axis-angle vector -> (..., 3, 3) skew-symmetric matrix ``phi^``."""
    phi = _as_float(phi)
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    out = np.zeros(phi.shape[:-1] + (3, 3))
    out[..., 0, 1] = -z
    out[..., 0, 2] = y
    out[..., 1, 0] = z
    out[..., 1, 2] = -x
    out[..., 2, 0] = -y
    out[..., 2, 1] = x
    return out


def so3_vee(Phi) -> np.ndarray:
    """(..., 3, 3) skew-symmetric matrix -> (..., 3) vector (inverse of :func:`so3_hat`)."""
    Phi = _as_float(Phi)
    return np.stack([Phi[..., 2, 1], Phi[..., 0, 2], Phi[..., 1, 0]], axis=-1)


def _angle_coefficients(theta: np.ndarray):
    """Return A = sin θ/θ, B = (1-cos θ)/θ², C = (θ - sin θ)/θ³ with small-angle series."""
    small = theta < SMALL_ANGLE
    t = np.where(small, 1.0, theta)  # safe divisor on the small branch
    t2 = theta * theta
    A = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0 - t2**3 / 5040.0, np.sin(t) / t)
    # 1 - cos θ = 2 sin²(θ/2) avoids the cancellation of 1 - cos θ for small θ.
    sinc_half = np.sin(0.5 * t) / (0.5 * t)
    B = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0 - t2**3 / 40320.0, 0.5 * sinc_half * sinc_half)
    C = np.where(
        small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0 - t2**3 / 362880.0, (t - np.sin(t)) / (t * t * t)
    )
    return A, B, C


def so3_exp(phi) -> np.ndarray:
    """Rodrigues' formula: (..., 3) -> (..., 3, 3) rotation ``R = expm(phi^)``."""
    phi = _as_float(phi)
    theta = np.linalg.norm(phi, axis=-1)
    A, B, _ = _angle_coefficients(theta)
    K = so3_hat(phi)
    KK = K @ K
    return np.eye(3) + A[..., None, None] * K + B[..., None, None] * KK


def so3_log(R) -> np.ndarray:
    """(..., 3, 3) rotation -> (..., 3) axis-angle with angle in [0, π].

    Angles below 3 rad (all the filters meet): θ = atan2(|w|, (tr R − 1)/2) with
    w = (R − Rᵀ)^∨ / 2 = sin θ · axis, and φ = θ / sin θ · w (series 1 + θ²/6 + 7θ⁴/360
    below SMALL_ANGLE) — accurate to rounding and ~20x faster than scipy for one matrix.
    Closer to π, where sin θ vanishes and the axis must come from the symmetric part,
    through the quaternion (:func:`quaternion_from_rotation`), accurate for every angle.
    """
    R = _as_float(R)
    lead = R.shape[:-2]
    flat = R.reshape(-1, 3, 3)
    if flat.shape[0] == 0:
        return np.zeros(lead + (3,))
    w = 0.5 * np.stack([flat[:, 2, 1] - flat[:, 1, 2], flat[:, 0, 2] - flat[:, 2, 0],
                        flat[:, 1, 0] - flat[:, 0, 1]], axis=-1)
    s = np.linalg.norm(w, axis=-1)  # sin θ
    c = 0.5 * (flat[:, 0, 0] + flat[:, 1, 1] + flat[:, 2, 2] - 1.0)  # cos θ
    theta = np.arctan2(s, c)
    if np.all(theta < 3.0):
        t2 = theta * theta
        small = theta < SMALL_ANGLE
        factor = np.where(small, 1.0 + t2 / 6.0 + 7.0 * t2 * t2 / 360.0, theta / np.where(small, 1.0, s))
        return (factor[:, None] * w).reshape(lead + (3,))
    q = quaternion_from_rotation(flat)
    q = np.where(q[:, 3:] < 0.0, -q, q)  # w ≥ 0: θ = 2 atan2(|q_v|, w) in [0, π]
    qv = q[:, :3]
    n = np.linalg.norm(qv, axis=-1)
    angle = 2.0 * np.arctan2(n, q[:, 3])
    # θ / sin(θ/2) = 2 (1 + θ²/24 + 7θ⁴/5760) below SMALL_ANGLE
    a2 = angle * angle
    small = angle < SMALL_ANGLE
    scale = np.where(small, 2.0 * (1.0 + a2 / 24.0 + 7.0 * a2 * a2 / 5760.0), angle / np.where(small, 1.0, n))
    return (scale[:, None] * qv).reshape(lead + (3,))


def quaternion_from_rotation(R) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions ``[x, y, z, w]``.

    The Shepperd–Markley method (scipy's ``Rotation.from_matrix``): the largest of
    ``1 + tr R`` and ``1 − tr R + 2 R_ii`` chooses which component is computed from the
    diagonal, so that no division by a vanishing number occurs at any angle. A matrix
    whose Gram matrix M Mᵀ is not the identity (numpy.isclose, rtol 1e-5, atol 1e-12,
    scipy's test) is first replaced by its nearest rotation (``U Vᵀ`` of its SVD), as
    scipy does. The sign is the one the chosen component's formula gives
    (q and −q are the same rotation)."""
    R = _as_float(R)
    lead = R.shape[:-2]
    M = R.reshape(-1, 3, 3).copy()
    gram = M @ np.swapaxes(M, -1, -2)
    off = ~np.all(np.isclose(gram, np.eye(3), rtol=1e-5, atol=1e-12), axis=(-2, -1))
    if off.any():
        U, _, Vt = np.linalg.svd(M[off])
        M[off] = U @ Vt
    tr = M[:, 0, 0] + M[:, 1, 1] + M[:, 2, 2]
    choice = np.argmax(np.stack([M[:, 0, 0], M[:, 1, 1], M[:, 2, 2], tr], axis=-1), axis=-1)
    q = np.empty((M.shape[0], 4))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        sel = choice == i
        Ms = M[sel]
        q[sel, i] = 1.0 - tr[sel] + 2.0 * Ms[:, i, i]
        q[sel, j] = Ms[:, j, i] + Ms[:, i, j]
        q[sel, k] = Ms[:, k, i] + Ms[:, i, k]
        q[sel, 3] = Ms[:, k, j] - Ms[:, j, k]
    sel = choice == 3
    Ms = M[sel]
    q[sel] = np.stack([Ms[:, 2, 1] - Ms[:, 1, 2], Ms[:, 0, 2] - Ms[:, 2, 0], Ms[:, 1, 0] - Ms[:, 0, 1],
                       1.0 + tr[sel]], axis=-1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q.reshape(lead + (4,))


def rotation_from_quaternion(q) -> np.ndarray:
    """(..., 4) quaternions ``[x, y, z, w]`` (normalized here) -> (..., 3, 3) rotations."""
    q = _as_float(q)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.stack([
        x * x - y * y - z * z + w * w, 2.0 * (x * y - z * w), 2.0 * (x * z + y * w),
        2.0 * (x * y + z * w), -x * x + y * y - z * z + w * w, 2.0 * (y * z - x * w),
        2.0 * (x * z - y * w), 2.0 * (y * z + x * w), -x * x - y * y + z * z + w * w,
    ], axis=-1)
    return R.reshape(q.shape[:-1] + (3, 3))


def so3_left_jacobian(phi) -> np.ndarray:
    """Left Jacobian of SO(3): ``J = I + B phi^ + C (phi^)^2`` (..., 3, 3)."""
    phi = _as_float(phi)
    if phi.shape == (3,):
        return _so3_left_jacobian_single(phi)
    theta = np.linalg.norm(phi, axis=-1)
    _, B, C = _angle_coefficients(theta)
    K = so3_hat(phi)
    return np.eye(3) + B[..., None, None] * K + C[..., None, None] * (K @ K)


def _so3_left_jacobian_single(phi: np.ndarray) -> np.ndarray:
    """:func:`so3_left_jacobian` of one vector with scalar coefficients (the prediction
    calls it per frame): the formulas and branches of :func:`_angle_coefficients`, in the
    same operation order, hence the same result."""
    x, y, z = phi.tolist()
    theta = math.sqrt(x * x + y * y + z * z)
    t2 = theta * theta
    if theta < SMALL_ANGLE:
        B = 0.5 - t2 / 24.0 + t2 * t2 / 720.0 - t2**3 / 40320.0
        C = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0 - t2**3 / 362880.0
    else:
        sinc_half = math.sin(0.5 * theta) / (0.5 * theta)
        B = 0.5 * sinc_half * sinc_half
        C = (theta - math.sin(theta)) / (theta * theta * theta)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return _EYE3 + B * K + C * (K @ K)


def so3_left_jacobian_inverse(phi) -> np.ndarray:
    """Inverse of :func:`so3_left_jacobian`: ``I - phi^/2 + D (phi^)^2``.

    D = (1 - θ sin θ / (2 (1 - cos θ))) / θ² = (1 - (θ/2) cot(θ/2)) / θ², with its series
    1/12 + θ²/720 + θ⁴/30240 for small θ. Valid for θ < 2π.
    """
    phi = _as_float(phi)
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < SMALL_ANGLE
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    # θ sin θ / (2 (1 - cos θ)) = (θ/2) / tan(θ/2): same value, without the cancellation of
    # 1 - cos θ, which cost ~1e-12 relative accuracy in J⁻¹ (and se3_log) just above SMALL_ANGLE.
    half = 0.5 * t
    D = np.where(
        small,
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
        (1.0 - half / np.tan(half)) / (t * t),
    )
    K = so3_hat(phi)
    return np.eye(3) - 0.5 * K + D[..., None, None] * (K @ K)


# ----------------------------------------------------------------------------- SE(3)


def se3_hat(xi) -> np.ndarray:
    """(..., 6) twist (v, ω) -> (..., 4, 4) matrix ``[[ω^, v], [0, 0]]``."""
    xi = _as_float(xi)
    out = np.zeros(xi.shape[:-1] + (4, 4))
    out[..., :3, :3] = so3_hat(xi[..., 3:])
    out[..., :3, 3] = xi[..., :3]
    return out


def se3_vee(X) -> np.ndarray:
    """(..., 4, 4) element of se(3) -> (..., 6) twist (v, ω)."""
    X = _as_float(X)
    return np.concatenate([X[..., :3, 3], so3_vee(X[..., :3, :3])], axis=-1)


def make_pose(R, p) -> np.ndarray:
    """Assemble (..., 4, 4) poses from rotations (..., 3, 3) and translations (..., 3)."""
    R = _as_float(R)
    p = _as_float(p)
    lead = np.broadcast_shapes(R.shape[:-2], p.shape[:-1])
    out = np.zeros(lead + (4, 4))
    out[..., :3, :3] = R
    out[..., :3, 3] = p
    out[..., 3, 3] = 1.0
    return out


def se3_exp(xi) -> np.ndarray:
    """Closed-form exponential: (..., 6) twist (v, ω) -> (..., 4, 4) pose.

    ``exp(xi) = [[R, J v], [0, 1]]`` with R from Rodrigues and J the SO(3) left Jacobian.
    """
    xi = _as_float(xi)
    if xi.shape == (6,):
        return _se3_exp_single(xi)
    phi = xi[..., 3:]
    theta = np.linalg.norm(phi, axis=-1)
    A, B, C = _angle_coefficients(theta)
    K = so3_hat(phi)
    KK = K @ K
    eye = np.eye(3)
    R = eye + A[..., None, None] * K + B[..., None, None] * KK
    J = eye + B[..., None, None] * K + C[..., None, None] * KK
    return make_pose(R, np.einsum("...ij,...j->...i", J, xi[..., :3]))


def _se3_exp_single(xi: np.ndarray) -> np.ndarray:
    """:func:`se3_exp` of one twist with scalar arithmetic (the filter calls it per frame;
    the batched path costs ~10x more for a single element). Same formulas and branches."""
    x, y, z = float(xi[3]), float(xi[4]), float(xi[5])
    t2 = x * x + y * y + z * z
    theta = math.sqrt(t2)
    if theta < SMALL_ANGLE:
        A = 1.0 - t2 / 6.0 + t2 * t2 / 120.0 - t2**3 / 5040.0
        B = 0.5 - t2 / 24.0 + t2 * t2 / 720.0 - t2**3 / 40320.0
        C = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0 - t2**3 / 362880.0
    else:
        A = math.sin(theta) / theta
        sinc_half = math.sin(0.5 * theta) / (0.5 * theta)
        B = 0.5 * sinc_half * sinc_half
        C = (theta - math.sin(theta)) / (theta * t2)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    KK = K @ K
    out = _EYE4.copy()
    out[:3, :3] += A * K + B * KK
    out[:3, 3] = (_EYE3 + B * K + C * KK) @ xi[:3]
    return out


def se3_log(T) -> np.ndarray:
    """(..., 4, 4) pose -> (..., 6) twist (v, ω) with rotation angle in [0, π]."""
    T = _as_float(T)
    if T.shape == (4, 4):
        out = _se3_log_single(T)
        if out is not None:
            return out
    phi = so3_log(T[..., :3, :3])
    Jinv = so3_left_jacobian_inverse(phi)
    v = np.einsum("...ij,...j->...i", Jinv, T[..., :3, 3])
    return np.concatenate([v, phi], axis=-1)


def _se3_log_single(T: np.ndarray) -> np.ndarray | None:
    """:func:`se3_log` of one pose with scalar arithmetic (the iterated update calls it
    twice per frame; the batched path costs ~10x more for a single element): the same
    formulas, branches and operation order as :func:`so3_log` and
    :func:`so3_left_jacobian_inverse`, hence the same result. None for angles of 3 rad
    and more (the batched path's scipy branch)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = T[:3, :3].tolist()
    # so3_log: w = (R − Rᵀ)^∨ / 2 = sin θ · axis,  cos θ = (tr R − 1)/2
    w0, w1, w2 = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    s = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    c = 0.5 * (r00 + r11 + r22 - 1.0)
    theta = math.atan2(s, c)
    if not theta < 3.0:
        return None
    t2 = theta * theta
    factor = 1.0 + t2 / 6.0 + 7.0 * t2 * t2 / 360.0 if theta < SMALL_ANGLE else theta / s
    x, y, z = factor * w0, factor * w1, factor * w2  # φ
    # so3_left_jacobian_inverse(φ) = I − φ^/2 + D (φ^)²
    theta = math.sqrt(x * x + y * y + z * z)
    t2 = theta * theta
    if theta < SMALL_ANGLE:
        D = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        half = 0.5 * theta
        D = (1.0 - half / math.tan(half)) / (theta * theta)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    Jinv = _EYE3 - 0.5 * K + D * (K @ K)
    out = np.empty(6)
    out[:3] = np.einsum("...ij,...j->...i", Jinv, T[:3, 3])
    out[3:] = (x, y, z)
    return out


def se3_inverse(T) -> np.ndarray:
    """Exact inverse of (..., 4, 4) rigid transforms: ``[[Rᵀ, -Rᵀ p], [0, 1]]``."""
    T = _as_float(T)
    if T.shape == (4, 4):  # one pose (several per frame in the filter): scalar arithmetic,
        # the same products and sums as the einsum below (3-term dot products in order)
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = T[:3, :3].tolist()
        x, y, z = T[:3, 3].tolist()
        return np.array([[r00, r10, r20, -(r00 * x + r10 * y + r20 * z)],
                         [r01, r11, r21, -(r01 * x + r11 * y + r21 * z)],
                         [r02, r12, r22, -(r02 * x + r12 * y + r22 * z)],
                         [0.0, 0.0, 0.0, 1.0]])
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def se3_adjoint(T) -> np.ndarray:
    """(..., 4, 4) pose -> (..., 6, 6) adjoint ``[[R, p^ R], [0, R]]`` for (v, ω) order."""
    T = _as_float(T)
    R = T[..., :3, :3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    if T.shape == (4, 4):  # one pose (per frame in the filters): p^ without so3_hat's batching
        x, y, z = T[:3, 3].tolist()
        out[:3, 3:] = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]) @ R
    else:
        out[..., :3, 3:] = so3_hat(T[..., :3, 3]) @ R
    return out


def se3_left_jacobian(xi) -> np.ndarray:
    """Left Jacobian of SE(3) at one twist ξ = (ρ, φ), (v, ω) order: (6, 6)
    ``[[J, Q], [0, J]]`` with J the SO(3) left Jacobian of φ and (Barfoot, State
    Estimation for Robotics, eq. 7.86)::

        Q = ½ρ^ + c₁ (φ^ρ^ + ρ^φ^ + φ^ρ^φ^) + c₂ (φ^φ^ρ^ + ρ^φ^φ^ − 3φ^ρ^φ^)
              + c₃ (φ^ρ^φ^φ^ + φ^φ^ρ^φ^),
        c₁ = (θ − sin θ)/θ³,  c₂ = (θ² + 2cos θ − 2)/(2θ⁴),  c₃ = (2θ − 3sin θ + θ cos θ)/(2θ⁵)

    so that ``exp(ξ + dξ) ≈ exp((J_l(ξ) dξ)^) exp(ξ)`` (equivalently J_l = Σ ad(ξ)ⁿ/(n+1)!).
    Below SMALL_ANGLE the coefficients are their Taylor series."""
    xi = _as_float(xi).reshape(6)
    phi = xi[3:]
    theta = float(np.linalg.norm(phi))
    t2 = theta * theta
    if theta < SMALL_ANGLE:
        c1 = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
        c2 = 1.0 / 24.0 - t2 / 720.0 + t2 * t2 / 40320.0
        c3 = 1.0 / 120.0 - t2 / 2520.0 + t2 * t2 / 120960.0
    else:
        s, c = math.sin(theta), math.cos(theta)
        c1 = (theta - s) / (theta * t2)
        c2 = (t2 + 2.0 * c - 2.0) / (2.0 * t2 * t2)
        c3 = (2.0 * theta - 3.0 * s + theta * c) / (2.0 * t2 * t2 * theta)
    P = so3_hat(phi)
    Rh = so3_hat(xi[:3])
    PR, RP, PP = P @ Rh, Rh @ P, P @ P
    PRP = PR @ P
    Q = 0.5 * Rh + c1 * (PR + RP + PRP) + c2 * (PP @ Rh + RP @ P - 3.0 * PRP) + c3 * (PRP @ P + PP @ RP)
    out = np.zeros((6, 6))
    J = so3_left_jacobian(phi)
    out[:3, :3] = J
    out[3:, 3:] = J
    out[:3, 3:] = Q
    return out


def se3_curly_hat(xi) -> np.ndarray:
    """The report's ``ad``/curly hat: (..., 6) twist -> (..., 6, 6) ``[[ω^, v^], [0, ω^]]``."""
    xi = _as_float(xi)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    w_hat = so3_hat(xi[..., 3:])
    out[..., :3, :3] = w_hat
    out[..., 3:, 3:] = w_hat
    out[..., :3, 3:] = so3_hat(xi[..., :3])
    return out


def se3_odot(p) -> np.ndarray:
    """The report's ⊙ operator: (..., 4) homogeneous point [s, λ] -> (..., 4, 6).

    ``[[λ I, -s^], [0ᵀ, 0ᵀ]]``, so that ``se3_hat(xi) @ p = se3_odot(p) @ xi``; hence
    ``d/dxi exp(xi^) p |_0 = odot(p)``. A (..., 3) input is taken as λ = 1.
    """
    p = _as_float(p)
    if p.shape[-1] == 3:
        s = p
        lam = np.ones(p.shape[:-1])
    else:
        s = p[..., :3]
        lam = p[..., 3]
    out = np.zeros(p.shape[:-1] + (4, 6))
    out[..., _I3, _I3] = lam[..., None]  # λ I
    # −s^ = [[−0, z, −y], [−z, −0, x], [y, −x, −0]] (the entries of -so3_hat(s), signed zeros included)
    out[..., _I3, _I3 + 3] = -0.0
    out[..., _ODOT_ROWS, _ODOT_COLS] = s[..., _ODOT_SRC] * _ODOT_SIGN
    return out


_I3 = np.arange(3)
_ODOT_ROWS, _ODOT_COLS = np.array([0, 0, 1, 1, 2, 2]), np.array([4, 5, 3, 5, 3, 4])
_ODOT_SRC, _ODOT_SIGN = np.array([2, 1, 2, 0, 1, 0]), np.array([1.0, -1.0, -1.0, 1.0, 1.0, -1.0])


def is_rigid_transform(T, tol: float = 1e-6) -> bool:
    """True when ``T`` is a finite 4x4 matrix with a rotation block (RᵀR = I, det R = 1)
    and last row ``[0, 0, 0, 1]``, each to within ``tol``."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.issubdtype(T.dtype, np.number) or not np.all(np.isfinite(T)):
        return False
    T = T.astype(np.float64)
    R = T[:3, :3]
    return bool(
        np.allclose(R.T @ R, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1.0) < tol
        and np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=tol)
    )
