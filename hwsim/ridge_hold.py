"""`hwsim ridges`: which ridges the truth cloth keeps on still belts, in every direction.

Ridges are laid every 15° from 0° to 165°, through the cloth's centre and through an off-centre point,
at three sizes, and pushed in by the hands along seeded random lines; each is held for a while with every
belt still. A ridge is kept when it never falls below 90 % of its settled height (docs/hwsim.md, "Holding
a wrinkle")."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from hwsim import scenario as scenarios
from hwsim.world import World

KEPT_FRACTION = 0.9
LAID_SIZES_M = ((0.005, 0.008), (0.010, 0.012), (0.020, 0.016))  # height, sigma
THROUGH_M = ((0.0, 0.0), (0.04, -0.03))
PUSH_SETTLE_S = 1.5  # the hands close in and let go


@dataclass(frozen=True)
class RidgeHold:
    case: str
    group: str
    settled_m: float  # highest node once laid (or pushed) and settled
    lowest_m: float  # the lowest that highest node came over the hold

    @property
    def kept(self) -> bool:
        return self.settled_m > 0.001 and self.lowest_m >= KEPT_FRACTION * self.settled_m


def _world(scenario: str, ridges: list[dict[str, object]]) -> World:
    data = scenarios.load(scenario).model_dump()
    data.update(duration_s=3600.0, settle_s=0.0, timeline=[], initial_pose={"ridges": ridges})
    return World(scenarios.parse(data), log_commands=False)


def _hold(world: World, hold_s: float, case: str, group: str) -> RidgeHold:
    settled = lowest = float(world.cloth.positions_m()[..., 2].max())
    for _ in range(round(hold_s * world.scenario.fps)):
        world.step()
        lowest = min(lowest, float(world.cloth.positions_m()[..., 2].max()))
    return RidgeHold(case, group, settled, lowest)


def ridge_holds(scenario: str, hold_s: float, pushes: int, seed: int) -> Iterator[RidgeHold]:
    for height_m, sigma_m in LAID_SIZES_M:
        group = f"laid {height_m * 1e3:.0f} mm, sigma {sigma_m * 1e3:.0f} mm"
        for degrees in range(0, 180, 15):
            for at_m in THROUGH_M:
                ridge = {
                    "height_m": height_m,
                    "sigma_m": sigma_m,
                    "direction_rad": math.radians(degrees),
                    "at_m": list(at_m),
                }
                case = f"{group}, {degrees} deg through ({at_m[0] * 1e3:.0f}, {at_m[1] * 1e3:.0f}) mm"
                yield _hold(_world(scenario, [ridge]), hold_s, case, group)
    rng = np.random.default_rng(seed)
    for _ in range(pushes):
        line_deg, slack_m = float(rng.uniform(0, 180)), float(rng.uniform(0.004, 0.012))
        at_m = (float(rng.uniform(-0.03, 0.03)), float(rng.uniform(-0.03, 0.03)))
        world = _world(scenario, [])
        world.push(scenarios.Push(at_m=at_m, direction_rad=math.radians(line_deg), slack_m=slack_m))
        for _ in range(round(PUSH_SETTLE_S * world.scenario.fps)):
            world.step()
        place = f"({at_m[0] * 1e3:.0f}, {at_m[1] * 1e3:.0f}) mm"
        case = f"pushed, {slack_m * 1e3:.1f} mm slack, {line_deg:.1f} deg at {place}"
        yield _hold(world, hold_s, case, "pushed by the hands")


def format_holds(rows: list[RidgeHold]) -> str:
    lines = [f"{'ridge':75s} {'settled':>8s} {'lowest':>8s}  kept"]
    for r in rows:
        lines.append(
            f"{r.case:75s} {r.settled_m * 1e3:6.2f}mm {r.lowest_m * 1e3:6.2f}mm  {'yes' if r.kept else 'NO'}"
        )
    lines.append("")
    for group in dict.fromkeys(r.group for r in rows):
        members = [r for r in rows if r.group == group]
        lines.append(f"{group}: kept {sum(r.kept for r in members)} of {len(members)}")
    return "\n".join(lines)
