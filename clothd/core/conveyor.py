"""The conveyor table as the tracker sees it: module layout and the belt velocity under any point.

The module commands are the filter's control input u. A module (col, row) sits at
((col - (mx-1)/2)·pitch, (row - (my-1)/2)·pitch) in the world (table plane, metres); its belt is a
square of side `module_size_m` turned to its heading, on a turntable of diameter `pitch_m`. Module
id = row·mx + col. This mirrors docs/recording-format.md; it is the tracker's own reading of the
layout, not the simulator's code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clothd.config import CellConfig, ModuleLimitsConfig


@dataclass(frozen=True)
class ConveyorLayout:
    modules_x: int
    modules_y: int
    pitch_m: float
    module_size_m: float  # the side of a module's square belt

    @classmethod
    def of_cell(cls, cell: CellConfig) -> ConveyorLayout:
        return cls(cell.modules_x, cell.modules_y, cell.pitch_m, cell.module_size_m)

    @property
    def n_modules(self) -> int:
        return self.modules_x * self.modules_y

    @property
    def centres_m(self) -> np.ndarray:
        """(n_modules, 2) module centres, indexed by module id."""
        cols, rows = np.meshgrid(np.arange(self.modules_x), np.arange(self.modules_y))
        return np.stack(
            [
                (cols.ravel() - (self.modules_x - 1) / 2.0) * self.pitch_m,
                (rows.ravel() - (self.modules_y - 1) / 2.0) * self.pitch_m,
            ],
            axis=1,
        )

    def belt_velocity(
        self, points_m: np.ndarray, speed_m_s: np.ndarray, heading_rad: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Surface velocity (n, 2) under world points (n, 2 or 3), and whether a belt is there (n,) bool.

        speed_m_s, heading_rad: (n_modules,) module commands. Points over the deck get zero velocity and
        False: the belts stand proud of the deck, so there is no friction there.
        """
        xy = np.asarray(points_m)[:, :2]
        col = np.rint(xy[:, 0] / self.pitch_m + (self.modules_x - 1) / 2.0).astype(int)
        row = np.rint(xy[:, 1] / self.pitch_m + (self.modules_y - 1) / 2.0).astype(int)
        on_table = (col >= 0) & (col < self.modules_x) & (row >= 0) & (row < self.modules_y)
        m = np.where(on_table, row * self.modules_x + col, 0)
        rel = xy - self.centres_m[m]
        c, s = np.cos(heading_rad[m]), np.sin(heading_rad[m])
        along = c * rel[:, 0] + s * rel[:, 1]
        across = -s * rel[:, 0] + c * rel[:, 1]
        half = self.module_size_m / 2.0
        on_belt = (
            on_table
            & (np.abs(along) <= half)
            & (np.abs(across) <= half)
            & (np.sum(rel * rel, axis=1) <= (self.pitch_m / 2.0) ** 2)
        )
        vel = np.where(on_belt[:, None], (speed_m_s[m])[:, None] * np.stack([c, s], axis=1), 0.0)
        return vel, on_belt


@dataclass(frozen=True)
class BeltField:
    """The control input u over one tick: what the modules are doing (signed speed, heading, (n_modules,)),
    and so the belts' surface velocity under any point of the table."""

    layout: ConveyorLayout
    speed_m_s: np.ndarray
    heading_rad: np.ndarray

    def velocity_at(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Belt velocity (n, 2) under world points (n, 2 or 3), and whether a belt is there (n,) bool."""
        return self.layout.belt_velocity(points_m, self.speed_m_s, self.heading_rad)

    def stopped(self) -> BeltField:
        """The same modules standing still: belts where they are, moving nowhere."""
        return BeltField(self.layout, np.zeros_like(self.speed_m_s), self.heading_rad)


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.asarray(np.pi - np.mod(np.pi - a, 2 * np.pi))


class ModuleModel:
    """What the modules are really doing, from what they were told: the steppers reach a command under
    an acceleration and a steering-rate limit, and a module reverses its belt rather than turning more
    than a quarter round (the controller's documented behaviour, docs/recording-format.md). Arrays are
    (n_modules,); speed is signed."""

    def __init__(self, n_modules: int, accel_limit_m_s2: float, steer_rate_limit_rad_s: float) -> None:
        self.accel_limit_m_s2 = accel_limit_m_s2
        self.steer_rate_limit_rad_s = steer_rate_limit_rad_s
        self.speed_m_s = np.zeros(n_modules)
        self.heading_rad = np.zeros(n_modules)

    @classmethod
    def stopped(cls, n_modules: int, limits: ModuleLimitsConfig) -> ModuleModel:
        """n_modules stopped and straight, under the configured limits."""
        return cls(n_modules, limits.accel_limit_m_s2, limits.steer_rate_limit_rad_s)

    def _step(self, cmd_speed: np.ndarray, cmd_heading: np.ndarray, dt_s: float) -> None:
        turn_fwd = _wrap(cmd_heading - self.heading_rad)
        turn_rev = _wrap(cmd_heading + np.pi - self.heading_rad)
        reverse = np.abs(turn_rev) < np.abs(turn_fwd)
        turn = np.where(cmd_speed > 0, np.where(reverse, turn_rev, turn_fwd), 0.0)
        target = np.where(reverse, -cmd_speed, cmd_speed)
        max_turn = self.steer_rate_limit_rad_s * dt_s
        self.heading_rad = _wrap(self.heading_rad + np.clip(turn, -max_turn, max_turn))
        max_dv = self.accel_limit_m_s2 * dt_s
        self.speed_m_s = self.speed_m_s + np.clip(target - self.speed_m_s, -max_dv, max_dv)

    def advance(
        self, cmd_speed_m_s: np.ndarray, cmd_heading_rad: np.ndarray, dt_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Advance by dt_s under the commands; returns the modules' (signed speed, heading) at mid-tick,
        the best single value for the tick's belt input."""
        self._step(cmd_speed_m_s, cmd_heading_rad, dt_s / 2)
        mid = (self.speed_m_s.copy(), self.heading_rad.copy())
        self._step(cmd_speed_m_s, cmd_heading_rad, dt_s / 2)
        return mid


def rigid_velocity_fit(points_m: np.ndarray, velocity_m_s: np.ndarray, centre_m: np.ndarray) -> np.ndarray:
    """Least-squares rigid motion [vx, vy, ω] about `centre_m` (2,) explaining velocities (n, 2) at points
    (n, 2): v_i ≈ v + ω·ẑ×(p_i − c). Zeros when there are no points."""
    if len(points_m) == 0:
        return np.zeros(3)
    r = points_m[:, :2] - centre_m
    # Rows for x: [1, 0, -r_y]; rows for y: [0, 1, r_x].
    A = np.zeros((2 * len(r), 3))
    A[0::2, 0] = 1.0
    A[0::2, 2] = -r[:, 1]
    A[1::2, 1] = 1.0
    A[1::2, 2] = r[:, 0]
    sol, *_ = np.linalg.lstsq(A, velocity_m_s.reshape(-1), rcond=None)
    return np.asarray(sol)
