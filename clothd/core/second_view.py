"""What the tracker asks of its further cameras: whether to wait for a paired frame before tracking
begins, the surface when it begins, and its points in every frame after (clothd/core/stereo.py has the
geometry, docs/second-view.md the method). A frame's heights need only what `HeightsFrame` keeps of it, so
they can be measured after its estimate is out, once its paired frame has arrived."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from clothd.config import StereoConfig
from clothd.core.camera_model import CameraModel
from clothd.core.feature_set import FeatureSet
from clothd.core.mesh import Binding, QuadMesh, blend
from clothd.core.messages import PairedView
from clothd.core.stereo import (
    HeightField,
    crest_heights,
    fit_height_field,
    measure_surface,
    quad_highest,
    table_warp,
)

# Tracking begins on a frame a further view pairs (its surface is measured then): this many frames are
# waited for one before tracking begins on one view.
PAIR_WAIT_FRAMES = 8


@dataclass(frozen=True)
class HeightsFrame:
    """What a tracked frame's heights are measured from: its grey image, the features that survived it
    (their pixels px (n, 2) and their binding to the mesh), the mesh's nodes (ny, nx, 3) after its
    correction, and its time. Copies: the tracker goes on with the next frame."""

    gray: np.ndarray
    px: np.ndarray
    binding: Binding
    nodes_m: np.ndarray
    t_s: float


class SecondView:
    """The first camera's model, the further cameras' (none: mono), the frames waited for a pair, the
    last measured frame's time and nodes (the features' motion between the two captures), and the last
    frame given while its heights are still to measure."""

    def __init__(self, first: CameraModel, others: Sequence[CameraModel], cfg: StereoConfig) -> None:
        self.first = first
        self.others = tuple(others)
        self.cfg = cfg
        self._waits = 0
        self._nodes_before: tuple[float, np.ndarray] | None = None
        self._due: HeightsFrame | None = None
        for other in self.others:  # the warp between the views, made now rather than in a frame
            table_warp(first, other)

    def reset(self) -> None:
        self._waits = 0
        self._nodes_before = None
        self._due = None

    def heights_now(
        self,
        gray: np.ndarray,
        features: FeatureSet,
        nodes_m: np.ndarray,
        t_s: float,
        views: Sequence[PairedView | None] | None,
    ) -> np.ndarray | None:
        """Each mesh quad's highest point (ny-1, nx-1) at the features (their pixels in the first view's
        frame `gray`) that a further view finds, starting where the mesh's nodes (ny, nx, 3) put them; None
        when none pairs or finds enough. views None: they come later, and the frame is kept for
        `heights_later` (None now). The mesh's own heights stay inferred (folds.py): set from these
        points, the nodes of `compress`'s folds went 90 mm astray (docs/second-view.md)."""
        self._due = HeightsFrame(gray, features.px.copy(), features.binding, nodes_m.copy(), t_s)
        return None if views is None else self.heights_later(views)

    def heights_later(self, views: Sequence[PairedView | None]) -> np.ndarray | None:
        """`heights_now` of the frame last given to it, from its views; None when it was measured
        already or none of them pairs it or finds enough."""
        frame, self._due = self._due, None
        if frame is None:
            return None
        nodes_m, t_s, binding = frame.nodes_m, frame.t_s, frame.binding
        before, self._nodes_before = self._nodes_before, (t_s, nodes_m)
        velocity = None  # the features' on the table, from the last frame's nodes to this one's
        if before is not None and t_s > before[0]:
            velocity = blend((nodes_m - before[1])[..., :2] / (t_s - before[0]), binding)
        points, found = self.points_now(frame.gray, frame.px, blend(nodes_m, binding), velocity, t_s, views)
        if points is None:
            return None
        ny, nx = nodes_m.shape[:2]
        return crest_heights(
            quad_highest(binding.quad[found], points[:, 2], (ny - 1, nx - 1)), points, nodes_m
        )

    def awaits_pair(self, t_s: float, views: Sequence[PairedView | None]) -> bool:
        """No further view pairs the frame taken at t_s closely enough: wait for one, PAIR_WAIT_FRAMES at
        most (then tracking begins on one view)."""
        if not self.others:
            return False
        paired = any(v is not None and abs(v.t_s - t_s) <= self.cfg.max_skew_ms * 1e-3 for v in views)
        if paired or self._waits >= PAIR_WAIT_FRAMES:
            self._waits = 0
            return False
        self._waits += 1
        return True

    def surface(
        self,
        gray: np.ndarray,
        px: np.ndarray,
        velocity_m_s: np.ndarray | None,
        t_s: float,
        views: Sequence[PairedView | None],
        footprint: QuadMesh,
    ) -> HeightField | None:
        """The surface over `footprint` from the first view's features px (n, 2) in its frame `gray`, moving
        at velocity_m_s (n, 2) on the table (None: still); None when no further view pairs it or finds
        enough of them."""
        found = self.points_now(gray, px, None, velocity_m_s, t_s, views)
        return None if found[0] is None else fit_height_field(found[0], footprint)

    def points_now(
        self,
        gray: np.ndarray,
        px: np.ndarray,
        guess_m: np.ndarray | None,
        velocity_m_s: np.ndarray | None,
        t_s: float,
        views: Sequence[PairedView | None],
    ) -> tuple[np.ndarray | None, np.ndarray]:
        """The surface's points (m, 3) at the features px (n, 2) a further view finds, and which they are
        (n,) bool; (None, nothing found) when no view pairs or finds enough. guess_m (n, 3): where the
        estimate puts them (None: on the table); velocity_m_s: as stereo.measure_surface's."""
        none = np.zeros(len(px), bool)
        if len(px) < self.cfg.min_matches:
            return None, none
        cams = self.others
        found = measure_surface(gray, px, t_s, self.first, cams, views, self.cfg, guess_m, velocity_m_s)
        return (None, none) if found is None else found
