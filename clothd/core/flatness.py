"""How flat the cloth is, from the mesh estimate: its highest node, how much of it lies compressed, and
the ridges it has.

An overhead camera sees a wrinkle as cloth that is shorter on the table than at rest (docs/flattening.md):
a quad of the mesh whose edges along some direction are shorter on the table than at rest by more than a
tolerance holds slack, which has risen out of the plane (a quad only sheared has lost area, not length).
The node heights come from the same shortening (core/folds.py). A ridge is a connected set of compressed
quads; it runs across its compressed direction, which is the principal axis of the quads' compression
tensor Σ (1 - d/L) e eᵀ over their shortened edges e.

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


@dataclass(frozen=True)
class Ridge:
    """A wrinkle: where it is (world x, y of its highest node), the direction its line runs in (world,
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


MIN_FLAP_QUADS = 2  # one unseen quad at the border is too little to tell from an edge misplaced by a pixel


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
    direction: half the largest eigenvalue of its compression tensor (its two edges along that direction,
    on average). A ridge across a quad shortens the edges it crosses; a quad only sheared (its area
    smaller, no edge shorter) holds no slack, and is not counted."""
    return np.asarray(np.linalg.eigvalsh(_compression_tensor(nodes_xy_m, rest_spacing_m))[..., -1] / 2.0)


def _compression_tensor(nodes_xy_m: np.ndarray, rest_spacing_m: tuple[float, float]) -> np.ndarray:
    """(ny-1, nx-1, 2, 2): per quad, Σ (1 - d/L)₊ ê êᵀ over its four edges (ê the unit edge direction)."""
    t = np.zeros((*nodes_xy_m.shape[:2], 2, 2))[:-1, :-1]
    for axis, rest in ((1, rest_spacing_m[0]), (0, rest_spacing_m[1])):
        e = np.diff(nodes_xy_m, axis=axis)
        length = np.maximum(np.linalg.norm(e, axis=-1), 1e-12)
        short = np.clip(1.0 - length / rest, 0.0, None)
        outer = short[..., None, None] * np.einsum(
            "...i,...j->...ij", e / length[..., None], e / length[..., None]
        )
        # Each quad has two edges along each axis: those of the node rows (columns) on either side of it.
        t += outer[:-1] + outer[1:] if axis == 1 else outer[:, :-1] + outer[:, 1:]
    return t


def find_ridges(
    nodes_m: np.ndarray, rest_spacing_m: tuple[float, float], shortening: np.ndarray, compressed: np.ndarray
) -> tuple[Ridge, ...]:
    """The ridges of the mesh nodes_m (ny, nx, 3): the connected sets of the `compressed` quads (bool,
    (ny-1, nx-1)), highest first; `shortening` is quad_shortening's of the same nodes."""
    xy = nodes_m[..., :2]
    count, labels = cv2.connectedComponents(compressed.astype(np.uint8), connectivity=8)
    tensor = _compression_tensor(xy, rest_spacing_m)
    quad_height = np.maximum.reduce(
        [nodes_m[:-1, :-1, 2], nodes_m[:-1, 1:, 2], nodes_m[1:, 1:, 2], nodes_m[1:, :-1, 2]]
    )
    rest_area = rest_spacing_m[0] * rest_spacing_m[1]
    quad_centres = (xy[:-1, :-1] + xy[:-1, 1:] + xy[1:, 1:] + xy[1:, :-1]) / 4.0
    ridges = []
    for k in range(1, count):
        quads = labels == k
        top = np.unravel_index(np.argmax(np.where(quads, quad_height, -np.inf)), quads.shape)
        corners = nodes_m[top[0] : top[0] + 2, top[1] : top[1] + 2].reshape(-1, 3)
        peak = corners[np.argmax(corners[:, 2])]
        evals, evecs = np.linalg.eigh(tensor[quads].sum(axis=0))
        across = evecs[:, np.argmax(evals)]
        along = np.array([-across[1], across[0]])  # the line runs perpendicular to `across`
        centres = quad_centres[quads]
        reach = centres @ along
        length = float(reach.max() - reach.min()) + math.sqrt(rest_area)
        ridges.append(
            Ridge(
                position_m=(float(peak[0]), float(peak[1])),
                direction_rad=math.atan2(along[1], along[0]) % math.pi,
                height_m=float(peak[2]),
                area_m2=float(quads.sum() * rest_area),
                slack_m=float((shortening[quads] * rest_area).sum()) / length,
                quad_centres_m=centres,
            )
        )
    return tuple(sorted(ridges, key=lambda r: (-r.height_m, -r.area_m2)))


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
        self, nodes_m: np.ndarray, cloth_size_m: tuple[float, float], quad_seen: np.ndarray | None = None
    ) -> Flatness:
        """The flatness of mesh nodes_m (ny, nx, 3); quad_seen (ny-1, nx-1) where known finds flaps."""
        ny, nx = nodes_m.shape[:2]
        spacing = (cloth_size_m[0] / (nx - 1), cloth_size_m[1] / (ny - 1))
        shortening = quad_shortening(nodes_m[..., :2], spacing)
        compressed = shortening > self.cfg.compressed_strain
        # `flat` reads only what starts a ridge: a quad kept by the hysteresis below is for the regulator to
        # finish pulling; lying flat with no more than that is lying flat (the cloth's crimp, docs).
        starting_pct = float(100.0 * np.mean(compressed))
        if self._compressed is not None and self._compressed.shape == compressed.shape:
            # A ridge moves a little as it is pulled: what held slack last tick, or lies beside it, keeps
            # holding it down to the release strain.
            near = cv2.dilate(self._compressed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            compressed |= near & (shortening > self.cfg.release_strain)
        self._compressed = compressed
        compressed_pct = float(100.0 * np.mean(compressed))
        max_height = float(max(nodes_m[..., 2].max(), 0.0))
        flaps = () if quad_seen is None else find_flaps(nodes_m, spacing, quad_seen)
        c = self.cfg
        if self.flat:
            self.flat = max_height <= 2 * c.flat_height_m and starting_pct <= 2 * c.flat_compressed_pct
        else:
            self.flat = max_height <= c.flat_height_m and starting_pct <= c.flat_compressed_pct
        self.flat = self.flat and not flaps  # a folded corner is not flat, and stays until a hand lifts it
        ridges = find_ridges(nodes_m, spacing, shortening, compressed)
        return Flatness(max_height, compressed_pct, self.flat, ridges, flaps)
