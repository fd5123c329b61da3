"""The table of steerable conveyor modules: layout, commands and the module dynamics.

Module `id = row * modules_x + col`; column index grows along world x, row index along world y, and the
array is centred on the world origin. Each module is a square belt of side `module_size_m` on a
turntable of diameter `pitch_m`: the drive stepper sets the belt's surface speed, the steering stepper
its heading. Between the belts is the static deck.

The modules obey the limits steppers have: surface speed changes at most `accel_limit_m_s2`, heading
at most `steer_rate_limit_rad_s`. A belt runs both ways, so a module reaches a commanded (speed,
heading) by whichever of (speed, heading) and (-speed, heading + π) needs less steering: reversing
a belt is quicker than turning a turntable half round.

A miscalibrated module (`TableSpec.miscalibrated`) turns each command into what it then does: the heading
plus its offset (and half a turn when reversed), the speed times its scale. The commands stay as told
(what commands.csv records); only the belts' motion, which the camera sees, carries the error.
"""

from __future__ import annotations

import math

import numpy as np

from hwsim.scenario import ModuleSelector, TableSpec


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles to (-π, π]."""
    return np.asarray(np.pi - np.mod(np.pi - a, 2 * np.pi))


class Table:
    """Module layout and state. Arrays are indexed by module id, shape (n_modules,)."""

    def __init__(self, spec: TableSpec) -> None:
        self.spec = spec
        cols, rows = np.meshgrid(np.arange(spec.modules_x), np.arange(spec.modules_y))
        self.centres_m = np.stack(
            [
                (cols.ravel() - (spec.modules_x - 1) / 2.0) * spec.pitch_m,
                (rows.ravel() - (spec.modules_y - 1) / 2.0) * spec.pitch_m,
            ],
            axis=1,
        )
        n = self.n_modules
        self.cmd_speed_m_s = np.zeros(n)
        self.cmd_heading_rad = np.zeros(n)
        self.speed_m_s = np.zeros(n)  # signed: negative runs the belt backwards
        self.heading_rad = np.zeros(n)
        self.travel_m = np.zeros(n)  # belt surface travelled, for scrolling its texture
        self.heading_error_rad = np.zeros(n)
        self.speed_scale = np.ones(n)
        for m in spec.miscalibrated:
            reversal_rad = math.pi if m.reversed else 0.0
            self.heading_error_rad[m.module] = math.radians(m.heading_offset_deg) + reversal_rad
            self.speed_scale[m.module] = m.speed_scale

    @property
    def n_modules(self) -> int:
        return self.spec.modules_x * self.spec.modules_y

    @property
    def half_extent_m(self) -> tuple[float, float]:
        """Half the table's size along x and y, to the outer edge of the outer turntables."""
        s = self.spec
        return (s.modules_x * s.pitch_m / 2.0, s.modules_y * s.pitch_m / 2.0)

    def select(self, selector: ModuleSelector) -> np.ndarray:
        """Module ids chosen by a scenario selector."""
        if selector.all:
            return np.arange(self.n_modules)
        if selector.ids is not None:
            return np.asarray(selector.ids, dtype=int)
        assert selector.region_m is not None
        x0, y0, x1, y1 = selector.region_m
        c = self.centres_m
        inside = (c[:, 0] >= x0) & (c[:, 0] <= x1) & (c[:, 1] >= y0) & (c[:, 1] <= y1)
        return np.flatnonzero(inside)

    def command(
        self, ids: np.ndarray, speed_m_s: np.ndarray | float, heading_rad: np.ndarray | float
    ) -> None:
        """What the stepper controller is told; speeds are clipped to the module's maximum."""
        self.cmd_speed_m_s[ids] = np.clip(speed_m_s, 0.0, self.spec.max_speed_m_s)
        self.cmd_heading_rad[ids] = wrap_angle(np.asarray(heading_rad, dtype=float))

    def stop_all(self) -> None:
        self.cmd_speed_m_s[:] = 0.0

    def step(self, dt_s: float) -> None:
        """Advance the module dynamics by dt_s under the acceleration and steering-rate limits."""
        heading = self.cmd_heading_rad + self.heading_error_rad
        speed = self.cmd_speed_m_s * self.speed_scale
        # The two equivalent targets; pick the one that needs the smaller steering move.
        turn_fwd = wrap_angle(heading - self.heading_rad)
        turn_rev = wrap_angle(heading + math.pi - self.heading_rad)
        use_rev = np.abs(turn_rev) < np.abs(turn_fwd)
        # A stopped command needs no steering at all.
        turn = np.where(speed > 0, np.where(use_rev, turn_rev, turn_fwd), 0.0)
        target_speed = np.where(use_rev, -speed, speed)
        max_turn = self.spec.steer_rate_limit_rad_s * dt_s
        self.heading_rad = wrap_angle(self.heading_rad + np.clip(turn, -max_turn, max_turn))
        max_dv = self.spec.accel_limit_m_s2 * dt_s
        new_speed = self.speed_m_s + np.clip(target_speed - self.speed_m_s, -max_dv, max_dv)
        self.travel_m += 0.5 * (self.speed_m_s + new_speed) * dt_s
        self.speed_m_s = new_speed

    def surface_velocity_m_s(self) -> np.ndarray:
        """Belt surface velocity of each module, world frame, (n_modules, 2)."""
        return self.speed_m_s[:, None] * np.stack([np.cos(self.heading_rad), np.sin(self.heading_rad)], 1)
