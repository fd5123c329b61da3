"""Checking a module with the camera: how its belt surface moved, and what that says of its calibration.

A module driven alone does not move a cloth that lies over it: the belts around hold the cloth by
friction, and the driven belt slides beneath it (hwsim: 0.02 mm of cloth motion for 20 mm of belt).
What moves with the belt is its own surface, or a card lying on it alone, so the check watches that: the
middle of the belt, a square that stays inside the belt at any heading, resampled from the picture onto
the table plane (`BeltPatch`), and its shift from frame to frame (phase correlation, then Lucas-Kanade).
The fitted surface velocity against the command gives the module's direction, heading offset and speed
scale (`calibration_of`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from clothd.core.camera_model import CameraModel

PATCH_M_PER_PX = 0.0005  # finer than the camera's ~1.1 mm pixel: the resampling keeps its sub-pixel detail
BLUR_PX = 2.0  # 1 mm
LK_WINDOW_PX = 21
LK_MARGIN_PX = 12  # grid points this far inside the patch, so their windows see only the belt's middle
LK_STEP_PX = 4


@dataclass(frozen=True)
class BeltPatch:
    """The square of side `side_m` centred on `centre_m` on the table, resampled to a top-down picture
    whose columns run along world +x and rows along world +y, PATCH_M_PER_PX a pixel."""

    map_x: np.ndarray
    map_y: np.ndarray
    window: np.ndarray

    @classmethod
    def of(cls, camera: CameraModel, centre_m: np.ndarray, side_m: float) -> BeltPatch:
        n = round(side_m / PATCH_M_PER_PX)
        offsets = (np.arange(n) - (n - 1) / 2.0) * PATCH_M_PER_PX
        gx, gy = np.meshgrid(centre_m[0] + offsets, centre_m[1] + offsets)
        px = camera.project(np.stack([gx, gy, np.zeros_like(gx)], axis=-1))
        window = cv2.createHanningWindow((n, n), cv2.CV_64F)
        return cls(px[..., 0].astype(np.float32), px[..., 1].astype(np.float32), window)

    def inside(self, width: int, height: int) -> bool:
        """Whether every sample lies in a width x height picture."""
        return bool(
            self.map_x.min() >= 0
            and self.map_y.min() >= 0
            and self.map_x.max() <= width - 1
            and self.map_y.max() <= height - 1
        )

    def sample(self, image_bgr: np.ndarray) -> np.ndarray:
        """The patch, 8-bit grey, from a BGR picture."""
        grey = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
        patch = cv2.remap(grey, self.map_x, self.map_y, cv2.INTER_LINEAR)
        # A JPEG camera's 8 x 8 blocks are edges that stand still: unblurred, they pulled hwsim's belts'
        # measured direction 1.2° towards the picture's axes.
        return np.asarray(cv2.GaussianBlur(patch, (0, 0), BLUR_PX))


def surface_shift_m(before: np.ndarray, after: np.ndarray, window: np.ndarray) -> np.ndarray | None:
    """How far the surface in patch `before` moved to reach `after` (8-bit, BeltPatch.sample), world
    [dx_m, dy_m]; None when too few points follow it. Phase correlation finds the shift to a pixel or so
    (a belt's ribs bias its sub-pixel part by up to 10 %, measured on hwsim's belts); Lucas-Kanade from
    there, on a grid of points, gives it to 1 % (their median: a speck of dust or a glint is outvoted)."""
    (dx_px, dy_px), _ = cv2.phaseCorrelate(before.astype(np.float64), after.astype(np.float64), window)
    n = before.shape[0]
    g = np.arange(LK_MARGIN_PX, n - LK_MARGIN_PX, LK_STEP_PX, dtype=np.float32)
    points = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 1, 2)
    guess = points + np.array([dx_px, dy_px], np.float32)
    moved, found, _ = cv2.calcOpticalFlowPyrLK(
        before,
        after,
        points,
        guess,
        winSize=(LK_WINDOW_PX, LK_WINDOW_PX),
        maxLevel=1,
        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    ok = found[:, 0] == 1
    if ok.sum() < len(points) // 2:
        return None
    return np.asarray(np.median((moved - points)[ok].reshape(-1, 2), axis=0), dtype=float) * PATCH_M_PER_PX


def mean_velocity_m_s(dt_s: np.ndarray, shifts_m: np.ndarray) -> np.ndarray:
    """The surface's mean velocity [vx, vy] over frame pairs dt_s (n,) apart that moved it shifts_m (n, 2):
    their sum over their time, so a pair left out (a glint) leaves a gap, not a jump."""
    return np.asarray(shifts_m.sum(axis=0) / dt_s.sum())


@dataclass(frozen=True)
class ModuleCalibrationEntry:
    """What a module does with a command: runs `reversed` or not, at heading + heading_offset_deg, at speed
    x speed_scale. A reversal and a 180° heading offset look alike; the offset is kept within ±90°."""

    module: int
    reversed: bool
    heading_offset_deg: float
    speed_scale: float


def calibration_of(
    module: int, speed_m_s: float, heading_rad: float, velocity_m_s: np.ndarray
) -> ModuleCalibrationEntry:
    """The calibration that turns the command (speed_m_s > 0 at heading_rad) into the measured velocity."""
    error = math.remainder(math.atan2(velocity_m_s[1], velocity_m_s[0]) - heading_rad, 2 * math.pi)
    reversed_ = abs(error) > math.pi / 2
    offset = math.remainder(error - math.pi, 2 * math.pi) if reversed_ else error
    scale = float(np.hypot(*velocity_m_s)) / speed_m_s
    return ModuleCalibrationEntry(module, reversed_, math.degrees(offset), scale)
