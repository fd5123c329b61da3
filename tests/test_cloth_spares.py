"""A world's cloths outlive it as spares for the next world of the same shape (hwsim/cloth_spares.py):
handed out again, and run bit for bit as a new cloth would."""

from __future__ import annotations

import gc
import weakref
from typing import Any

import numpy as np
import pytest

from hwsim import scenario as scenarios
from hwsim.cloth_spares import make_cloth
from hwsim.scenario import Pose
from hwsim.world import World

pytestmark = pytest.mark.clock_free

# A small cloth with a laid ridge and belts running under it: every field of the solver is used.
SCENARIO: dict[str, Any] = {
    "name": "spares",
    "duration_s": 2.0,
    "settle_s": 0.0,
    "cloth": {"size_m": [0.12, 0.09], "spacing_m": 0.0075, "substep_s": 0.0005, "stretch_iterations": 1},
    "initial_pose": {"x_m": 0.01, "y_m": -0.02, "theta_rad": 0.3, "ridges": [{"height_m": 0.008}]},
    "timeline": [{"t_s": 0.1, "modules": {"all": True}, "speed_m_s": 0.08, "heading_rad": 0.5}],
}


def _run(world: World, steps: int = 12) -> np.ndarray:
    for _ in range(steps):
        world.step()
    return np.asarray(world.cloth.positions_m())


def test_a_world_gone_leaves_its_cloth_to_the_next_which_runs_as_a_new_one() -> None:
    sc = scenarios.parse(SCENARIO)
    first = World(sc, log_commands=False)
    # Built while the first holds its cloth: a cloth of its own.
    second = World(sc, log_commands=False)
    assert second.cloth is not first.cloth
    expected = _run(first)
    np.testing.assert_array_equal(_run(second), expected)
    spared = [weakref.ref(first.cloth), weakref.ref(second.cloth)]
    del first, second
    gc.collect()
    third = World(sc, log_commands=False)
    assert any(third.cloth is ref() for ref in spared)
    np.testing.assert_array_equal(_run(third), expected)


def test_a_spare_goes_only_to_a_cloth_of_its_shape() -> None:
    sc = scenarios.parse(SCENARIO)
    world = World(sc, log_commands=False)
    cloth = world.cloth
    del world
    gc.collect()
    larger = {**SCENARIO["cloth"], "size_m": [0.15, 0.09]}
    other = make_cloth(scenarios.ClothSpec.model_validate(larger), sc.table, Pose(), 0.0005, 0)
    assert other is not cloth
    # The spare stays for a cloth of its own shape.
    assert make_cloth(sc.cloth, sc.table, Pose(), 0.0005, 0) is cloth
