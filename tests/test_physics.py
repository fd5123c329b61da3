"""Sanity of the ground-truth cloth: rest, energy, friction drive, contact, and the compress fold."""

import numpy as np
import pytest

from hwsim import scenario as scenarios
from hwsim.cloth_constants import GRAVITY_M_S2
from hwsim.world import World

pytestmark = pytest.mark.clock_free


def _world(**overrides: object) -> World:
    data: dict[str, object] = {"name": "t", "duration_s": 2.0, "settle_s": 0.0}
    data.update(overrides)
    return World(scenarios.parse(data))


def _energy_j(world: World) -> float:
    """Kinetic + gravitational + stretch energy of the truth cloth."""
    x, v, m = world.cloth.positions_m(), world.cloth.velocities_m_s(), world.cloth.mass_kg
    k = world.scenario.cloth.stretch_stiffness_n_m
    g = world.cloth.grid
    stretch = sum(
        0.5 * k * np.sum((np.linalg.norm(np.diff(x, axis=ax), axis=-1) - rest) ** 2)
        for ax, rest in ((1, g.dx_m), (0, g.dy_m))
    )
    return float(0.5 * np.sum(m * np.sum(v * v, axis=-1)) + GRAVITY_M_S2 * np.sum(m * x[..., 2]) + stretch)


def test_cloth_at_rest_stays_at_rest() -> None:
    world = _world()
    x0 = world.cloth.positions_m()
    for _ in range(30):
        world.step()
    assert np.abs(world.cloth.positions_m() - x0).max() < 1e-6
    assert np.abs(world.cloth.velocities_m_s()).max() < 1e-4


def test_energy_does_not_blow_up_after_a_drop() -> None:
    world = _world()
    x = world.cloth.positions_m()
    x[..., 2] += 0.02  # drop the sheet from 2 cm
    world.cloth.set_positions(x)
    e0 = _energy_j(world)
    energies = []
    for _ in range(45):
        world.step()
        energies.append(_energy_j(world))
    assert max(energies) <= e0 * 1.01
    assert energies[-1] < 0.05 * e0  # it landed and came to rest
    # The yarns' friction keeps what the landing bent, as a real cloth does: a ripple a tenth of a
    # millimetre high (0.11 mm; the elastic cloth lay within 0.1 mm).
    assert world.cloth.positions_m()[..., 2].max() < 5e-4


@pytest.mark.parametrize("heading_rad", [0.0, 1.5707963, 2.5])
def test_cloth_carried_by_modules_moves_at_their_speed(heading_rad: float) -> None:
    speed = 0.05
    world = _world(
        timeline=[{"t_s": 0.0, "modules": {"all": True}, "speed_m_s": speed, "heading_rad": heading_rad}]
    )
    for _ in range(30):  # steer, accelerate and stick
        world.step()
    c0 = world.cloth_centre_m()
    for _ in range(15):
        world.step()
    velocity = (world.cloth_centre_m() - c0) / (15 * world.dt_s)
    expected = speed * np.array([np.cos(heading_rad), np.sin(heading_rad)])
    np.testing.assert_allclose(velocity, expected, atol=0.03 * speed)


def test_cloth_never_penetrates_the_table() -> None:
    world = World(scenarios.load("compress", duration_s=1.0))
    lowest = 0.0
    for _ in range(world.scenario.frame_count):
        world.step()
        lowest = min(lowest, float(world.cloth.positions_m()[..., 2].min()))
    assert lowest >= 0.0


def test_compress_buckles_and_flattens() -> None:
    world = World(scenarios.load("compress"))
    heights = []
    for _ in range(world.scenario.frame_count):
        heights.append(float(world.cloth.positions_m()[..., 2].max()))
        world.step()
    assert max(heights) >= 0.015
    assert heights[-1] <= 0.003
    # The fold rises while the sides push (0-0.75 s), not at the start.
    assert heights[0] < 0.006


def _stretch_end_y_mm(name: str, seed: int, y_m: float | None = None) -> float:
    """The truth cloth's centre y at the end of a shirt-stretch scenario, with hwsim's seed (the belts'
    vibration) and, optionally, the cloth laid at another y."""
    data = scenarios.load(name).model_dump()
    data["seed"] = seed
    if y_m is not None:
        data["initial_pose"]["y_m"] = y_m
    world = World(scenarios.parse(data), log_commands=False)
    for _ in range(world.scenario.frame_count - 1):
        world.step()
    return 1000.0 * float(world.cloth_centre_m()[1])


@pytest.mark.slow
def test_the_centred_tug_of_war_is_a_coin_flip_and_the_offset_one_is_not() -> None:
    """shirt-stretch pulls the cloth's halves apart evenly, so the belts' vibration picks the winner: its
    centre ends 25 mm towards -y with seed 1 and +y with seed 10 (which seed goes which way changes with
    any change to hwsim's solver: pick two again from a sweep over seeds). shirt-stretch-offset (clothd
    bench tune's held-out footage) lays the cloth 20 mm towards +y, so the upper half wins whatever the
    seed, and the mirrored start ends mirrored."""
    assert _stretch_end_y_mm("shirt-stretch", 1) == pytest.approx(-25.3, abs=1.0)
    assert _stretch_end_y_mm("shirt-stretch", 10) == pytest.approx(25.3, abs=1.0)
    ends = [_stretch_end_y_mm("shirt-stretch-offset", seed) for seed in (1, 2)]
    assert ends[0] == pytest.approx(45.5, abs=1.0)
    assert ends[1] == pytest.approx(ends[0], abs=0.5)
    assert _stretch_end_y_mm("shirt-stretch-offset", 1, y_m=-0.02) == pytest.approx(-ends[0], abs=0.5)
