"""The production flow's section of the configuration, `flow:` (docs/flow.md): where each piece is placed
before it is driven out over the +x edge, and how pieces are taken in, flattened and let go.

The placement must be the one the next station expects; in the simulated cell it is the scenario's
`flow.placement`, which hwsim's outfeed judges against.
"""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import Field

from clothd.config.strict import Strict

_Side = Annotated[float, Field(gt=0.01, le=5.0)]


class PlacementConfig(Strict):
    """A piece's pose before it leaves: its centre on the table and its long (s) axis's heading."""

    x_m: float = Field(0.15, ge=-10, le=10)
    y_m: float = Field(0.0, ge=-10, le=10)
    theta_deg: float = Field(0.0, ge=-180, le=180)

    @property
    def pose(self) -> tuple[float, float, float]:
        """[X_m, Y_m, theta_rad]."""
        return self.x_m, self.y_m, math.radians(self.theta_deg)


class FlowConfig(Strict):
    placement: PlacementConfig = PlacementConfig()
    intake_speed_m_s: float = Field(
        0.1, gt=0, le=1, description="the belts under an entering piece pull it in at this speed"
    )
    exit_speed_m_s: float = Field(0.08, gt=0, le=1, description="a placed piece is driven out at this speed")
    still_mm: float = Field(
        2.0, gt=0, le=50, description="a piece in is still when it moved less than this between two looks"
    )
    search_every: int = Field(5, ge=1, le=30, description="frames between two looks for pieces coming in")
    flat_for_s: float = Field(0.5, ge=0, le=10, description="flat this long before it is placed")
    flatten_timeout_s: float = Field(8.0, gt=0, le=120, description="not flat for this long: a reject")
    flap_for_s: float = Field(1.0, gt=0, le=30, description="a folded-over corner seen this long: a reject")
    placed_mm: float = Field(1.5, gt=0, le=50, description="within this of the placement it is placed ...")
    placed_deg: float = Field(0.3, gt=0, le=10, description="... and within this of its heading")
    place_timeout_s: float = Field(15.0, gt=0, le=120, description="not placed by then: a reject")
    gap_m: float = Field(0.03, ge=0, le=1, description="the gap a piece keeps to the one ahead")
    warm_at_start: bool = Field(
        False,
        description="build the pieces' trackers when the daemon starts (~0.5 s each): mode flow is refused "
        "without it, as a tracker built in a tick would stall the loop",
    )
    exit_gain_1_s: float = Field(
        2.0, ge=0, le=20, description="how fast a leaving piece's drift from the placement is corrected"
    )
    piece_max_m: tuple[_Side, _Side] = Field(
        (0.35, 0.26),
        description="the largest piece the line lays (long side, short side): a region larger is pieces "
        "touching, rejected rather than tracked as one",
    )
