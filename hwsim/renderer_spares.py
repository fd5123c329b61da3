"""Renderers of cameras that are gone, kept for the next camera of the same layout (hwsim/spares.py says
why: one run of the tests that read no clock built 50 renderers of 13 layouts, each compiling its own
kernels). A spare is loaded with the new camera's view (`Renderer.load`) and renders bit for bit as a new
one."""

from __future__ import annotations

import weakref

from hwsim.camera import Camera
from hwsim.cloth_grid import ClothGrid
from hwsim.render_textures import render_textures
from hwsim.renderer import Renderer, layout_key, render_px_per_m
from hwsim.scenario import Scenario
from hwsim.spares import Spares

_spares: Spares[tuple[object, ...], Renderer] = Spares()


def make_renderer(scenario: Scenario, camera: Camera, grid: ClothGrid, owner: object) -> Renderer:
    """A Renderer of this camera's view; a spare of the same layout where there is one. It is kept for the
    next once nothing holds `owner` any longer (owner must not be reachable from the Renderer)."""
    textures = render_textures(scenario, render_px_per_m(scenario, camera))
    key = layout_key(scenario, camera, grid, textures)
    renderer = _spares.take(key)
    if renderer is None:
        renderer = Renderer(scenario, camera, grid, textures)
    else:
        renderer.load(scenario, camera, grid, textures)
    weakref.finalize(owner, _spares.give, key, renderer)
    return renderer
