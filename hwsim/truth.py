"""Reading ground truth: where a material point of the cloth is, in the world and in the image.

The truth surface is the node grid split into triangles along each cell's (j, i)-(j+1, i+1) diagonal,
the surface the renderer draws. A material point (s, t) lies in cell (j, i) = (⌊t/dy⌋, ⌊s/dx⌋) at
fractions (a, b) = (s/dx - i, t/dy - j): in the triangle (j,i), (j,i+1), (j+1,i+1) when a >= b,
else in (j,i), (j+1,i+1), (j+1,i); its position is the barycentric blend of those three nodes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Truth:
    t_s: np.ndarray  # (F,)
    nodes_m: np.ndarray  # (F, ny, nx, 3)
    st_m: np.ndarray  # (ny, nx, 2)
    visible: np.ndarray  # (F, ny, nx) bool

    @classmethod
    def load(cls, recording_dir: Path) -> Truth:
        with np.load(recording_dir / "truth.npz") as z:
            return cls(z["t_s"], z["nodes_m"].astype(np.float64), z["st_m"], z["visible"])

    @property
    def spacing_m(self) -> tuple[float, float]:
        return float(self.st_m[0, 1, 0] - self.st_m[0, 0, 0]), float(self.st_m[1, 0, 1] - self.st_m[0, 0, 1])

    @property
    def size_m(self) -> tuple[float, float]:
        return float(self.st_m[0, -1, 0]), float(self.st_m[-1, 0, 1])


def surface_weights(
    st_m: np.ndarray, spacing_m: tuple[float, float], shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """For material points (n, 2): node indices (n, 3, 2) as (j, i) and barycentric weights (n, 3)."""
    dx, dy = spacing_m
    ny, nx = shape
    fs, ft = st_m[:, 0] / dx, st_m[:, 1] / dy
    i = np.clip(np.floor(fs).astype(int), 0, nx - 2)
    j = np.clip(np.floor(ft).astype(int), 0, ny - 2)
    a, b = fs - i, ft - j
    lower = a >= b
    idx = np.empty((len(st_m), 3, 2), int)
    w = np.empty((len(st_m), 3))
    idx[:, 0] = np.stack([j, i], 1)
    idx[:, 2] = np.stack([j + 1, i + 1], 1)
    idx[:, 1] = np.where(lower[:, None], np.stack([j, i + 1], 1), np.stack([j + 1, i], 1))
    w[:, 0] = np.where(lower, 1 - a, 1 - b)
    w[:, 1] = np.where(lower, a - b, b - a)
    w[:, 2] = np.where(lower, b, a)
    return idx, w


def surface_points(nodes_m: np.ndarray, idx: np.ndarray, w: np.ndarray) -> np.ndarray:
    """World positions (..., n, 3) of material points from nodes (..., ny, nx, 3)."""
    corners = nodes_m[..., idx[:, :, 0], idx[:, :, 1], :]  # (..., n, 3, 3)
    return np.asarray(np.einsum("...nkc,nk->...nc", corners, w))


def surface_normals(nodes_m: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Unit normals (..., n, 3) of the triangles holding the material points (oriented along s x t)."""
    c = nodes_m[..., idx[:, :, 0], idx[:, :, 1], :]
    e1, e2 = c[..., 1, :] - c[..., 0, :], c[..., 2, :] - c[..., 0, :]
    n = np.cross(e1, e2)
    # Lower triangles run (0,0)->(0,1)->(1,1): s then t, counter-clockwise seen from +z; upper ones
    # run (0,0)->(1,1)->(1,0): clockwise. Make both point along s x t.
    lower = idx[:, 1, 0] == idx[:, 0, 0]
    n = np.where(lower[:, None], n, -n)
    return np.asarray(n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-15))
