"""Drive scripts: chosen modules driven over time, for tune recordings and for checking the modules.

The format means what hwsim's scenario timeline means (docs/scenarios.md), read by clothd's own schema:
from `t_s` on, the modules chosen (exactly one of `all`, `ids`, `region_m`) are told `speed_m_s` at
`heading_rad`, held until a later entry changes them; at `duration_s` every module stops (an entry
starting at or after it is refused). A script is
bounded (its length, its entries) and, compiled for a cell (`DrivePlan.compile`), refused with the reason
when it names a module the cell lacks or asks a module for more than its maximum speed.

How far a script may carry the cloth (`cloth_reach_m`) bounds what the workspace check needs: friction
moves no point of the cloth faster than the fastest belt under it, so the cloth's travel is at most the
integral over the script of the fastest speed among the modules it can reach.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag

from clothd.core.conveyor import ConveyorLayout
from clothd.core.messages import ModuleCommands
from clothd.errors import InvalidRequestError

MAX_DURATION_S = 300.0
# Within the API's 4 KB body: one more entry, or one more id, than allowed is refused as invalid (422),
# not as too large (413). More modules at once are chosen by region_m.
MAX_ENTRIES = 32
MAX_IDS = 64


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class AllModules(_Strict):
    all: Literal[True]


class ModuleIds(_Strict):
    ids: list[Annotated[int, Field(ge=0, le=4095)]] = Field(min_length=1, max_length=MAX_IDS)


class ModuleRegion(_Strict):
    region_m: tuple[float, float, float, float] = Field(
        description="x_min, y_min, x_max, y_max of module centres, world metres"
    )


_KEY_OF: dict[type, str] = {AllModules: "all", ModuleIds: "ids", ModuleRegion: "region_m"}


def _choice_key(value: Any) -> str | None:
    """Which way of choosing `value` names: its one key of all, ids, region_m (None: none, or several)."""
    if isinstance(value, dict):
        keys = [k for k in _KEY_OF.values() if k in value]
        return keys[0] if len(keys) == 1 else None
    return _KEY_OF.get(type(value))


# Exactly one way of choosing, as alternatives the JSON schema states (oneOf), so that a client's
# validator and the daemon's agree on what is well formed. The key picks the alternative, so a bad one is
# refused with that alternative's reason alone, not with every alternative's.
ModuleChoice = Annotated[
    Annotated[AllModules, Tag("all")]
    | Annotated[ModuleIds, Tag("ids")]
    | Annotated[ModuleRegion, Tag("region_m")],
    Discriminator(
        _choice_key,
        custom_error_type="module_choice",
        custom_error_message="exactly one of all, ids, region_m chooses the modules",
    ),
]


class DriveEntry(_Strict):
    t_s: float = Field(ge=0, le=MAX_DURATION_S, allow_inf_nan=False)
    modules: ModuleChoice
    speed_m_s: float = Field(ge=0, le=2.0, allow_inf_nan=False)
    heading_rad: float = Field(ge=-2 * math.pi, le=2 * math.pi, allow_inf_nan=False)


class DriveScript(_Strict):
    duration_s: float = Field(
        gt=0, le=MAX_DURATION_S, allow_inf_nan=False, description="every module stops then"
    )
    timeline: list[DriveEntry] = Field(min_length=1, max_length=MAX_ENTRIES)


def chosen(choice: ModuleChoice, centres_m: np.ndarray) -> np.ndarray:
    """Module ids (k,) an entry drives; ids are checked against the cell by the caller."""
    if isinstance(choice, AllModules):
        return np.arange(len(centres_m))
    if isinstance(choice, ModuleIds):
        return np.asarray(choice.ids, dtype=int)
    x0, y0, x1, y1 = choice.region_m
    c = centres_m
    return np.flatnonzero((c[:, 0] >= x0) & (c[:, 0] <= x1) & (c[:, 1] >= y0) & (c[:, 1] <= y1))


@dataclass(frozen=True)
class DrivePlan:
    """A script compiled for a cell: step k holds from t_s[k] on; speed_m_s and heading_rad are
    (steps, n_modules). After duration_s every module is stopped."""

    t_s: np.ndarray
    speed_m_s: np.ndarray
    heading_rad: np.ndarray
    duration_s: float

    @classmethod
    def compile(cls, script: DriveScript, layout: ConveyorLayout, max_speed_m_s: float) -> DrivePlan:
        """The plan, or InvalidRequestError naming the entry that the cell cannot do."""
        late = [i for i, e in enumerate(script.timeline) if e.t_s >= script.duration_s]
        if late:
            raise InvalidRequestError(
                f"timeline{late}: start at or after duration_s ({script.duration_s:g} s)"
            )
        n = layout.n_modules
        centres = layout.centres_m
        entries = sorted(enumerate(script.timeline), key=lambda ie: ie[1].t_s)
        speed, heading = np.zeros(n), np.zeros(n)
        times, speeds, headings = [0.0], [speed.copy()], [heading.copy()]
        for i, e in entries:
            if e.speed_m_s > max_speed_m_s:
                raise InvalidRequestError(
                    f"timeline[{i}]: speed_m_s {e.speed_m_s:g} exceeds the modules' {max_speed_m_s:g} m/s"
                    " (cell.max_speed_m_s)"
                )
            ids = chosen(e.modules, centres)
            if not len(ids):  # a region that holds no module's centre: a typo, most likely
                raise InvalidRequestError(f"timeline[{i}]: modules.region_m holds no module's centre")
            bad = ids[ids >= n]
            if len(bad):
                raise InvalidRequestError(
                    f"timeline[{i}]: modules {bad.tolist()} out of range (the cell has {n})"
                )
            speed[ids], heading[ids] = e.speed_m_s, e.heading_rad
            if e.t_s == times[-1]:
                speeds[-1], headings[-1] = speed.copy(), heading.copy()
            else:
                times.append(e.t_s)
                speeds.append(speed.copy())
                headings.append(heading.copy())
        return cls(np.array(times), np.array(speeds), np.array(headings), script.duration_s)

    @property
    def n_modules(self) -> int:
        return int(self.speed_m_s.shape[1])

    def commands_at(self, elapsed_s: float) -> ModuleCommands:
        """What the modules are told `elapsed_s` into the script (all stopped before 0 and after the end)."""
        k = int(np.searchsorted(self.t_s, elapsed_s, side="right")) - 1
        if k < 0 or elapsed_s >= self.duration_s:
            heading = self.heading_rad[max(k, 0)]
            return ModuleCommands.all_stop(self.n_modules, heading)
        return ModuleCommands(self.speed_m_s[k].copy(), self.heading_rad[k].copy())

    def travel_m(self, modules: np.ndarray) -> float:
        """The integral over the script of the fastest speed among `modules` (bool, n_modules)."""
        ends = np.append(self.t_s[1:], self.duration_s)
        fastest = self.speed_m_s[:, modules].max(axis=1, initial=0.0)
        return float(np.sum(fastest * (ends - self.t_s)))


def cloth_reach_m(plan: DrivePlan, outline_m: np.ndarray, layout: ConveyorLayout) -> float:
    """How far the script can carry any point of the cloth whose outline (k, 2) is given: the travel of
    the modules whose belts lie within reach of the outline, reach bounded first by every module's."""
    every = plan.travel_m(np.ones(plan.n_modules, dtype=bool))
    contour = outline_m.astype(np.float32).reshape(-1, 1, 2)
    belt_reach_m = every + layout.module_size_m / math.sqrt(2.0)
    near = np.array(
        [
            cv2.pointPolygonTest(contour, (float(x), float(y)), True) >= -belt_reach_m
            for x, y in layout.centres_m
        ]
    )
    return plan.travel_m(near)


def swept_box_m(outline_m: np.ndarray, reach_m: float) -> np.ndarray:
    """The corners (4, 2) of the outline's bounding box grown by reach_m on every side."""
    lo = outline_m.min(axis=0) - reach_m
    hi = outline_m.max(axis=0) + reach_m
    return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
