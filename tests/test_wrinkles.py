"""Ridges in hwsim's cloth: laid anywhere, in any direction, without stretching the sheet; kept the way a
table keeps a wrinkle while the belts are still, and flattened when the belts pull its two sides apart
(docs/hwsim.md, "Friction"); an overhanging ridge is refused with its key."""

import math

import numpy as np
import pytest

from hwsim import scenario as scenarios
from hwsim.cloth_grid import FLAP_THICKNESS_M, ClothGrid
from hwsim.ridges import lay_ridges
from hwsim.stretch import stretch_under_turn
from hwsim.world import World

pytestmark = pytest.mark.clock_free

CELL_CLOTH = scenarios.load("cell").cloth.model_dump()  # the live cell's cloth, as `hwsim serve` runs it
RECORDED_CLOTH = scenarios.ClothSpec().model_dump()  # the finer cloth `hwsim record`'s scenarios default to
ELASTIC_CLOTH = CELL_CLOTH | {"bending_hysteresis_n": 0.0}  # ... without the yarns' friction in bending
DENIM_BENDING_HYSTERESIS_N = scenarios.load("cell-yarn-friction").cloth.bending_hysteresis_n


def _world(ridges: list[dict[str, object]], **overrides: object) -> World:
    data: dict[str, object] = {"name": "t", "duration_s": 90.0, "settle_s": 0.0, "cloth": CELL_CLOTH}
    data["initial_pose"] = {"ridges": ridges}
    data.update(overrides)
    return World(scenarios.parse(data))


def _height_m(world: World) -> float:
    return float(world.cloth.positions_m()[..., 2].max())


@pytest.mark.slow
@pytest.mark.parametrize(
    "ridge",
    [
        {"height_m": 0.010},
        {"height_m": 0.020, "sigma_m": 0.016},
        {"height_m": 0.012, "at_m": [0.0, 0.0], "direction_rad": 1.2},
        {"height_m": 0.010, "direction_rad": math.pi / 4},
    ],
    ids=["10mm", "20mm", "12mm-oblique", "10mm-diagonal"],
)
def test_a_laid_in_ridge_stays_for_a_minute_on_still_belts(ridge: dict[str, object]) -> None:
    world = _world([ridge])
    laid_m = _height_m(world)
    assert laid_m > 0.005
    lowest_m = laid_m
    for _ in range(60 * round(world.scenario.fps)):
        world.step()
        lowest_m = min(lowest_m, _height_m(world))
    print(f"ridge {ridge}: laid {laid_m * 1e3:.2f} mm, lowest over 60 s {lowest_m * 1e3:.2f} mm")
    assert lowest_m >= 0.9 * laid_m


def _lowest_over_m(world: World, seconds: float) -> float:
    lowest_m = _height_m(world)
    for _ in range(round(seconds * world.scenario.fps)):
        world.step()
        lowest_m = min(lowest_m, _height_m(world))
    return lowest_m


@pytest.mark.slow
@pytest.mark.parametrize("direction_deg", [30.0, 105.0])
def test_a_small_ridge_across_the_threads_is_held_by_the_yarns_friction(direction_deg: float) -> None:
    """5 mm, bent one cell wide, at an angle to the rows and columns: the yarns' friction in bending (the
    live cell's, and a typical denim's) holds it; without it (purely elastic bending, as before) it pushes
    its feet apart and falls flat."""
    ridge = {"height_m": 0.005, "sigma_m": 0.008, "direction_rad": math.radians(direction_deg)}
    assert CELL_CLOTH["bending_hysteresis_n"] > 0.0
    for hysteresis_n in (CELL_CLOTH["bending_hysteresis_n"], DENIM_BENDING_HYSTERESIS_N):
        world = _world([ridge], cloth=CELL_CLOTH | {"bending_hysteresis_n": hysteresis_n})
        laid_m = _height_m(world)
        assert laid_m > 0.003
        assert _lowest_over_m(world, 20.0) >= 0.9 * laid_m
    elastic = _world([ridge], cloth=ELASTIC_CLOTH)
    elastic_laid_m = _height_m(elastic)
    assert _lowest_over_m(elastic, 20.0) < 0.5 * elastic_laid_m


@pytest.mark.slow
def test_the_recorded_scenarios_cloth_holds_an_oblique_ridge_too() -> None:
    """`hwsim record`'s finer cloth (5 mm, 1 ms substeps) has the yarns' friction by default as well: it
    holds a 10 mm ridge at 30° off centre, which without it slides flat within 10 s."""
    ridge = {"height_m": 0.010, "sigma_m": 0.012, "direction_rad": math.radians(30.0), "at_m": [0.04, -0.03]}
    assert RECORDED_CLOTH["bending_hysteresis_n"] > 0.0
    assert RECORDED_CLOTH["spacing_m"] < CELL_CLOTH["spacing_m"]
    world = _world([ridge], cloth=RECORDED_CLOTH)
    laid_m = _height_m(world)
    assert laid_m > 0.005
    assert _lowest_over_m(world, 10.0) >= 0.9 * laid_m
    elastic = _world([ridge], cloth=RECORDED_CLOTH | {"bending_hysteresis_n": 0.0})
    elastic_laid_m = _height_m(elastic)
    assert elastic_laid_m > 0.005
    assert _lowest_over_m(elastic, 10.0) < 0.5 * elastic_laid_m


@pytest.mark.slow
@pytest.mark.parametrize("yarn_friction", [False, True], ids=["elastic", "yarn-friction"])
def test_a_ridge_flattens_when_the_belts_pull_its_sides_apart(yarn_friction: bool) -> None:
    pull_m_s = 0.03
    left, right = [-0.3, -0.3, -0.01, 0.3], [0.01, -0.3, 0.3, 0.3]
    timeline = [
        {"t_s": 0.0, "modules": {"region_m": left}, "speed_m_s": pull_m_s, "heading_rad": math.pi},
        {"t_s": 0.0, "modules": {"region_m": right}, "speed_m_s": pull_m_s, "heading_rad": 0.0},
        {"t_s": 1.0, "modules": {"all": True}, "speed_m_s": 0.0, "heading_rad": 0.0},
    ]
    hysteresis_n = DENIM_BENDING_HYSTERESIS_N if yarn_friction else 0.0
    world = _world(
        [{"height_m": 0.010}], timeline=timeline, cloth=CELL_CLOTH | {"bending_hysteresis_n": hysteresis_n}
    )
    assert _height_m(world) > 0.005
    for _ in range(round(2.0 * world.scenario.fps)):
        world.step()
    assert _height_m(world) < 0.001


def test_the_live_cloth_does_not_stretch_when_the_belts_turn_it() -> None:
    """Denim barely stretches under friction; at 2 ms substeps the solver left edges 3.8 % long here."""
    cloth = scenarios.load("cell").cloth
    stretch = stretch_under_turn("cell", cloth.substep_s, cloth.stretch_iterations, frames=30)
    assert stretch.max_strain < 0.01


@pytest.mark.parametrize(
    "slack_m, direction_rad", [(0.006, 0.1), (0.006, 1.9), (0.008, 1.31), (0.008, math.pi / 4)]
)
def test_a_push_leaves_a_ridge_that_stays(slack_m: float, direction_rad: float) -> None:
    """The hands draw the line up as they close in: a kick up at the start alone let most pushes
    squeeze the strip flat in its plane, and it sprang back when they let go (docs/hwsim.md, "Hands")."""
    world = _world([])
    world.push(scenarios.Push(at_m=(0.01, -0.005), direction_rad=direction_rad, slack_m=slack_m))
    for _ in range(round(2.5 * world.scenario.fps)):
        world.step()
    measures = world.sheet_measures()
    assert measures["max_height_m"] > 0.008
    assert measures["area_ratio"] < 0.985


def test_a_push_on_belts_turned_every_which_way_stays() -> None:
    """The hands let go slowly (docs/hwsim.md, "Hands"): dropped from the tent they held, this ridge slid
    out within 3 s on these belts, while it stood on belts all at heading 0."""
    world = _world([])
    rng = np.random.default_rng(2)
    world.table.heading_rad[:] = world.table.cmd_heading_rad[:] = rng.uniform(-math.pi, math.pi, 48)
    world.push(scenarios.Push(at_m=(0.01, -0.005), direction_rad=0.32, slack_m=0.008))
    fps = round(world.scenario.fps)
    for _ in range(round(1.5 * fps)):
        world.step()
    pushed_m = _height_m(world)
    for _ in range(3 * fps):
        world.step()
    assert pushed_m > 0.008
    assert _height_m(world) >= 0.9 * pushed_m


def test_ridges_are_laid_without_stretching_the_sheet() -> None:
    grid = ClothGrid.from_spec(scenarios.ClothSpec())
    ridges = [
        scenarios.Ridge(height_m=0.012, at_m=(0.05, 0.0), direction_rad=1.2),
        scenarios.Ridge(height_m=0.008, sigma_m=0.010, at_m=(-0.08, 0.0), direction_rad=math.pi / 2),
    ]
    centre = np.array([(grid.nx - 1) * grid.dx_m, (grid.ny - 1) * grid.dy_m]) / 2.0
    xy, z = lay_ridges(grid.st_m - centre, ridges)
    x = np.concatenate([xy, z[..., None]], axis=-1)
    assert np.abs(grid.edge_strains(x)).max() < 0.01
    assert z.max() == pytest.approx(0.012, rel=0.02)
    assert z[grid.ny // 2, grid.nx // 2 - round(0.08 / grid.dx_m)] == pytest.approx(0.008, rel=0.02)


@pytest.mark.slow
def test_a_folded_corner_stays_folded_on_still_belts() -> None:
    world = _world([], initial_pose={"theta_rad": 0.2, "flaps": [{"corner": "+s+t", "size_m": 0.06}]})
    laid = world.sheet_measures()["folded_ratio"]
    # The triangle's share of the rest area, less the quads the fold line cuts.
    assert 0.7 * 0.06**2 / 2 / (0.25 * 0.20) < laid < 0.06**2 / 2 / (0.25 * 0.20)
    for _ in range(30 * round(world.scenario.fps)):
        world.step()
    assert world.sheet_measures()["folded_ratio"] >= 0.95 * laid
    assert world.sheet_measures()["max_height_m"] == pytest.approx(FLAP_THICKNESS_M, abs=2e-4)


def test_a_flap_larger_than_half_the_cloth_is_refused_with_its_key() -> None:
    with pytest.raises(scenarios.ScenarioError, match=r"initial_pose\.flaps\.0\.size_m"):
        scenarios.parse(
            {"name": "t", "duration_s": 1.0, "initial_pose": {"flaps": [{"corner": "-s-t", "size_m": 0.15}]}}
        )


def test_an_overhanging_ridge_is_refused_with_its_key() -> None:
    with pytest.raises(scenarios.ScenarioError, match=r"initial_pose\.ridges\.0"):
        scenarios.parse(
            {
                "name": "t",
                "duration_s": 1.0,
                "initial_pose": {"ridges": [{"height_m": 0.02, "sigma_m": 0.01}]},
            }
        )
