"""How flat the cloth is, from the mesh estimate: its highest point, how much of it lies compressed, and
the ridges it has.

An overhead camera sees a wrinkle as cloth that is shorter on the table than at rest (docs/flattening.md):
a quad of the mesh whose edges along some direction are shorter on the table than at rest by more than a
tolerance holds slack, which has risen out of the plane (a quad only sheared has lost area, not length).
The node heights come from the same shortening (core/folds.py); a fold narrower than an edge rises
between two nodes left on the table, as high as the edge's slack lets it (edge_apexes). A ridge is a
connected set of compressed quads (find_ridges: one ridge's two feet joined, parallel ridges parted); it
runs across its compressed direction, the principal axis of the sum of its quads' shortening tensors.

A flap, a corner folded over onto the cloth, shows no slack: it shows as cloth missing where the estimate
puts some. The tracker reports, per quad, whether the cloth is seen at its centre (Estimate.quad_seen); a
flap is a connected set of unseen quads at the mesh's border. Belts cannot unfold it, so the regulator
leaves the modules under it alone.

`FlatnessMonitor` adds hysteresis to the `flat` flag, so that it does not chatter at the threshold.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from clothd.config import FlatnessConfig
from clothd.core.modes import FlatnessBasis
from clothd.core.stereo import backed_heights


@dataclass(frozen=True)
class Ridge:
    """A wrinkle: where it is (world x, y of its highest point), the direction its line runs in (world,
    [0, π)), its estimated height, the rest area of its compressed quads, the slack it holds (the length
    the cloth is short by across it, on average along it), and the centres of its quads (k, 2)."""

    position_m: tuple[float, float]
    direction_rad: float
    height_m: float
    area_m2: float
    slack_m: float
    quad_centres_m: np.ndarray

    @property
    def compressed_direction_rad(self) -> float:
        return (self.direction_rad + math.pi / 2) % math.pi


@dataclass(frozen=True)
class Flap:
    """A corner or edge folded over: the centre of its unseen quads (world x, y), their rest area, and
    their centres (k, 2)."""

    position_m: tuple[float, float]
    area_m2: float
    quad_centres_m: np.ndarray


@dataclass(frozen=True)
class Flatness:
    max_height_m: float
    compressed_area_pct: float
    flat: bool
    ridges: tuple[Ridge, ...]
    flaps: tuple[Flap, ...] = ()
    basis: FlatnessBasis = FlatnessBasis.SINCE_START


MIN_FLAP_QUADS = 2  # one unseen quad at the border is too little to tell from an edge misplaced by a pixel
# Measured heights: a quad this many times the flat height up holds slack (twice: clear of the measured
# points' noise, and held by the hysteresis down to the flat height itself) ...
RAISED_FLAT_RATIO = 2.0
# ... and shortening counts only beside a quad this high (the highest of a flat cloth's ~600 measured
# points reads up to 1.3 mm).
RISEN_FLAT_RATIO = 1.5


def find_flaps(
    nodes_m: np.ndarray, rest_spacing_m: tuple[float, float], quad_seen: np.ndarray
) -> tuple[Flap, ...]:
    """The flaps of the mesh nodes_m (ny, nx, 3): connected sets of at least MIN_FLAP_QUADS quads, not seen
    (quad_seen False, (ny-1, nx-1)), that reach the mesh's border; largest first."""
    unseen = ~quad_seen
    count, labels = cv2.connectedComponents(unseen.astype(np.uint8), connectivity=8)
    xy = nodes_m[..., :2]
    quad_centres = (xy[:-1, :-1] + xy[:-1, 1:] + xy[1:, 1:] + xy[1:, :-1]) / 4.0
    border = np.ones_like(unseen)
    border[1:-1, 1:-1] = False
    flaps = []
    for k in range(1, count):
        quads = labels == k
        if quads.sum() < MIN_FLAP_QUADS or not (quads & border).any():
            continue
        centres = quad_centres[quads]
        middle = centres.mean(axis=0)
        area = float(quads.sum() * rest_spacing_m[0] * rest_spacing_m[1])
        flaps.append(Flap((float(middle[0]), float(middle[1])), area, centres))
    return tuple(sorted(flaps, key=lambda f: -f.area_m2))


def quad_shortening(nodes_xy_m: np.ndarray, rest_spacing_m: tuple[float, float]) -> np.ndarray:
    """(ny-1, nx-1): for each quad, how much shorter it is on the table than at rest in its most shortened
    direction: the largest eigenvalue of its shortening tensor. A ridge across a quad, in any direction,
    shortens it across the ridge by its slack over the quad's width; a quad only sheared (its area
    smaller, no edge shorter) holds no slack, and is not counted."""
    return np.asarray(np.linalg.eigvalsh(_shortening_tensor(nodes_xy_m, rest_spacing_m))[..., -1])


def _shortening_tensor(nodes_xy_m: np.ndarray, rest_spacing_m: tuple[float, float]) -> np.ndarray:
    """(ny-1, nx-1, 2, 2): per quad, the tensor C whose êᵀ C ê is the quad's shortening 1 - d/L along ê.

    Cloth threads hardly stretch, so the slack along the mesh's x and y (its warp and weft) is what its
    x and y edges are short by (the mean of the quad's two each, not below 0), and these are C's diagonal
    in the quad's own axes. They cannot tell a ridge at +φ to the threads from one at -φ: the quad's two
    diagonals can, and give the cross term, (s₊ - s₋) / (2 sin 2φ) for diagonals at ±φ to x. The cross
    term is kept within ±√(C_xx C_yy), so that C ≥ 0: a quad only sheared (edges at rest, one diagonal
    short, one long) holds no slack. Built from the x and y edges alone, C's axes were always the mesh's,
    and a ridge at 45° to the threads was read at 0° or 90° and as half as deep."""
    lx, ly = rest_spacing_m
    ex = np.diff(nodes_xy_m, axis=1)  # (ny, nx-1, 2)
    ey = np.diff(nodes_xy_m, axis=0)  # (ny-1, nx, 2)
    short_x = np.clip(1.0 - np.linalg.norm(ex, axis=-1) / lx, 0.0, None)
    short_y = np.clip(1.0 - np.linalg.norm(ey, axis=-1) / ly, 0.0, None)
    c_xx = (short_x[:-1] + short_x[1:]) / 2.0
    c_yy = (short_y[:, :-1] + short_y[:, 1:]) / 2.0
    x_hat = _unit(ex[:-1] + ex[1:])
    y_hat = _unit(ey[:, :-1] + ey[:, 1:])
    diagonal_m = math.hypot(lx, ly)
    up = np.linalg.norm(nodes_xy_m[1:, 1:] - nodes_xy_m[:-1, :-1], axis=-1)  # along +x +y
    down = np.linalg.norm(nodes_xy_m[:-1, 1:] - nodes_xy_m[1:, :-1], axis=-1)  # along +x -y
    c_xy = (down - up) / diagonal_m / (2.0 * math.sin(2.0 * math.atan2(ly, lx)))
    bound = np.sqrt(c_xx * c_yy)
    c_xy = np.clip(c_xy, -bound, bound)
    xy_sym = np.einsum("...i,...j->...ij", x_hat, y_hat)
    return np.asarray(
        c_xx[..., None, None] * np.einsum("...i,...j->...ij", x_hat, x_hat)
        + c_yy[..., None, None] * np.einsum("...i,...j->...ij", y_hat, y_hat)
        + c_xy[..., None, None] * (xy_sym + np.swapaxes(xy_sym, -1, -2))
    )


def _unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12))


@dataclass(frozen=True)
class EdgeApexes:
    """The highest point of the cloth over each x edge (ny, nx-1) and y edge (ny-1, nx) of a mesh: its
    height (m) and where it lies (world x, y; (..., 2))."""

    x_height_m: np.ndarray
    y_height_m: np.ndarray
    x_at_m: np.ndarray
    y_at_m: np.ndarray


def edge_apexes(
    nodes_m: np.ndarray, rest_spacing_m: tuple[float, float], min_shortening: float
) -> EdgeApexes:
    """How high the cloth rises over each edge of the mesh nodes_m (ny, nx, 3): over an edge shorter on the
    table than (1 - min_shortening) of its rest length, as high as its slack lets it (at its middle); over
    any other, to its higher node (there).

    A fold narrower than the mesh puts its slack into one edge, whose nodes stay on the table (the fold
    lift needs a climb and a descent over two edges: core/folds.py). The edge's cloth, of rest length L,
    still joins its two nodes, so its highest point lies on the ellipse with the nodes as foci and major
    axis L: for nodes at one height, d apart on the table, half of √(L² − d²) above them; for an edge
    whose slack the lift has already raised into its nodes (its 3-D chord L), its higher node."""
    x_height, x_at = _apexes(nodes_m[:, :-1], nodes_m[:, 1:], rest_spacing_m[0], min_shortening)
    y_height, y_at = _apexes(nodes_m[:-1], nodes_m[1:], rest_spacing_m[1], min_shortening)
    return EdgeApexes(x_height, y_height, x_at, y_at)


def _apexes(
    a: np.ndarray, b: np.ndarray, rest_m: float, min_shortening: float
) -> tuple[np.ndarray, np.ndarray]:
    """The highest points (height, world x y) over edges from nodes a to nodes b (..., 3) of rest length
    rest_m: the top of the ellipse with foci a and b and major axis rest_m, whose major axis makes the
    angle φ with the table, lies sqrt((L/2)² sin²φ + b² cos²φ) above its centre (b its semi-minor axis)."""
    d = np.linalg.norm(b[..., :2] - a[..., :2], axis=-1)
    rise = b[..., 2] - a[..., 2]
    chord = np.maximum(np.hypot(d, rise), 1e-12)
    semi_minor_sq = np.clip((rest_m / 2.0) ** 2 - (chord / 2.0) ** 2, 0.0, None)
    sin_sq = (rise / chord) ** 2
    top = (a[..., 2] + b[..., 2]) / 2.0 + np.sqrt(
        (rest_m / 2.0) ** 2 * sin_sq + semi_minor_sq * (1.0 - sin_sq)
    )
    higher = np.where((rise > 0.0)[..., None], b, a)
    rises = (d < (1.0 - min_shortening) * rest_m) & (top > higher[..., 2])
    height = np.where(rises, top, higher[..., 2])
    at = np.where(rises[..., None], (a[..., :2] + b[..., :2]) / 2.0, higher[..., :2])
    return np.asarray(height), np.asarray(at)


def measured_apexes(nodes_m: np.ndarray, quad_height_m: np.ndarray) -> EdgeApexes:
    """EdgeApexes from heights measured over each quad (ny-1, nx-1) (a second view): an edge is as high
    as the higher quad beside it, at its middle."""
    q = np.pad(quad_height_m, 1, constant_values=-np.inf)
    x_height = np.maximum(q[:-1, 1:-1], q[1:, 1:-1])  # (ny, nx-1): the quads before and after each x edge
    y_height = np.maximum(q[1:-1, :-1], q[1:-1, 1:])  # (ny-1, nx)
    xy = nodes_m[..., :2]
    return EdgeApexes(x_height, y_height, (xy[:, :-1] + xy[:, 1:]) / 2.0, (xy[:-1] + xy[1:]) / 2.0)


VALLEY_RATIO = 0.5  # a dip across a component below this share of the peaks on both its sides parts it
PARALLEL_GAP_M = 0.06  # parallel ridges nearer than this are one: no belt (65 mm) fits between them
PARALLEL_DEG = 20.0  # bands of a ridge compressed within this of one direction are one ridge's
MIN_PROFILE_WEIGHT = 1e-4  # a compressed quad's weight across a ridge, however little shorter or risen


def find_ridges(
    nodes_m: np.ndarray,
    rest_spacing_m: tuple[float, float],
    shortening: np.ndarray,
    compressed: np.ndarray,
    apexes: EdgeApexes,
    quad_height_m: np.ndarray | None = None,
) -> tuple[Ridge, ...]:
    """The ridges of the mesh nodes_m (ny, nx, 3) among its `compressed` quads (bool, (ny-1, nx-1)),
    highest first; `shortening` is quad_shortening's of the same nodes, `apexes` edge_apexes'. A ridge is
    as high as the highest point over the edges of its quads.

    A ridge's two feet are compressed and its crest hardly (the cloth lies level there), so on a fine
    mesh one ridge is two bands of quads with a row between. Bands of connected quads a quad apart or
    less, compressed in the same direction (within PARALLEL_DEG), are taken together; what is taken
    together is then parted where it holds parallel ridges far enough apart for belts between them
    (`_part_parallel`): across them, by the quads' measured heights (ny-1, nx-1) where a second view gives
    them, else by their shortening. Two laid ridges 84 mm apart shortened the quads between them too, and
    read as one; their heights have a valley between them."""
    xy = nodes_m[..., :2]
    # A quad a second view measured risen may be hardly shorter: it still weighs a little.
    profile = np.maximum(shortening if quad_height_m is None else quad_height_m, MIN_PROFILE_WEIGHT)
    tensor = _shortening_tensor(xy, rest_spacing_m)
    quad_centres = (xy[:-1, :-1] + xy[:-1, 1:] + xy[1:, 1:] + xy[1:, :-1]) / 4.0
    _, bands = cv2.connectedComponents(compressed.astype(np.uint8), connectivity=8)
    near = cv2.dilate(compressed.astype(np.uint8), np.ones((3, 3), np.uint8))
    count, groups = cv2.connectedComponents(near, connectivity=8)
    parts = []
    for k in range(1, count):
        members = [bands == b for b in np.unique(bands[(groups == k) & compressed])]
        directions = np.array([_across(band, tensor) for band in members])
        parallel = np.abs(directions @ directions.T).min() >= math.cos(math.radians(PARALLEL_DEG))
        for quads in [np.logical_or.reduce(members)] if parallel else members:
            parts.extend(_part_parallel(quads, tensor, quad_centres, profile, min(rest_spacing_m)))
    ridges = [
        _ridge(quads, apexes, tensor, quad_centres, shortening, rest_spacing_m, quad_height_m)
        for quads in parts
    ]
    return tuple(sorted(ridges, key=lambda r: (-r.height_m, -r.area_m2)))


def _across(quads: np.ndarray, tensor: np.ndarray) -> np.ndarray:
    """The unit direction the quads are most compressed along: their summed tensor's principal axis."""
    evals, evecs = np.linalg.eigh(tensor[quads].sum(axis=0))
    return np.asarray(evecs[:, np.argmax(evals)])


def _part_parallel(
    quads: np.ndarray, tensor: np.ndarray, quad_centres: np.ndarray, weight: np.ndarray, bin_m: float
) -> list[np.ndarray]:
    """The quads (bool mask) as one ridge or, where they hold parallel ridges, several. Two ridges a
    belt's width apart have compressed quads that touch; read as one, their line runs between them and
    the belts between them push material into both (docs/flattening.md). Across their common direction
    their weight (height or shortening), smoothed over half a quad (the quads of a slanted ridge lie on a
    grid, not on its line), then has two peaks and a dip; the quads are parted at the deepest dip below
    VALLEY_RATIO of the peaks on both sides, where the sides' centres (weighted so) lie PARALLEL_GAP_M apart
    or more, and each side is looked at again. One ridge's two feet, 2σ apart, stay together."""
    centres = quad_centres[quads]
    offset = centres @ _across(quads, tensor)
    grid = np.arange(offset.min() - bin_m, offset.max() + bin_m, bin_m / 4.0)
    kernel = np.exp(-0.5 * ((grid[:, None] - offset[None, :]) / (bin_m / 2.0)) ** 2)
    profile = kernel @ weight[quads]
    best, cut_m = VALLEY_RATIO, None
    for i in range(1, len(grid) - 1):
        if not profile[i] <= min(profile[i - 1], profile[i + 1]):
            continue
        ratio = profile[i] / min(profile[:i].max(), profile[i:].max())
        gap_m = np.average(grid[i:], weights=profile[i:]) - np.average(grid[:i], weights=profile[:i])
        if ratio < best and gap_m >= PARALLEL_GAP_M:
            best, cut_m = ratio, grid[i]
    if cut_m is None:
        return [quads]
    near = np.zeros_like(quads)
    near[quads] = offset < cut_m
    far = quads & ~near
    return [
        part for side in (near, far) for part in _part_parallel(side, tensor, quad_centres, weight, bin_m)
    ]


def _ridge(
    quads: np.ndarray,
    apexes: EdgeApexes,
    tensor: np.ndarray,
    quad_centres: np.ndarray,
    shortening: np.ndarray,
    rest_spacing_m: tuple[float, float],
    quad_height_m: np.ndarray | None,
) -> Ridge:
    """The ridge over `quads`: as high as the highest edge around them, there; measured, as its highest
    quad, at its centre (an edge it shares with a ridge beside it took that one's height)."""
    rest_area = rest_spacing_m[0] * rest_spacing_m[1]
    if quad_height_m is None:
        x_edges = np.zeros(apexes.x_height_m.shape, bool)  # the x and y edges of the quads
        x_edges[:-1] |= quads
        x_edges[1:] |= quads
        y_edges = np.zeros(apexes.y_height_m.shape, bool)
        y_edges[:, :-1] |= quads
        y_edges[:, 1:] |= quads
        heights = np.concatenate([apexes.x_height_m[x_edges], apexes.y_height_m[y_edges]])
        places = np.concatenate([apexes.x_at_m[x_edges], apexes.y_at_m[y_edges]])
    else:
        heights, places = quad_height_m[quads], quad_centres[quads]
    top = int(np.argmax(heights))
    across = _across(quads, tensor)
    along = np.array([-across[1], across[0]])  # the line runs perpendicular to `across`
    centres = quad_centres[quads]
    reach = centres @ along
    length = float(reach.max() - reach.min()) + math.sqrt(rest_area)
    return Ridge(
        position_m=(float(places[top, 0]), float(places[top, 1])),
        direction_rad=math.atan2(along[1], along[0]) % math.pi,
        height_m=float(heights[top]),
        area_m2=float(quads.sum() * rest_area),
        slack_m=float((shortening[quads] * rest_area).sum()) / length,
        quad_centres_m=centres,
    )


class FlatnessMonitor:
    """The flatness of each estimate, with hysteresis twice over: a quad starts holding slack past
    `compressed_strain`, and a quad that held it, or lies beside one that did, holds it until below
    `release_strain` (so the last millimetre of a ridge, below what starts one, is still seen and pulled
    out, even as the ridge moves); `flat` turns on below the configured height and share of quads past
    `compressed_strain` (those kept by the hysteresis do not count) and off only past twice them."""

    def __init__(self, cfg: FlatnessConfig) -> None:
        self.cfg = cfg
        self.flat = False
        self._compressed: np.ndarray | None = None

    def reset(self) -> None:
        self.flat = False
        self._compressed = None

    def update(
        self,
        nodes_m: np.ndarray,
        cloth_size_m: tuple[float, float],
        quad_seen: np.ndarray | None = None,
        basis: FlatnessBasis = FlatnessBasis.SINCE_START,
        quad_height_m: np.ndarray | None = None,
    ) -> Flatness:
        """The flatness of mesh nodes_m (ny, nx, 3); quad_seen (ny-1, nx-1) where known finds flaps; basis:
        what the mesh's rest shape rests on (the estimate's). quad_height_m (ny-1, nx-1), each quad's
        highest point as a second view measured it: a quad risen past RAISED_FLAT_RATIO x flat_height_m
        holds slack however little shorter it looks, and the heights reported are the measured ones."""
        ny, nx = nodes_m.shape[:2]
        spacing = (cloth_size_m[0] / (nx - 1), cloth_size_m[1] / (ny - 1))
        shortening = quad_shortening(nodes_m[..., :2], spacing)
        compressed = shortening > self.cfg.compressed_strain
        beside = np.ones_like(compressed)
        slack_height_m = quad_height_m
        if quad_height_m is not None and quad_seen is not None:
            # A folded-over corner stands up at its fold, a quad or two past the cloth missing where it was:
            # not slack, and not to be pulled (find_flaps).
            unseen = cv2.dilate((~quad_seen).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
            slack_height_m = np.where(unseen, 0.0, quad_height_m)
        if slack_height_m is not None:
            # Measured: slack has risen, so shortening with no height beside it is the rest shape's noise
            # (a flat cloth's unfolded rest read 3.4 % short at one quad), and height is slack however
            # little shorter it looks.
            risen = slack_height_m > RISEN_FLAT_RATIO * self.cfg.flat_height_m
            beside = cv2.dilate(risen.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            raised = slack_height_m > RAISED_FLAT_RATIO * self.cfg.flat_height_m
            compressed = (compressed & beside) | raised
        # `flat` reads only what starts a ridge: a quad kept by the hysteresis below is for the regulator to
        # finish pulling; lying flat with no more than that is lying flat (the cloth's crimp, docs).
        starting_pct = float(100.0 * np.mean(compressed))
        if self._compressed is not None and self._compressed.shape == compressed.shape:
            # A ridge moves a little as it is pulled: what held slack last tick, or lies beside it, keeps
            # holding it down to the release strain.
            near = cv2.dilate(self._compressed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            held = near & (shortening > self.cfg.release_strain)
            if slack_height_m is not None:
                held = (held & beside) | (near & (slack_height_m > self.cfg.flat_height_m))
            compressed |= held
        self._compressed = compressed
        compressed_pct = float(100.0 * np.mean(compressed))
        c = self.cfg
        if quad_height_m is None:
            apexes = edge_apexes(nodes_m, spacing, c.compressed_strain)
        else:
            apexes = measured_apexes(nodes_m, quad_height_m)
        ridges = find_ridges(nodes_m, spacing, shortening, compressed, apexes, quad_height_m)
        max_height = float(max(nodes_m[..., 2].max(), 0.0, *(r.height_m for r in ridges)))
        if quad_height_m is not None:
            # One quad alone risen is noise (a flat cloth's read 1.27 mm).
            max_height = float(max(backed_heights(quad_height_m).max(), 0.0))
        flaps = () if quad_seen is None else find_flaps(nodes_m, spacing, quad_seen)
        if self.flat:
            self.flat = max_height <= 2 * c.flat_height_m and starting_pct <= 2 * c.flat_compressed_pct
        else:
            self.flat = max_height <= c.flat_height_m and starting_pct <= c.flat_compressed_pct
        self.flat = self.flat and not flaps  # a folded corner is not flat, and stays until a hand lifts it
        return Flatness(max_height, compressed_pct, self.flat, ridges, flaps, basis)
