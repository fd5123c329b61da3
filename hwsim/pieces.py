"""The pieces of cloth on the table: each its own mass-spring (ClothSim), measured from its truth nodes.

Pieces meet only through the belts: there is no cloth-cloth contact, so two pieces laid over one another
would pass through each other (the infeed lays a piece only where none lies, docs/hwsim.md, "A production
flow"). A piece that leaves parks its ClothSim in a pool for the next one, since a new one compiles its
solver for seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hwsim.cloth import ClothSim
from hwsim.cloth_grid import ClothGrid
from hwsim.cloth_spares import make_cloth
from hwsim.scenario import ClothSpec, Pose, TableSpec


@dataclass
class Piece:
    """A piece on the table: `texture` indexes the renderer's fabrics (0: the scenario's own texture)."""

    id: int
    cloth: ClothSim
    fabric: str
    texture: int
    laid_s: float
    flap: bool = False
    judged: bool = False  # its leading edge reached the outfeed, where it was judged


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.asarray(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0])


def cloth_pose(cloth: ClothSim) -> np.ndarray:
    """[X_m, Y_m, theta_rad]: the centre of the truth nodes and the rotation that best maps the cloth's
    material axes onto them (2-D Kabsch)."""
    xy = cloth.positions_m()[..., :2].reshape(-1, 2)
    st = cloth.grid.st_m.reshape(-1, 2)
    c = xy.mean(axis=0)
    M = (st - st.mean(axis=0)).T @ (xy - c)
    return np.array([c[0], c[1], math.atan2(M[0, 1] - M[1, 0], M[0, 0] + M[1, 1])])


def sheet_measures(cloth: ClothSim) -> dict[str, float]:
    """How flat and how stretched the truth cloth is: its highest node (m), its area projected on the
    table over its rest area (the quads' shoelace areas, a folded-over quad's counted where it lies),
    the share of that area folded over (quads the wrong way up), and its most stretched grid edge."""
    x = cloth.positions_m()
    g = cloth.grid
    p = x[..., :2]
    a, b, c, d = p[:-1, :-1], p[:-1, 1:], p[1:, 1:], p[1:, :-1]
    signed = 0.5 * (_cross(a, b) + _cross(b, c) + _cross(c, d) + _cross(d, a))
    rest_area = (g.nx - 1) * g.dx_m * (g.ny - 1) * g.dy_m
    return {
        "max_height_m": float(x[..., 2].max()),
        "area_ratio": float(np.abs(signed).sum() / rest_area),
        "folded_ratio": float(-signed[signed < 0].sum() / rest_area),
        "max_strain": float(g.edge_strains(x).max()),
    }


def piece_truth(piece: Piece) -> dict[str, object]:
    """One piece in GET /truth's `pieces`: its id, fabric, when it was laid, pose and sheet measures."""
    return {
        "id": piece.id,
        "fabric": piece.fabric,
        "flap": piece.flap,
        "laid_s": piece.laid_s,
        "judged": piece.judged,
        "pose": cloth_pose(piece.cloth).tolist(),
        **sheet_measures(piece.cloth),
    }


def capacity_for(specs: list[ClothSpec]) -> tuple[int, int]:
    """(ny, nx) that holds the grid of every spec."""
    grids = [ClothGrid.from_spec(s) for s in specs]
    return max(g.ny for g in grids), max(g.nx for g in grids)


class ClothPool:
    """ClothSims of one capacity, handed out and taken back."""

    def __init__(
        self, table: TableSpec, capacity: tuple[int, int], infeed_belt: tuple[float, float, float]
    ) -> None:
        self.table = table
        self.capacity = capacity
        self.infeed_belt = np.array(infeed_belt)  # what hwsim.cloth.ClothSim.infeed_belt holds
        self._parked: list[ClothSim] = []

    def fill(self, count: int, spec: ClothSpec, seed: int) -> None:
        """Make `count` cloths now and park them. Taichi allocates a new cloth's fields on the thread that
        started it only, and `hwsim serve` steps the world on a thread of its own: an infeed that made a
        cloth there failed (Taichi's "this_thread == main_thread" assertion)."""
        for _ in range(count):
            self._parked.append(make_cloth(spec, self.table, Pose(), spec.substep_s, seed, self.capacity))

    def take(self, spec: ClothSpec, pose: Pose, seed: int, module_heading_rad: np.ndarray) -> ClothSim:
        """A cloth of `spec` laid at `pose` on the belts as they are turned now."""
        if self._parked:
            cloth = self._parked.pop()
        else:  # made flat (nothing to settle), then laid as any reused one is
            cloth = make_cloth(spec, self.table, Pose(), spec.substep_s, seed, self.capacity)
        cloth.infeed_belt.from_numpy(self.infeed_belt * [1.0, 1.0, 0.0])  # still while it is laid
        cloth.reuse(spec, pose, seed, module_heading_rad)
        cloth.infeed_belt.from_numpy(self.infeed_belt)
        return cloth

    def park(self, cloth: ClothSim) -> None:
        self._parked.append(cloth)

    def parked(self) -> list[ClothSim]:
        return list(self._parked)
