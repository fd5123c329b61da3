"""The production flow in lockstep: hwsim's flow scenario (its infeed laying pieces, its outfeed judging
them) and clothd's piece tracking and flow controller in one process, tick by tick, as fast as the CPU
allows (as clothd/tools/lockstep.py does for one cloth; what it leaves out is said there).

The clothd side is configured for the scenario's table (its modules) and placement: a plant sets the
daemon's `flow.placement` to what the next station expects, and hwsim judges against its own.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from clothd.config import Config, with_overrides
from clothd.core.flow_cell import FlowCell
from clothd.core.pieces import Piece
from clothd.taichi_runtime import start_taichi
from clothd.tools.lockstep import CAMERA_FPS, command_table, frames_of, scenario_cameras
from hwsim import scenario as scenarios
from hwsim.world import World


def flow_scenario(rate_per_min: float, seed: int, name: str = "flow") -> scenarios.Scenario:
    """The flow scenario with the infeed's rate and the world's seed (its pieces' draws) set."""
    sc = scenarios.load(name, seed=seed)
    if sc.infeed is None:
        raise ValueError(f"scenario {name} has no infeed")
    data = sc.model_dump()
    data["infeed"]["rate_per_min"] = rate_per_min
    return scenarios.parse(data, name)


def config_for(cfg: Config, sc: scenarios.Scenario) -> Config:
    """clothd's configuration for the scenario's table and placement."""
    if sc.flow is None:
        raise ValueError(f"scenario {sc.name} has no flow.placement")
    placement = sc.flow.placement
    return with_overrides(
        cfg,
        {
            "cell": {"modules_x": sc.table.modules_x, "modules_y": sc.table.modules_y},
            "flow": {
                "placement": {"x_m": placement.x_m, "y_m": placement.y_m, "theta_deg": placement.theta_deg}
            },
        },
    )


class LockstepFlow:
    """hwsim's flow scenario and clothd's flow, advanced together by `run`."""

    def __init__(self, cfg: Config, sc: scenarios.Scenario, cameras: int | None = None) -> None:
        start_taichi(cfg.taichi.arch)
        cfg = config_for(cfg, sc)
        self.world = World(sc, log_commands=False)
        self.period_s = cfg.loop.period_s
        if not np.isclose(self.world.dt_s, self.period_s):
            raise ValueError(f"lockstep needs the world's step ({self.world.dt_s:g} s) to be the tick")
        self.sensors, models = scenario_cameras(sc, self.world, cameras)
        self.camera_every = max(1, round(sc.fps / CAMERA_FPS))
        self.cell = FlowCell(
            cfg.flow, cfg.tracker, cfg.control, cfg.cell, models[0], models[1:], self.period_s
        )
        self.cell.tracking.warm(models[0].width, models[0].height)  # as the daemon does at its start
        self.commands = self.cell.stop()
        self.ticks = 0
        self.multi_piece_ticks = 0  # two or more pieces on the table, by hwsim's truth
        self.frame_ms: list[float] = []  # each frame's tracking and control, on this machine
        # Each tick's commands, this long after the tick began: its own work, after whatever the last
        # tick's left for after its commands (a frame's upkeep, a piece's start) ran into it.
        self.tick_ms: list[float] = []
        self._busy_ms = 0.0
        self.control_ms: list[float] = []  # each tick's control alone

    @property
    def pieces(self) -> list[Piece]:
        return self.cell.pieces

    def run(self, seconds: float) -> None:
        for _ in range(max(1, round(seconds / self.period_s))):
            self._tick()

    def summary(self) -> dict[str, Any]:
        """What the loop's side saw: its rejects and the time each frame took."""
        rejected = [p for p in [*self.cell.tracking.gone, *self.pieces] if p.reason is not None]
        frame_ms = np.array(self.frame_ms or [0.0])
        tick_ms = np.array(self.tick_ms or [0.0])
        return {
            "rejected": [{"id": p.id, "reason": p.reason} for p in rejected],
            "frame_ms_p50": round(float(np.median(frame_ms)), 2),
            "frame_ms_p99": round(float(np.percentile(frame_ms, 99)), 2),
            "missed_tick_pct": round(100.0 * float(np.mean(tick_ms > self.period_s * 1e3)), 3),
            "multi_piece_time_pct": round(100.0 * self.multi_piece_ticks / max(self.ticks, 1), 2),
        }

    def _tick(self) -> None:
        command_table(self.world, self.commands)
        in_force = self.commands
        self.world.step()
        self.ticks += 1
        self.multi_piece_ticks += len(self.world.pieces) >= 2
        frame = self.world.frame_index % self.camera_every == 0
        t0 = time.perf_counter()
        if frame:
            k = self.world.frame_index // self.camera_every
            image, views = frames_of(self.world, self.sensors, k)
            t0 = time.perf_counter()  # the rendering is hwsim's
            self.cell.track(image, self.world.t_s, in_force, views)
        t1 = time.perf_counter()
        self.commands = self.cell.step(self.world.t_s)
        t2 = time.perf_counter()
        self.control_ms.append((t2 - t1) * 1e3)
        late_ms = self._busy_ms - self.period_s * 1e3  # the last tick's work ran into this one
        self.tick_ms.append(max(late_ms, 0.0) + (t2 - t0) * 1e3)
        self._busy_ms = (t2 - t0) * 1e3
        if frame:
            self.frame_ms.append((t2 - t0) * 1e3)
            self.cell.upkeep()  # after the commands, as the compute process does after its reply
            self._busy_ms = (time.perf_counter() - t0) * 1e3
