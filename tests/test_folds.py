"""Node heights from inextensibility (clothd/core/folds.py), on hand-built meshes."""

import numpy as np
import pytest

from clothd.core.folds import (
    HELD_TOLERANCE_FRACTION,
    even_slack_lengths_m,
    fold_heights_m,
    fold_reading,
    within_reach_m,
)

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


def test_a_fold_dying_down_holds_until_its_edges_are_nearly_back_to_length() -> None:
    def peaked(short: float) -> np.ndarray:  # both edges around node 4 short by this fraction
        d = L_M * (1.0 - short)
        x = [0, L_M, 2 * L_M, 3 * L_M, 3 * L_M + d, 3 * L_M + 2 * d]
        return _with_row_x(x + [x[-1] + L_M * (k + 1) for k in range(NX - len(x))])

    risen, folded = fold_reading(peaked(0.2), _rest(), 0.1)
    assert np.all(risen[:, 4] > 0.0)
    dying = peaked(0.06)  # within the tolerance, past the held fraction of it
    assert np.all(fold_heights_m(dying, _rest(), 0.1) == 0.0)  # a fold never seen is noise
    held, folded = fold_reading(dying, _rest(), 0.1, held=folded)
    np.testing.assert_allclose(held[:, 4], L_M * np.sqrt(1.0 - 0.94**2))
    back = peaked(0.9 * HELD_TOLERANCE_FRACTION * 0.1)
    assert np.all(fold_reading(back, _rest(), 0.1, held=folded)[0] == 0.0)


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


def _pleat_row_x(foot_m: float) -> list[float]:
    """A row whose nodes 4 and 5 stand on the flanks of a narrow pleat between nodes 3 and 6: each
    flank edge lies foot_m on the table, the edge over the crest 2 mm."""
    x = [0.0, L_M, 2 * L_M, 3 * L_M, 3 * L_M + foot_m, 3 * L_M + foot_m + 0.002, 3 * L_M + 2 * foot_m + 0.002]
    return x + [x[-1] + L_M * (k + 1) for k in range(NX - len(x))]


def _quads_with_crest(height_m: float, columns: list[int]) -> np.ndarray:
    """Quad heights (NY-1, NX-1): flat but for the given quad columns, measured height_m high."""
    q = np.full((NY - 1, NX - 1), 0.0003)
    q[:, columns] = height_m
    return q


def test_a_measured_pleat_stands_on_its_feet_not_on_straight_edges() -> None:
    foot = 0.005  # a vertical pleat: each flank edge 5 mm on the table, its remaining 15 mm straight up
    xy = _with_row_x(_pleat_row_x(foot))
    slack = 3 * L_M - (2 * foot + 0.002)
    crest = slack / 2  # as tall as half its slack: vertical
    straight = fold_heights_m(xy, _rest(), 0.1)
    measured = fold_heights_m(xy, _rest(), 0.1, _quads_with_crest(crest, [3, 4, 5]))
    np.testing.assert_allclose(straight[:, [4, 5]], np.sqrt(L_M**2 - foot**2))  # 19.4 mm
    # On the flank, as high as the slack before it: 15 mm, each flank edge's own (the crest edge holds 18).
    np.testing.assert_allclose(measured[:, [4, 5]], L_M - foot)
    assert np.all(np.delete(measured, [4, 5], axis=1) == 0.0)


def test_a_measured_pleat_holds_its_unseen_flank_nodes_to_an_even_share_of_its_slack() -> None:
    foot = 0.005
    x = _pleat_row_x(foot)
    x[5] += 0.003  # a flank node no camera sees, spread 3 mm out: its outer edge 3 mm shorter
    crest = (3 * L_M - (2 * foot + 0.002)) / 2
    target = even_slack_lengths_m(_with_row_x(x), _rest(), _quads_with_crest(crest, [3, 4, 5]))
    share = (3 * L_M - (2 * foot + 0.002)) / 3  # the run's 48 mm of slack over its three edges
    np.testing.assert_allclose(target.rows[:, 3:6], L_M - share)
    assert np.all(np.isnan(np.delete(target.rows, [3, 4, 5], axis=1)))
    assert np.all(np.isnan(target.cols))  # along the pleat the cloth keeps its length: no run holds slack


def test_a_rise_measured_without_slack_to_share_holds_nothing() -> None:
    target = even_slack_lengths_m(_rest(), _rest(), _quads_with_crest(0.004, [3, 4, 5]))
    assert np.all(np.isnan(target.rows)) and np.all(np.isnan(target.cols))


def test_a_quad_higher_than_the_cloth_can_reach_was_something_else() -> None:
    x = list(np.arange(NX) * L_M)
    x[5] -= 0.0008  # 1.6 mm of slack in every row: no point of a row reaches 0.5 sqrt(180² - 178.4²) = 12 mm
    x[6:] = [v - 0.0016 for v in x[6:]]
    xy = _with_row_x(x)
    arm = _quads_with_crest(0.25, [4, 5])  # an arm over the cloth, 250 mm up
    np.testing.assert_array_equal(within_reach_m(xy, _rest(), arm), np.where(arm > 0.1, 0.0, arm))
    assert np.all(fold_heights_m(xy, _rest(), 0.1, arm) == 0.0)  # not the cloth risen: no fold
    low = _quads_with_crest(0.004, [4, 5])
    np.testing.assert_array_equal(within_reach_m(xy, _rest(), low), low)
    assert fold_heights_m(xy, _rest(), 0.1, low)[:, 5].min() > 0.0


def test_a_measured_broad_ridge_rises_as_its_straight_edges() -> None:
    d = 0.016  # a low peak at node 4: 20 % short, 12 mm high on straight edges
    x = [0, L_M, 2 * L_M, 3 * L_M, 3 * L_M + d, 3 * L_M + 2 * d]
    x += [x[-1] + L_M * (k + 1) for k in range(NX - len(x))]
    xy = _with_row_x(x)
    straight = fold_heights_m(xy, _rest(), 0.1)
    measured = fold_heights_m(xy, _rest(), 0.1, _quads_with_crest(straight.max(), [3, 4]))
    np.testing.assert_allclose(measured, straight)


def test_a_measured_rise_folds_edges_shorter_than_the_noise_tolerance() -> None:
    x = list(np.arange(NX) * L_M)
    x[5] -= 0.0008  # the edges either side of node 5 are 4 % short each: within the tolerance
    x[6:] = [v - 0.0016 for v in x[6:]]
    xy = _with_row_x(x)
    assert np.all(fold_heights_m(xy, _rest(), 0.1) == 0.0)
    flat = fold_heights_m(xy, _rest(), 0.1, _quads_with_crest(0.0003, []))
    assert np.all(flat == 0.0)  # measured flat: the tolerance stands
    risen = fold_heights_m(xy, _rest(), 0.1, _quads_with_crest(0.004, [4, 5]))
    np.testing.assert_allclose(risen[:, 5], 0.004)  # a peak at node 5 as high as the crest measured
    assert np.all(np.delete(risen, 5, axis=1) == 0.0)


def test_a_noisy_edge_row_takes_its_neighbours_fold_shape() -> None:
    foot = 0.005
    xy = _with_row_x(_pleat_row_x(foot))
    xy[0, 5:, 0] += 0.004  # the edge row reads its flank 4 mm wider: less slack, a steeper rise per slack
    crest = (3 * L_M - (2 * foot + 0.002)) / 2
    z = fold_heights_m(xy, _rest(), 0.1, _quads_with_crest(crest, [3, 4, 5]))
    # Its flank edge's slack at its neighbours' rise per slack (1: vertical), not its own steeper one.
    np.testing.assert_allclose(z[0, 4], L_M - foot, atol=1e-9)
