"""Flatness from the mesh estimate: compressed area, ridges with their direction, and the flat flag's
hysteresis (core/flatness.py)."""

import math

import numpy as np
import pytest

from clothd.config import FlatnessConfig
from clothd.core.flatness import (
    FlatnessMonitor,
    Ridge,
    edge_apexes,
    find_ridges,
    measured_apexes,
    quad_shortening,
)
from hwsim.ridges import lay_ridges
from hwsim.scenario import Ridge as HwsimRidge

pytestmark = pytest.mark.clock_free

SIZE_M = (0.25, 0.20)
NX, NY = 12, 12
SPACING_M = (SIZE_M[0] / (NX - 1), SIZE_M[1] / (NY - 1))


def _mesh(theta_rad: float = 0.0, ridge_cols: tuple[int, ...] = (), height_m: float = 0.0) -> np.ndarray:
    """A rest mesh centred on the origin; the columns of edges in ridge_cols are drawn 40 % shorter in x
    (a ridge along t, the slack risen into it) and their nodes lifted; then the mesh is turned by theta."""
    dx = np.full(NX - 1, SPACING_M[0])
    dx[list(ridge_cols)] *= 0.6
    x = np.concatenate([[0.0], np.cumsum(dx)])
    x -= x.mean()
    y = (np.arange(NY) - (NY - 1) / 2) * SPACING_M[1]
    xx, yy = np.meshgrid(x, y)
    z = np.zeros_like(xx)
    for c in ridge_cols:
        z[:, c + 1] = height_m
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.stack([c * xx - s * yy, s * xx + c * yy, z], axis=-1)


def _ridges(nodes: np.ndarray) -> tuple[Ridge, ...]:
    shortening = quad_shortening(nodes[..., :2], SPACING_M)
    return find_ridges(nodes, SPACING_M, shortening, shortening > 0.05, edge_apexes(nodes, SPACING_M, 0.05))


def test_a_flat_mesh_has_no_ridge_and_is_flat() -> None:
    monitor = FlatnessMonitor(FlatnessConfig())
    f = monitor.update(_mesh(0.4), SIZE_M)
    assert f.ridges == () and f.flat and f.max_height_m == 0.0
    assert f.compressed_area_pct == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("theta_rad", [0.0, 0.5, -1.2])
def test_a_ridge_is_found_with_its_position_direction_and_height(theta_rad: float) -> None:
    """A fold narrower than the mesh: all its slack in one column of edges, their nodes on the table. Its
    cloth rises between them, as high as the slack lets it: half of sqrt(L² - d²) for d = 0.6 L."""
    nodes = _mesh(theta_rad, ridge_cols=(7,))
    (ridge,) = _ridges(nodes)
    # The ridge runs along the cloth's t axis, turned by theta; the cloth is short across it.
    assert math.remainder(ridge.direction_rad - (math.pi / 2 + theta_rad), math.pi) == pytest.approx(
        0, abs=1e-6
    )
    assert math.remainder(ridge.compressed_direction_rad - theta_rad, math.pi) == pytest.approx(0, abs=1e-6)
    assert ridge.height_m == pytest.approx(0.4 * SPACING_M[0])
    middles = (nodes[:, 7, :2] + nodes[:, 8, :2]) / 2.0
    assert np.linalg.norm(middles - np.array(ridge.position_m), axis=1).min() < 1e-9
    assert ridge.area_m2 == pytest.approx((NY - 1) * SPACING_M[0] * SPACING_M[1])


def test_a_fold_the_lift_has_raised_peaks_at_its_highest_node() -> None:
    """Two columns 40 % short with the node between them lifted by sqrt(L² - d²): each edge is its rest
    length in 3-D, so the cloth rises no higher than that node."""
    nodes = _mesh(0.0, ridge_cols=(6, 7))
    nodes[:, 7, 2] = 0.8 * SPACING_M[0]
    (ridge,) = _ridges(nodes)
    assert ridge.height_m == pytest.approx(0.8 * SPACING_M[0])
    assert np.linalg.norm(nodes[:, 7, :2] - np.array(ridge.position_m), axis=1).min() < 1e-9


def test_two_ridges_are_two_and_the_higher_comes_first() -> None:
    nodes = _mesh(0.0, ridge_cols=(2, 8))
    nodes[:, 9:, 0] -= 0.2 * SPACING_M[0]  # the second 60 % short: half of sqrt(1 - 0.4²) L high
    ridges = _ridges(nodes)
    assert len(ridges) == 2 and ridges[0].position_m[0] > 0 > ridges[1].position_m[0]
    assert ridges[0].height_m == pytest.approx(0.5 * math.sqrt(1 - 0.4**2) * SPACING_M[0])
    assert ridges[1].height_m == pytest.approx(0.4 * SPACING_M[0])
    monitor = FlatnessMonitor(FlatnessConfig())
    f = monitor.update(nodes, SIZE_M)
    assert f.compressed_area_pct == pytest.approx(100.0 * 2 / (NX - 1))
    assert not f.flat and f.max_height_m == pytest.approx(ridges[0].height_m)


def _laid(
    direction_rad: float, offsets_m: tuple[float, ...], height_m: float = 0.013, sigma_m: float = 0.012
) -> np.ndarray:
    """The default mesh's nodes with a ridge (height, σ) along direction_rad through each point offsets_m
    off the centre, across the ridge (+ to the right of its direction), laid as hwsim lays one: the cloth
    keeps its length over a Gaussian bump."""
    x = (np.arange(NX) - (NX - 1) / 2) * SPACING_M[0]
    y = (np.arange(NY) - (NY - 1) / 2) * SPACING_M[1]
    across = (math.sin(direction_rad), -math.cos(direction_rad))
    ridges = [
        HwsimRidge(
            height_m=height_m,
            sigma_m=sigma_m,
            direction_rad=direction_rad,
            at_m=(at * across[0], at * across[1]),
        )
        for at in offsets_m
    ]
    xy, z = lay_ridges(np.stack(np.meshgrid(x, y), axis=-1), ridges)
    return np.concatenate([xy, z[..., None]], axis=-1)


@pytest.mark.parametrize("direction_deg", [20.0, 45.0, 70.0, 105.0, 135.0, 160.0])
def test_a_ridge_slanted_to_the_threads_is_read_in_its_own_direction(direction_deg: float) -> None:
    """A quad's x and y edges alone cannot tell a ridge at +φ to the threads from one at -φ; read from
    them only, every ridge came out along a mesh axis (45° off, at worst) and half as deep."""
    straight = _ridges(_laid(math.pi / 2, (0.0,)))
    (ridge,) = _ridges(_laid(math.radians(direction_deg), (0.0,)))
    off_deg = math.degrees(math.remainder(ridge.direction_rad - math.radians(direction_deg), math.pi))
    assert abs(off_deg) < 5.0
    assert ridge.slack_m == pytest.approx(straight[0].slack_m, rel=0.3)


@pytest.mark.parametrize("direction_deg", [0.0, 30.0, 105.0])
def test_two_parallel_ridges_a_belt_apart_are_two(direction_deg: float) -> None:
    """70 mm apart their compressed quads touch; read as one ridge, its line ran between them, and the
    belts between them pushed material into both (the flatten bench's one failing start)."""
    gap_m = 0.07
    ridges = _ridges(_laid(math.radians(direction_deg), (-gap_m / 2, gap_m / 2)))
    assert len(ridges) == 2
    across = np.array([math.sin(math.radians(direction_deg)), -math.cos(math.radians(direction_deg))])
    lines_m = sorted(float(r.quad_centres_m.mean(axis=0) @ across) for r in ridges)
    assert lines_m == pytest.approx([-gap_m / 2, gap_m / 2], abs=0.012)


def test_one_broad_ridge_is_not_parted() -> None:
    """Its foot on either side is compressed and its crest hardly (the cloth there is level): on a fine
    mesh those are two bands, one ridge still, no belt fits between them."""
    for direction_deg in range(0, 180, 15):
        ridges = _ridges(_laid(math.radians(direction_deg), (0.0,), height_m=0.02, sigma_m=0.025))
        assert len(ridges) == 1, direction_deg


def test_the_flat_flag_has_hysteresis() -> None:
    cfg = FlatnessConfig(flat_height_m=0.001, flat_compressed_pct=100.0)
    monitor = FlatnessMonitor(cfg)
    bumped = _mesh()
    bumped[5, 5, 2] = 0.0015
    assert not monitor.update(bumped, SIZE_M).flat  # not yet flat: above the bar
    assert monitor.update(_mesh(), SIZE_M).flat
    assert monitor.update(bumped, SIZE_M).flat  # flat stays flat up to twice the bar
    bumped[5, 5, 2] = 0.0025
    assert not monitor.update(bumped, SIZE_M).flat
    monitor.reset()
    assert not monitor.flat


def test_a_ridge_once_seen_is_followed_down_below_what_starts_one() -> None:
    monitor = FlatnessMonitor(FlatnessConfig(compressed_strain=0.05, release_strain=0.025))
    faint = _mesh(0.0, ridge_cols=(7,), height_m=0.0)
    faint[:, 8:, 0] += 0.4 * SPACING_M[0] - 0.03 * SPACING_M[0]  # the ridge's column only 3 % short now
    assert monitor.update(faint, SIZE_M).ridges == ()  # never seen: 3 % does not start a ridge
    assert len(monitor.update(_mesh(0.0, ridge_cols=(7,), height_m=0.005), SIZE_M).ridges) == 1
    assert len(monitor.update(faint, SIZE_M).ridges) == 1  # seen: followed down to 2.5 %
    # ... and pulled at, but the cloth counts as flat again: one column 3 % short and nothing risen is
    # within the bench's flat (0.3 % of the area), and hwsim's cloth keeps as much after a ridge has gone.
    assert monitor.update(faint, SIZE_M).flat
    moved = _mesh(0.0, ridge_cols=(8,), height_m=0.0)  # the faint ridge a column on
    moved[:, 9:, 0] += 0.4 * SPACING_M[0] - 0.03 * SPACING_M[0]
    assert len(monitor.update(moved, SIZE_M).ridges) == 1  # still followed, beside where it was
    assert monitor.update(_mesh(), SIZE_M).ridges == ()


def _corner_unseen(quads: int) -> np.ndarray:
    """quad_seen for the default mesh with the top-right corner's triangle of `quads` rows unseen."""
    seen = np.ones((NY - 1, NX - 1), dtype=bool)
    for k in range(quads):
        seen[-1 - k, NX - 1 - quads + k :] = False
    return seen


def test_a_folded_corner_is_a_flap_where_the_cloth_is_missing() -> None:
    nodes = _mesh()
    flatness = FlatnessMonitor(FlatnessConfig()).update(nodes, SIZE_M, _corner_unseen(3))
    assert len(flatness.flaps) == 1
    flap = flatness.flaps[0]
    assert flap.area_m2 == pytest.approx(6 * SPACING_M[0] * SPACING_M[1])
    # In the corner the unseen quads' centres lie in: their mean.
    centres = (nodes[:-1, :-1, :2] + nodes[1:, 1:, :2]) / 2.0
    assert flap.position_m == pytest.approx(tuple(centres[~_corner_unseen(3)].mean(axis=0)))
    assert flap.position_m[0] > 0.05 and flap.position_m[1] > 0.05
    assert not flatness.flat and not flatness.ridges


def test_unseen_quads_inside_the_cloth_or_a_single_one_at_its_edge_are_no_flap() -> None:
    inside = np.ones((NY - 1, NX - 1), dtype=bool)
    inside[4:6, 4:6] = False  # an arm's shadow, say: the cloth is there, only hidden
    single = _corner_unseen(1)
    monitor = FlatnessMonitor(FlatnessConfig())
    assert monitor.update(_mesh(), SIZE_M, inside).flaps == ()
    flatness = monitor.update(_mesh(), SIZE_M, single)
    assert flatness.flaps == () and flatness.flat


def test_a_sheared_mesh_holds_no_slack() -> None:
    """Trellised by 20°: every quad has lost 6 % of its area, no edge is shorter, and nothing is wrinkled
    (the estimate showed this after a ridge had gone, and never turned flat while it counted area)."""
    i, j = np.meshgrid(np.arange(NX), np.arange(NY))
    shear = math.radians(20.0)
    x = i * SPACING_M[0] + j * SPACING_M[1] * math.sin(shear)
    y = j * SPACING_M[1] * math.cos(shear)
    nodes = np.stack([x - x.mean(), y - y.mean(), np.zeros_like(x)], axis=-1)
    assert np.all(quad_shortening(nodes[..., :2], SPACING_M) < 1e-9)
    flatness = FlatnessMonitor(FlatnessConfig()).update(nodes, SIZE_M)
    assert flatness.compressed_area_pct == 0.0 and flatness.flat and not flatness.ridges


@pytest.mark.parametrize(("rise_m", "table_m"), [(0.0, 0.012), (0.006, 0.010), (-0.009, 0.004)])
def test_an_edge_rises_as_high_as_its_cloth_can_reach(rise_m: float, table_m: float) -> None:
    """The highest point of a 20 mm length of cloth joining two nodes: the top of the ellipse with the
    nodes as foci, found here by sampling every point whose distances to them add up to 20 mm."""
    rest_m = 0.020
    nodes = np.array([[[0.0, 0.0, 0.01], [table_m, 0.0, 0.01 + rise_m]]])
    apexes = edge_apexes(nodes, (rest_m, rest_m), 0.05)
    a, b = nodes[0, 0, [0, 2]], nodes[0, 1, [0, 2]]
    angles = np.linspace(0.0, math.pi, 200_001)
    u = (b - a) / np.linalg.norm(b - a)
    semi_minor = math.sqrt((rest_m / 2) ** 2 - (np.linalg.norm(b - a) / 2) ** 2)
    points = (
        (a + b) / 2
        + np.outer(np.cos(angles), u) * rest_m / 2
        + np.outer(np.sin(angles), [-u[1], u[0]]) * semi_minor
    )
    assert apexes.x_height_m[0, 0] == pytest.approx(points[:, 1].max(), abs=1e-7)
    assert apexes.x_at_m[0, 0] == pytest.approx([table_m / 2, 0.0])


def test_measured_heights_part_two_ridges_whose_shortening_runs_together() -> None:
    # Seven columns of quads equally shorter across (as between two laid ridges 82 mm apart, unfolded),
    # and a second view's heights: two crests with a valley between.
    nodes = _mesh(0.0, ridge_cols=(1, 2, 3, 4, 5, 6, 7))
    shortening = quad_shortening(nodes[..., :2], SPACING_M)
    heights = np.full((NY - 1, NX - 1), 0.0002)
    heights[:, 1], heights[:, 7] = 0.008, 0.005
    compressed = shortening > 0.05
    centres = (nodes[:-1, :-1, :2] + nodes[1:, 1:, :2]) / 2.0
    by_shortening = find_ridges(nodes, SPACING_M, shortening, compressed, measured_apexes(nodes, heights))
    assert len(by_shortening) == 1
    ridges = find_ridges(nodes, SPACING_M, shortening, compressed, measured_apexes(nodes, heights), heights)
    assert [r.height_m for r in ridges] == [0.008, 0.005]
    for ridge, column in zip(ridges, (1, 7), strict=True):
        assert ridge.position_m[0] == pytest.approx(centres[0, column, 0])
        assert ridge.direction_rad == pytest.approx(math.pi / 2, abs=0.1)
