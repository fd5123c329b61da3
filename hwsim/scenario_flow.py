"""Scenario keys of a production flow (docs/scenarios.md, "A production flow"): `infeed`, which lays pieces
at the table's -x edge at a rate, each drawn from seeded ranges, and `flow`, the placement that the outfeed
judges each piece against as it leaves over the +x edge."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

# The fabrics an infeed lays: the cloth's physical keys (its mesh, substep and vibration stay the
# scenario's `cloth`) and the weave it is rendered with. Denim is `cloth`'s default; shirting and lining
# are those of the shirt-* and lining-* scenarios.
FABRICS: dict[str, tuple[dict[str, object], str]] = {
    "denim": ({}, "denim"),
    "shirting": (
        {
            "areal_density_kg_m2": 0.11,
            "stretch_stiffness_n_m": 5000.0,
            "shear_stiffness_n_m": 150.0,
            "bending_stiffness_n_m": 5.0e-7,
            "bending_hysteresis_n": 0.0,
            "friction": {"mu": 0.35, "mu_static": 0.4},
        },
        "gingham",
    ),
    "lining": (
        {
            "areal_density_kg_m2": 0.07,
            "stretch_stiffness_n_m": 3000.0,
            "shear_stiffness_n_m": 60.0,
            "bending_stiffness_n_m": 2.0e-7,
            "bending_hysteresis_n": 0.0,
            "friction": {"mu": 0.25, "mu_static": 0.3},
        },
        "plain_twill",
    ),
}
FabricName = Literal["denim", "shirting", "lining"]
MAX_PIECES = 4  # on the table at once: the renderer's and the cloth pool's capacity


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _ordered(name: str, pair: tuple[float, float]) -> None:
    if pair[0] > pair[1]:
        raise ValueError(f"{name}: the low end ({pair[0]}) exceeds the high end ({pair[1]})")


Length = Annotated[float, Field(gt=0.05, le=1.0)]


class Infeed(_Strict):
    """Pieces laid at the -x edge, one every 60/rate_per_min seconds from first_s, each drawn from the
    ranges [low, high] (uniform) with a Generator seeded from the scenario's seed. A piece is laid at rest
    with its leading edge lead_m in over the edge, the rest on the infeed's slide plate, once no other piece
    lies within clear_m of where it goes; until then it waits."""

    rate_per_min: float = Field(6.0, gt=0, le=60, description="pieces laid per minute")
    first_s: float = Field(0.0, ge=0, le=3600, description="when the first infeed piece is due")
    size_s_m: tuple[Length, Length] = Field((0.22, 0.28), description="length along the piece's s axis")
    size_t_m: tuple[Length, Length] = Field((0.18, 0.22), description="width along its t axis")
    fabrics: list[FabricName] = Field(["denim"], min_length=1, max_length=3, description="drawn evenly")
    heading_deg: tuple[float, float] = Field((-10.0, 10.0), description="s axis from world +x")
    y_m: tuple[float, float] = Field((-0.03, 0.03), description="centre's y where laid")
    ridges: tuple[int, int] = Field((1, 2), description="how many ridges (0 to 4)")
    ridge_height_mm: tuple[float, float] = Field((5.0, 15.0), description="each ridge's height as laid")
    flap_share: float = Field(0.0, ge=0, le=1, description="share of pieces laid with a corner folded over")
    flap_size_m: float = Field(0.04, gt=0.005, le=0.1)
    speed_m_s: float = Field(0.05, ge=0, le=0.5, description="the infeed conveyor's speed, +x")
    lead_m: float = Field(0.075, gt=0.01, le=0.5, description="leading edge's reach in over the edge")
    clear_m: float = Field(0.02, ge=0, le=0.5, description="gap to other pieces needed to lay one")
    max_pieces: int = Field(3, ge=2, le=MAX_PIECES, description="pieces on the table at once, at most")

    @model_validator(mode="after")
    def _ranges(self) -> Infeed:
        for name in ("size_s_m", "size_t_m", "heading_deg", "y_m", "ridges", "ridge_height_mm"):
            _ordered(name, getattr(self, name))
        if not (self.ridges[0] >= 0 and self.ridges[1] <= 4):
            raise ValueError(f"ridges: counts from 0 to 4, got {list(self.ridges)}")
        if not (self.ridge_height_mm[0] >= 0.5 and self.ridge_height_mm[1] <= 30.0):
            raise ValueError(f"ridge_height_mm: heights from 0.5 to 30 mm, got {list(self.ridge_height_mm)}")
        if not (self.heading_deg[0] >= -90.0 and self.heading_deg[1] <= 90.0):
            raise ValueError(f"heading_deg: from -90 to 90, got {list(self.heading_deg)}")
        if self.flap_share > 0 and self.flap_size_m > min(self.size_s_m[0], self.size_t_m[0]) / 2:
            raise ValueError("flap_size_m must be at most half the smallest piece's shorter side")
        return self

    @property
    def period_s(self) -> float:
        return 60.0 / self.rate_per_min


class Placement(_Strict):
    """Where a piece is to be brought before it is driven out: its centre and its s axis's heading."""

    x_m: float = Field(0.0, ge=-5, le=5)
    y_m: float = Field(0.0, ge=-5, le=5)
    theta_deg: float = Field(0.0, ge=-180, le=180)

    @property
    def theta_rad(self) -> float:
        return math.radians(self.theta_deg)


class Flow(_Strict):
    placement: Placement = Placement()
