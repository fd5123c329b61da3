"""What the tracker asks of its further cameras: whether to wait for a paired frame before tracking
begins, the surface when it begins, and its points in every frame after (clothd/core/stereo.py has the
geometry, docs/second-view.md the method). A frame's heights need only what `HeightsFrame` keeps of it, so
they are measured after its estimate is out, once its paired frame has arrived, on a thread of their own:
the next frame's tracking runs meanwhile, and takes them (`collect`) when its correction needs them.
OpenCV releases the GIL, so the two views' LK passes share the cores (docs/second-view.md, "Heights in
every frame")."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
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

# A feature's height as the estimate puts it and as the last frame measured it, further apart than this:
# one of them may start LK in a look-alike's basin (hwsim's twill repeats every ~5 px, some 13 mm of height
# along the default cell's epipolar lines: half of that), so the feature is searched for afresh.
PRIORS_APART_M = 0.0065
# Tracking begins on a frame a further view pairs (its surface is measured then): this many frames are
# waited for one before tracking begins on one view.
PAIR_WAIT_FRAMES = 8


@dataclass(frozen=True)
class HeightsFrame:
    """What a tracked frame's heights are measured from: its grey image, the features that survived it
    (their ids (n,), pixels px (n, 2) and binding to the mesh), the mesh's nodes (ny, nx, 3) after its
    correction, and its time. Copies: the tracker goes on with the next frame."""

    gray: np.ndarray
    ids: np.ndarray
    px: np.ndarray
    binding: Binding
    nodes_m: np.ndarray
    t_s: float


@dataclass(frozen=True)
class FeatureHeights:
    """Features' measured heights: ids (n,) ascending, z_m (n,)."""

    ids: np.ndarray
    z_m: np.ndarray

    @staticmethod
    def of(ids: np.ndarray, z_m: np.ndarray) -> FeatureHeights:
        order = np.argsort(ids)
        return FeatureHeights(ids[order], z_m[order])

    def at(self, ids: np.ndarray) -> np.ndarray:
        """The heights (m,) of features ids (m,); NaN for those not among them."""
        if not len(self.ids):
            return np.full(len(ids), np.nan)
        slot = np.minimum(np.searchsorted(self.ids, ids), len(self.ids) - 1)
        return np.where(self.ids[slot] == ids, self.z_m[slot], np.nan)


class SecondView:
    """The first camera's model, the further cameras' (none: mono), the frames waited for a pair, the
    last measured frame's time and nodes (the features' motion between the two captures), the last
    frame given while its heights are still to measure, and the frame being measured."""

    def __init__(
        self,
        first: CameraModel,
        others: Sequence[CameraModel],
        cfg: StereoConfig,
        clock: Callable[[], float] = lambda: 0.0,
    ) -> None:
        self.first = first
        self.others = tuple(others)
        self.cfg = cfg
        self.clock = clock  # times the measuring only
        self._waits = 0
        self._nodes_before: tuple[float, np.ndarray] | None = None
        self._due: HeightsFrame | None = None
        self._points_before: FeatureHeights | None = None  # the features the last measured frame found
        self._measuring: Future[tuple[np.ndarray | None, float, FeatureHeights | None]] | None = None
        # Settled and not yet collected: the heights (None: none measured) and how long they took.
        self._measured: tuple[np.ndarray | None, float] | None = None
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="second-view") if self.others else None
        for other in self.others:  # the warp between the views, made now rather than in a frame
            table_warp(first, other)

    def reset(self) -> None:
        """Forget the frames; one being measured is let finish, unread."""
        self._measuring = None
        self._measured = None
        self._points_before = None
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
    ) -> None:
        """Keep the frame `gray` of the first view, its features and the mesh's nodes (ny, nx, 3) after its
        correction, and start measuring each mesh quad's highest point at the features a further view
        finds, from `views` (None: they come later, `heights_later`). `collect` gives them. The mesh's own
        heights stay inferred (folds.py): set from these points, the nodes of `compress`'s folds went 90 mm
        astray (docs/second-view.md)."""
        self._due = HeightsFrame(
            gray, features.ids.copy(), features.px.copy(), features.binding, nodes_m.copy(), t_s
        )
        if views is not None:
            self.heights_later(views)

    def heights_later(self, views: Sequence[PairedView | None]) -> None:
        """Start measuring the frame last given to `heights_now` from its views, unless it was already."""
        frame, self._due = self._due, None
        if frame is None or self._thread is None:
            return
        before, self._nodes_before = self._nodes_before, (frame.t_s, frame.nodes_m)
        self._settle()  # one frame at a time: the one before keeps its heights, and gives its points'
        self._measuring = self._thread.submit(self._measure, frame, before, self._points_before, list(views))

    def collect(self) -> tuple[np.ndarray | None, float | None]:
        """The quad heights (ny-1, nx-1) last measured and not yet collected, once the frame being measured
        is done (waited for), and how long measuring took on its thread; (None, None) when no frame was
        measured since, (None, seconds) when no view paired it or found enough."""
        self._settle()
        measured, self._measured = self._measured, None
        return (None, None) if measured is None else measured

    def _settle(self) -> None:
        measuring, self._measuring = self._measuring, None
        if measuring is None:
            return
        heights, took_s, points = measuring.result()
        if heights is None and self._measured is not None:  # an unpaired frame keeps the one before's
            heights = self._measured[0]
        self._measured = heights, took_s
        self._points_before = self._points_before if points is None else points

    def _measure(
        self,
        frame: HeightsFrame,
        before: tuple[float, np.ndarray] | None,
        points_before: FeatureHeights | None,
        views: Sequence[PairedView | None],
    ) -> tuple[np.ndarray | None, float, FeatureHeights | None]:
        """The frame's quad heights (None: none measured), how long they took, and the heights of the
        features found; from `before` (the last frame measured: its time and nodes) and `points_before`
        (the features it found): the work of the measuring thread, on its arguments alone.

        LK starts where the estimate puts each feature, unless the last frame measured it more than
        PRIORS_APART_M from there: then it is searched for over the whole height, from the table plane.
        Always from the estimate, a flat edge quad whose nodes a ridge's inferred fold had lifted 17 mm was
        looked for there, and two of its features matched a look-alike of the weave 21 mm up, every other
        frame (laid start 17 of `clothd bench flatten --lockstep --start laid --seed 0`)."""
        t0 = self.clock()
        nodes_m, t_s, binding = frame.nodes_m, frame.t_s, frame.binding
        velocity = None  # the features' on the table, from the last frame's nodes to this one's
        if before is not None and t_s > before[0]:
            velocity = blend((nodes_m - before[1])[..., :2] / (t_s - before[0]), binding)
        guess_m = blend(nodes_m, binding)
        if points_before is not None:  # NaN rows: searched for over the whole height
            guess_m[np.abs(guess_m[:, 2] - points_before.at(frame.ids)) > PRIORS_APART_M] = np.nan
        points, found = self.points_now(frame.gray, frame.px, guess_m, velocity, t_s, views)
        if points is None:
            return None, self.clock() - t0, None
        ny, nx = nodes_m.shape[:2]
        highest = quad_highest(binding.quad[found], points[:, 2], (ny - 1, nx - 1))
        heights = FeatureHeights.of(frame.ids[found], points[:, 2])
        return crest_heights(highest, points, nodes_m), self.clock() - t0, heights

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
