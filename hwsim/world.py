"""The simulated cell: table, ground-truth cloth and the scenario's operator, stepped frame by frame.

The cloth is piece 0, laid at the scenario's initial_pose. A scenario with an `infeed` lays more pieces at
the -x edge and judges and takes off each piece that reaches the +x edge (hwsim/infeed.py,
hwsim/outfeed.py); the single-cloth calls (`cloth`, `cloth_pose`, `lay`, `push`, ...) then act on the
lead piece, the one that has been on the table longest.

Frame k shows the world at t_k = k / fps. `step()` issues the commands due at t_k and advances the world
to t_{k+1}; the module dynamics run at `MODULE_STEPS_PER_FRAME` times the frame rate so the steppers'
acceleration ramps reach the cloth smoothly.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np

from hwsim.cloth import ClothSim
from hwsim.cloth_constants import LAY_IN_DAMPING_1_S
from hwsim.cloth_spares import make_cloth, spare
from hwsim.infeed import InfeedPlan, largest_specs
from hwsim.outfeed import judge, leading_x_m, past_edge
from hwsim.pieces import ClothPool, Piece, capacity_for, cloth_pose, sheet_measures
from hwsim.scenario import Pose, Push, Scenario, check_flap
from hwsim.scenario_flow import Placement
from hwsim.scene import SceneCloth, SceneState, arms_at
from hwsim.table import Table
from hwsim.taichi_runtime import ensure_taichi
from hwsim.timeline import Operator

MODULE_STEPS_PER_FRAME = 5
# Hands let go of a pushed ridge slowly, lowering it until it carries itself: its settling is quasi-static
# for this long (as when a cloth is laid down with ridges), not a drop from the tent they held.
LET_GO_S = 0.5


@dataclass(frozen=True)
class CommandRow:
    """One line of commands.csv: what the stepper controller was told, from t_s on."""

    t_s: float
    module: int
    speed_m_s: float
    heading_rad: float


@dataclass(frozen=True)
class _PushInProgress:
    push: Push
    started_s: float
    walls: np.ndarray  # (ny, nx) nodes the hands press down
    crest: np.ndarray  # (ny, nx) nodes the fingers draw up
    wall_velocity_m_s: np.ndarray  # (ny, nx, 3)


def _spare_cloths(pieces: list[Piece], pool: ClothPool) -> None:
    """A world's cloths, on the table and parked, once nothing holds the world."""
    spare([p.cloth for p in pieces] + pool.parked())


class World:
    def __init__(self, scenario: Scenario, arch: str = "cpu", log_commands: bool = True) -> None:
        ensure_taichi(arch)
        self.scenario = scenario
        self.dt_s = 1.0 / scenario.fps
        self.table = Table(scenario.table)
        # Without an infeed the one cloth is sized to itself, as it always was.
        capacity = capacity_for(largest_specs(scenario)) if scenario.infeed else None
        first = make_cloth(
            scenario.cloth,
            scenario.table,
            scenario.initial_pose,
            scenario.cloth.substep_s,
            scenario.seed,
            capacity,
        )
        self.pieces = [Piece(0, first, "cloth", 0, 0.0)]
        self.infeed = InfeedPlan(scenario, scenario.infeed) if scenario.infeed else None
        belt = self.infeed.conveyor() if self.infeed else (-math.inf, 0.0, 0.0)
        first.infeed_belt.from_numpy(np.array(belt))
        self.pool = ClothPool(scenario.table, capacity or (first.grid.ny, first.grid.nx), belt)
        if scenario.infeed is not None:  # every cloth the table can hold, made on this thread
            self.pool.fill(scenario.infeed.max_pieces - 1, scenario.cloth, scenario.seed)
        # Its cloths outlive the world, as spares for the next one (hwsim/cloth_spares.py).
        weakref.finalize(self, _spare_cloths, self.pieces, self.pool)
        self.placement = scenario.flow.placement if scenario.flow else Placement()
        self.outfeed: list[dict[str, Any]] = []  # the judged pieces, in the order they left
        self.operator = Operator(scenario, self.table)
        self.frame_index = 0
        self.log_commands = log_commands  # a live cell runs for hours: it keeps no log
        self.command_log: list[CommandRow] = []
        self._push: _PushInProgress | None = None
        self._letting_go_until_s = -math.inf
        self._told_speed = np.full(self.table.n_modules, np.nan)
        self._told_heading = np.full(self.table.n_modules, np.nan)
        for _ in range(round(scenario.settle_s * scenario.fps)):
            self._advance()

    @property
    def t_s(self) -> float:
        return self.frame_index * self.dt_s

    @property
    def cloth(self) -> ClothSim:
        """The lead piece's cloth; a LookupError while the table is empty (only a flow empties it)."""
        if not self.pieces:
            raise LookupError("no piece on the table")
        return self.pieces[0].cloth

    def cloth_centre_m(self) -> np.ndarray:
        """Mean x, y of the lead piece's truth nodes, (2,)."""
        return np.asarray(self.cloth.positions_m()[..., :2].reshape(-1, 2).mean(axis=0))

    def cloth_pose(self) -> np.ndarray:
        """The lead piece's pose, [X_m, Y_m, theta_rad] (hwsim.pieces.cloth_pose)."""
        return cloth_pose(self.cloth)

    def sheet_measures(self) -> dict[str, float]:
        """How flat and how stretched the lead piece is (hwsim.pieces.sheet_measures)."""
        return sheet_measures(self.cloth)

    def push(self, push: Push) -> None:
        """Start two hands pushing a ridge into the cloth (hwsim.scenario.Push); they let go by themselves.
        The hands press the cloth down on either side of the line and close in, while fingers draw the line
        up as high as the slack pushed in so far allows (a tent over the strip between the hands): a flat
        sheet squeezed exactly in its plane has nothing to buckle from (docs/hwsim.md, "Hands")."""
        x = self.cloth.positions_m()
        normal = np.array([-math.sin(push.direction_rad), math.cos(push.direction_rad)])
        u = (x[..., :2] - np.asarray(push.at_m)) @ normal
        walls = (np.abs(u) >= push.reach_m / 4) & (np.abs(u) <= push.reach_m)
        crest = np.abs(u) < 0.75 * self.cloth.grid.dx_m
        closing = np.zeros(x.shape)
        closing[..., :2] = -np.sign(u)[..., None] * (push.slack_m / 2.0 / push.duration_s) * normal
        self._push = _PushInProgress(push, self.t_s, walls, crest, np.where(walls[..., None], closing, 0.0))
        self._drive_hands()

    def _drive_hands(self) -> None:
        """Set the hands' velocities for the coming frame: walls closing in, the crest rising to the tent's
        apex, sqrt(l² - (l - s/2)²) for half-strip l and slack s pushed in by the frame's end."""
        p = self._push
        assert p is not None
        half_strip_m = p.push.reach_m / 4

        def apex_m(t_s: float) -> float:
            s = p.push.slack_m * min(1.0, (t_s - p.started_s) / p.push.duration_s)
            return math.sqrt(max(0.0, half_strip_m**2 - (half_strip_m - s / 2.0) ** 2))

        velocity = p.wall_velocity_m_s.copy()
        velocity[p.crest, 2] = (apex_m(self.t_s + self.dt_s) - apex_m(self.t_s)) / self.dt_s
        self.cloth.hold(p.walls | p.crest, velocity)

    def lay(self, pose: Pose) -> None:
        """Lay the cloth down again at `pose` (its ridges laid in, its flaps folded over) on the belts as
        they are turned now. A flap larger than the cloth allows is a ValueError naming it."""
        for i, flap in enumerate(pose.flaps):
            check_flap(flap, self.cloth.spec, f"flaps.{i}")
        self._push = None
        self._letting_go_until_s = -math.inf
        self.cloth.lay(pose, self.table.heading_rad)

    def scene_state(self, before_s: float = 0.0) -> SceneState:
        """What the camera sees `before_s` before now; motion blur looks a few ms back, extrapolating the
        cloth and belts at their current velocities."""
        return SceneState(
            tuple(
                SceneCloth(
                    p.cloth.positions_m() - before_s * p.cloth.velocities_m_s(),
                    (p.cloth.grid.dx_m, p.cloth.grid.dy_m),
                    p.texture,
                )
                for p in self.pieces
            ),
            self.table.heading_rad.copy(),
            self.table.travel_m - before_s * self.table.speed_m_s,
            arms_at(self.scenario.occluders, self.t_s - before_s),
        )

    def step(self) -> None:
        """Issue the commands due at t_k, then advance to t_{k+1}; then the outfeed takes what reached it
        and the infeed lays what is due."""
        centre = self.cloth_centre_m() if self.pieces else np.zeros(2)
        self.operator.apply(self.t_s, self.dt_s, centre)
        if self.log_commands:
            self._log_commands()
        self._advance()
        self.frame_index += 1
        if self._push is not None:
            if self.t_s >= self._push.started_s + self._push.push.duration_s - 1e-9:
                self.cloth.release()
                self._push = None
                self._letting_go_until_s = self.t_s + LET_GO_S
            else:
                self._drive_hands()
        if self.infeed is not None:
            self._outfeed()
            self._infeed()

    def _advance(self) -> None:
        dt = self.dt_s / MODULE_STEPS_PER_FRAME
        damping_1_s = LAY_IN_DAMPING_1_S if self.t_s < self._letting_go_until_s - 1e-9 else None
        for _ in range(MODULE_STEPS_PER_FRAME):
            self.table.step(dt)
            for k, piece in enumerate(self.pieces):  # the hands hold the lead piece only
                piece.cloth.advance(
                    dt, self.table.speed_m_s, self.table.heading_rad, damping_1_s if k == 0 else None
                )

    def _outfeed(self) -> None:
        """Judge each piece whose leading edge reached the +x edge; take off those past it."""
        x_max_m = self.table.half_extent_m[0]
        for piece in self.pieces:
            if not piece.judged and leading_x_m(piece) >= x_max_m:
                self.outfeed.append(judge(piece, self.t_s, self.placement))
                piece.judged = True
        for piece in [p for p in self.pieces if p.judged and past_edge(p, x_max_m)]:
            if piece is self.pieces[0]:  # the hands were on it
                self._push, self._letting_go_until_s = None, -math.inf
            self.pieces.remove(piece)
            self.pool.park(piece.cloth)

    def _infeed(self) -> None:
        """Lay the next due piece once its place is clear (one a frame)."""
        plan = self.infeed
        assert plan is not None
        others = [float(p.cloth.positions_m()[..., 0].min()) for p in self.pieces]
        if plan.waiting(self.t_s) > 0 and plan.entry_clear(others):
            drawn = plan.draw()
            cloth = self.pool.take(drawn.spec, drawn.pose, drawn.seed, self.table.heading_rad)
            self.pieces.append(
                Piece(plan.laid_count, cloth, drawn.fabric, drawn.texture, self.t_s, drawn.flap)
            )

    def _log_commands(self) -> None:
        t = self.table
        changed = (t.cmd_speed_m_s != self._told_speed) | (t.cmd_heading_rad != self._told_heading)
        for m in np.flatnonzero(changed):
            self.command_log.append(
                CommandRow(self.t_s, int(m), float(t.cmd_speed_m_s[m]), float(t.cmd_heading_rad[m]))
            )
        self._told_speed = t.cmd_speed_m_s.copy()
        self._told_heading = t.cmd_heading_rad.copy()
