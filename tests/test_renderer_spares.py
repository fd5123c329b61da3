"""A gone camera's renderer serves the next camera of the same layout (hwsim/renderer_spares.py), and
renders bit for bit as a new one would."""

from __future__ import annotations

import gc
import weakref
from typing import Any

import numpy as np
import pytest
from test_cloth_spares import SCENARIO as CLOTH_SCENARIO

from hwsim import scenario as scenarios
from hwsim.camera import Camera
from hwsim.renderer import Renderer
from hwsim.renderer_spares import make_renderer
from hwsim.world import World

pytestmark = pytest.mark.clock_free

# The spare cloths' scenario (a laid ridge: shading; running belts: their scroll), with a weave's relief.
SCENARIO: dict[str, Any] = {**CLOTH_SCENARIO, "name": "renderer-spares", "texture": {"relief_m": 0.0005}}
# The same layout seen differently: every field `Renderer.load` writes holds other values.
OTHER = {
    **SCENARIO,
    "texture": {"seed": 11, "relief_m": 0.0005},
    "light": {"direction": [-0.2, 0.3, 1.0], "ambient": 0.5},
    "camera": {"position_m": [0.02, -0.03, 0.9], "tilt_rad": 0.1},
}


class Owner:
    """Stands for a sensor or world: the renderer is spared once it is gone."""


def _frame(sc: scenarios.Scenario, renderer: Renderer) -> tuple[np.ndarray, np.ndarray]:
    world = World(sc, log_commands=False)
    for _ in range(3):
        world.step()
    return renderer.render([world.scene_state()])


def test_a_spare_renderer_renders_the_next_camera_as_a_new_one_would() -> None:
    sc, other = scenarios.parse(SCENARIO), scenarios.parse(OTHER)
    grid = World(sc, log_commands=False).cloth.grid
    camera, other_camera = Camera.from_spec(sc.camera), Camera.from_spec(other.camera)
    image, seen = _frame(sc, Renderer(sc, camera, grid))
    owner = Owner()
    spare = make_renderer(other, other_camera, grid, owner)
    other_image, _ = _frame(other, spare)
    assert np.abs(other_image - image).mean() > 0.01  # a different view: load has something to rewrite
    kept = weakref.ref(spare)
    del owner, spare
    gc.collect()
    reused = make_renderer(sc, camera, grid, Owner())
    assert reused is kept()
    again, seen_again = _frame(sc, reused)
    np.testing.assert_array_equal(again, image)
    np.testing.assert_array_equal(seen_again, seen)


def test_a_renderer_is_spared_only_for_its_own_layout() -> None:
    sc = scenarios.parse(SCENARIO)
    grid = World(sc, log_commands=False).cloth.grid
    camera = Camera.from_spec(sc.camera)
    owner = Owner()
    kept = weakref.ref(make_renderer(sc, camera, grid, owner))
    other = make_renderer(sc, Camera.from_spec(sc.camera.model_copy(update={"width": 320})), grid, Owner())
    assert other is not kept()  # the spare is not there yet: its owner lives
    del owner
    gc.collect()
    smaller = make_renderer(sc, Camera.from_spec(sc.camera.model_copy(update={"width": 320})), grid, Owner())
    assert smaller is not kept()
    assert make_renderer(sc, camera, grid, Owner()) is kept()
