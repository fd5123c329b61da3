"""The workspace: the part of the table the cloth may occupy while the modules move it.

A move whose target would put any corner of the cloth outside it is refused; a moving cloth whose
estimated outline leaves it (slipping, being flattened) is stopped, unless this tick's motion brings it
back in (`comes_back`): a cloth halted just past the edge must still be movable inward. By default it is
the rectangle the belts cover, less a margin: past the outer belts nothing holds or steers the cloth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clothd.config import CellConfig


@dataclass(frozen=True)
class Workspace:
    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float

    @classmethod
    def of_cell(cls, cell: CellConfig) -> Workspace:
        if cell.workspace is not None:
            a = cell.workspace
            return cls(a.x_min_m, a.x_max_m, a.y_min_m, a.y_max_m)
        # Module centres span ±(n - 1)/2 pitches; a belt reaches half its size beyond its centre.
        half_x = (cell.modules_x - 1) / 2 * cell.pitch_m + cell.module_size_m / 2 - cell.workspace_margin_m
        half_y = (cell.modules_y - 1) / 2 * cell.pitch_m + cell.module_size_m / 2 - cell.workspace_margin_m
        return cls(-half_x, half_x, -half_y, half_y)

    def outside(self, points_xy_m: np.ndarray) -> np.ndarray:
        """(n,) bool: which of the points (n, 2) lie outside."""
        x, y = points_xy_m[:, 0], points_xy_m[:, 1]
        return np.asarray((x < self.x_min_m) | (x > self.x_max_m) | (y < self.y_min_m) | (y > self.y_max_m))

    def excess_m(self, points_xy_m: np.ndarray) -> np.ndarray:
        """(n,): how far each point (n, 2) lies outside (0 inside)."""
        x, y = points_xy_m[:, 0], points_xy_m[:, 1]
        dx = np.maximum(self.x_min_m - x, 0.0) + np.maximum(x - self.x_max_m, 0.0)
        dy = np.maximum(self.y_min_m - y, 0.0) + np.maximum(y - self.y_max_m, 0.0)
        return np.asarray(np.hypot(dx, dy))

    def comes_back(self, outline_xy_m: np.ndarray, pose: np.ndarray, twist: np.ndarray, dt_s: float) -> bool:
        """Whether moving the outline rigidly by `twist` [vx_m_s, vy_m_s, omega_rad_s] about the cloth's
        centre pose[:2] for dt_s brings it back in: no point goes further out, and some come closer."""
        before = self.excess_m(outline_xy_m)
        after = self.excess_m(rigid_step(outline_xy_m, pose[:2], twist, dt_s))
        return bool(np.all(after <= before) and after.sum() < before.sum())

    def leaves(self, outline_xy_m: np.ndarray) -> str | None:
        """Why an outline (k, 2) is not inside, in words; None when it is."""
        out = self.outside(outline_xy_m)
        if not out.any():
            return None
        x, y = outline_xy_m[np.flatnonzero(out)[0]]
        return (
            f"the cloth would reach ({x:.3f}, {y:.3f}) m, outside the workspace"
            f" x {self.x_min_m:.3f}..{self.x_max_m:.3f} m, y {self.y_min_m:.3f}..{self.y_max_m:.3f} m"
            " (cell.workspace)"
        )


def cloth_corners_m(pose: np.ndarray, size_m: tuple[float, float]) -> np.ndarray:
    """The corners (4, 2) of a width x height cloth at pose [X_m, Y_m, theta_rad]."""
    w, h = size_m[0] / 2, size_m[1] / 2
    c, s = math.cos(pose[2]), math.sin(pose[2])
    body = np.array([[-w, -h], [w, -h], [w, h], [-w, h]])
    return np.asarray(body @ np.array([[c, s], [-s, c]]) + pose[:2])


def rigid_step(points_xy_m: np.ndarray, centre_m: np.ndarray, twist: np.ndarray, dt_s: float) -> np.ndarray:
    """The points (n, 2) after turning by twist[2] * dt_s about `centre_m` and moving by twist[:2] * dt_s."""
    a = float(twist[2]) * dt_s
    c, s = math.cos(a), math.sin(a)
    rel = points_xy_m - centre_m
    turned = rel @ np.array([[c, s], [-s, c]])
    return np.asarray(turned + centre_m + np.asarray(twist[:2]) * dt_s)
