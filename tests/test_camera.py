"""Property tests of the report's stereo camera model ``vislam.core.camera``.

``z = M π(q)`` with ``π(q) = q / q_z`` and the report's 4x4 stereo matrix M; its
inverse (the landmark initialization) and both Jacobians. Calibrations: the KITTI left
camera (K below, baseline 0.537 m) and random ones (focal 300–2000 px, principal point
anywhere on a 1500x600 image, baseline 0.1–1 m). Points are drawn in front of the camera
at depths 1–200 m (|x| ≤ 2 z, |y| ≤ z), in batches of leading shape (), (5,), (2, 3).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from vislam.core.camera import StereoCamera, dpi_dq, stereo_matrix
from vislam.errors import GeometryError, VislamError

KITTI_K = np.array([[707.0912, 0.0, 601.8873], [0.0, 707.0912, 183.1104], [0.0, 0.0, 1.0]])
KITTI_BASELINE_M = 0.537
SHAPES = ((), (5,), (2, 3))

PROPERTY = settings(max_examples=40, deadline=None)


# ----------------------------------------------------------------------------- strategies


@st.composite
def cameras(draw):
    if draw(st.booleans()):
        return StereoCamera(KITTI_K, KITTI_BASELINE_M)
    fsu = draw(st.floats(300.0, 2000.0))
    fsv = fsu * draw(st.floats(0.8, 1.25))
    cu = draw(st.floats(0.0, 1500.0))
    cv = draw(st.floats(0.0, 600.0))
    b = draw(st.floats(0.1, 1.0))
    return StereoCamera(np.array([[fsu, 0.0, cu], [0.0, fsv, cv], [0.0, 0.0, 1.0]]), b)


@st.composite
def points_in_front(draw, shape=None):
    """Points (*shape, 3) in the left camera frame, depth 1–200 m, |x| ≤ 2z, |y| ≤ z."""
    if shape is None:
        shape = draw(st.sampled_from(SHAPES))
    n = math.prod(shape)
    z = draw(hnp.arrays(np.float64, (n,), elements=st.floats(1.0, 200.0)))
    a = draw(hnp.arrays(np.float64, (n,), elements=st.floats(-2.0, 2.0)))
    c = draw(hnp.arrays(np.float64, (n,), elements=st.floats(-1.0, 1.0)))
    return np.stack([a * z, c * z, z], axis=-1).reshape(tuple(shape) + (3,))


def assert_close(actual, desired, atol, what=""):
    actual = np.asarray(actual, dtype=np.float64)
    desired = np.asarray(desired, dtype=np.float64)
    assert actual.shape == desired.shape, f"{what}: shape {actual.shape} != {desired.shape}"
    assert np.all(np.isfinite(actual)), f"{what}: non-finite values"
    err = np.abs(actual - desired)
    atol = np.broadcast_to(np.asarray(atol, dtype=np.float64), err.shape)
    if np.any(err > atol):
        i = np.unravel_index(np.argmax(err / atol), err.shape)
        raise AssertionError(f"{what}: error {err[i]:.3g} > tol {atol[i]:.3g} at {i} (x{err[i] / atol[i]:.3g})")


def homogeneous(p):
    return np.concatenate([p, np.ones(p.shape[:-1] + (1,))], axis=-1)


def central_fd(f, x0, steps):
    """Central differences of f: (..., n) -> (..., m) at x0 with per-element steps (...,);
    returns (..., m, n)."""
    cols = []
    for k in range(x0.shape[-1]):
        e = np.zeros(x0.shape)
        e[..., k] = steps
        cols.append((f(x0 + e) - f(x0 - e)) / (2 * steps[..., None]))
    return np.stack(cols, axis=-1)


def per_element_scale(J):
    """max |J| per batch element, broadcast back over the matrix."""
    return np.max(np.abs(J), axis=(-2, -1), keepdims=True)


# ----------------------------------------------------------------------------- the matrix M


def test_kitti_stereo_matrix_layout():
    """M = [[fsu, 0, cu, 0], [0, fsv, cv, 0], [fsu, 0, cu, -fsu b], [0, fsv, cv, 0]]."""
    cam = StereoCamera(KITTI_K, KITTI_BASELINE_M)
    fsu, fsv, cu, cv, b = 707.0912, 707.0912, 601.8873, 183.1104, 0.537
    expected = np.array(
        [[fsu, 0, cu, 0], [0, fsv, cv, 0], [fsu, 0, cu, -fsu * b], [0, fsv, cv, 0]], dtype=np.float64
    )
    np.testing.assert_array_equal(cam.M, expected)
    np.testing.assert_array_equal(stereo_matrix(KITTI_K, KITTI_BASELINE_M), expected)
    assert cam.M[2, 3] == pytest.approx(-379.7079744, rel=1e-15)
    assert (cam.fsu, cam.fsv, cam.cu, cam.cv, cam.baseline_m) == (fsu, fsv, cu, cv, b)
    with pytest.raises(ValueError):
        cam.M[0, 0] = 1.0  # read-only: a camera cannot be changed behind the filter's back
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0


@PROPERTY
@given(cam=cameras())
def test_stereo_matrix_layout_random_calibrations(cam):
    fsu, fsv, cu, cv, b = cam.fsu, cam.fsv, cam.cu, cam.cv, cam.baseline_m
    assert (fsu, fsv, cu, cv) == (cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2])
    expected = np.array([[fsu, 0, cu, 0], [0, fsv, cv, 0], [fsu, 0, cu, -fsu * b], [0, fsv, cv, 0]])
    np.testing.assert_array_equal(cam.M, expected)
    np.testing.assert_array_equal(stereo_matrix(cam.K, b), expected)


# ----------------------------------------------------------------------------- projection


@PROPERTY
@given(cam=cameras(), p=points_in_front())
def test_projection_is_two_rectified_pinholes(cam, p):
    """project(p) = [fsu x/z + cu, fsv y/z + cv, fsu (x − b)/z + cu, fsv y/z + cv]
    (to 1e-12 (1 + |pixel|)); vL = vR exactly; uL − uR = fsu b / z (to 8 ε max(|uL|, |uR|));
    batched output equals the loop over single points (1e-13 of the terms summed)."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    fsu, fsv, cu, cv, b = cam.fsu, cam.fsv, cam.cu, cam.cv, cam.baseline_m
    pix = cam.project(p)
    expected = np.stack([fsu * x / z + cu, fsv * y / z + cv, fsu * (x - b) / z + cu, fsv * y / z + cv], -1)
    assert_close(pix, expected, 1e-12 * (1 + np.abs(expected)), "two-pinhole model")
    np.testing.assert_array_equal(pix[..., 1], pix[..., 3])
    disparity = pix[..., 0] - pix[..., 2]
    np.testing.assert_array_equal(cam.disparity_px(pix), disparity)
    assert_close(
        disparity, fsu * b / z, 8 * np.finfo(float).eps * np.maximum(np.abs(pix[..., 0]), np.abs(pix[..., 2])),
        "uL − uR = fsu b / z",
    )
    assert np.all(disparity > 0)
    # same from homogeneous input, and invariant to the scale of q; rounding is relative to
    # the terms summed (f x/z and the principal point), not to their sum, which can cancel
    # (uL ≈ 0.05 px from cu = 985 px and f x/z ≈ −985 px)
    q = homogeneous(p)
    terms = 1 + np.abs(pix) + np.abs(np.array([cu, cv, cu, cv]))
    assert_close(cam.project(q), pix, 1e-13 * terms, "homogeneous q")
    assert_close(cam.project(37.5 * q), pix, 1e-13 * terms, "project(c q) = project(q)")
    for idx in np.ndindex(*p.shape[:-1]):
        assert_close(pix[idx], cam.project(p[idx]), 1e-13 * terms[idx], "batched vs single")


@PROPERTY
@given(cam=cameras(), p=points_in_front())
def test_triangulate_inverts_project(cam, p):
    """triangulate(project(p)) = p to relative 1e-10 (the brief asks 1e-9; rounding of
    uL − uR costs ≤ ε |uL| / d ≈ 2.2e-16 · 2100 px / 0.15 px = 3e-12 in the worst corner,
    a 200 m point at 0.15 px disparity); project(triangulate(z)) = z for observations
    with vR = vL; batched equals single."""
    pix = cam.project(p)
    p_back = cam.triangulate(pix)
    assert_close(p_back, p, 1e-10 * np.linalg.norm(p, axis=-1, keepdims=True), "triangulate(project(p))")
    assert_close(cam.project(p_back), pix, 1e-10 * (1 + np.abs(pix)), "project(triangulate(z))")
    for idx in np.ndindex(*p.shape[:-1]):
        # per point: a coordinate near 0 comes from (u − c) z / f and rounds like z
        assert_close(p_back[idx], cam.triangulate(pix[idx]), 1e-13 * (1 + np.linalg.norm(p[idx])),
                     "batched vs single")


# ----------------------------------------------------------------------------- Jacobians


@PROPERTY
@given(cam=cameras(), p=points_in_front(), lam=st.floats(0.1, 10.0))
def test_projection_jacobian_matches_finite_differences(cam, p, lam):
    """M dπ/dq vs central differences of project wrt homogeneous q = λ [p, 1] (all four
    components, λ ≠ 1 too) and wrt the 3-D point (first 3 columns); dπ/dq vs central
    differences of q / q_z. Steps 1e-5 q_z; tolerance 1e-6 max|J| per point."""
    q = lam * homogeneous(p)
    J = cam.projection_jacobian(q)
    steps = 1e-5 * q[..., 2]
    J_fd = central_fd(cam.project, q, steps)
    assert_close(J, J_fd, 1e-6 * per_element_scale(J), "M dπ/dq vs FD (homogeneous q)")

    J3 = cam.projection_jacobian(p)[..., :3]
    J3_fd = central_fd(cam.project, p, 1e-5 * p[..., 2])
    assert_close(J3, J3_fd, 1e-6 * per_element_scale(J3), "M dπ/dq[:, :3] vs FD (3-D point)")

    D = dpi_dq(q)
    D_fd = central_fd(lambda x: x / x[..., 2:3], q, steps)
    assert_close(D, D_fd, 1e-6 * per_element_scale(D), "dπ/dq vs FD")
    np.testing.assert_array_equal(cam.projection_jacobian(q), cam.M @ D)
    for idx in np.ndindex(*p.shape[:-1]):
        assert_close(J[idx], cam.projection_jacobian(q[idx]), 1e-13 * per_element_scale(J[idx]), "batched")


@PROPERTY
@given(cam=cameras(), p=points_in_front())
def test_triangulation_jacobian_matches_finite_differences(cam, p):
    """d triangulate / d[uL, vL, uR, vR] vs central differences (step 1e-4 × disparity,
    tolerance 1e-6 max|J| per point); vR does not enter (its column is exactly 0)."""
    pix = cam.project(p)
    G = cam.triangulation_jacobian(pix)
    steps = 1e-4 * cam.disparity_px(pix)
    G_fd = central_fd(cam.triangulate, pix, steps)
    assert_close(G, G_fd, 1e-6 * per_element_scale(G), "triangulation Jacobian vs FD")
    np.testing.assert_array_equal(G[..., :, 3], 0.0)
    for idx in np.ndindex(*p.shape[:-1]):
        assert_close(G[idx], cam.triangulation_jacobian(pix[idx]), 1e-13 * per_element_scale(G[idx]), "batched")


@PROPERTY
@given(cam=cameras(), p=points_in_front())
def test_triangulation_jacobian_inverts_projection_jacobian(cam, p):
    """triangulate ∘ project = id, so by the chain rule
    triangulation_jacobian(project(p)) @ (M dπ/dq)[:, :3] = I₃ (to 1e-10; measured ≤ 2e-12)."""
    G = cam.triangulation_jacobian(cam.project(p))
    H = cam.projection_jacobian(p)[..., :3]
    assert_close(G @ H, np.broadcast_to(np.eye(3), G.shape[:-2] + (3, 3)), 1e-10, "G H = I")


# ----------------------------------------------------------------------------- refused input


def _kitti():
    return StereoCamera(KITTI_K, KITTI_BASELINE_M)


@pytest.mark.parametrize(
    "pixels",
    [
        [700.0, 200.0, 700.0, 200.0],  # zero disparity (point at infinity)
        [650.0, 200.0, 700.0, 200.0],  # negative disparity
        [np.nan, 200.0, 690.0, 200.0],
        [700.0, np.nan, 690.0, 200.0],
        [700.0, 200.0, np.nan, 200.0],
        [700.0, 200.0, 690.0, np.nan],
        [np.inf, 200.0, 690.0, 200.0],
        [700.0, 200.0, -np.inf, 200.0],
        [5e-324, 200.0, 0.0, 200.0],  # subnormal disparity: depth would overflow to inf
        [1e308, 200.0, -1e308, 200.0],  # disparity overflows to inf: depth would be 0
    ],
)
def test_triangulate_refuses_degenerate_observations(pixels):
    cam = _kitti()
    good = cam.project(np.array([[1.0, 0.5, 10.0], [-3.0, 1.0, 40.0]]))
    for obs in (np.array(pixels), np.vstack([good, pixels]), np.vstack([good, pixels])[None]):
        with pytest.raises(GeometryError):
            cam.triangulate(obs)
        with pytest.raises(GeometryError):
            cam.triangulation_jacobian(obs)


@pytest.mark.parametrize(
    "point",
    [
        [1.0, 2.0, 0.0],
        [1.0, 2.0, -0.0],
        [1.0, 2.0, -5.0],
        [1.0, 2.0, -1e-300],
        [1.0, 2.0, np.nan],
        [np.nan, 2.0, 10.0],
        [1.0, np.inf, 10.0],
        [1.0, 2.0, np.inf],
        [1e10, 2.0, 1e-300],  # in front, but so close to the camera plane that π(q) overflows
        [1.0, 2.0, 5e-324],
    ],
)
def test_projection_refuses_points_at_or_behind_the_camera(point):
    cam = _kitti()
    good = np.array([[1.0, 0.5, 10.0], [-3.0, 1.0, 40.0]])
    for q in (np.array(point), np.vstack([good, point]), homogeneous(np.vstack([good, point]))[None]):
        for fn in (cam.project, cam.projection_jacobian, dpi_dq):
            with pytest.raises(GeometryError):
                fn(q)


def test_geometry_error_is_a_vislam_error():
    """The CLI turns VislamError into a one-line message; GeometryError must be one."""
    with pytest.raises(VislamError, match="disparity"):
        _kitti().triangulate([600.0, 200.0, 610.0, 200.0])


_ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=200, deadline=None)
@given(
    pixels=hnp.arrays(np.float64, st.sampled_from([(4,), (3, 4)]), elements=_ANY_FLOAT),
    points=hnp.arrays(np.float64, st.sampled_from([(3,), (3, 3), (2, 4)]), elements=_ANY_FLOAT),
)
def test_never_returns_inf_or_nan(pixels, points):
    """For arbitrary float input (any magnitude, inf, NaN) every function either raises
    GeometryError or returns finite numbers, without emitting numpy RuntimeWarnings."""
    cam = _kitti()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for fn, x in (
            (cam.triangulate, pixels),
            (cam.triangulation_jacobian, pixels),
            (cam.project, points),
            (cam.projection_jacobian, points),
            (dpi_dq, points),
        ):
            try:
                out = fn(x)
            except GeometryError:
                continue
            assert np.all(np.isfinite(out)), f"{fn.__name__}({x!r}) = {out!r}"
