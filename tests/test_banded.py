"""Banded normal equations (clothd/core/banded.py) against the dense ones."""

import numpy as np
import pytest

from clothd.core.banded import gram_band, solve_band, transpose_times

pytestmark = pytest.mark.clock_free


def _dense(cols: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    J = np.zeros((len(cols), n))
    for r, (c, v) in enumerate(zip(cols, values, strict=True)):
        np.add.at(J[r], c, v)
    return J


def test_the_band_holds_the_normal_equations_and_solves_them() -> None:
    rng = np.random.default_rng(0)
    n, band = 40, 5
    first = rng.integers(0, n - band, 300)
    cols = np.stack([first, first + rng.integers(0, band + 1, 300), first + band], axis=1)
    cols[::7, 1] = cols[::7, 0]  # a column twice in a row adds up
    values = rng.normal(size=cols.shape)
    J = _dense(cols, values, n)
    ab = gram_band(cols, values, n, band)
    A = J.T @ J
    for d in range(band + 1):  # ab's row band - d holds A's d-th superdiagonal
        assert np.allclose(ab[band - d, d:], np.diag(A, d))
    r = rng.normal(size=len(cols))
    assert np.allclose(transpose_times(cols, values, r, n), J.T @ r)
    ab[-1] += 1.0
    assert np.allclose(solve_band(ab, J.T @ r), np.linalg.solve(A + np.eye(n), J.T @ r))


def test_a_row_wider_than_the_band_is_refused() -> None:
    with pytest.raises(ValueError, match="past the band of 2"):
        gram_band(np.array([[0, 3]]), np.ones((1, 2)), 5, 2)
