"""Solves of the filter's small dense systems at the cost of their arithmetic.

A sparse frame's update solves a handful of 4x4 and 6x6 systems; ``numpy.linalg``
spends longer checking and wrapping its arguments than LAPACK spends solving them. The
functions here call the same gufuncs (``numpy.linalg._umath_linalg``) that
``numpy.linalg.solve`` and ``numpy.linalg.cholesky`` call, with the same error state,
so they return the same numbers bit for bit and raise the same
:class:`numpy.linalg.LinAlgError` on a singular (not positive definite) matrix — also
inside the filter's ``np.errstate(invalid="ignore")``. Their inputs are float64 arrays
(the filter's); where numpy lacks the gufuncs, or they do not answer as
``numpy.linalg`` does on a test system at import, these fall back to ``numpy.linalg``.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dtrtrs

__all__ = ["solve", "cholesky", "solve_lower"]


def _raise_singular(err, flag):
    raise np.linalg.LinAlgError("Singular matrix")


def _raise_not_positive_definite(err, flag):
    raise np.linalg.LinAlgError("Matrix is not positive definite")


def _private_gufuncs():
    """numpy's (solve, solve1, cholesky_lo) gufuncs, or None when this numpy lacks them or
    they do not give numpy.linalg's answers on a small system (they are private: checked
    once, here)."""
    try:
        from numpy.linalg import _umath_linalg

        gufuncs = _umath_linalg.solve, _umath_linalg.solve1, _umath_linalg.cholesky_lo
        a, b = np.array([[4.0, 1.0], [1.0, 3.0]]), np.array([[1.0], [2.0]])
        ok = (np.array_equal(gufuncs[0](a, b, signature="dd->d"), np.linalg.solve(a, b))
              and np.array_equal(gufuncs[1](a, b[:, 0], signature="dd->d"), np.linalg.solve(a, b[:, 0]))
              and np.array_equal(gufuncs[2](a, signature="d->d"), np.linalg.cholesky(a)))
    except Exception:  # pragma: no cover - another numpy
        return None
    return gufuncs if ok else None


_GUFUNCS = _private_gufuncs()
_SOLVE, _SOLVE1, _CHOLESKY = _GUFUNCS or (None, None, None)


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``numpy.linalg.solve(a, b)`` for float64 ``a`` (..., M, M) and ``b`` (M,) or
    (..., M, K)."""
    if _SOLVE is None:  # pragma: no cover
        return np.linalg.solve(a, b)
    with np.errstate(call=_raise_singular, invalid="call", over="ignore", divide="ignore", under="ignore"):
        return (_SOLVE1 if b.ndim == 1 else _SOLVE)(a, b, signature="dd->d")


def cholesky(a: np.ndarray) -> np.ndarray:
    """``numpy.linalg.cholesky(a)`` (the lower factor; reads the lower triangle) for
    float64 ``a`` (..., M, M)."""
    if _SOLVE is None:  # pragma: no cover
        return np.linalg.cholesky(a)
    with np.errstate(call=_raise_not_positive_definite, invalid="call", over="ignore", divide="ignore",
                     under="ignore"):
        return _CHOLESKY(a, signature="d->d")


def solve_lower(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """L⁻¹ b for a lower-triangular float64 L (M, M) and ``b`` (M,) or (M, K):
    ``scipy.linalg.solve_triangular(L, b, lower=True, check_finite=False)`` without its
    validation and dispatch — the same LAPACK call (trtrs), hence the same result."""
    if L.flags.f_contiguous:
        x, info = dtrtrs(L, b, lower=1, trans=0)
    else:  # trtrs expects Fortran order: solve the transposed system with Lᵀ's view
        x, info = dtrtrs(L.T, b, lower=0, trans=1)
    if info > 0:
        raise np.linalg.LinAlgError(f"singular matrix: resolution failed at diagonal {info - 1}")
    if info < 0:
        raise ValueError(f"illegal value in {-info}-th argument of internal trtrs")
    return x
