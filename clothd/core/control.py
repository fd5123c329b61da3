"""From setpoint and estimate to module commands.

Modes: `idle` stops every module; `hold` keeps the pose the cloth had when hold began; `move` drives it to
a target pose [X_m, Y_m, theta_rad]; `flatten` holds the pose and flattens the cloth; `drive` plays a
drive script (core/drive_script.py), the modules told what it says rather than planned here. hold and move
flatten as they go when `control.flatten` is set (core/flattening.py).

The cloth is moved as a rigid body. Its planned twist (vx, vy, ω about its centre) heads for the target
at a speed that is the least of the configured maximum, the speed from which the acceleration limit
can still stop it in the remaining distance, and gain x distance (a smooth final approach); the twist
changes by at most the acceleration limit per tick. Every module under the cloth is then commanded to
the velocity of the rigid field at its centre, v = V + ω ẑ × (c_m − X); friction carries the cloth with
it. Modules not under the cloth stop. If the fastest module would exceed its maximum speed, the whole
field is scaled down, which keeps it rigid.

The flattening regulator's per-module velocities join the rigid field in `module_commands`, before the
speed limit is applied.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from clothd.config import CellConfig, ControlConfig
from clothd.core.drive_script import DrivePlan
from clothd.core.messages import ModuleCommands
from clothd.core.modes import Mode

STILL_SPEED_M_S = 1e-6  # slower than this a module is stopped and keeps its heading


@dataclass(frozen=True)
class Setpoint:
    mode: Mode
    pose: np.ndarray | None  # (3,) target [X_m, Y_m, theta_rad] for move and hold
    drive: DrivePlan | None = None  # the script a drive plays (core/drive_script.py)
    started_mono_s: float = 0.0  # when it was set, on the host's monotonic clock (both processes')


def _approach_speed(distance: float, v_max: float, a_max: float, gain: float) -> float:
    return min(v_max, math.sqrt(2.0 * a_max * distance), gain * distance)


class PoseController:
    """Plans the cloth's rigid twist towards a target pose and turns it into module commands.

    module_centres_m (n_modules, 2): where each module sits, indexed by module id. `plan_twist` keeps the
    twist of the last tick (the acceleration limit acts across ticks); `stop` and `reset` zero it."""

    def __init__(self, cfg: ControlConfig, cell: CellConfig, module_centres_m: np.ndarray) -> None:
        self.cfg = cfg
        self.cell = cell
        self.centres_m = module_centres_m  # (n_modules, 2)
        self.twist = np.zeros(3)  # the planned (vx, vy, ω) of the last tick
        self.heading_rad = np.zeros(len(module_centres_m))  # stopped modules keep their heading

    def reset(self) -> None:
        self.twist = np.zeros(3)

    def plan_twist(self, pose: np.ndarray, target: np.ndarray, dt_s: float) -> np.ndarray:
        """The twist (3,) for this tick, from pose (3,) towards target (3,), within the limits."""
        c = self.cfg
        err_xy = target[:2] - pose[:2]
        dist = float(np.linalg.norm(err_xy))
        v_want = (
            err_xy / dist * _approach_speed(dist, c.max_speed_m_s, c.max_accel_m_s2, c.gain_1_s)
            if dist > 0
            else np.zeros(2)
        )
        err_th = math.remainder(float(target[2] - pose[2]), 2 * math.pi)
        w_want = math.copysign(
            _approach_speed(abs(err_th), c.max_rate_rad_s, c.max_ang_accel_rad_s2, c.gain_1_s), err_th
        )
        dv = v_want - self.twist[:2]
        dv_max = c.max_accel_m_s2 * dt_s
        norm = float(np.linalg.norm(dv))
        if norm > dv_max:
            dv *= dv_max / norm
        dw = float(
            np.clip(w_want - self.twist[2], -c.max_ang_accel_rad_s2 * dt_s, c.max_ang_accel_rad_s2 * dt_s)
        )
        self.twist = np.array([self.twist[0] + dv[0], self.twist[1] + dv[1], self.twist[2] + dw])
        return self.twist.copy()

    def module_commands(
        self, pose: np.ndarray, twist: np.ndarray, under: np.ndarray, shaping_m_s: np.ndarray | None = None
    ) -> ModuleCommands:
        """Commands for every module: the rigid field of `twist` about the cloth centre pose[:2], plus the
        shaping velocities (n_modules, 2) when given, for the modules `under` the cloth (bool, n_modules);
        zero elsewhere."""
        rel = self.centres_m - pose[:2]
        v = twist[:2] + twist[2] * np.stack([-rel[:, 1], rel[:, 0]], axis=1)
        if shaping_m_s is not None:
            v = v + shaping_m_s
        v[~under] = 0.0
        speed = np.linalg.norm(v, axis=1)
        fastest = float(speed.max(initial=0.0))
        if fastest > self.cell.max_speed_m_s:
            v *= self.cell.max_speed_m_s / fastest
            speed *= self.cell.max_speed_m_s / fastest
        moving = speed > STILL_SPEED_M_S
        self.heading_rad = np.where(moving, np.arctan2(v[:, 1], v[:, 0]), self.heading_rad)
        return ModuleCommands(speed, self.heading_rad.copy())

    def stop(self) -> ModuleCommands:
        self.twist = np.zeros(3)
        return ModuleCommands.all_stop(len(self.centres_m), self.heading_rad)

    def modules_under(self, outline_xy: np.ndarray, margin_m: float | None = None) -> np.ndarray:
        """(n_modules,) bool: the module's centre lies at least margin_m (None: `under_cloth_margin_m`)
        inside the outline; a negative margin reaches outside it."""
        contour = outline_xy.astype(np.float32).reshape(-1, 1, 2)
        margin = self.cfg.under_cloth_margin_m if margin_m is None else margin_m
        return np.array(
            [cv2.pointPolygonTest(contour, (float(x), float(y)), True) >= margin for x, y in self.centres_m]
        )
