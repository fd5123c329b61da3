"""The scenario's operator: turns the timeline and random drives into module commands, frame by frame.

Commands are applied at frame boundaries: a `SetCommand` with t_s in (t_prev, t] takes effect for the
frame interval starting at t. A random drive re-commands every module each frame from a smooth random
rigid velocity field about the cloth's centre, pulled back towards the table centre.
"""

from __future__ import annotations

import math

import numpy as np

from hwsim.scenario import RandomDrive, Scenario
from hwsim.table import Table

_PULL_GAIN_1_S = 1.0


class _RandomDriveState:
    """Ornstein–Uhlenbeck translation velocity (2,) and yaw rate, seeded."""

    def __init__(self, spec: RandomDrive) -> None:
        self.spec = spec
        self.rng = np.random.default_rng(spec.seed)
        self.v_m_s = np.zeros(2)
        self.omega_rad_s = 0.0
        self.finished = False

    def active(self, t_s: float) -> bool:
        return self.spec.t_s <= t_s < self.spec.t_end_s

    def step(self, dt_s: float, centre_m: np.ndarray) -> tuple[np.ndarray, float]:
        s = self.spec
        # Exact OU discretisation: stationary std is the spec's typical value, whatever dt_s.
        decay = math.exp(-dt_s / s.correlation_s)
        spread = math.sqrt(1.0 - decay**2)
        self.v_m_s = decay * self.v_m_s + spread * s.speed_m_s * self.rng.standard_normal(2)
        self.omega_rad_s = decay * self.omega_rad_s + spread * s.yaw_rate_rad_s * self.rng.standard_normal()
        v = self.v_m_s.copy()
        r = float(np.linalg.norm(centre_m))
        if r > s.keep_within_m:
            # Past the radius: cancel any outward drift, then pull back in proportion (gain 1/s).
            inward = -centre_m / r
            outward_m_s = max(0.0, -float(v @ inward))
            v += inward * (outward_m_s + (r - s.keep_within_m) * _PULL_GAIN_1_S)
        return v, self.omega_rad_s


class Operator:
    """Applies a scenario's commands to the table; records what the controller was told."""

    def __init__(self, scenario: Scenario, table: Table) -> None:
        self.table = table
        self._sets = sorted(scenario.timeline, key=lambda c: c.t_s)
        self._next_set = 0
        self._drives = [_RandomDriveState(d) for d in scenario.random_drives]

    def apply(self, t_s: float, dt_s: float, cloth_centre_m: np.ndarray) -> None:
        """Issue every command due by t_s. `cloth_centre_m` (2,) steers the random drives."""
        while self._next_set < len(self._sets) and self._sets[self._next_set].t_s <= t_s + 1e-9:
            cmd = self._sets[self._next_set]
            self.table.command(self.table.select(cmd.modules), cmd.speed_m_s, cmd.heading_rad)
            self._next_set += 1
        for drive in self._drives:
            if drive.active(t_s):
                v, omega = drive.step(dt_s, cloth_centre_m)
                rel = self.table.centres_m - cloth_centre_m
                field = v + omega * np.stack([-rel[:, 1], rel[:, 0]], axis=1)
                self.table.command(
                    np.arange(self.table.n_modules),
                    np.linalg.norm(field, axis=1),
                    np.arctan2(field[:, 1], field[:, 0]),
                )
            elif t_s >= drive.spec.t_end_s and not drive.finished:
                self.table.stop_all()
                drive.finished = True
