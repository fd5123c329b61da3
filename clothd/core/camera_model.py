"""The tracker's camera: pinhole K, OpenCV lens distortion (k1, k2, p1, p2, k3) and a pose over the table.

Conventions (docs/recording-format.md): world = table plane z = 0, metres, z up; `T_cam_world` maps world
points to OpenCV camera coordinates (x right, y down, z forward); the centre of the top-left pixel is
(0, 0). For a world point P the pixel is

    p_c = R P + t,   (x, y) = (p_c,x / p_c,z, p_c,y / p_c,z),   r² = x² + y²
    radial = 1 + k1 r² + k2 r⁴ + k3 r⁶
    x_d = x radial + 2 p1 x y + p2 (r² + 2 x²),   y_d = y radial + p1 (r² + 2 y²) + 2 p2 x y
    u = fx x_d + s y_d + cx,   v = fy y_d + cy          (s = K[0, 1], zero for OpenCV-made K)

which is cv2.projectPoints (that ignores a skew s; so does hwsim's camera only when s = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# Camera looking straight down: its x along world +x, its y along world -y, its z along world -z.
_LOOK_DOWN = np.diag([1.0, -1.0, -1.0])


def _frozen(a: np.ndarray) -> np.ndarray:
    out = np.array(a, dtype=np.float64)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class CameraModel:
    """K (3, 3), dist (5,) in OpenCV order (k1, k2, p1, p2, k3), T_cam_world (4, 4), image size in px.

    The arrays are copied to read-only float64 on construction. Points must lie in front of the camera
    (p_c,z > 0); nothing checks that in `project`, a point behind it gives a meaningless pixel."""

    K: np.ndarray
    dist: np.ndarray
    T_cam_world: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K, dist, T = _frozen(self.K), _frozen(self.dist).ravel(), _frozen(self.T_cam_world)
        if K.shape != (3, 3) or dist.shape != (5,) or T.shape != (4, 4):
            raise ValueError(
                f"camera: K (3, 3), dist (5,), T_cam_world (4, 4); got {K.shape}, {dist.shape}, {T.shape}"
            )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "T_cam_world", T)

    @classmethod
    def ideal(cls, width: int, height: int, f_px: float, distance_m: float) -> CameraModel:
        """No calibration: principal point at the image centre ((w-1)/2, (h-1)/2), no distortion, camera
        straight down at (0, 0, distance_m); image x along world +x, image y along world -y."""
        K = np.array([[f_px, 0.0, (width - 1) / 2.0], [0.0, f_px, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        T = np.eye(4)
        T[:3, :3] = _LOOK_DOWN  # its own inverse: R_cam_world = R_world_cam
        T[:3, 3] = -_LOOK_DOWN @ np.array([0.0, 0.0, distance_m])
        return cls(K, np.zeros(5), T, int(width), int(height))

    @property
    def centre_m(self) -> np.ndarray:
        """Optical centre in world coordinates, (3,), metres: c = -Rᵀ t."""
        R, t = self.T_cam_world[:3, :3], self.T_cam_world[:3, 3]
        return np.asarray(-R.T @ t)

    def to_camera(self, points_m: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera-frame points (..., 3), metres: p_c = R P + t."""
        R, t = self.T_cam_world[:3, :3], self.T_cam_world[:3, 3]
        return np.asarray(np.asarray(points_m, dtype=float) @ R.T + t)

    def _distort(self, xy: np.ndarray) -> np.ndarray:
        """Normalised undistorted (..., 2) -> normalised distorted (..., 2)."""
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def _distort_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """d(x_d, y_d)/d(x, y) at normalised points (..., 2) -> (..., 2, 2)."""
        k1, k2, p1, p2, k3 = self.dist
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        g = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r²
        cross = 2.0 * x * y * g + 2.0 * p1 * x + 2.0 * p2 * y  # the same in both off-diagonal terms
        J = np.empty((*xy.shape[:-1], 2, 2))
        J[..., 0, 0] = radial + 2.0 * x * x * g + 2.0 * p1 * y + 6.0 * p2 * x
        J[..., 0, 1] = cross
        J[..., 1, 0] = cross
        J[..., 1, 1] = radial + 2.0 * y * y * g + 6.0 * p1 * y + 2.0 * p2 * x
        return J

    def _to_pixels(self, xyd: np.ndarray) -> np.ndarray:
        K = self.K
        u = K[0, 0] * xyd[..., 0] + K[0, 1] * xyd[..., 1] + K[0, 2]
        v = K[1, 1] * xyd[..., 1] + K[1, 2]
        return np.stack([u, v], axis=-1)

    def table_homography(self) -> np.ndarray:
        """H (3, 3) mapping table-plane points [x, y, 1] (metres, z = 0) to pixels, lens distortion left
        out: K [r1 r2 t] of the plane's pose. For drawing and picking in a browser, not for measuring."""
        R, t = self.T_cam_world[:3, :3], self.T_cam_world[:3, 3]
        H = self.K @ np.column_stack([R[:, 0], R[:, 1], t])
        return np.asarray(H / H[2, 2])

    def project(self, points_m: np.ndarray) -> np.ndarray:
        """World points (..., 3), metres -> pixels (..., 2), lens distortion included."""
        pc = self.to_camera(points_m)
        return self._to_pixels(self._distort(pc[..., :2] / pc[..., 2:3]))

    def project_jacobian(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (n, 3) -> (pixels (n, 2), J (n, 2, 3) = d pixel / d world point, px/m).

        Analytic chain rule: J = K₂ₓ₂ · D(x, y) · [[1/z, 0, -x/z], [0, 1/z, -y/z]] · R, where K₂ₓ₂ is
        [[fx, s], [0, fy]] and D the distortion Jacobian at the normalised point (x, y)."""
        pc = self.to_camera(np.asarray(points_m, dtype=float).reshape(-1, 3))
        inv_z = 1.0 / pc[:, 2]
        xy = pc[:, :2] * inv_z[:, None]
        pixels = self._to_pixels(self._distort(xy))
        d_norm = np.zeros((len(pc), 2, 3))  # d(x, y)/d p_c
        d_norm[:, 0, 0] = inv_z
        d_norm[:, 1, 1] = inv_z
        d_norm[:, :, 2] = -xy * inv_z[:, None]
        K2 = self.K[:2, :2]
        J = K2 @ self._distort_jacobian(xy) @ d_norm @ self.T_cam_world[:3, :3]
        return pixels, J

    def undistort(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) -> normalised undistorted coordinates (n, 2) (x, y with p_c = z (x, y, 1)).

        cv2.undistortPoints' fixed-point iteration, then two Newton steps on the analytic distortion
        Jacobian so that `project` is inverted to ~1e-12 rather than to OpenCV's iteration tolerance."""
        pix = np.asarray(pixels, dtype=float).reshape(-1, 2)
        K = self.K
        # Undo K ourselves (OpenCV's undistortPoints ignores a skew) and hand OpenCV an identity matrix.
        yd = (pix[:, 1] - K[1, 2]) / K[1, 1]
        xd = (pix[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        target = np.column_stack([xd, yd])
        if not np.any(self.dist):
            return target
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)
        xy = cv2.undistortPoints(target.reshape(-1, 1, 2), np.eye(3), self.dist, criteria=criteria)
        xy = xy.reshape(-1, 2)
        for _ in range(2):
            residual = self._distort(xy) - target
            xy = xy - np.linalg.solve(self._distort_jacobian(xy), residual[..., None])[..., 0]
        return np.asarray(xy)

    def backproject_to_plane(self, pixels: np.ndarray, z_m: float = 0.0) -> np.ndarray:
        """Pixels (n, 2) -> world points (n, 3), metres, on the plane z = z_m seen at each pixel.

        The ray c + λ d with d = Rᵀ (x, y, 1) meets the plane at λ = (z_m - c_z) / d_z; NaN where the
        ray is parallel to the plane or meets it behind the camera (λ <= 0)."""
        xy = self.undistort(pixels)
        rays = np.column_stack([xy, np.ones(len(xy))]) @ self.T_cam_world[:3, :3]  # Rᵀ d_c for each row
        c = self.centre_m
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (z_m - c[2]) / rays[:, 2]
        lam = np.where(np.isfinite(lam) & (lam > 0.0), lam, np.nan)
        return np.asarray(c + lam[:, None] * rays)
