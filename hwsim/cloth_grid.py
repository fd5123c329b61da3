"""The truth cloth's grid: its nodes' material layout, where a pose lays them (ridges laid in, flaps folded
over), their strains and masses, and their bends measured as the solver measures them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hwsim.ridges import lay_ridges
from hwsim.scenario import ClothSpec, Flap, Pose

# A flap lies on the cloth beneath it: its nodes' floor is one cloth thickness up (hwsim has no
# self-contact; the floor stays with those nodes wherever they go).
FLAP_THICKNESS_M = 0.001


def bends_in_own_frames(x_m: np.ndarray) -> np.ndarray:
    """Second differences along axis 1 of nodes x_m (ny, nx, 3), each in its own frame (along its chord,
    across it, up): (ny, nx - 2, 3), as `ClothSim._bend_frame` measures them."""
    bend = x_m[:, :-2] - 2.0 * x_m[:, 1:-1] + x_m[:, 2:]
    chord = x_m[:, 2:, :2] - x_m[:, :-2, :2]
    # A flap's crease may stack a chord's ends: no direction then, and no NaN.
    along = chord / np.maximum(np.linalg.norm(chord, axis=-1, keepdims=True), 1e-12)
    across = np.stack([-along[..., 1], along[..., 0]], axis=-1)
    level = bend[..., :2]
    local = np.stack([(level * along).sum(axis=-1), (level * across).sum(axis=-1), bend[..., 2]], axis=-1)
    return np.ascontiguousarray(local, dtype=np.float64)


@dataclass(frozen=True)
class ClothGrid:
    """Node layout of the truth mesh. `st_m` (ny, nx, 2): material (flat) coordinates, origin at a corner."""

    nx: int
    ny: int
    dx_m: float
    dy_m: float

    @classmethod
    def from_spec(cls, spec: ClothSpec) -> ClothGrid:
        w, h = spec.size_m
        nx = round(w / spec.spacing_m) + 1
        ny = round(h / spec.spacing_m) + 1
        return cls(nx, ny, w / (nx - 1), h / (ny - 1))

    @property
    def st_m(self) -> np.ndarray:
        s, t = np.meshgrid(np.arange(self.nx) * self.dx_m, np.arange(self.ny) * self.dy_m)
        return np.stack([s, t], axis=-1)

    def placed(self, pose: Pose) -> np.ndarray:
        """World positions (ny, nx, 3) of the cloth with its centre at (x, y), rotated by theta: flat, or
        with the pose's ridges laid in (hwsim/ridges.py), which keeps the sheet's lengths, and its flaps
        folded over."""
        centre = np.array([(self.nx - 1) * self.dx_m, (self.ny - 1) * self.dy_m]) / 2.0
        xy, z = lay_ridges(self.st_m - centre, pose.ridges)
        for flap in pose.flaps:
            xy, z = self._fold(flap, xy, z, centre)
        c, s = np.cos(pose.theta_rad), np.sin(pose.theta_rad)
        x = c * xy[..., 0] - s * xy[..., 1] + pose.x_m
        y = s * xy[..., 0] + c * xy[..., 1] + pose.y_m
        return np.stack([x, y, z], axis=-1)

    def edge_strains(self, x_m: np.ndarray) -> np.ndarray:
        """Strain of every grid edge of nodes (ny, nx, 3), those along rows then along columns, flattened."""
        along_x = np.linalg.norm(np.diff(x_m, axis=1), axis=-1) / self.dx_m - 1.0
        along_y = np.linalg.norm(np.diff(x_m, axis=0), axis=-1) / self.dy_m - 1.0
        return np.concatenate([along_x.ravel(), along_y.ravel()])

    def folded(self, pose: Pose) -> np.ndarray:
        """(ny, nx) the nodes that the pose's flaps fold over."""
        mask = np.zeros((self.ny, self.nx), dtype=bool)
        for flap in pose.flaps:
            mask |= self._flap_local_m(flap).sum(axis=-1) < flap.size_m
        return mask

    def _flap_local_m(self, flap: Flap) -> np.ndarray:
        """Material distances (ny, nx, 2) of the nodes from the flap's corner, along its two edges."""
        size = np.array([(self.nx - 1) * self.dx_m, (self.ny - 1) * self.dy_m])
        high = np.array([flap.corner[0] == "+", flap.corner[2] == "+"])
        return np.abs(self.st_m - np.where(high, size, 0.0))

    def _fold(
        self, flap: Flap, xy: np.ndarray, z: np.ndarray, centre: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Fold the corner over along a + b = size (a, b: distances from the corner along its edges):
        a node at (a, b) lands on the material point at (size - b, size - a), one thickness up."""
        ab = self._flap_local_m(flap)
        over = ab.sum(axis=-1) < flap.size_m
        high = np.array([flap.corner[0] == "+", flap.corner[2] == "+"])
        size = np.array([(self.nx - 1) * self.dx_m, (self.ny - 1) * self.dy_m])
        corner = np.where(high, size, 0.0)
        inward = np.where(high, -1.0, 1.0)
        landing = corner + inward * (flap.size_m - ab[..., ::-1])
        xy = xy.copy()
        xy[over] = landing[over] - centre
        z = np.where(over, z + FLAP_THICKNESS_M, z)
        return xy, z

    def node_masses_kg(self, areal_density_kg_m2: float) -> np.ndarray:
        """Lumped masses (ny, nx): each node carries the area of the cell quarters around it."""
        wx = np.full(self.nx, self.dx_m)
        wx[[0, -1]] /= 2
        wy = np.full(self.ny, self.dy_m)
        wy[[0, -1]] /= 2
        return np.asarray(areal_density_kg_m2 * np.outer(wy, wx))
