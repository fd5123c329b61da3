"""The simulated camera: pinhole K with OpenCV lens distortion and a pose over the table.

World: the table plane is z = 0, metres, z up. Camera frame: OpenCV's (x right, y down, z forward).
`T_cam_world` maps world points into the camera frame. Pixel centres sit at integer coordinates, as in
OpenCV; `scaled()` keeps that convention for a supersampled render.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from hwsim.scenario import CameraSpec

# Camera looking straight down: its x along world x, its y along world -y, its z along world -z.
_LOOK_DOWN = np.diag([1.0, -1.0, -1.0])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@dataclass(frozen=True)
class Camera:
    """K (3, 3), dist (5,) in OpenCV order (k1, k2, p1, p2, k3), T_cam_world (4, 4), image size."""

    K: np.ndarray
    dist: np.ndarray
    T_cam_world: np.ndarray
    width: int
    height: int

    @classmethod
    def from_spec(cls, spec: CameraSpec) -> Camera:
        cx, cy = spec.principal_px or ((spec.width - 1) / 2.0, (spec.height - 1) / 2.0)
        K = np.array([[spec.f_px, 0.0, cx], [0.0, spec.f_px, cy], [0.0, 0.0, 1.0]])
        R_world_cam = _rot_z(spec.yaw_rad) @ _rot_x(spec.tilt_rad) @ _LOOK_DOWN
        centre_m = np.asarray(spec.position_m, dtype=float)
        T = np.eye(4)
        T[:3, :3] = R_world_cam.T
        T[:3, 3] = -R_world_cam.T @ centre_m
        return cls(K, np.asarray(spec.dist, dtype=float), T, spec.width, spec.height)

    @property
    def centre_m(self) -> np.ndarray:
        """Optical centre in world coordinates, (3,)."""
        R, t = self.T_cam_world[:3, :3], self.T_cam_world[:3, 3]
        return np.asarray(-R.T @ t)

    def scaled(self, factor: int) -> Camera:
        """The same camera rendering `factor` times more pixels per side. Low-res pixel u covers hi-res
        pixels factor*u .. factor*u + factor - 1, whose mean centre is factor*u + (factor - 1)/2."""
        K = self.K.copy()
        K[:2, :2] *= factor
        K[:2, 2] = K[:2, 2] * factor + (factor - 1) / 2.0
        return Camera(K, self.dist, self.T_cam_world, self.width * factor, self.height * factor)

    def to_camera(self, points_m: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera-frame points (..., 3)."""
        R, t = self.T_cam_world[:3, :3], self.T_cam_world[:3, 3]
        return np.asarray(points_m @ R.T + t)

    def project(self, points_m: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> pixels (..., 2), with lens distortion. Points must be in front."""
        pc = self.to_camera(points_m)
        x = pc[..., 0] / pc[..., 2]
        y = pc[..., 1] / pc[..., 2]
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        u = self.K[0, 0] * xd + self.K[0, 1] * yd + self.K[0, 2]
        v = self.K[1, 1] * yd + self.K[1, 2]
        return np.stack([u, v], axis=-1)

    def pixel_rays(self) -> np.ndarray:
        """Unit viewing rays in world coordinates for every pixel centre, (height, width, 3)."""
        us, vs = np.meshgrid(
            np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64)
        )
        pix = np.stack([us.ravel(), vs.ravel()], axis=-1).reshape(-1, 1, 2)
        norm = cv2.undistortPoints(pix, self.K, self.dist).reshape(-1, 2)
        rays_cam = np.concatenate([norm, np.ones((len(norm), 1))], axis=1)
        rays_world = rays_cam @ self.T_cam_world[:3, :3]  # R^T applied to each row
        rays_world /= np.linalg.norm(rays_world, axis=1, keepdims=True)
        return rays_world.reshape(self.height, self.width, 3)

    def table_points(self) -> np.ndarray:
        """Where each pixel's ray meets the table plane z = 0, world metres, (height, width, 2).
        Pixels whose ray misses the plane (looking up) get NaN."""
        rays = self.pixel_rays()
        c = self.centre_m
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.where(rays[..., 2] < -1e-9, -c[2] / rays[..., 2], np.nan)
        return c[:2] + lam[..., None] * rays[..., :2]

    def to_json(self) -> dict[str, object]:
        return {
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "width": self.width,
            "height": self.height,
            "T_cam_world": self.T_cam_world.tolist(),
        }

    def save(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n")

    @classmethod
    def load(cls, path: Path) -> Camera:
        d = json.loads(path.read_text())
        return cls(
            np.asarray(d["K"], dtype=float),
            np.asarray(d["dist"], dtype=float),
            np.asarray(d["T_cam_world"], dtype=float),
            int(d["width"]),
            int(d["height"]),
        )
