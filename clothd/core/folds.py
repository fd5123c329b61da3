"""Heights of the mesh nodes from inextensibility: where the cloth is shorter on the table than it is
long, it has risen into a fold.

An overhead camera hardly sees height (a node 20 mm up near the image centre moves a fraction of a
pixel), so the filter estimates the nodes on the table plane and this module lifts them. Along every
row and column of the mesh, an edge whose length on the table d is shorter than (1 - tolerance) of its
rest length L has folded, and rises by sqrt(L² - d²): the cloth does not stretch, so the 3-D edge
keeps its rest length and the model's springs are left at rest in the fold. A node with unfolded edges
on both sides lies on the table; between two such nodes the cloth rises as far as it falls again, and
each node is as high as the lower of its climbs from either side (a peaked fold, a flat-topped one, or
several folds along one row all come out right).

A fold is a ridge across many rows, while tracking noise is local; so whether an edge has folded, and
how far it rises, is the median over that edge and the same edge of the two rows on either side. The
median also lifts the cloth's edge rows, where features are scarce, with the rows inside them. A node's
height is the higher of its row's and its column's, so a fold in either direction is found.
"""

from __future__ import annotations

import numpy as np

# Chains either side whose rise an edge's median takes in. With one, a fold dying down at its release
# lifted some rows and not the next (a node 11 mm off on compress's edge row, where the model's springs
# then pulled the unlifted node in along the fold); two hold the fold's line.
ACROSS = 2


def fold_heights_m(nodes_xy_m: np.ndarray, rest_xy_m: np.ndarray, tolerance_strain: float) -> np.ndarray:
    """Node heights (ny, nx) in metres for node positions on the table (ny, nx, 2) and the rest mesh
    (ny, nx, 2). An edge has folded only when it is shorter than (1 - tolerance_strain) of its rest
    length."""
    rows = _chain_heights(nodes_xy_m, rest_xy_m, tolerance_strain)
    cols = _chain_heights(nodes_xy_m.transpose(1, 0, 2), rest_xy_m.transpose(1, 0, 2), tolerance_strain)
    return np.maximum(rows, cols.T)


def _chain_heights(xy: np.ndarray, rest: np.ndarray, tolerance_strain: float) -> np.ndarray:
    """Heights (c, k) of c neighbouring chains of k nodes along axis 1."""
    rest_length = np.linalg.norm(np.diff(rest, axis=1), axis=2)
    length = np.linalg.norm(np.diff(xy, axis=1), axis=2)
    folded = length < (1.0 - tolerance_strain) * rest_length
    rise = np.where(folded, np.sqrt(np.maximum(rest_length**2 - length**2, 0.0)), 0.0)  # (c, k-1)
    rise = _median_across(rise)
    flat = np.pad(rise == 0.0, ((0, 0), (1, 1)), constant_values=True)
    on_table = flat[:, :-1] & flat[:, 1:]
    climb_left = _climb(rise, on_table)
    climb_right = _climb(rise[:, ::-1], on_table[:, ::-1])[:, ::-1]
    return np.minimum(climb_left, climb_right)


def _median_across(rise: np.ndarray) -> np.ndarray:
    """The median of each edge's rise and the same edge's in the ACROSS chains either side (mirrored at
    the first and last chains, so that an edge row follows the rows inside it)."""
    if len(rise) <= ACROSS:
        return rise
    padded = np.pad(rise, ((ACROSS, ACROSS), (0, 0)), mode="reflect")
    return np.asarray(np.median([padded[k : k + len(rise)] for k in range(2 * ACROSS + 1)], axis=0))


def _climb(rise: np.ndarray, on_table: np.ndarray) -> np.ndarray:
    """(c, k): for each node, the sum of the edge rises since the last node on the table."""
    total = np.concatenate([np.zeros((len(rise), 1)), np.cumsum(rise, axis=1)], axis=1)
    # total never decreases, so the running maximum over the nodes on the table is the last one's.
    since = np.maximum.accumulate(np.where(on_table, total, 0.0), axis=1)
    return np.asarray(total - since)
