"""The infeed: which piece comes next, and when and where it is laid (scenario key `infeed`).

Pieces are due every 60/rate_per_min seconds from first_s. Each is drawn, in order, from the infeed's
ranges by one Generator seeded from the scenario's seed, so piece k is the same piece however the run's
timing went. A due piece is laid at rest, flat but for its ridges (and a folded corner, for the share
`flap_share`), with its leading edge `lead_m` in over the table's -x edge: the rest of it lies on the
infeed's slide plate, at table height and without friction (as the deck between belts is), and the belts
under its leading part pull it in. It waits while another piece lies within `clear_m` of where it goes,
or while `max_pieces` are on the table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hwsim.cloth_grid import ClothGrid
from hwsim.scenario import ClothSpec, Flap, Pose, Ridge, Scenario, TextureSpec
from hwsim.scenario_flow import FABRICS, Infeed

_STREAM = 0x1F  # the infeed's own stream of the scenario's seed: the world's vibration keeps its draws
_RIDGE_SIGMA_M = 0.012  # as a laid ridge's default; wider for the highest, which must not overhang


@dataclass(frozen=True)
class DrawnPiece:
    spec: ClothSpec
    pose: Pose
    fabric: str
    texture: int  # the renderer's fabric index: 1 + the fabric's place in infeed.fabrics
    flap: bool
    seed: int  # its belts' vibration


def fabric_spec(cloth: ClothSpec, fabric: str, size_m: tuple[float, float]) -> ClothSpec:
    """The scenario's cloth (its mesh, substep and vibration) with a fabric's physical keys and a size."""
    keys, _ = FABRICS[fabric]
    return ClothSpec.model_validate({**cloth.model_dump(), **keys, "size_m": size_m})


def fabric_textures(scenario: Scenario) -> list[tuple[TextureSpec, tuple[float, float]]]:
    """Every texture the renderer needs, with the cloth size it covers: the scenario's own (piece 0),
    then one per infeed fabric, covering the largest piece. The weave's relief is the scenario's."""
    own = (scenario.texture, scenario.cloth.size_m)
    infeed = scenario.infeed
    if infeed is None:
        return [own]
    relief = scenario.texture.relief_m if scenario.texture.kind != "image" else 0.0
    largest = (infeed.size_s_m[1], infeed.size_t_m[1])
    return [own] + [
        (TextureSpec(kind=FABRICS[f][1], seed=scenario.texture.seed, relief_m=relief), largest)
        for f in infeed.fabrics
    ]


def largest_specs(scenario: Scenario) -> list[ClothSpec]:
    """The largest piece of every fabric the infeed lays: what the cloth pool and renderer must hold."""
    infeed = scenario.infeed
    if infeed is None:
        return [scenario.cloth]
    largest = (infeed.size_s_m[1], infeed.size_t_m[1])
    return [scenario.cloth] + [fabric_spec(scenario.cloth, f, largest) for f in infeed.fabrics]


class InfeedPlan:
    """Draws the pieces in order and keeps the schedule."""

    def __init__(self, scenario: Scenario, infeed: Infeed) -> None:
        self.scenario = scenario
        self.infeed = infeed
        self.rng = np.random.default_rng((scenario.seed, _STREAM))
        self.due_count = 0  # pieces due so far (laid or waiting)
        self.laid_count = 0
        self.x_min_m = -scenario.table.modules_x * scenario.table.pitch_m / 2.0

    def conveyor(self) -> tuple[float, float, float]:
        """The infeed conveyor up to the -x edge, as wide as the table: (its end x, half width, speed)."""
        half_y_m = self.scenario.table.modules_y * self.scenario.table.pitch_m / 2.0
        return self.x_min_m, half_y_m, self.infeed.speed_m_s

    def due_by(self, t_s: float) -> int:
        """How many pieces have come due by t_s."""
        if t_s < self.infeed.first_s - 1e-9:
            return 0
        return math.floor((t_s - self.infeed.first_s) / self.infeed.period_s + 1e-9) + 1

    def waiting(self, t_s: float) -> int:
        """Pieces due by t_s and not yet laid."""
        return self.due_by(t_s) - self.laid_count

    def entry_clear(self, others_min_x_m: list[float]) -> bool:
        """No other piece reaches back to within clear_m of the new piece's leading edge."""
        reach = self.x_min_m + self.infeed.lead_m + self.infeed.clear_m
        return len(others_min_x_m) < self.infeed.max_pieces and all(x >= reach for x in others_min_x_m)

    def draw(self) -> DrawnPiece:
        """The next piece, laid with its leading edge lead_m in over the -x edge."""
        f, r = self.infeed, self.rng
        size = (float(r.uniform(*f.size_s_m)), float(r.uniform(*f.size_t_m)))
        k = int(r.integers(len(f.fabrics)))
        spec = fabric_spec(self.scenario.cloth, f.fabrics[k], size)
        theta = math.radians(float(r.uniform(*f.heading_deg)))
        y = float(r.uniform(*f.y_m))
        ridges = [self._ridge(size) for _ in range(int(r.integers(f.ridges[0], f.ridges[1] + 1)))]
        flap = bool(r.uniform() < f.flap_share)
        corner = ("-s-t", "+s-t", "+s+t", "-s+t")[int(r.integers(4))]
        flaps = [Flap(corner=corner, size_m=f.flap_size_m)] if flap else []
        seed = int(r.integers(2**31))
        at_origin = Pose(theta_rad=theta, ridges=ridges, flaps=flaps)
        reach_m = float(ClothGrid.from_spec(spec).placed(at_origin)[..., 0].max())
        pose = at_origin.model_copy(update={"x_m": self.x_min_m + f.lead_m - reach_m, "y_m": y})
        self.laid_count += 1
        return DrawnPiece(spec, pose, f.fabrics[k], 1 + k, flap, seed)

    def _ridge(self, size_m: tuple[float, float]) -> Ridge:
        """A ridge of the infeed's heights across the piece, through a point in its middle half."""
        r = self.rng
        height_m = float(r.uniform(*self.infeed.ridge_height_mm)) / 1e3
        at = (float(r.uniform(-0.25, 0.25)) * size_m[0], float(r.uniform(-0.25, 0.25)) * size_m[1])
        return Ridge(
            height_m=height_m,
            sigma_m=max(_RIDGE_SIGMA_M, 0.65 * height_m),
            at_m=at,
            direction_rad=float(r.uniform(0.0, math.pi)),
        )
