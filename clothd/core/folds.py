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

Where a second view measures the quads' heights, two things are known that lengths alone cannot say:
- Whether the cloth beside an edge has risen at all. There an edge folds at any shortening past
  `RAISED_TOLERANCE_STRAIN`, not only past the tolerance that keeps tracking noise on a flat cloth flat.
- How steep the fold's flanks are. A fold holding slack S (the sum of L - d over its run of folded
  edges) under a measured crest H is a tent whose flanks rise 2H / S per unit of slack (cot(θ/2) for
  flank angle θ): an edge rises by (L - d)·2H / S, never more than straight. A broad ridge (H large
  against S) rises nearly straight; a pleat as tall as half its slack stands vertical, each edge rising
  by its slack. Straight edges read compress's pleat nodes 3-6 mm above the truth: the cloth lies on the
  table up to the pleat's foot and climbs its flank, while a straight edge leaves the table at the node.
  More slack than a vertical pleat of that height holds (S > 2H) has fallen over: 1 per unit of slack.
  How a run's slack splits between its edges depends on where the nodes up in the fold stand, which no
  camera sees; the filter holds them to share it evenly (`even_slack_lengths_m`), as a prior the features
  can overrule, and the heights read the slack the filter left.
- Which quads it saw something else in: a quad measured higher than the cloth across it can reach
  (`within_reach_m`) is taken as flat.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clothd.core.nanmedian import nanmedian
from clothd.core.stereo import CREST_ABOVE_M  # a quad measured this high has risen

# Chains either side whose rise an edge's median takes in. With one, a fold dying down at its release
# lifted some rows and not the next (a node 11 mm off on compress's edge row, where the model's springs
# then pulled the unlifted node in along the fold); two hold the fold's line.
ACROSS = 2
# A folded edge stays folded until it is back within this fraction of the tolerance. At the threshold an
# edge's rise jumps from nothing to 0.44 of its length, so a fold dying down flickered on and off from
# row to row, and the model's springs between lifted and unlifted rows pulled the cloth's edge row in
# along the fold (compress's worst node, two cameras: 6.84 mm; held to 0.3 of it, 6.09; to 0.5, 6.26).
HELD_TOLERANCE_FRACTION = 0.3
# Where the cloth beside an edge has risen, the edge has folded once it is this much shorter than at rest.
RAISED_TOLERANCE_STRAIN = 0.02


@dataclass(frozen=True)
class FoldedEdges:
    """Which edges had folded: along the rows (ny, nx-1) and along the columns (nx, ny-1)."""

    rows: np.ndarray
    cols: np.ndarray


def folds_across(folded: FoldedEdges) -> FoldedEdges:
    """Where the fold lies: each edge folded as most of its chain and the ACROSS chains either side are
    (an edge folded alone in its chain is noise, or a node dragged along the fold)."""
    return FoldedEdges(
        _median_across(folded.rows.astype(float)) > 0.5, _median_across(folded.cols.astype(float)) > 0.5
    )


def fold_heights_m(
    nodes_xy_m: np.ndarray,
    rest_xy_m: np.ndarray,
    tolerance_strain: float,
    quad_height_m: np.ndarray | None = None,
) -> np.ndarray:
    """Node heights (ny, nx) in metres for node positions on the table (ny, nx, 2) and the rest mesh
    (ny, nx, 2). An edge has folded only when it is shorter than (1 - tolerance_strain) of its rest
    length. quad_height_m (ny-1, nx-1): each quad's highest point as a further view measured it, or None
    with one view."""
    return fold_reading(nodes_xy_m, rest_xy_m, tolerance_strain, quad_height_m)[0]


def fold_reading(
    nodes_xy_m: np.ndarray,
    rest_xy_m: np.ndarray,
    tolerance_strain: float,
    quad_height_m: np.ndarray | None = None,
    held: FoldedEdges | None = None,
) -> tuple[np.ndarray, FoldedEdges]:
    """`fold_heights_m`, and which edges have folded. held: which had at the last reading of the same
    cloth (None: none); those stay folded down to HELD_TOLERANCE_FRACTION of the tolerance."""
    if quad_height_m is not None:
        quad_height_m = within_reach_m(nodes_xy_m, rest_xy_m, quad_height_m)
    q_cols = None if quad_height_m is None else quad_height_m.T
    rows, folded_rows = _chain_heights(
        nodes_xy_m,
        rest_xy_m,
        tolerance_strain,
        _edge_heights(quad_height_m),
        None if held is None else held.rows,
    )
    cols, folded_cols = _chain_heights(
        nodes_xy_m.transpose(1, 0, 2),
        rest_xy_m.transpose(1, 0, 2),
        tolerance_strain,
        _edge_heights(q_cols),
        None if held is None else held.cols,
    )
    return np.maximum(rows, cols.T), FoldedEdges(folded_rows, folded_cols)


def _edge_heights(quad_height_m: np.ndarray | None) -> np.ndarray | None:
    """(c, k-1): the higher of the two quads beside each edge of c chains along axis 1, from the quads'
    heights (c-1, k-1)."""
    if quad_height_m is None:
        return None
    padded = np.pad(quad_height_m, ((1, 1), (0, 0)))
    return np.asarray(np.maximum(padded[:-1], padded[1:]))


def _chain_heights(
    xy: np.ndarray,
    rest: np.ndarray,
    tolerance_strain: float,
    edge_height_m: np.ndarray | None,
    held: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Heights (c, k) of c neighbouring chains of k nodes along axis 1, and which of their edges (c, k-1)
    have folded."""
    rest_length = np.linalg.norm(np.diff(rest, axis=1), axis=2)
    length = np.linalg.norm(np.diff(xy, axis=1), axis=2)
    tolerance = np.full(length.shape, tolerance_strain)
    if edge_height_m is not None:
        tolerance[_risen(edge_height_m)] = min(tolerance_strain, RAISED_TOLERANCE_STRAIN)
    if held is not None:
        tolerance[held] = np.minimum(tolerance[held], HELD_TOLERANCE_FRACTION * tolerance_strain)
    folded = length < (1.0 - tolerance) * rest_length
    rise = np.where(folded, np.sqrt(np.maximum(rest_length**2 - length**2, 0.0)), 0.0)  # (c, k-1)
    if edge_height_m is not None:
        slack = np.where(folded, rest_length - length, 0.0)
        # A fold's slack is the same in the rows it crosses, but not its noise (a node 3 mm off on an
        # edge row read that row's fold 30 % short): each edge takes the median of its chains' folds.
        per_slack = np.where(folded, _median_across(_rise_per_slack(folded, slack, edge_height_m)), np.nan)
        rise = np.where(np.isnan(per_slack), rise, np.minimum(rise, slack * per_slack))
    rise = _median_across(rise)
    flat = np.pad(rise == 0.0, ((0, 0), (1, 1)), constant_values=True)
    on_table = flat[:, :-1] & flat[:, 1:]
    climb_left = _climb(rise, on_table)
    climb_right = _climb(rise[:, ::-1], on_table[:, ::-1])[:, ::-1]
    return np.minimum(climb_left, climb_right), folded


def _risen(edge_height_m: np.ndarray) -> np.ndarray:
    """(c, k-1): edges beside a quad measured risen, or next to such an edge along the chain (a fold's
    crest lies between two nodes, and the quads beside its feet may hold no point high on it)."""
    risen = np.pad(edge_height_m > CREST_ABOVE_M, ((0, 0), (1, 1)))
    return np.asarray(risen[:, :-2] | risen[:, 1:-1] | risen[:, 2:])


def _rise_per_slack(folded: np.ndarray, slack_m: np.ndarray, edge_height_m: np.ndarray) -> np.ndarray:
    """(c, k-1): how far each folded edge rises per metre of its slack, for the fold it belongs to (a run
    of folded edges along a chain): cot(θ/2) = 2H / S for the fold's slack S and measured crest H, at
    least 1 (θ at most 90°: more slack than a vertical pleat as tall holds has fallen over); NaN (the
    edge straight) where the fold has not measurably risen."""
    per_slack = np.full(folded.shape, np.nan)
    for c, k0, k1 in _runs(folded):
        crest = float(edge_height_m[max(c - ACROSS, 0) : c + ACROSS + 1, k0:k1].max())
        if crest > CREST_ABOVE_M:
            per_slack[c, k0:k1] = max(2.0 * crest / float(slack_m[c, k0:k1].sum()), 1.0)
    return per_slack


def _runs(mask: np.ndarray) -> list[tuple[int, int, int]]:
    """(chain, first, end) of every run of True along axis 1 of (c, k) mask."""
    edges = np.diff(np.pad(mask.astype(np.int8), ((0, 0), (1, 1))), axis=1)
    starts, ends = np.nonzero(edges == 1), np.nonzero(edges == -1)
    return [(int(c), int(a), int(b)) for c, a, b in zip(starts[0], starts[1], ends[1], strict=True)]


def _median_across(value: np.ndarray) -> np.ndarray:
    """The median of each edge's value and the same edge's in the ACROSS chains either side (mirrored at
    the first and last chains, so that an edge row follows the rows inside it), NaNs left out."""
    if len(value) <= ACROSS:
        return value
    padded = np.pad(value, ((ACROSS, ACROSS), (0, 0)), mode="reflect")
    window = np.stack([padded[k : k + len(value)] for k in range(2 * ACROSS + 1)])
    if not np.isnan(value).any():
        return np.asarray(np.median(window, axis=0))
    return nanmedian(window, axis=0)  # an edge NaN in every chain of its window stays NaN


def _climb(rise: np.ndarray, on_table: np.ndarray) -> np.ndarray:
    """(c, k): for each node, the sum of the edge rises since the last node on the table."""
    total = np.concatenate([np.zeros((len(rise), 1)), np.cumsum(rise, axis=1)], axis=1)
    # total never decreases, so the running maximum over the nodes on the table is the last one's.
    since = np.maximum.accumulate(np.where(on_table, total, 0.0), axis=1)
    return np.asarray(total - since)


def even_slack_lengths_m(
    nodes_xy_m: np.ndarray, rest_xy_m: np.ndarray, quad_height_m: np.ndarray
) -> FoldedEdges:
    """In-plane lengths to hold the edges of a measured fold at, rows (ny, nx-1) and columns (nx, ny-1), NaN
    where none: along each chain, a run of edges beside quads measured risen that holds slack shares its
    slack evenly (each edge its rest length less the run's mean slack). The feet of a fold are seen, its
    nodes up in the fold are not: on compress the features on a dying fold's flank pulled its top node 2 mm
    into the crest, its outer edge read 3 % over length, the node on the table, 5.4 mm low (two cameras'
    worst node, 5.82 mm; held to an even share, σ 1 mm, 4.51). A run holding no more slack
    than the noise (RAISED_TOLERANCE_STRAIN) is the cloth along a fold, not across it: left alone."""
    quad_height_m = within_reach_m(nodes_xy_m, rest_xy_m, quad_height_m)
    rows = _even_slack(nodes_xy_m, rest_xy_m, _edge_heights(quad_height_m))
    cols = _even_slack(
        nodes_xy_m.transpose(1, 0, 2), rest_xy_m.transpose(1, 0, 2), _edge_heights(quad_height_m.T)
    )
    return FoldedEdges(rows, cols)


def _even_slack(xy: np.ndarray, rest: np.ndarray, edge_height_m: np.ndarray | None) -> np.ndarray:
    """`even_slack_lengths_m` along c chains of k nodes (c, k, 2): (c, k-1), NaN where none."""
    rest_length = np.linalg.norm(np.diff(rest, axis=1), axis=2)
    length = np.linalg.norm(np.diff(xy, axis=1), axis=2)
    out = np.full(length.shape, np.nan)
    assert edge_height_m is not None
    for c, k0, k1 in _runs(edge_height_m > CREST_ABOVE_M):
        if k1 - k0 < 2:
            continue
        slack = float((rest_length[c, k0:k1] - length[c, k0:k1]).mean())
        if slack > RAISED_TOLERANCE_STRAIN * float(rest_length[c, k0:k1].mean()):
            out[c, k0:k1] = rest_length[c, k0:k1] - slack
    return out


def within_reach_m(nodes_xy_m: np.ndarray, rest_xy_m: np.ndarray, quad_height_m: np.ndarray) -> np.ndarray:
    """The quads' measured heights (ny-1, nx-1), 0 where a quad reads higher than the cloth across it can
    reach: a chain of nodes whose ends lie on the table (as this module's heights always put them) spans
    D on the table and is Λ long at rest, so no point of it stands higher than a tent of two straight
    flanks, sqrt(Λ² - D²) / 2. A quad is bounded by the higher of its two rows' and two columns' reach;
    past it, the further view saw something else there (an arm over the cloth read 246 mm high on occlude,
    where the cloth around it lay flat)."""
    rows = _reach_m(nodes_xy_m, rest_xy_m)  # (ny,)
    cols = _reach_m(nodes_xy_m.transpose(1, 0, 2), rest_xy_m.transpose(1, 0, 2))  # (nx,)
    reach = np.maximum(np.maximum(rows[:-1], rows[1:])[:, None], np.maximum(cols[:-1], cols[1:])[None, :])
    return np.asarray(np.where(quad_height_m > reach, 0.0, quad_height_m))


def _reach_m(xy: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """(c,): how high a point of each of c chains along axis 1 can stand, its ends on the table."""
    rest_length = np.linalg.norm(np.diff(rest, axis=1), axis=2).sum(axis=1)
    span = np.linalg.norm(xy[:, -1] - xy[:, 0], axis=1)
    return np.asarray(0.5 * np.sqrt(np.maximum(rest_length**2 - span**2, 0.0)))
