"""What the camera sees at one instant: every piece of cloth, the belts and any arms over the table."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hwsim.scenario import Occluder


@dataclass(frozen=True)
class Arm:
    """An occluding arm: a capsule from shoulder to hand, world metres, of the given radius."""

    shoulder_m: np.ndarray
    hand_m: np.ndarray
    radius_m: float


@dataclass(frozen=True)
class SceneCloth:
    """One piece of cloth: its truth nodes (ny, nx, 3), world, their material spacing, and which of the
    renderer's fabrics it shows (0: the scenario's texture; hwsim.infeed.fabric_textures)."""

    nodes_m: np.ndarray
    spacing_m: tuple[float, float]  # the grid's material spacing along s and t
    texture: int = 0


@dataclass(frozen=True)
class SceneState:
    cloths: tuple[SceneCloth, ...]  # the lead piece first
    heading_rad: np.ndarray  # (n_modules,)
    travel_m: np.ndarray  # (n_modules,) belt surface travelled, for scrolling the belt texture
    arms: tuple[Arm, ...]

    @property
    def nodes_m(self) -> np.ndarray:
        """The lead piece's truth nodes (ny, nx, 3)."""
        return self.cloths[0].nodes_m


def arms_at(occluders: list[Occluder], t_s: float) -> tuple[Arm, ...]:
    """The arms in view at t_s."""
    arms = []
    for occ in occluders:
        if not occ.t_start_s <= t_s < occ.t_end_s:
            continue
        shoulder, start, end = (np.asarray(p, dtype=float) for p in (occ.shoulder_m, occ.from_m, occ.to_m))
        # The hand reaches in from the shoulder, sweeps from `from_m` to `to_m`, and withdraws.
        into, left = t_s - occ.t_start_s, occ.t_end_s - t_s
        sweep_s = occ.t_end_s - occ.t_start_s - 2 * occ.reach_s
        if into < occ.reach_s:
            hand = shoulder + (start - shoulder) * into / occ.reach_s
        elif left < occ.reach_s:
            hand = shoulder + (end - shoulder) * left / occ.reach_s
        else:
            hand = start + (end - start) * (into - occ.reach_s) / sweep_s
        z = occ.height_m
        arms.append(Arm(np.array([*shoulder, z]), np.array([*hand, z]), occ.width_m / 2.0))
    return tuple(arms)
