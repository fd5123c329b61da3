"""The tracking mesh: a regular nx x ny grid of nodes over the cloth in cloth space (s, t), bilinear quads.

Cloth space is the flat table-plane position of the cloth at initialisation, metres. The grid's first
axis a₁ = (cos θ, sin θ) runs along the cloth's long side, the second a₂ = (-sin θ, cos θ) is a₁ turned
+90° (so a₁ × a₂ = +z). Node (j, i) — row j along a₂, column i along a₁ — sits at

    st(j, i) = origin + i dx a₁ + j dy a₂,   dx = width / (nx - 1),   dy = height / (ny - 1)

with flat index n = j nx + i. Quad q = j (nx - 1) + i is the cell whose lowest corner is node (j, i). A point
in that cell has local coordinates (ξ, η) ∈ [-1, 1]², ξ along a₁, and its position is Σ_k N_k(ξ, η) x_k
over the corners in FEM order N1 (-1,-1) = (j, i), N2 (+1,-1) = (j, i+1), N3 (+1,+1) = (j+1, i+1),
N4 (-1,+1) = (j+1, i).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clothd.core.camera_model import CameraModel

# A point this many cells outside the mesh still counts as inside (absorbs rounding on the boundary).
_INSIDE_TOL_CELLS = 1e-9


@dataclass(frozen=True, eq=False)
class Binding:
    """Cloth-space points bound to the mesh, n points.

    quad (n,) int: the cell, q = j (nx-1) + i; xi_eta (n, 2) in [-1, 1]; nodes (n, 4) int: flat node
    indices of the corners in the order N1..N4; weights (n, 4): the shape functions at xi_eta (they sum
    to 1); inside (n,) bool: the point lies on the mesh. A point outside is clamped onto the nearest
    point of the mesh boundary (valid quad, (ξ, η) clipped), so `blend` works for every point, but it
    does not move with the cloth the way the point does: drop it with `inside`."""

    quad: np.ndarray
    xi_eta: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    inside: np.ndarray

    def __len__(self) -> int:
        return len(self.quad)

    def subset(self, keep: np.ndarray) -> Binding:
        """The binding of the points selected by `keep` (a boolean mask (n,) or an index array)."""
        return Binding(
            self.quad[keep], self.xi_eta[keep], self.nodes[keep], self.weights[keep], self.inside[keep]
        )


def shape_functions(xi_eta: np.ndarray) -> np.ndarray:
    """Bilinear shape functions, (n, 2) -> (n, 4):
    N1 = ¼(1−ξ)(1−η), N2 = ¼(1+ξ)(1−η), N3 = ¼(1+ξ)(1+η), N4 = ¼(1−ξ)(1+η)."""
    xe = np.asarray(xi_eta, dtype=float)
    xi, eta = xe[..., 0], xe[..., 1]
    return 0.25 * np.stack(
        [(1 - xi) * (1 - eta), (1 + xi) * (1 - eta), (1 + xi) * (1 + eta), (1 - xi) * (1 + eta)], axis=-1
    )


@dataclass(frozen=True, eq=False)
class QuadMesh:
    """nx x ny nodes (both >= 2) covering a width_m x height_m rectangle of cloth space; node (0, 0) at
    origin_m (2,), metres; the first axis at theta_rad from cloth-space s."""

    nx: int
    ny: int
    origin_m: np.ndarray
    theta_rad: float
    width_m: float
    height_m: float

    def __post_init__(self) -> None:
        if self.nx < 2 or self.ny < 2:
            raise ValueError(f"mesh: nx and ny must be >= 2, got {self.nx} x {self.ny}")
        if not (self.width_m > 0 and self.height_m > 0):
            raise ValueError(f"mesh: width and height must be > 0, got {self.width_m} x {self.height_m}")
        origin = np.array(self.origin_m, dtype=np.float64).reshape(2)
        origin.setflags(write=False)
        object.__setattr__(self, "origin_m", origin)

    @classmethod
    def covering(cls, corners_m: np.ndarray, nx: int, ny: int) -> QuadMesh:
        """The mesh over a rectangle given by its 4 corners (4, 2), metres, in any order (cv2.boxPoints
        will do). The first axis runs along the longer side, θ normalised to (-π/2, π/2] (to (-π/4, π/4]
        for a square, sides equal to 1e-6), so node (0, 0) is the corner at the low end of both axes."""
        c = np.asarray(corners_m, dtype=np.float64).reshape(4, 2)
        centre = c.mean(axis=0)
        # Walk the corners round the centre so that consecutive corners share an edge.
        c = c[np.argsort(np.arctan2(c[:, 1] - centre[1], c[:, 0] - centre[0]))]
        e = np.roll(c, -1, axis=0) - c
        lengths = np.linalg.norm(e, axis=1)
        side_a, side_b = (lengths[0] + lengths[2]) / 2, (lengths[1] + lengths[3]) / 2
        # Opposite edges point opposite ways: their difference averages the pair's direction.
        if side_a >= side_b:
            u, width, height = e[0] - e[2], side_a, side_b
        else:
            u, width, height = e[1] - e[3], side_b, side_a
        theta = math.atan2(u[1], u[0])
        if math.isclose(width, height, rel_tol=1e-6):  # float32 corners (cv2.boxPoints) are square to ~1e-7
            theta = math.pi / 4 - (math.pi / 4 - theta) % (math.pi / 2)
        else:
            theta = math.pi / 2 - (math.pi / 2 - theta) % math.pi
        a1 = np.array([math.cos(theta), math.sin(theta)])
        a2 = np.array([-a1[1], a1[0]])
        origin = centre - 0.5 * width * a1 - 0.5 * height * a2
        return cls(int(nx), int(ny), origin, theta, float(width), float(height))

    @property
    def n_nodes(self) -> int:
        return self.nx * self.ny

    @property
    def n_quads(self) -> int:
        return (self.nx - 1) * (self.ny - 1)

    @property
    def axes(self) -> np.ndarray:
        """(2, 2): rows a₁ and a₂, the grid's unit axes in cloth space."""
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return np.array([[c, s], [-s, c]])

    @property
    def spacing_m(self) -> tuple[float, float]:
        """(dx, dy): node spacing along the first and second axis, metres."""
        return self.width_m / (self.nx - 1), self.height_m / (self.ny - 1)

    @property
    def centre_m(self) -> np.ndarray:
        """(2,): the rectangle's centre in cloth space, metres."""
        return np.asarray(self.origin_m + np.array([self.width_m, self.height_m]) @ self.axes / 2.0)

    def rest_nodes_m(self) -> np.ndarray:
        """(ny, nx, 2): node positions in cloth space, metres."""
        dx, dy = self.spacing_m
        jj, ii = np.meshgrid(np.arange(self.ny) * dy, np.arange(self.nx) * dx, indexing="ij")
        return np.asarray(self.origin_m + np.stack([ii, jj], axis=-1) @ self.axes)

    def quad_nodes(self) -> np.ndarray:
        """(n_quads, 4) int: flat node indices of every quad's corners in the order N1..N4."""
        j, i = np.divmod(np.arange(self.n_quads), self.nx - 1)
        n1 = j * self.nx + i
        return np.stack([n1, n1 + 1, n1 + self.nx + 1, n1 + self.nx], axis=-1)

    def bind(self, st_m: np.ndarray) -> Binding:
        """Cloth-space points (n, 2), metres -> their quads and (ξ, η). With (a, b) = the point in grid
        axes relative to the origin, in cells: f_i = a / dx, f_j = b / dy; i = ⌊f_i⌋ (clamped to
        0..nx-2, so a point on the far edge takes the last cell with ξ = +1); ξ = 2 (f_i - i) - 1.
        Points outside the mesh are clamped onto it and get inside = False (see Binding)."""
        st = np.asarray(st_m, dtype=np.float64).reshape(-1, 2)
        dx, dy = self.spacing_m
        local = (st - self.origin_m) @ self.axes.T  # (a, b): components along a₁ and a₂
        f = local / np.array([dx, dy])
        hi = np.array([self.nx - 1, self.ny - 1])
        inside = np.all((f >= -_INSIDE_TOL_CELLS) & (f <= hi + _INSIDE_TOL_CELLS), axis=1)
        f = np.clip(f, 0.0, hi)
        cell = np.minimum(np.floor(f), hi - 1).astype(np.int64)
        xi_eta = np.clip(2.0 * (f - cell) - 1.0, -1.0, 1.0)
        i, j = cell[:, 0], cell[:, 1]
        quad = j * (self.nx - 1) + i
        return Binding(quad, xi_eta, self.quad_nodes()[quad], shape_functions(xi_eta), inside)


def blend(nodes_m: np.ndarray, binding: Binding) -> np.ndarray:
    """Node positions (n_nodes, d) (or (ny, nx, d)) -> the bound points (n, d): p = Σ_k N_k x_k."""
    x = np.asarray(nodes_m, dtype=np.float64)
    x = x.reshape(-1, x.shape[-1])
    return np.asarray(np.einsum("nk,nkd->nd", binding.weights, x[binding.nodes]))


def measurement_jacobian(
    camera: CameraModel, nodes_m: np.ndarray, binding: Binding
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted pixels h (n, 2) of the bound points and the non-zero blocks of dh/dx, (n, 4, 2, 3).

    h_i = π(Σ_k N_k x_k) for node positions x (n_nodes, 3) (or (ny, nx, 3)), world metres, so
    ∂h_i/∂x_k = J_π(p_i) N_k: block [i, k] (px/m) goes in the 3 position columns of node
    binding.nodes[i, k]; the row pair of feature i has no other non-zeros."""
    pixels, J = camera.project_jacobian(blend(nodes_m, binding))
    return pixels, J[:, None, :, :] * binding.weights[:, :, None, None]
