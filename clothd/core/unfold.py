"""The cloth as it would lie flat, from its measured surface: the tracking mesh's rest shape, and where its
nodes lie now.

A cloth laid down wrinkled covers less of the table than it would flat: across a ridge, the table
distance between two points is shorter than the cloth between them. With the surface measured (a height
field over the footprint, clothd/core/stereo.py), each edge of a grid laid over the footprint has its
length along the surface (the arc over the field). Unfolding lays that grid out flat with those lengths
(least squares over its sides and diagonals, Gauss–Newton from the footprint itself): the cloth's own,
material layout. The tracking mesh is a regular grid over that material rectangle, and its nodes start
where the material points lie on the table now, at the surface's height. Its rest shape then holds the
slack the piece arrived with: seen from the first tick, reported, and flattened like slack pushed in
later (docs/flattening.md).
"""

from __future__ import annotations

import cv2
import numpy as np

from clothd.core.banded import gram_band, solve_band, transpose_times
from clothd.core.binding import cloth_coordinates
from clothd.core.mesh import QuadMesh, blend
from clothd.core.stereo import HeightField

ARC_SAMPLES = 12  # points along each edge to follow the surface over it (a ridge can be narrower than one)
GAUSS_NEWTON_STEPS = 4
ANCHOR_WEIGHT = 1e-3  # holds the layout's place and turn (a gauge), far too weak to undo any stretch


def surface_lengths_m(field: HeightField, a_m: np.ndarray, b_m: np.ndarray) -> np.ndarray:
    """The length along the surface of the straight table segments a_m -> b_m (k, 2): (k,)."""
    t = np.linspace(0.0, 1.0, ARC_SAMPLES + 1)
    xy = a_m[:, None, :] + t[None, :, None] * (b_m - a_m)[:, None, :]  # (k, s, 2)
    z = field.at(xy.reshape(-1, 2)).reshape(len(a_m), -1)
    steps = np.concatenate([np.diff(xy, axis=1), np.diff(z, axis=1)[..., None]], axis=2)
    return np.asarray(np.linalg.norm(steps, axis=2).sum(axis=1))


def _edges(ny: int, nx: int) -> np.ndarray:
    """(e, 2) flat node pairs: every side and both diagonals of every quad of an ny x nx grid."""
    idx = np.arange(ny * nx).reshape(ny, nx)
    pairs = [
        (idx[:, :-1], idx[:, 1:]),
        (idx[:-1, :], idx[1:, :]),
        (idx[:-1, :-1], idx[1:, 1:]),
        (idx[:-1, 1:], idx[1:, :-1]),
    ]
    return np.concatenate([np.stack([a.ravel(), b.ravel()], axis=1) for a, b in pairs])


def unfold_layout(grid_m: np.ndarray, lengths_m: np.ndarray, edges: np.ndarray, nx: int) -> np.ndarray:
    """Node positions (n, 2) in the plane whose edges have the given lengths, as near as least squares
    gets them, starting from grid_m (n, 2): the nodes of a grid nx wide, numbered row by row, whose edges
    join nodes at most a row and a column apart (so the normal equations are banded)."""
    x = grid_m.copy()
    n = len(x)
    a, b = edges[:, 0], edges[:, 1]
    cols = np.stack([2 * a, 2 * a + 1, 2 * b, 2 * b + 1], axis=1)
    band = 2 * nx + 3  # x of a node to y of the node a row and a column on
    for _ in range(GAUSS_NEWTON_STEPS):
        d = x[b] - x[a]
        length = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        u = d / length[:, None]
        J = np.concatenate([-u, u], axis=1)
        ab = gram_band(cols, J, 2 * n, band)
        ab[-1] += ANCHOR_WEIGHT**2
        rhs = transpose_times(cols, J, lengths_m - length, 2 * n) - ANCHOR_WEIGHT**2 * (x - grid_m).ravel()
        x = x + solve_band(ab, rhs).reshape(n, 2)
    return x


def outline_rectangle(outline_m: np.ndarray) -> np.ndarray:
    """The 4 corners (4, 2) of the rectangle an outline (k, 2) traces: turned as its minimum-area
    rectangle, each side at the median of the outline's points along that side's middle 80 %. The
    minimum-area rectangle itself lies on the outline's outermost points: a cloth's edge waves by a few
    pixels (2 to 3 mm on the default cell), and it came out 4 mm wider than the cloth."""
    (cx, cy), (w, h), angle_deg = cv2.minAreaRect(outline_m.astype(np.float32))
    a = np.radians(angle_deg)
    axes = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    local = (outline_m - [cx, cy]) @ axes.T
    lo, hi = np.empty(2), np.empty(2)
    for k, half_across in ((0, 0.4 * h), (1, 0.4 * w)):
        side = np.abs(local[:, 1 - k]) < half_across
        lo[k] = np.median(local[side & (local[:, k] < 0), k])
        hi[k] = np.median(local[side & (local[:, k] > 0), k])
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    return np.asarray(corners @ axes + [cx, cy])


def unfold(footprint: QuadMesh, field: HeightField, outline_m: np.ndarray) -> tuple[QuadMesh, np.ndarray]:
    """The material mesh (a regular grid over the cloth laid flat, nx x ny like the footprint's) and its
    nodes' positions now (n, 3): on the table where the material points lie, at the surface's height.
    outline_m (k, 2) (or (k, 3), z unused): the cloth's outline on the table, whose laid-out rectangle
    the material is."""
    nx, ny = footprint.nx, footprint.ny
    grid = footprint.rest_nodes_m().reshape(-1, 2)
    edges = _edges(ny, nx)
    lengths = surface_lengths_m(field, grid[edges[:, 0]], grid[edges[:, 1]])
    flat = unfold_layout(grid, lengths, edges, nx)
    # An oblique ridge shifts the cloth beyond it sideways too: the footprint's rectangle is wider than the
    # cloth and turned off its axes (by 1.5 deg, 4 mm on the default cloth), and the laid-out grid with
    # it. The outline laid out is the cloth's own rectangle again.
    material = QuadMesh.covering(outline_rectangle(blend(flat, footprint.bind(outline_m[:, :2]))), nx, ny)
    rest = material.rest_nodes_m().reshape(-1, 2)
    # A material node lies where the footprint point of the same place in the laid-out grid does: the
    # laid-out grid's quads map back onto the footprint's. Nodes just past its border (the material's
    # rectangle rounds off the grid's own edges) keep their offset from the nearest laid-out node.
    xy, found = cloth_coordinates(footprint, flat, rest)
    nearest = np.argmin(np.linalg.norm(rest[~found, None] - flat[None], axis=2), axis=1)
    xy[~found] = grid[nearest] + (rest[~found] - flat[nearest])
    return material, np.column_stack([xy, field.at(xy)])
