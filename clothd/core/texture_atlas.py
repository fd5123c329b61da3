"""Where a new feature lies on the cloth, from texture: the first frame's cloth, in cloth space.

A feature found mid-run is bound to cloth space through the current estimate (clothd/core/binding.py).
Where the estimate is off (the nodes an occluder dragged along), the feature is bound through that
error and, right about its pixel, holds the error in for as long as it lives. Features found beside an
occluder are worse: their patch is partly the occluder's, and LK follows it.

The atlas is the first frame's image of the cloth resampled onto a grid in cloth space (`CELL_M` a
cell) through the first estimate. A new feature's neighbourhood, resampled the same way through the
current estimate, is matched (zero-mean NCC) against the atlas around where the estimate binds it:
- where it matches well (`MIN_NCC`) and nowhere else nearly as well, the match says which cloth point
  the feature is, whatever the estimate says: it is bound there;
- where it matches nothing, it is not the cloth as the atlas knows it (an occluder, its edge, a glint),
  and is not taken, provided the atlas still matches the cloth's features of long standing
  (`atlas_holds`): a cloth that now looks different everywhere (light, blur) says nothing about one
  feature;
- otherwise (a look-alike as good nearby) the estimate's binding stands.
Only where the cloth lies flat, now and in the first frame (no node of the feature's quad `FLAT_BELOW_M`
or higher): a fold's flanks look nothing like the flat cloth, and the quad mesh cannot place them
anyway (docs/second-view.md). Nor where most of the neighbourhood is off the cloth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from clothd.core.estimators.base import Estimator
from clothd.core.estimators.mesh import MeshEstimator
from clothd.core.feature_set import FeatureSet
from clothd.core.mesh import QuadMesh, blend

CELL_M = 0.001  # about a pixel on the default cell (f 900 px at 1 m)
HALF_PATCH_CELLS = 8  # a 17 mm square of cloth around the feature
SEARCH_CELLS = 8  # how far from the estimate's binding the atlas is searched, each way
MIN_NCC = 0.8  # a match must correlate this well ...
MIN_MARGIN = 0.1  # ... and this much better than the best match away from it
AWAY_CELLS = 2  # "away": further than this from the best match
MIN_INSIDE_FRACTION = 0.5  # of the neighbourhood on the cloth, or no match is tried
FLAT_BELOW_M = 0.002  # a node this high is up in a fold (a flat cloth's measured heights: under 1 mm)
REFERENCE_FEATURES = 32  # the features of long standing that tell whether the atlas still holds
# Placing costs about 0.1 ms a feature in the upkeep, before the next frame: at most this many a frame (an
# arm leaving the cloth bared room for 148 at once); the rest are found again at the next upkeep.
MAX_PLACED_PER_UPKEEP = 48


@dataclass(frozen=True)
class Matches:
    """Per feature (m): the best NCC in the search (nan: not tried), and the match's offset from the
    estimate's binding (m, 2) metres along the mesh's axes (nan where there is no clear match)."""

    best: np.ndarray
    offset_m: np.ndarray


class TextureAtlas:
    """The first frame's grey image of the cloth on a CELL_M grid over the mesh's rest rectangle, rows along
    its second axis, columns along its first."""

    def __init__(self, mesh: QuadMesh, gray: np.ndarray, nodes_px: np.ndarray, flat: np.ndarray) -> None:
        """mesh at rest; gray (h, w) the first frame; nodes_px (n_nodes, 2) where the first estimate
        projects the nodes; flat (n_nodes,) bool: the node lies on the table."""
        self.mesh = mesh
        cols, rows = int(mesh.width_m / CELL_M) + 1, int(mesh.height_m / CELL_M) + 1
        u, v = np.meshgrid(np.arange(cols) * CELL_M, np.arange(rows) * CELL_M)
        px = blend(nodes_px, mesh.bind(self._to_cloth(np.stack([u.ravel(), v.ravel()], axis=1))))
        px = px.astype(np.float32).reshape(rows, cols, 2)
        image = cv2.remap(gray, px[..., 0], px[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        self.image = image.astype(np.float32)
        self.flat_at_start = np.asarray(flat, bool).copy()

    def _to_cloth(self, uv_m: np.ndarray) -> np.ndarray:
        """Grid coordinates (k, 2) (metres along the mesh's axes from its origin) -> cloth space (k, 2)."""
        return np.asarray(self.mesh.origin_m + uv_m @ self.mesh.axes)

    def match(
        self, gray: np.ndarray, nodes_px: np.ndarray, flat: np.ndarray, cloth_st: np.ndarray
    ) -> Matches:
        """Match the neighbourhoods of the cloth points cloth_st (m, 2) in the frame gray, whose nodes
        the estimate projects to nodes_px (n_nodes, 2) (flat (n_nodes,) as in __init__), against the
        atlas around the same points."""
        m = len(cloth_st)
        best, offset = np.full(m, np.nan), np.full((m, 2), np.nan)
        corners = self.mesh.bind(np.nan_to_num(cloth_st)).nodes
        tried = np.flatnonzero((flat & self.flat_at_start)[corners].all(axis=1) & np.isfinite(cloth_st[:, 0]))
        if len(tried) == 0:
            return Matches(best, offset)
        h, r = HALF_PATCH_CELLS, SEARCH_CELLS
        d = np.arange(-h, h + 1) * CELL_M
        du, dv = (g.ravel() for g in np.meshgrid(d, d))
        uv0 = (cloth_st[tried] - self.mesh.origin_m) @ self.mesh.axes.T  # (k, 2)
        uv = uv0[:, None, :] + np.stack([du, dv], axis=1)[None]  # (k, p, 2): rows along v, columns along u
        binding = self.mesh.bind(self._to_cloth(uv.reshape(-1, 2)))
        px = blend(nodes_px, binding).astype(np.float32).reshape(len(tried), -1, 2)
        size, region = 2 * h + 1, 2 * (h + r) + 1
        patches = cv2.remap(gray, px[..., 0], px[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        patches = patches.astype(np.float32).reshape(len(tried), size, size)
        inside = binding.inside.reshape(len(tried), size, size)
        for k, i in enumerate(tried):
            if inside[k].mean() < MIN_INSIDE_FRACTION:
                continue
            centre = (float(uv0[k, 0] / CELL_M), float(uv0[k, 1] / CELL_M))
            search = cv2.getRectSubPix(self.image, (region, region), centre)
            # The masked match costs four times the plain one, which equals it on a patch wholly on the cloth.
            mask = None if inside[k].all() else inside[k].astype(np.float32)
            scores = cv2.matchTemplate(search, patches[k], cv2.TM_CCOEFF_NORMED, mask=mask)
            scores = np.nan_to_num(scores, nan=-1.0)
            best[i] = float(scores.max())
            offset[i] = (_peak(scores) - r) * CELL_M
        return Matches(best, offset)

    def relocate(
        self, gray: np.ndarray, nodes_px: np.ndarray, flat: np.ndarray, cloth_st: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """New features bound at cloth_st (m, 2) through the current estimate (`match`'s arguments): their
        cloth coordinates (m, 2), placed by the atlas where it matches clearly, and which (m,) match
        nothing (best NCC under MIN_NCC)."""
        found = self.match(gray, nodes_px, flat, cloth_st)
        placed = np.isfinite(found.offset_m[:, 0])
        st = np.array(cloth_st, dtype=np.float64, copy=True)
        st[placed] += found.offset_m[placed] @ self.mesh.axes
        return st, found.best < MIN_NCC  # nan (not tried) compares False


def atlas_holds(
    atlas: TextureAtlas, gray: np.ndarray, nodes_px: np.ndarray, flat: np.ndarray, st: np.ndarray
) -> bool:
    """Whether the atlas still matches the cloth: the median best NCC of the cloth points st (k, 2) (the
    features of long standing) reaches MIN_NCC."""
    best = atlas.match(gray, nodes_px, flat, st).best
    best = best[np.isfinite(best)]
    return len(best) > 0 and float(np.median(best)) >= MIN_NCC


def _peak(scores: np.ndarray) -> np.ndarray:
    """The sub-cell (x, y) of the best score in scores (s, s); nan when it is weak, on the border of the
    search (the true one may lie beyond), or not clearly better than the best away from it."""
    y, x = np.unravel_index(int(np.argmax(scores)), scores.shape)
    best, s = float(scores[y, x]), scores.shape[0]
    none = np.full(2, np.nan)
    if best < MIN_NCC or x in (0, s - 1) or y in (0, s - 1):
        return none
    away = np.ones(scores.shape, bool)
    away[max(y - AWAY_CELLS, 0) : y + AWAY_CELLS + 1, max(x - AWAY_CELLS, 0) : x + AWAY_CELLS + 1] = False
    if best - float(scores[away].max()) < MIN_MARGIN:
        return none
    sub = []
    for lo, hi in ((scores[y, x - 1], scores[y, x + 1]), (scores[y - 1, x], scores[y + 1, x])):
        curve = lo - 2.0 * best + hi
        sub.append(0.0 if curve >= 0 else float(np.clip(0.5 * (lo - hi) / curve, -0.5, 0.5)))
    return np.array([x + sub[0], y + sub[1]])


class NewFeatureBinding:
    """How the tracker binds the features it finds mid-run: through the estimator, placed and sifted by
    the atlas of the first frame gray (the module docstring) where the estimator is the mesh EKF (it has
    nodes to resample through, and corrects them)."""

    def __init__(self, estimator: Estimator, mesh: QuadMesh, gray: np.ndarray) -> None:
        self.estimator = estimator
        self.atlas: TextureAtlas | None = None
        if isinstance(estimator, MeshEstimator) and estimator.corrects:
            nodes_px, z = estimator.nodes_px()
            self.atlas = TextureAtlas(mesh, gray, nodes_px, z < FLAT_BELOW_M)

    def bind(self, gray: np.ndarray, px: np.ndarray, features: FeatureSet) -> tuple[np.ndarray, np.ndarray]:
        """Cloth coordinates (m, 2) of new features at pixels px (m, 2) of the frame gray, and which (m,)
        to take. features: those tracked already (the oldest tell whether the atlas still holds)."""
        st, on = self.estimator.cloth_coordinates(px)
        atlas, estimator = self.atlas, self.estimator
        if atlas is None or not isinstance(estimator, MeshEstimator):
            return st, on
        on = on & (np.cumsum(on) <= MAX_PLACED_PER_UPKEEP)  # the strongest corners first (FeatureEngine)
        nodes_px, z = estimator.nodes_px()
        flat = z < FLAT_BELOW_M
        st, unlike = atlas.relocate(gray, nodes_px, flat, np.where(on[:, None], st, np.nan))
        if unlike.any():
            oldest = np.argsort(features.ids, kind="stable")[:REFERENCE_FEATURES]
            if atlas_holds(atlas, gray, nodes_px, flat, features.cloth_st[oldest]):
                on = on & ~unlike
        return st, on
