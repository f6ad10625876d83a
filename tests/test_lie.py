"""Property tests of ``vislam.core.lie`` (SO(3)/SE(3), tangent order (v, ω)).

In the style of jaxlie's tests: every property is checked numerically, with a stated
tolerance, on samples from three regimes of rotation angle θ:

* ``random``        θ uniform in [0, π),
* ``large``         θ in [π − 1e-3, π),
* ``near_identity`` θ in [0, 1e-6], always including exactly 0 and 1e-12,

with translations up to ~100 m per axis, and on batches of leading shape (), (5,) and
(2, 3): every property is evaluated on the whole batch at once, and a separate test
checks each batched function against a loop over single elements.

Tolerances are absolute errors in the natural unit of each quantity; where a translation
enters, they scale with ``1 + |translation|`` (metres), since float64 rounding is
relative to the magnitude of the numbers involved.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.linalg import expm

from vislam.core.lie import (
    SMALL_ANGLE,
    is_rigid_transform,
    make_pose,
    se3_adjoint,
    se3_curly_hat,
    se3_exp,
    se3_hat,
    se3_inverse,
    se3_log,
    se3_odot,
    se3_vee,
    so3_exp,
    so3_hat,
    so3_left_jacobian,
    so3_left_jacobian_inverse,
    so3_log,
    so3_vee,
)

EPS = np.finfo(np.float64).eps
REGIMES = ("random", "large", "near_identity")
SHAPES = ((), (5,), (2, 3))
MAX_TRANSLATION_M = 100.0

PROPERTY = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# ----------------------------------------------------------------------------- strategies

_ANGLES = {
    "random": st.floats(0.0, math.pi, exclude_max=True),
    "large": st.floats(math.pi - 1e-3, math.pi, exclude_max=True),
    "near_identity": st.one_of(st.just(0.0), st.just(1e-12), st.floats(0.0, 1e-6)),
}


@st.composite
def unit_vectors(draw, shape):
    """Unit 3-vectors (*shape, 3) in random directions."""
    n = math.prod(shape)
    axes = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-1.0, 1.0)))
    norms = np.linalg.norm(axes, axis=-1, keepdims=True)
    ok = norms > 1e-3
    axes = np.where(ok, axes / np.where(ok, norms, 1.0), np.array([1.0, 0.0, 0.0]))
    return axes.reshape(tuple(shape) + (3,))


@st.composite
def rotvecs(draw, regime: str, shape=None):
    """Axis-angle vectors (*shape, 3) with angle from ``regime`` and a random axis.

    In the near-identity regime the first element of every batch is exactly 0 and the
    second (when there is one) has angle 1e-12, so these are always exercised."""
    if shape is None:
        shape = draw(st.sampled_from(SHAPES))
    n = math.prod(shape)
    axes = draw(unit_vectors((n,)))
    angles = draw(hnp.arrays(np.float64, (n,), elements=_ANGLES[regime]))
    if regime == "near_identity":
        angles[:2] = [0.0, 1e-12][: min(n, 2)]
    return (axes * angles[:, None]).reshape(tuple(shape) + (3,))


@st.composite
def translations(draw, shape):
    n = math.prod(shape)
    v = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-MAX_TRANSLATION_M, MAX_TRANSLATION_M)))
    return v.reshape(tuple(shape) + (3,))


@st.composite
def twists(draw, regime: str, shape=None):
    """Twists (*shape, 6) in the (v, ω) order: |v_i| <= 100 m, ω from ``regime``."""
    if shape is None:
        shape = draw(st.sampled_from(SHAPES))
    omega = draw(rotvecs(regime, shape))
    return np.concatenate([draw(translations(shape)), omega], axis=-1)


@st.composite
def points_h(draw, shape):
    """Homogeneous points [s, λ] (*shape, 4) with λ in [-2, 2] (including 0 and 1)."""
    s = draw(translations(shape))
    n = math.prod(shape)
    lam = draw(
        hnp.arrays(np.float64, (n,), elements=st.one_of(st.just(1.0), st.just(0.0), st.floats(-2.0, 2.0)))
    )
    return np.concatenate([s, lam.reshape(tuple(shape) + (1,))], axis=-1)


def _shape_of(x, core: int):
    return x.shape[: x.ndim - core]


# ----------------------------------------------------------------------------- helpers


def assert_close(actual, desired, atol, what: str = ""):
    """|actual - desired| <= atol elementwise (atol broadcast against the arrays)."""
    actual = np.asarray(actual, dtype=np.float64)
    desired = np.asarray(desired, dtype=np.float64)
    assert actual.shape == desired.shape, f"{what}: shape {actual.shape} != {desired.shape}"
    assert np.all(np.isfinite(actual)), f"{what}: non-finite values"
    err = np.abs(actual - desired)
    atol = np.broadcast_to(np.asarray(atol, dtype=np.float64), err.shape)
    bad = err > atol
    if np.any(bad):
        ratio = np.max(err / atol)
        i = np.unravel_index(np.argmax(err / atol), err.shape)
        raise AssertionError(
            f"{what}: max |error|/tol = {ratio:.3g} at {i}: error {err[i]:.3g} > tol {atol[i]:.3g}"
        )


def mat_tol(tol, scale):
    """Tolerance array for (..., n, m) matrices: ``tol * scale`` per leading element."""
    return (tol * np.asarray(scale))[..., None, None]


def trans_scale(xi):
    """1 + |v| for twists (..., 6): the scale of translations produced from them."""
    return 1.0 + np.linalg.norm(xi[..., :3], axis=-1)


def pose_scale(T):
    return 1.0 + np.linalg.norm(T[..., :3, 3], axis=-1)


def loop_apply(fn, x, core_in: int):
    """fn applied to every single element of the batch x (core dims ``core_in``)."""
    lead = _shape_of(x, core_in)
    outs = [fn(x[idx]) for idx in np.ndindex(*lead)]
    if not outs:
        return None
    return np.stack(outs).reshape(lead + outs[0].shape)


def angle(phi):
    return np.linalg.norm(phi, axis=-1)


def random_rotation_matrices(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def left_jacobian_reference(phi):
    """J_l(φ) = ∫₀¹ exp(s φ^) ds, the top-right block of expm([[φ^, I], [0, 0]])."""
    A = np.zeros((6, 6))
    A[:3, :3] = so3_hat(phi)
    A[:3, 3:] = np.eye(3)
    return expm(A)[:3, 3:]


# ----------------------------------------------------------------------------- batching

# (function, input strategy factory(regime, shape), number of core input dims)
_BATCHED = {
    "so3_hat": (so3_hat, lambda r, s: rotvecs(r, s), 1),
    "so3_vee": (so3_vee, lambda r, s: rotvecs(r, s).map(so3_hat), 2),
    "so3_exp": (so3_exp, lambda r, s: rotvecs(r, s), 1),
    "so3_log": (so3_log, lambda r, s: rotvecs(r, s).map(so3_exp), 2),
    "so3_left_jacobian": (so3_left_jacobian, lambda r, s: rotvecs(r, s), 1),
    "so3_left_jacobian_inverse": (so3_left_jacobian_inverse, lambda r, s: rotvecs(r, s), 1),
    "se3_hat": (se3_hat, lambda r, s: twists(r, s), 1),
    "se3_vee": (se3_vee, lambda r, s: twists(r, s).map(se3_hat), 2),
    "se3_exp": (se3_exp, lambda r, s: twists(r, s), 1),
    "se3_log": (se3_log, lambda r, s: twists(r, s).map(se3_exp), 2),
    "se3_inverse": (se3_inverse, lambda r, s: twists(r, s).map(se3_exp), 2),
    "se3_adjoint": (se3_adjoint, lambda r, s: twists(r, s).map(se3_exp), 2),
    "se3_curly_hat": (se3_curly_hat, lambda r, s: twists(r, s), 1),
    "se3_odot": (se3_odot, lambda r, s: points_h(s), 1),
    "se3_odot_3d": (se3_odot, lambda r, s: translations(s), 1),
}


@pytest.mark.parametrize("regime", REGIMES)
@pytest.mark.parametrize("name", sorted(_BATCHED))
@settings(max_examples=10, deadline=None)
@given(data=st.data())
def test_batched_equals_loop(name, regime, data):
    """Every function on a batch of leading shape (), (5,), (2, 3) or (0,) equals a loop
    over the single elements (relative 1e-14; batched matmul may round differently)."""
    fn, make, core = _BATCHED[name]
    shape = data.draw(st.sampled_from(SHAPES + ((0,),)), label="shape")
    x = data.draw(make(regime, shape), label="x")
    out = fn(x)
    assert out.shape[: len(shape)] == shape
    looped = loop_apply(fn, x, core)
    if looped is None:  # empty batch: only the shape is defined
        return
    scale = 1.0 + np.max(np.abs(looped))
    assert_close(out, looped, 1e-14 * scale, name)


# ----------------------------------------------------------------------------- hat / vee


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_so3_hat_vee_inverse_and_skew(regime, data):
    phi = data.draw(rotvecs(regime))
    Phi = so3_hat(phi)
    # exact: hat only places (and negates) the components
    np.testing.assert_array_equal(so3_vee(Phi), phi)
    np.testing.assert_array_equal(np.swapaxes(Phi, -1, -2), -Phi)
    np.testing.assert_array_equal(np.diagonal(Phi, axis1=-2, axis2=-1), 0.0)
    # φ^ w = φ × w
    w = data.draw(translations(phi.shape[:-1]))
    assert_close(
        np.einsum("...ij,...j->...i", Phi, w), np.cross(phi, w), 4 * EPS * (1 + np.abs(np.cross(phi, w))), "φ^ w"
    )
    # vee is a left inverse of hat on all skew matrices: hat(vee(S)) = S exactly
    A = data.draw(hnp.arrays(np.float64, phi.shape[:-1] + (3, 3), elements=st.floats(-100, 100)))
    S = A - np.swapaxes(A, -1, -2)
    np.testing.assert_array_equal(so3_hat(so3_vee(S)), S)


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_se3_hat_vee_inverse(regime, data):
    xi = data.draw(twists(regime))
    X = se3_hat(xi)
    np.testing.assert_array_equal(se3_vee(X), xi)
    np.testing.assert_array_equal(X[..., 3, :], 0.0)
    np.testing.assert_array_equal(X[..., :3, :3], so3_hat(xi[..., 3:]))
    np.testing.assert_array_equal(X[..., :3, 3], xi[..., :3])  # (v, ω) order
    np.testing.assert_array_equal(se3_hat(se3_vee(X)), X)


# ----------------------------------------------------------------------------- exp vs expm


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_exp_matches_expm(regime, data):
    """so3_exp/se3_exp equal scipy.linalg.expm of the hat matrix: rotation to 5e-14,
    translation to 5e-14 (1 + |v|) (expm's own rounding reaches ~1e-14 at large angles:
    Hypothesis found 1.1e-14)."""
    xi = data.draw(twists(regime))
    R = so3_exp(xi[..., 3:])
    T = se3_exp(xi)
    R_ref = loop_apply(lambda p: expm(so3_hat(p)), xi[..., 3:], 1)
    T_ref = loop_apply(lambda x: expm(se3_hat(x)), xi, 1)
    assert_close(R, R_ref, 5e-14, "so3_exp vs expm")
    assert_close(T[..., :3, :3], T_ref[..., :3, :3], 5e-14, "se3_exp rotation vs expm")
    assert_close(T[..., :3, 3], T_ref[..., :3, 3], 5e-14 * trans_scale(xi)[..., None], "se3_exp translation")
    np.testing.assert_array_equal(T[..., 3, :], np.broadcast_to([0.0, 0.0, 0.0, 1.0], T[..., 3, :].shape))


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_so3_exp_is_rotation_and_inverse_is_inverse(regime, data):
    """RᵀR = I and det R = 1 to 1e-14; se3_inverse(T) T = T se3_inverse(T) = I
    to 1e-14 (1 + |p|)."""
    xi = data.draw(twists(regime))
    R = so3_exp(xi[..., 3:])
    assert_close(np.swapaxes(R, -1, -2) @ R, np.broadcast_to(np.eye(3), R.shape), 1e-14, "RᵀR")
    assert_close(np.linalg.det(R), np.ones(R.shape[:-2]), 1e-14, "det R")
    T = se3_exp(xi)
    Ti = se3_inverse(T)
    tol = mat_tol(1e-14, pose_scale(T))
    eye = np.broadcast_to(np.eye(4), T.shape)
    assert_close(Ti @ T, eye, tol, "inv(T) T")
    assert_close(T @ Ti, eye, tol, "T inv(T)")
    assert_close(Ti, np.linalg.inv(T), tol, "se3_inverse vs np.linalg.inv")
    # the inverse of exp(ξ) is exp(-ξ)
    assert_close(se3_exp(-xi), Ti, tol, "exp(-ξ) = exp(ξ)⁻¹")


# ----------------------------------------------------------------------------- exp / log


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_log_exp_round_trip(regime, data):
    """log(exp(ξ)) = ξ for θ <= π − 1e-6 (ω to 1e-12 + 1e-9 |ω|, v to 1e-13 (1 + |v|));
    exp(log(T)) = T for all samples (to 1e-13 (1 + |p|)) and log's angle is in [0, π].
    Closer than 1e-6 to π only the pose is compared: there log may legitimately return
    the antipodal twist (same rotation, angle π − ε about −axis)."""
    xi = data.draw(twists(regime))
    T = se3_exp(xi)
    xi_log = se3_log(T)
    theta = angle(xi[..., 3:])
    assert np.all(angle(xi_log[..., 3:]) <= math.pi * (1 + 4 * EPS))
    assert_close(se3_exp(xi_log), T, mat_tol(1e-13, pose_scale(T)), "exp(log(T))")
    assert_close(so3_exp(so3_log(T[..., :3, :3])), T[..., :3, :3], 1e-13, "so3 exp(log(R))")
    unambiguous = theta <= math.pi - 1e-6
    w = xi[unambiguous, 3:]
    assert_close(xi_log[unambiguous, 3:], w, 1e-12 + 1e-9 * angle(w)[:, None], "log ω")
    v_tol = 1e-13 * trans_scale(xi[unambiguous])[:, None]
    assert_close(xi_log[unambiguous, :3], xi[unambiguous, :3], v_tol, "log v")


@pytest.mark.parametrize("seed", range(3))
def test_exp_log_round_trip_random_poses(seed):
    """exp(log(T)) = T for poses built from uniformly random rotations (not from exp),
    translations up to 100 m, in batches (5,) and (2, 3) (to 1e-13 (1 + |p|))."""
    rng = np.random.default_rng(seed)
    for shape in [(5,), (2, 3), (200,)]:
        n = math.prod(shape)
        T = make_pose(random_rotation_matrices(rng, n), rng.uniform(-100, 100, (n, 3))).reshape(shape + (4, 4))
        assert_close(se3_exp(se3_log(T)), T, mat_tol(1e-13, pose_scale(T)), "exp(log(T))")


# ----------------------------------------------------------------------------- adjoint


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_adjoint_identities(regime, data):
    """T exp(ξ) T⁻¹ = exp(Ad_T ξ); Ad(T1 T2) = Ad(T1) Ad(T2); Ad(T⁻¹) Ad(T) = I.
    Tolerances 1e-13 times the product of the translation scales involved."""
    shape = data.draw(st.sampled_from(SHAPES))
    T1 = se3_exp(data.draw(twists(regime, shape)))
    T2 = se3_exp(data.draw(twists(regime, shape)))
    xi = data.draw(twists(regime, shape))
    s1, s2, sx = pose_scale(T1), pose_scale(T2), trans_scale(xi)

    lhs = T1 @ se3_exp(xi) @ se3_inverse(T1)
    rhs = se3_exp(np.einsum("...ij,...j->...i", se3_adjoint(T1), xi))
    assert_close(lhs, rhs, mat_tol(1e-13, s1 * sx), "T exp(ξ) T⁻¹ = exp(Ad ξ)")

    assert_close(
        se3_adjoint(T1 @ T2), se3_adjoint(T1) @ se3_adjoint(T2), mat_tol(1e-13, s1 * s2), "Ad(T1 T2)"
    )
    Ad = se3_adjoint(T1)
    Ad_inv = se3_adjoint(se3_inverse(T1))
    eye6 = np.broadcast_to(np.eye(6), Ad.shape)
    assert_close(Ad_inv @ Ad, eye6, mat_tol(1e-13, s1), "Ad(T⁻¹) Ad(T)")
    assert_close(Ad @ Ad_inv, eye6, mat_tol(1e-13, s1), "Ad(T) Ad(T⁻¹)")
    # the hat form of the same identity: T ξ^ T⁻¹ = (Ad ξ)^
    assert_close(
        T1 @ se3_hat(xi) @ se3_inverse(T1),
        se3_hat(np.einsum("...ij,...j->...i", Ad, xi)),
        mat_tol(1e-13, s1 * sx),
        "T ξ^ T⁻¹ = (Ad ξ)^",
    )


# ----------------------------------------------------------------------------- curly hat


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_curly_hat_identities(regime, data):
    """expm(curly_hat(ξ)) = adjoint(exp(ξ)) (the report's exp(−τ ad u) prediction) to
    1e-13 (1 + |v|); curly_hat(ξ) ξ = 0; curly_hat(a) b = −curly_hat(b) a; and
    curly_hat(a) b is the Lie bracket vee(a^ b^ − b^ a^)."""
    shape = data.draw(st.sampled_from(SHAPES))
    a = data.draw(twists(regime, shape))
    b = data.draw(twists(regime, shape))
    sa, sb = trans_scale(a), trans_scale(b)

    ref = loop_apply(lambda x: expm(se3_curly_hat(x)), a, 1)
    assert_close(ref, se3_adjoint(se3_exp(a)), mat_tol(1e-13, sa), "expm(curly_hat) = Ad(exp)")
    # the report's prediction uses exp(−τ ad u): check that sign as well
    ref_neg = loop_apply(lambda x: expm(-0.1 * se3_curly_hat(x)), a, 1)
    assert_close(ref_neg, se3_adjoint(se3_exp(-0.1 * a)), mat_tol(1e-13, sa), "expm(−τ ad u)")

    def apply(M, x):
        return np.einsum("...ij,...j->...i", M, x)

    assert_close(apply(se3_curly_hat(a), a), np.zeros_like(a), (1e-14 * sa * sa)[..., None], "ad(ξ) ξ")
    ab = apply(se3_curly_hat(a), b)
    assert_close(ab, -apply(se3_curly_hat(b), a), (1e-14 * sa * sb)[..., None], "ad(a) b = −ad(b) a")
    bracket = se3_vee(se3_hat(a) @ se3_hat(b) - se3_hat(b) @ se3_hat(a))
    assert_close(ab, bracket, (1e-13 * sa * sb)[..., None], "ad(a) b = [a^, b^]")


# ----------------------------------------------------------------------------- odot


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_odot_identities(regime, data):
    """ξ^ p = p^⊙ ξ for homogeneous p = [s, λ] (λ = 0, 1 and random) to 1e-13 (1 + |ξ||p|);
    a 3-vector is read as λ = 1."""
    shape = data.draw(st.sampled_from(SHAPES))
    xi = data.draw(twists(regime, shape))
    p = data.draw(points_h(shape))
    lhs = np.einsum("...ij,...j->...i", se3_hat(xi), p)
    rhs = np.einsum("...ij,...j->...i", se3_odot(p), xi)
    scale = 1.0 + np.linalg.norm(xi, axis=-1) * np.linalg.norm(p, axis=-1)
    assert_close(lhs, rhs, 1e-14 * scale[..., None], "ξ^ p = p^⊙ ξ")
    p1 = p.copy()
    p1[..., 3] = 1.0
    np.testing.assert_array_equal(se3_odot(p1[..., :3]), se3_odot(p1))


def _central_fd(f, x0, h):
    """Central-difference Jacobian of f: (..., n) -> (..., m) at x0, as (..., m, n)."""
    cols = []
    for k in range(x0.shape[-1]):
        e = np.zeros(x0.shape[-1])
        e[k] = h
        cols.append((f(x0 + e) - f(x0 - e)) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_odot_is_derivative_of_exp_action(regime, data):
    """d/dξ exp(ξ) p |₀ = p^⊙ and d/dδ exp(δ) T p |₀ = (T p)^⊙ (left perturbation), by
    central differences with h = 1e-6: tolerance 1e-8 (1 + |p|) (FD round-off ~1e-10 |p|)."""
    shape = data.draw(st.sampled_from(SHAPES))
    p = data.draw(points_h(shape))
    T = se3_exp(data.draw(twists(regime, shape)))
    zero = np.zeros(shape + (6,))

    def act(M, x):
        return np.einsum("...ij,...j->...i", M, x)

    J = _central_fd(lambda d: act(se3_exp(d), p), zero, 1e-6)
    assert_close(J, se3_odot(p), mat_tol(1e-8, 1 + np.linalg.norm(p, axis=-1)), "d exp(ξ) p / dξ")

    Tp = act(T, p)
    J_left = _central_fd(lambda d: act(se3_exp(d) @ T, p), zero, 1e-6)
    assert_close(J_left, se3_odot(Tp), mat_tol(1e-8, 1 + np.linalg.norm(Tp, axis=-1)), "d exp(δ) T p / dδ")


# ----------------------------------------------------------------------------- left Jacobian


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_left_jacobian_first_order(regime, data):
    """exp(φ + δ) ≈ exp(J_l(φ) δ) exp(φ):
    * J_l equals the central-difference Jacobian of δ ↦ log(exp(φ + δ) exp(φ)ᵀ) at 0
      (h = 1e-6, tolerance 1e-8);
    * the residual |exp(φ + δ) − exp(J_l δ) exp(φ)| for |δ| = 1e-5 is second order
      (≤ |δ|² = 1e-10, while a wrong J would leave ~1e-5);
    * J_l equals its integral definition ∫₀¹ exp(s φ^) ds (block expm) to 1e-14."""
    phi = data.draw(rotvecs(regime))
    J = so3_left_jacobian(phi)
    R = so3_exp(phi)
    Rt = np.swapaxes(R, -1, -2)
    J_fd = _central_fd(lambda d: so3_log(so3_exp(phi + d) @ Rt), np.zeros_like(phi), 1e-6)
    assert_close(J_fd, J, 1e-8, "J_l vs FD")

    delta = 1e-5 * data.draw(unit_vectors(phi.shape[:-1]))
    lhs = so3_exp(phi + delta)
    rhs = so3_exp(np.einsum("...ij,...j->...i", J, delta)) @ R
    assert_close(lhs, rhs, 1e-10, "exp(φ+δ) vs exp(J δ) exp(φ)")

    assert_close(J, loop_apply(left_jacobian_reference, phi, 1), 1e-14, "J_l vs ∫ exp(s φ^) ds")


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_left_jacobian_inverse(regime, data):
    """so3_left_jacobian_inverse(φ) J_l(φ) = I to 1e-14. The brief asks for θ < π − 0.1;
    J_l is invertible (σ_min ≥ 2/π) for all θ < 2π, so the large regime is checked too."""
    phi = data.draw(rotvecs(regime))
    J = so3_left_jacobian(phi)
    Jinv = so3_left_jacobian_inverse(phi)
    eye = np.broadcast_to(np.eye(3), J.shape)
    assert_close(Jinv @ J, eye, 1e-14, "J_l⁻¹ J_l")
    assert_close(J @ Jinv, eye, 1e-14, "J_l J_l⁻¹")


# ----------------------------------------------------------------------------- is_rigid_transform


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_is_rigid_transform(regime, data):
    xi = data.draw(twists(regime, (4,)))
    Ts = se3_exp(xi)
    scale = data.draw(st.one_of(st.floats(0.1, 0.999), st.floats(1.001, 10.0)))
    for T in Ts:
        assert is_rigid_transform(T)
        assert is_rigid_transform(T.tolist())
        assert is_rigid_transform(se3_inverse(T))
        scaled = T.copy()
        scaled[:3, :3] *= scale
        assert not is_rigid_transform(scaled), "scaled rotation"
        reflected = T.copy()
        reflected[:3, :3] = T[:3, :3] @ np.diag([1.0, 1.0, -1.0])
        assert not is_rigid_transform(reflected), "reflection (det -1)"
        minus = T.copy()
        minus[:3, :3] = -T[:3, :3]
        assert not is_rigid_transform(minus), "−R (det −1)"
        for row in ([0.0, 0.0, 0.1, 1.0], [0.0, 0.0, 0.0, 2.0], [0.0, 0.0, 0.0, 0.0]):
            bad = T.copy()
            bad[3] = row
            assert not is_rigid_transform(bad), f"last row {row}"
        for value in (np.nan, np.inf):
            bad = T.copy()
            bad[data.draw(st.integers(0, 3)), data.draw(st.integers(0, 3))] = value
            assert not is_rigid_transform(bad), f"{value} entry"
        for wrong in (T[:3, :3], T[:3], T[None], T.reshape(16), T[..., None]):
            assert not is_rigid_transform(wrong), f"shape {wrong.shape}"
    # the tolerance is honoured: 1e-9 orthogonality error passes, 1e-4 fails
    T = Ts[0].copy()
    T[:3, :3] *= 1 + 1e-9
    assert is_rigid_transform(T)
    T[:3, :3] *= 1 + 1e-4
    assert not is_rigid_transform(T)
    assert is_rigid_transform(np.eye(4, dtype=int))
    assert not is_rigid_transform(np.full((4, 4), "a"))


# ----------------------------------------------------------------------------- small angles


@settings(max_examples=50, deadline=None)
@given(axes=unit_vectors((8,)), v=translations((8,)))
def test_small_angle_branches_are_used_and_accurate(axes, v):
    """Accuracy at θ = 1e-8, where naive closed forms lose everything ((1 − cos θ)/θ²
    evaluates to 0, which the original B coefficient did above SMALL_ANGLE): these checks
    need an accurate small-angle evaluation:
    * so3_exp(φ) = I + φ^ + φ^²/2 to 1e-15;
    * J_l(φ) = I + φ^/2 + φ^²/6 and J_l⁻¹(φ) = I − φ^/2 + φ^²/12 to 1e-15;
    * se3_exp translation = v + ω×v/2 to 1e-15 (1 + |v|);
    * se3_log returns the input twist to relative 1e-9 (ω) and 1e-15 (1 + |v|) (v)."""
    phi = 1e-8 * axes
    K = so3_hat(phi)
    eye = np.eye(3)
    assert_close(so3_exp(phi), eye + K + K @ K / 2, 1e-15, "so3_exp near identity")
    R = so3_exp(phi)
    assert_close(so3_vee((R - R.swapaxes(-1, -2)) / 2), phi, 1e-12 * 1e-8, "so3_exp skew part (relative 1e-12)")
    assert_close(so3_left_jacobian(phi), eye + K / 2 + K @ K / 6, 1e-15, "J_l near identity")
    assert_close(so3_left_jacobian_inverse(phi), eye - K / 2 + K @ K / 12, 1e-15, "J_l⁻¹ near identity")
    xi = np.concatenate([v, phi], axis=-1)
    T = se3_exp(xi)
    s = trans_scale(xi)[:, None]
    assert_close(T[:, :3, 3], v + np.cross(phi, v) / 2, 1e-15 * s, "se3_exp translation near identity")
    xi_log = se3_log(T)
    assert_close(xi_log[:, 3:], phi, 1e-9 * 1e-8, "se3_log ω (relative 1e-9)")
    assert_close(xi_log[:, :3], v, 1e-15 * s, "se3_log v")


def test_exactly_zero_and_tiny_angles_without_floating_point_warnings():
    """θ = 0, 1e-12 and the smallest subnormal give exact identities / finite results and
    raise no divide-by-zero or invalid-value warnings anywhere (harmless underflow of θ² is allowed)."""
    v = np.array([3.0, -40.0, 100.0])
    with np.errstate(divide="raise", invalid="raise", over="raise"):
        zero = np.zeros(3)
        np.testing.assert_array_equal(so3_exp(zero), np.eye(3))
        np.testing.assert_array_equal(so3_left_jacobian(zero), np.eye(3))
        np.testing.assert_array_equal(so3_left_jacobian_inverse(zero), np.eye(3))
        np.testing.assert_array_equal(so3_log(np.eye(3)), zero)
        np.testing.assert_array_equal(se3_exp(np.r_[v, zero]), make_pose(np.eye(3), v))
        np.testing.assert_array_equal(se3_log(make_pose(np.eye(3), v)), np.r_[v, zero])
        for theta in (1e-12, 5e-324):
            phi = np.array([0.0, 0.0, theta])
            for out in (so3_exp(phi), so3_left_jacobian(phi), so3_left_jacobian_inverse(phi)):
                assert np.all(np.isfinite(out))
            xi_log = se3_log(se3_exp(np.r_[v, phi]))
            assert_close(xi_log, np.r_[v, phi], np.r_[1e-15 * np.abs(v), 1e-9 * np.abs(phi) + 1e-300], "tiny θ")


def test_continuity_across_small_angle_threshold():
    """Just below, at and just above SMALL_ANGLE the Taylor and closed-form branches
    agree with expm to 1e-14: so3_exp, se3_exp (|v| ≤ 1), J_l (vs block expm),
    J_l⁻¹ J_l = I, and se3_log(se3_exp(ξ)) = ξ."""
    rng = np.random.default_rng(12345)
    thetas = [
        SMALL_ANGLE * (1 - 1e-6),
        np.nextafter(SMALL_ANGLE, 0.0),
        SMALL_ANGLE,
        np.nextafter(SMALL_ANGLE, 1.0),
        SMALL_ANGLE * (1 + 1e-6),
        SMALL_ANGLE * 1.5,
        SMALL_ANGLE * 3,
    ]
    for theta in thetas:
        axes = rng.normal(size=(20, 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        phi = theta * axes
        v = rng.uniform(-1, 1, (20, 3)) / np.sqrt(3)
        xi = np.concatenate([v, phi], axis=1)
        R_ref = loop_apply(lambda p: expm(so3_hat(p)), phi, 1)
        T_ref = loop_apply(lambda x: expm(se3_hat(x)), xi, 1)
        J_ref = loop_apply(left_jacobian_reference, phi, 1)
        assert_close(so3_exp(phi), R_ref, 1e-14, f"so3_exp θ={theta!r}")
        assert_close(se3_exp(xi), T_ref, 1e-14, f"se3_exp θ={theta!r}")
        J = so3_left_jacobian(phi)
        assert_close(J, J_ref, 1e-14, f"J_l θ={theta!r}")
        eye = np.broadcast_to(np.eye(3), J.shape)
        assert_close(so3_left_jacobian_inverse(phi) @ J, eye, 1e-14, f"J_l⁻¹ J_l θ={theta!r}")
        assert_close(se3_log(se3_exp(xi)), xi, 1e-14, f"log(exp(ξ)) θ={theta!r}")


def test_adjoint_block_layout():
    """The documented layout for the (v, ω) order: Ad = [[R, p^ R], [0, R]]."""
    R = so3_exp([0.3, -0.2, 0.5])
    p = np.array([1.0, 2.0, 3.0])
    Ad = se3_adjoint(make_pose(R, p))
    np.testing.assert_array_equal(Ad[:3, :3], R)
    np.testing.assert_array_equal(Ad[3:, 3:], R)
    np.testing.assert_array_equal(Ad[3:, :3], 0.0)
    assert_close(Ad[:3, 3:], so3_hat(p) @ R, 1e-15, "p^ R block")


# ----------------------------------------------------------------------------- quaternions


@pytest.mark.parametrize("regime", REGIMES)
@PROPERTY
@given(data=st.data())
def test_quaternions_match_scipy_and_round_trip(regime, data):
    """quaternion_from_rotation is scipy's Rotation.from_matrix (the same sign too) and
    rotation_from_quaternion its inverse, to rounding, at every angle, π included."""
    from scipy.spatial.transform import Rotation

    from vislam.core.lie import quaternion_from_rotation, rotation_from_quaternion

    phi = data.draw(rotvecs(regime, (7,)))
    R = so3_exp(phi)
    q = quaternion_from_rotation(R)
    np.testing.assert_allclose(q, Rotation.from_matrix(R).as_quat(), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, rtol=0, atol=4 * EPS)
    np.testing.assert_allclose(rotation_from_quaternion(q), R, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rotation_from_quaternion(-3.0 * q), R, rtol=0, atol=1e-14)  # any scale, either sign


def test_quaternion_of_a_not_quite_orthogonal_matrix_is_its_nearest_rotation():
    """A rotation perturbed by 1e-9 (a pose printed with 9 digits) gives the quaternion of
    its nearest rotation, as scipy does, not of the raw entries."""
    from scipy.spatial.transform import Rotation

    from vislam.core.lie import quaternion_from_rotation

    rng = np.random.default_rng(3)
    R = so3_exp(rng.normal(size=(20, 3))) + 1e-9 * rng.normal(size=(20, 3, 3))
    np.testing.assert_allclose(quaternion_from_rotation(R), Rotation.from_matrix(R).as_quat(), rtol=0, atol=1e-13)


def test_so3_log_near_pi_matches_scipy():
    """Past 3 rad so3_log goes through the quaternion; it agrees with scipy's rotvec up to
    the axis sign that θ = π leaves free."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(4)
    axis = rng.normal(size=(50, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    theta = np.concatenate([np.linspace(3.0, math.pi, 49), [0.0]])  # one exact identity in the batch
    phi = theta[:, None] * axis
    R = so3_exp(phi)
    got, ref = so3_log(R), Rotation.from_matrix(R).as_rotvec()
    near_pi = np.pi - theta < 1e-7
    np.testing.assert_allclose(got[~near_pi], ref[~near_pi], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[~near_pi], phi[~near_pi], rtol=0, atol=1e-7)
    sign = np.sign(np.einsum("ki,ki->k", got[near_pi], ref[near_pi]))
    np.testing.assert_allclose(got[near_pi] * sign[:, None], ref[near_pi], rtol=0, atol=1e-12)
