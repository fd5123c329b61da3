"""Least squares whose normal equations are banded, assembled straight into LAPACK's upper band storage.

The height field (core/stereo.py) and the unfolded layout (core/unfold.py) are grids: each row of their
Jacobians touches a few unknowns close together in the grid's numbering, so JᵀJ is symmetric positive
definite and banded. Building JᵀJ through scipy.sparse cost more than the banded Cholesky solve itself
(a piece's tracker start spent ~12 ms in sparse bookkeeping); summing each row's products into the band
with one bincount costs a fraction of a millisecond.

Band storage (scipy.linalg.solveh_banded, lower=False): ab[band + i - j, j] = A[i, j] for i <= j.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla


def gram_band(cols: np.ndarray, values: np.ndarray, n: int, band: int) -> np.ndarray:
    """JᵀJ in upper band storage (band + 1, n), for a Jacobian whose row r holds values[r] (m, k) at
    columns cols[r] (m, k); every pair of columns in a row must lie within `band` of each other."""
    ci, cj = cols[:, :, None], cols[:, None, :]
    upper = np.broadcast_to(ci <= cj, (len(cols), cols.shape[1], cols.shape[1]))
    products = (values[:, :, None] * values[:, None, :])[upper]
    i, j = np.broadcast_to(ci, upper.shape)[upper], np.broadcast_to(cj, upper.shape)[upper]
    if len(i) and int((j - i).max()) > band:
        raise ValueError(f"a row couples columns {int((j - i).max())} apart, past the band of {band}")
    flat = (band + i - j) * n + j
    return np.bincount(flat, products, minlength=(band + 1) * n).reshape(band + 1, n)


def transpose_times(cols: np.ndarray, values: np.ndarray, r: np.ndarray, n: int) -> np.ndarray:
    """Jᵀr (n,) for the same Jacobian and a vector r (m,)."""
    return np.bincount(cols.ravel(), (values * r[:, None]).ravel(), minlength=n)


def solve_band(ab: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """A⁻¹ rhs for A symmetric positive definite in upper band storage."""
    return np.asarray(sla.solveh_banded(ab, rhs, check_finite=False))
