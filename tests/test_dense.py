"""vislam.core.dense: the filter's small solves give numpy.linalg's numbers bit for bit
and its errors, also under the filter's np.errstate(invalid="ignore")."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import solve_triangular

from vislam.core import dense


def spd(rng, shape, m):
    A = rng.normal(size=(*shape, m, m))
    return A @ np.swapaxes(A, -1, -2) + 1e-3 * np.eye(m)


@pytest.mark.parametrize("m", [3, 4, 6, 12])
@pytest.mark.parametrize("batch", [(), (1,), (7,)])
def test_solve_and_cholesky_are_numpys(m, batch):
    rng = np.random.default_rng(m * 10 + len(batch))
    for _ in range(20):
        A = spd(rng, batch, m) * 10.0 ** rng.uniform(-6, 6)
        for b in ([rng.normal(size=m)] if not batch else []) + [rng.normal(size=(*batch, m, 1)),
                                                                 rng.normal(size=(*batch, m, 5))]:
            assert np.array_equal(dense.solve(A, b), np.linalg.solve(A, b))
        assert np.array_equal(dense.cholesky(A), np.linalg.cholesky(A))


def test_solve_lower_is_scipys_in_either_memory_order():
    rng = np.random.default_rng(3)
    L = np.linalg.cholesky(spd(rng, (), 9))
    for b in (rng.normal(size=9), rng.normal(size=(9, 4)), np.asfortranarray(rng.normal(size=(9, 4)))):
        for L_in in (L, np.asfortranarray(L)):
            assert np.array_equal(dense.solve_lower(L_in, b), solve_triangular(L_in, b, lower=True, check_finite=False))
        assert np.allclose(L @ dense.solve_lower(L, b), b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("ignore", [False, True])
def test_singular_and_indefinite_matrices_raise_as_numpy_does(ignore):
    singular = np.array([[1.0, 2.0], [2.0, 4.0]])
    batch = np.stack([np.eye(2), singular])
    indefinite = np.diag([1.0, -1.0])
    with np.errstate(invalid="ignore" if ignore else "warn"):
        for a, b in ((singular, np.ones(2)), (batch, np.ones((2, 2, 1)))):
            with pytest.raises(np.linalg.LinAlgError):
                np.linalg.solve(a, b)
            with pytest.raises(np.linalg.LinAlgError, match="Singular"):
                dense.solve(a, b)
        with pytest.raises(np.linalg.LinAlgError):
            np.linalg.cholesky(indefinite)
        with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
            dense.cholesky(indefinite)
        with pytest.raises(np.linalg.LinAlgError, match="singular"):
            dense.solve_lower(np.diag([1.0, 0.0]), np.ones(2))


def test_the_numpy_installed_takes_the_gufunc_path():
    """The gufuncs answer as numpy.linalg on this numpy (else the module falls back, and
    the filter is slower but the same)."""
    assert dense._GUFUNCS is not None
