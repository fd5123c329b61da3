"""Cloths of worlds that are gone, kept for the next world of the same shape (hwsim/spares.py says why:
one run of the tests that read no clock compiled the cloth solver 71 times, 407 s of its CPU). A spare
cloth is the same solver on the same fields, laid afresh by `ClothSim.reuse`: its state is all rewritten,
so it runs bit for bit as a new one.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from hwsim.cloth import ClothSim
from hwsim.cloth_grid import ClothGrid
from hwsim.scenario import ClothSpec, Pose, TableSpec
from hwsim.spares import Spares

_Shape = tuple[tuple[int, int], int, int]  # the fields' capacity, and the table's modules (in the kernels)
_spares: Spares[_Shape, ClothSim] = Spares()


def _shape(capacity: tuple[int, int], table: TableSpec) -> _Shape:
    return ((capacity[0], capacity[1]), table.modules_x, table.modules_y)


def make_cloth(
    spec: ClothSpec,
    table: TableSpec,
    pose: Pose,
    substep_s: float,
    seed: int,
    capacity: tuple[int, int] | None = None,
) -> ClothSim:
    """A ClothSim as its constructor makes it; a spare of the same shape where there is one."""
    grid = ClothGrid.from_spec(spec)
    cloth = _spares.take(_shape(capacity or (grid.ny, grid.nx), table))
    if cloth is None:
        return ClothSim(spec, table, pose, substep_s, seed, capacity)
    cloth.table, cloth.substep_s = table, substep_s
    cloth.infeed_belt.from_numpy(np.array([-math.inf, 0.0, 0.0]))
    cloth.reuse(spec, pose, seed, np.zeros(table.modules_x * table.modules_y))
    return cloth


def spare(cloths: Iterable[ClothSim]) -> None:
    """Keep cloths that no world holds any longer for `make_cloth`."""
    for cloth in cloths:
        _spares.give(_shape(cloth.capacity, cloth.table), cloth)
