"""The textures a camera's renderer samples, at the mip level that suits its pixel density, and the
constants its kernels take from them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hwsim.infeed import fabric_textures
from hwsim.scenario import Scenario, TextureSpec
from hwsim.texture import (
    belt_texture,
    cloth_texture,
    deck_texture,
    image_texture,
    mip_level_for,
    mip_pyramid,
    weave_slopes,
)

BELT_LOOP_M = 0.2  # belt texture period along the direction of travel
DECK_TILE_M = 0.3  # deck texture tile; it repeats (small, so it stays in cache)
# The belts and deck are made at this density for every camera, each camera sampling the mip level that
# suits it: made at each camera's own density, their noise came out a different pattern in each view.
TABLE_TEXELS_PER_M = 2000.0


def texel_offset(level: int) -> float:
    """Level 0's texel i is centred at i + 0.5, and cv2.pyrDown centres level L's texel i on level 0's
    2**L i: level L's coordinate is (level 0's - 0.5) / 2**L. (- 0.5 at every level shifted the pattern
    between cameras sampling different levels: a disparity, read as height.)"""
    return 0.5 / 2**level


@dataclass(frozen=True)
class FabricTexture:
    """One fabric's colour (H, W, 3) and relief slopes (h, w, 2; a 1 x 1 dummy without relief), float32,
    on its mip level, whose texels per metre and offset (`texel_offset`) the sampler uses."""

    colour: np.ndarray
    slopes: np.ndarray
    texels_per_m: float
    texel_offset: float
    relief: bool


@dataclass(frozen=True)
class RenderTextures:
    """Every fabric's texture (piece 0's, then the infeed's), and the belts' and deck's."""

    fabrics: tuple[FabricTexture, ...]
    belt: np.ndarray
    deck: np.ndarray
    table_texels_per_m: float
    table_texel_offset: float

    def layout(self) -> tuple[object, ...]:
        """What of them a renderer's fields' shapes and its kernels' constants hold."""
        fabrics = tuple(
            (f.colour.shape, f.slopes.shape, f.texels_per_m, f.texel_offset, f.relief) for f in self.fabrics
        )
        return (fabrics, self.belt.shape, self.deck.shape, self.table_texels_per_m, self.table_texel_offset)


def render_textures(scenario: Scenario, px_per_m: float) -> RenderTextures:
    """The scenario's textures for a render of px_per_m pixels per metre on a flat cloth under the camera."""
    fabrics = tuple(_fabric(spec, size, px_per_m) for spec, size in fabric_textures(scenario))
    seed = scenario.texture.seed
    level = mip_level_for(TABLE_TEXELS_PER_M, px_per_m)
    belt = belt_texture(seed + 1, BELT_LOOP_M, scenario.table.module_size_m, TABLE_TEXELS_PER_M)
    deck = deck_texture(seed + 2, (DECK_TILE_M, DECK_TILE_M), TABLE_TEXELS_PER_M)
    return RenderTextures(
        fabrics,
        _float32(mip_pyramid(belt, level + 1)[level]),
        _float32(mip_pyramid(deck, level + 1)[level]),
        TABLE_TEXELS_PER_M / 2**level,
        texel_offset(level),
    )


def _fabric(spec: TextureSpec, size: tuple[float, float], px_per_m: float) -> FabricTexture:
    if spec.kind == "image":
        assert spec.path is not None
        tex = image_texture(spec.path, size, spec.texels_per_m)
    else:
        tex = cloth_texture(spec.kind, spec.seed, size, spec.texels_per_m)
    level = mip_level_for(spec.texels_per_m, px_per_m)
    # The relief's slopes, low-passed to the same mip level as the colour.
    slopes = np.zeros((1, 1, 2), np.float32)
    if spec.relief_m > 0:
        assert spec.kind != "image"
        slopes = weave_slopes(spec.kind, spec.seed, size, spec.texels_per_m, spec.relief_m)
        slopes = mip_pyramid(slopes, level + 1)[level]
    return FabricTexture(
        _float32(mip_pyramid(tex, level + 1)[level]),
        _float32(slopes),
        spec.texels_per_m / 2**level,
        texel_offset(level),
        spec.relief_m > 0,
    )


def _float32(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)
