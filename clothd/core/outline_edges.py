"""The cloth's outline as a measurement: where its edge lies across the mesh's border, frame by frame.

On a strictly periodic weave (hwsim's plain twill) every patch inside the cloth is a piece of
the same stripes: LK measures each feature across the wales and hardly at all along them (the aperture
problem), and nothing inside the cloth can tell a shift along the wales from none. The cloth's edges can:
the border of the mesh is the cloth's outline, and against the belts it is a colour edge. So, as model-based
edge trackers do (RAPiD, Harris 1992), points on the mesh's border are searched for along the outline's
normal, in the colour distance from the background that found the cloth at the start (segmentation's
ClothColour), and each found edge is a measurement across the outline only (its whitening is the
aperture's: along the edge it says next to nothing).

Each point's offset at the start (where the rectangle laid over the cloth put the border against where
the colour edge is) is kept and subtracted, so a border that sat a pixel off the true edge from the
start is not pulled onto it later.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from clothd.core.camera_model import CameraModel
from clothd.core.mesh import Binding, QuadMesh, blend
from clothd.core.segmentation import ClothColour

_INSET_M = 0.004  # a second point this far inside gives the outline's outward normal in the image
_STEP_PX = 0.5  # the search samples the colour every half pixel


@dataclass(frozen=True)
class EdgeMeasurements:
    """binding: the border points (m); px (m, 2) where their edge was found; ok (m,) bool where it was;
    whiten (m, 2, 2) the measurements' whitening (across the outline only)."""

    binding: Binding
    px: np.ndarray
    ok: np.ndarray
    whiten: np.ndarray


class OutlineEdges:
    """per_side points on each side of the mesh, searched for within search_px of where the estimate puts
    them; max_ratio as FeatureConfig.aperture_max_ratio."""

    def __init__(
        self,
        mesh: QuadMesh,
        colour: ClothColour,
        camera: CameraModel,
        per_side: int,
        search_px: float,
        max_ratio: float,
    ) -> None:
        self.colour = colour
        self.camera = camera
        self.search_px = search_px
        self.max_ratio = max_ratio
        f = (np.arange(per_side) + 0.5) / per_side
        w, h = mesh.width_m, mesh.height_m
        eps = 1e-9
        # (a, b) along the mesh's axes: bottom, top, left and right sides, and the inward step of each.
        ab = np.concatenate(
            [
                np.stack([f * w, np.full_like(f, eps)], 1),
                np.stack([f * w, np.full_like(f, h - eps)], 1),
                np.stack([np.full_like(f, eps), f * h], 1),
                np.stack([np.full_like(f, w - eps), f * h], 1),
            ]
        )
        inward = np.repeat(np.array([[0.0, 1.0], [0.0, -1.0], [1.0, 0.0], [-1.0, 0.0]]), per_side, axis=0)
        to_st = lambda p: mesh.origin_m + p @ mesh.axes  # noqa: E731 - grid axes (a, b) to cloth (s, t)
        self.binding = mesh.bind(to_st(ab))
        self._inner = mesh.bind(to_st(ab + _INSET_M * inward))
        self.offset_px: np.ndarray | None = None  # each point's edge offset at the start; NaN: never found

    def measure(self, image_bgr: np.ndarray, nodes_m: np.ndarray) -> EdgeMeasurements:
        """Search the image (h, w, 3) for the edge at each border point of the mesh with node positions
        nodes_m (n, 3). The first call sets the points' offsets at the start and measures nothing."""
        p = self.camera.project(blend(nodes_m, self.binding))
        q = self.camera.project(blend(nodes_m, self._inner))
        out = p - q
        normal = out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-9)
        offset = self._edge_offsets(image_bgr, p, normal)
        m = len(p)
        if self.offset_px is None:
            self.offset_px = offset
            found = np.zeros(m, bool)
        else:
            found = np.isfinite(offset) & np.isfinite(self.offset_px)
        shift = np.where(found, np.nan_to_num(offset) - np.nan_to_num(self.offset_px), 0.0)
        px = p + shift[:, None] * normal
        along = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
        whiten = np.einsum("ki,kj->kij", normal, normal) + np.einsum("ki,kj->kij", along, along) / np.sqrt(
            self.max_ratio
        )
        return EdgeMeasurements(self.binding, px, found, whiten)

    def _edge_offsets(self, image_bgr: np.ndarray, p: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """(m,) where along each normal (pixels from p, outward positive) the colour turns from the cloth's
        to the background's: the crossing of the chroma threshold nearest p, linearly interpolated; NaN
        where the profile does not go from cloth (inside) to background (outside)."""
        steps = np.arange(-self.search_px, self.search_px + 1e-9, _STEP_PX)
        pts = p[:, None, :] + steps[None, :, None] * normal[:, None, :]  # (m, k, 2)
        mx = np.ascontiguousarray(pts[..., 0], dtype=np.float32)
        my = np.ascontiguousarray(pts[..., 1], dtype=np.float32)
        bgr = cv2.remap(image_bgr, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        lab = cv2.cvtColor(bgr, cv2.COLOR_BGR2Lab).astype(np.float32)
        a0, b0 = self.colour.background_ab
        # The edge is where the chroma distance from the background crosses the level that told cloth
        # from background at the start. (The level halfway between the profile's inner and outer ends,
        # which a symmetric blur keeps at the edge, did worse: a twill's pale weft bands near the edge
        # move the inner end. docs/benchmarks.md, "Weaves and fast belts".)
        d = np.hypot(lab[..., 1] - a0, lab[..., 2] - b0) - self.colour.edge_chroma  # (m, k): > 0 cloth
        h, w = image_bgr.shape[:2]
        seen = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
        cross = (d[:, :-1] > 0) & (d[:, 1:] <= 0) & seen[:, :-1] & seen[:, 1:]
        # The crossing nearest p; the profile must start on cloth and end on background.
        mid = 0.5 * (steps[:-1] + steps[1:])
        dist = np.where(cross, np.abs(mid)[None, :], np.inf)
        k = np.argmin(dist, axis=1)
        rows = np.arange(len(p))
        valid = np.isfinite(dist[rows, k]) & (d[:, 0] > 0) & (d[:, -1] <= 0)
        d0, d1 = d[rows, k], d[rows, k + 1]
        frac = d0 / np.where(d0 - d1 != 0, d0 - d1, 1.0)
        return np.where(valid, steps[k] + frac * _STEP_PX, np.nan)
