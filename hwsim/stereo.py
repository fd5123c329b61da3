"""How precisely a camera pair measures height: first-order error propagation through triangulation.

A point X seen by cameras a and b at pixels p = (P_a(X), P_b(X)) is triangulated by least squares; with
independent pixel noise of sigma px on every coordinate its covariance is sigma² (JᵀJ)⁻¹, J the 4 x 3
Jacobian of p by X. The height precision is the z standard deviation. Used to choose the live cell's
oblique camera (docs/hwsim.md, "Two cameras").
"""

from __future__ import annotations

import math

import numpy as np

from hwsim.camera import Camera
from hwsim.scenario import CameraSpec

_STEP_M = 1e-6  # central differences of the projection; it is smooth at this scale


def triangulation_cov_m2(cameras: list[Camera], point_m: np.ndarray, pixel_noise_px: float) -> np.ndarray:
    """The 3 x 3 covariance (m²) of `point_m` triangulated from `cameras` with that pixel noise."""
    point_m = np.asarray(point_m, dtype=float)
    rows = []
    for cam in cameras:
        cols = []
        for axis in range(3):
            d = np.zeros(3)
            d[axis] = _STEP_M
            cols.append((cam.project(point_m + d) - cam.project(point_m - d)) / (2 * _STEP_M))
        rows.append(np.stack(cols, axis=-1))  # (2, 3) pixels per metre
    J = np.concatenate(rows, axis=0)
    return np.asarray(pixel_noise_px**2 * np.linalg.inv(J.T @ J))


def height_precision_mm(
    cam_a: Camera, cam_b: Camera, pixel_noise_px: float, point_m: tuple[float, float, float] = (0, 0, 0)
) -> float:
    """Standard deviation (mm) of the height of `point_m` (default the table's centre) triangulated from
    the pair, each pixel coordinate carrying `pixel_noise_px` of independent noise."""
    cov = triangulation_cov_m2([cam_a, cam_b], np.asarray(point_m, dtype=float), pixel_noise_px)
    return float(math.sqrt(cov[2, 2]) * 1e3)


def oblique_spec(base: CameraSpec, angle_rad: float, range_m: float, f_px: float, name: str) -> CameraSpec:
    """A camera `range_m` from the table's centre, on the -y side, tilted `angle_rad` from vertical so
    that it looks at the centre: its baseline to a camera straight above is range_m·sin(angle)."""
    position = (0.0, -range_m * math.sin(angle_rad), range_m * math.cos(angle_rad))
    return base.model_copy(update={"position_m": position, "tilt_rad": angle_rad, "f_px": f_px, "name": name})


def sees_table(camera: Camera, half_extent_m: tuple[float, float], margin_px: float = 4.0) -> bool:
    """Every corner of the table's rectangle lies inside the image, `margin_px` from its border."""
    hx, hy = half_extent_m
    corners = np.array([[sx * hx, sy * hy, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    if np.any(camera.to_camera(corners)[:, 2] <= 0):
        return False
    px = camera.project(corners)
    inside_u = (px[:, 0] >= margin_px) & (px[:, 0] <= camera.width - 1 - margin_px)
    inside_v = (px[:, 1] >= margin_px) & (px[:, 1] <= camera.height - 1 - margin_px)
    return bool(np.all(inside_u & inside_v))
