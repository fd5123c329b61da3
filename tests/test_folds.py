"""Node heights from inextensibility (clothd/core/folds.py), on hand-built meshes."""

import numpy as np
import pytest

from clothd.core.folds import fold_heights_m

pytestmark = pytest.mark.clock_free

L_M = 0.02  # rest spacing along rows and columns
NX, NY = 10, 6


def _rest() -> np.ndarray:
    x, y = np.meshgrid(np.arange(NX) * L_M, np.arange(NY) * L_M)
    return np.stack([x, y], axis=-1)


def _with_row_x(x_m: list[float], rows: slice = slice(None)) -> np.ndarray:
    """The rest mesh with the given node x positions on the chosen rows."""
    xy = _rest()
    xy[rows, :, 0] = np.asarray(x_m)
    return xy


def test_flat_cloth_has_no_height() -> None:
    np.testing.assert_array_equal(fold_heights_m(_rest(), _rest(), 0.1), 0.0)


def test_compression_within_the_tolerance_is_noise_not_a_fold() -> None:
    x = np.arange(NX) * L_M * 0.95  # every edge 5 % short
    assert np.all(fold_heights_m(_with_row_x(list(x)), _rest(), 0.1) == 0.0)


def test_a_peaked_fold_keeps_its_edges_at_rest_length() -> None:
    d = 0.012  # both edges around node 4 span 12 mm on the table
    x = [0, L_M, 2 * L_M, 3 * L_M, 3 * L_M + d, 3 * L_M + 2 * d]
    x += [x[-1] + L_M * (k + 1) for k in range(NX - len(x))]
    z = fold_heights_m(_with_row_x(x), _rest(), 0.1)
    rise = np.sqrt(L_M**2 - d**2)
    np.testing.assert_allclose(z[:, 4], rise)
    assert np.all(np.delete(z, 4, axis=1) == 0.0)


def test_a_flat_topped_fold_lifts_both_top_nodes() -> None:
    d = 0.012
    x = [0, L_M, 2 * L_M, 2 * L_M + d, 3 * L_M + d, 3 * L_M + 2 * d]  # up, along the top, down
    x += [x[-1] + L_M * (k + 1) for k in range(NX - len(x))]
    z = fold_heights_m(_with_row_x(x), _rest(), 0.1)
    rise = np.sqrt(L_M**2 - d**2)
    np.testing.assert_allclose(z[:, [3, 4]], rise)
    assert np.all(np.delete(z, [3, 4], axis=1) == 0.0)


def test_two_folds_with_cloth_on_the_table_between_them() -> None:
    d = 0.01
    x = [0.0, d, 2 * d, 2 * d + L_M, 2 * d + 2 * L_M, 2 * d + 3 * L_M, 3 * d + 3 * L_M, 4 * d + 3 * L_M]
    x += [x[-1] + L_M * (k + 1) for k in range(NX - len(x))]
    z = fold_heights_m(_with_row_x(x), _rest(), 0.1)
    rise = np.sqrt(L_M**2 - d**2)
    np.testing.assert_allclose(z[:, [1, 6]], rise)
    assert np.all(z[:, 3:5] == 0.0)  # between the folds the cloth lies on the table


def test_a_fold_along_the_rows_is_found_in_the_columns() -> None:
    d = 0.012
    y = [0, L_M, L_M + d, L_M + 2 * d, 2 * L_M + 2 * d, 3 * L_M + 2 * d]
    xy = _rest()
    xy[:, :, 1] = np.asarray(y)[:, None]
    z = fold_heights_m(xy, _rest(), 0.1)
    np.testing.assert_allclose(z[2], np.sqrt(L_M**2 - d**2))


def test_one_noisy_row_does_not_fold_but_an_edge_row_follows_its_fold() -> None:
    d = 0.012
    x = [0, L_M, 2 * L_M, 3 * L_M, 3 * L_M + d, 3 * L_M + 2 * d]
    x += [x[-1] + L_M * (k + 1) for k in range(NX - len(x))]
    lone = fold_heights_m(_with_row_x(x, slice(2, 3)), _rest(), 0.1)
    assert np.all(lone == 0.0)  # one row disagreeing with both neighbours is noise
    edge_lost = _with_row_x(x, slice(1, None))  # every row folded but the edge row 0
    z = fold_heights_m(edge_lost, _rest(), 0.1)
    np.testing.assert_allclose(z[:, 4], np.sqrt(L_M**2 - d**2))
