"""Several pieces on the table at once: each found as it comes in, given its own tracker once all of it is
in and still, told apart from the others, and released when it leaves (docs/flow.md).

Finding pieces costs a whole-frame segmentation (12-20 ms on a 960 x 480 frame), so it runs every
`flow.search_every` frames, beside the frame's tracking; tracking runs every frame, a tracker per piece.
A piece is known by where it lies on the table: a region found in a frame is the tracked piece whose
estimated outline holds its centre, else the untracked piece last seen nearest it, else a new piece.
Pieces apart have a region each; pieces touching come as one region, from which a tracked piece's
outline is taken out, and one larger than a piece is rejected (core/piece_regions.py).

A tracker starts on a piece only when the piece lies inside the workspace and has not moved between two
looks: tracking begins on a cloth at rest, as the single-piece tracker's does. It starts after that
frame's commands (`upkeep`), one piece a frame. The trackers come from a pool and go back to it when a
piece leaves; a new piece reuses one, so that nothing grows with the number of pieces that passed.

This module only sees. Which state a piece is in past `tracked` (flattening, placing, leaving) is the flow
controller's (core/flow.py), which also says when a piece has left.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from clothd.config import FlowConfig
from clothd.core.camera_model import CameraModel
from clothd.core.flatness import Flatness
from clothd.core.messages import Estimate, ModuleCommands, PairedView
from clothd.core.modes import PieceState
from clothd.core.piece_regions import Tracked, larger_than, outside_tracked
from clothd.core.segmentation import ClothRegion, find_cloths, full_frame_region
from clothd.core.workspace import Workspace

if TYPE_CHECKING:  # the status (and so the API process) reads pieces' reports without Taichi's import
    from clothd.core.tracker import Tracker

# A frame as `track` took it: (image, t_s, commands in force, further views).
_Frame = tuple[np.ndarray, float, ModuleCommands | None, Sequence[PairedView | None]]

GONE_KEPT = 50  # pieces that left or were rejected, kept for the API
MATCH_M = 0.08  # an untracked piece is the region seen this near where it was last seen
# An untracked piece not seen in this many looks in a row has gone from view: it is let go, rejected, so
# that it claims no modules (what it claimed was stopped, and a piece beside it could not be placed).
MISSED_LOOKS = 2
LOST_FROM_VIEW = "lost from view"
TOUCHING = "pieces touching"  # a region larger than one piece: its reason begins so


@dataclass
class Piece:
    """One piece of cloth on the table, as far as the cell knows it."""

    id: int
    state: PieceState
    since_s: float  # when it entered its state
    outline_m: np.ndarray  # (k, 2) on the table: its estimate's, or where it was last seen (then moved on)
    found_s: float  # when it was first seen
    estimate: Estimate | None = None  # this frame's, while it is tracked
    slot: int | None = None  # its tracker in the pool, while it has one
    reason: str | None = None  # why it was rejected, or why it stopped
    left_s: float | None = None
    missed_looks: int = 0  # looks in a row that did not see it (untracked pieces only)
    last_centre_m: np.ndarray | None = None  # where the last look saw it (untracked pieces only)
    still: bool = False  # the last two looks saw it in the same place
    driven_out: bool = False  # the flow drives it out over the outfeed (core/flow.py): it leaves the view
    tracked_since_s: float | None = None  # when its tracking last began: what the controller knew is stale
    beside: bool = False  # touching a tracked piece at the last look: held, its tracking not started
    region: ClothRegion | None = field(default=None, repr=False)  # what its tracker starts on

    @property
    def centre_m(self) -> np.ndarray:
        return np.asarray(self.outline_m.mean(axis=0))

    @property
    def tracking(self) -> bool:
        return self.estimate is not None and self.estimate.tracking

    def enter(self, state: PieceState, now_s: float, reason: str | None = None) -> None:
        self.state, self.since_s = state, now_s
        if reason is not None:
            self.reason = reason


@dataclass(frozen=True)
class PieceReport:
    """A piece as the API shows it: its state, pose and flatness, and why it was rejected."""

    id: int
    state: PieceState
    pose: tuple[float, float, float] | None  # [X_m, Y_m, theta_rad] while tracked
    flat: bool | None  # None: its flatness is not read (not tracked yet)
    max_height_mm: float | None
    reason: str | None
    found_s: float  # on the host's monotonic clock
    left_s: float | None

    @classmethod
    def of(cls, piece: Piece, flatness: Flatness | None) -> PieceReport:
        est = piece.estimate
        pose = None
        if est is not None and est.tracking:
            pose = (float(est.pose[0]), float(est.pose[1]), float(est.pose[2]))
        return cls(
            piece.id,
            piece.state,
            pose,
            None if flatness is None else flatness.flat,
            None if flatness is None else round(flatness.max_height_m * 1e3, 2),
            piece.reason,
            piece.found_s,
            piece.left_s,
        )


def contains(outline_m: np.ndarray, point_m: np.ndarray) -> bool:
    contour = outline_m.astype(np.float32).reshape(-1, 1, 2)
    return cv2.pointPolygonTest(contour, (float(point_m[0]), float(point_m[1])), False) >= 0


class PieceTracking:
    """The pieces on the table and their trackers. `track` once per frame, in order."""

    def __init__(
        self,
        cfg: FlowConfig,
        camera_model: CameraModel,
        workspace: Workspace,
        make_tracker: Callable[[], Tracker],
        max_pieces: int = 4,
    ) -> None:
        self.cfg = cfg
        self.camera_model = camera_model
        self.workspace = workspace
        self._make_tracker = make_tracker
        self._trackers: list[Tracker] = []
        self._free: list[int] = []
        self.max_pieces = max_pieces
        self.pieces: list[Piece] = []  # on the table, oldest first
        self.gone: deque[Piece] = deque(maxlen=GONE_KEPT)  # left or rejected and gone, oldest first
        self._next_id = 0
        self._frames = 0
        self._segmenter = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pieces-look")
        self._frame: _Frame | None = None  # the last frame tracked, for `upkeep`

    def warm(self, width: int, height: int, frames: int = 10) -> None:
        """Build every tracker of the pool and run each over a few frames of noise: a tracker's first
        frames compile its Taichi kernels (~0.5 s), and the first segmentation costs ~80 ms more than
        the next, which in a tick would stall the loop past its bound."""
        image = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
        find_cloths(image)
        region = full_frame_region(width, height)
        while len(self._trackers) < self.max_pieces:
            tracker = self._make_tracker()
            tracker.find_region = lambda _image: region
            for k in range(frames):
                tracker.track(image, k / 15.0, None)
                tracker.upkeep()
            tracker.reset()
            self._trackers.append(tracker)
            self._free.append(len(self._trackers) - 1)

    def reset(self) -> None:
        """Forget every piece, those gone too: the next look finds them afresh, numbered from 0."""
        for piece in list(self.pieces):
            self._release(piece)
        self.pieces.clear()
        self.gone.clear()
        self._next_id = 0
        self._frames = 0
        self._frame = None

    def track(
        self,
        image: np.ndarray,
        t_s: float,
        commands: ModuleCommands | None,
        views: Sequence[PairedView | None] = (),
    ) -> list[Piece]:
        """Track every piece in this frame, and look for pieces every `search_every` frames. The look's
        segmentation runs on a second thread while the pieces are tracked (both spend their time in
        OpenCV and numpy, which let go of the GIL); the regions it finds are told apart after. A piece
        whose tracking is to start starts in `upkeep`."""
        look = self._frames % self.cfg.search_every == 0
        self._frames += 1
        regions = self._segmenter.submit(find_cloths, image) if look else None
        for piece in self.pieces:
            if piece.slot is None:
                piece.estimate = None
            elif piece.region is None:
                self._track_piece(piece, image, t_s, commands, views)
        if regions is not None:
            self._look(regions.result(), image.shape, t_s)
        self._frame = (image, t_s, commands, views)
        return self.pieces

    def upkeep(self) -> None:
        """This frame's work that its commands do not wait for, done after them: the trackers' upkeep
        (Tracker.upkeep; else each tracker does it at its next frame), and one piece's start of tracking
        on this frame. A piece whose tracking starts lies still with its modules stopped, so no command
        waits for its start (~25 ms, as much as tracking two pieces: in the frame, beside the others, it
        kept the frame's commands past the tick)."""
        frame, self._frame = self._frame, None
        for piece in self.pieces:
            if piece.slot is not None and piece.region is None:
                self._trackers[piece.slot].upkeep()
        starting = next((p for p in self.pieces if p.region is not None), None)
        if frame is not None and starting is not None:
            self._track_piece(starting, *frame)

    def _track_piece(
        self,
        piece: Piece,
        image: np.ndarray,
        t_s: float,
        commands: ModuleCommands | None,
        views: Sequence[PairedView | None],
    ) -> None:
        assert piece.slot is not None
        tracker = self._trackers[piece.slot]
        estimate = tracker.track(image, t_s, commands, views)
        piece.estimate = estimate
        if estimate.tracking and estimate.outline_m is not None:
            piece.outline_m = estimate.outline_m
            if piece.region is not None:  # its tracking began with this frame
                piece.region, piece.tracked_since_s = None, t_s
            if piece.state == PieceState.ENTERING:
                piece.enter(PieceState.TRACKED, t_s)
        elif piece.region is None or not tracker.initialising:
            self._release(piece)  # lost: found again by a later look, and started again when still

    def leave(self, piece: Piece, now_s: float) -> None:
        """The flow controller's word that a piece has gone: its tracker goes back to the pool."""
        self._release(piece)
        piece.left_s = now_s
        self.pieces.remove(piece)
        self.gone.append(piece)

    # -- finding pieces -------------------------------------------------------------------------------

    def _look(self, regions: list[ClothRegion], frame_shape: tuple[int, ...], t_s: float) -> None:
        h, w = frame_shape[:2]
        seen: set[int] = set()
        untracked: list[tuple[np.ndarray, int]] = []  # the untracked pieces' regions this look, and whose
        for region, beside in self._apart_from_tracked(regions):
            outline = self.camera_model.backproject_to_plane(region.corners_px.astype(np.float64))[:, :2]
            centre = outline.mean(axis=0)
            piece = self._owner(centre, seen, outline)
            if piece is None:
                if outline[:, 0].max() > self.workspace.x_max_m or len(self.pieces) >= self.max_pieces:
                    continue  # the rest of a piece that has left, going over the outfeed edge
                piece = Piece(self._next_id, PieceState.ENTERING, t_s, outline, t_s)
                self._next_id += 1
                self.pieces.append(piece)
            seen.add(piece.id)
            if piece.slot is not None:
                continue
            moved = np.inf if piece.last_centre_m is None else np.linalg.norm(centre - piece.last_centre_m)
            piece.still = bool(moved * 1e3 < self.cfg.still_mm)
            piece.outline_m, piece.last_centre_m, piece.missed_looks = outline, centre, 0
            piece.beside = beside
            untracked.append((outline, piece.id))
            inside = self.workspace.leaves(outline) is None and not _touches_border(region.corners_px, w, h)
            if inside and piece.still and not beside:
                self._start(piece, region, outline, t_s)
        for piece in list(self.pieces):
            if piece.slot is not None or piece.id in seen:
                continue
            into = next((k for o, k in untracked if contains(o, piece.centre_m)), None)
            if into is not None and not piece.driven_out:
                # Its region merged into another untracked piece's (pieces touching): one piece now, and
                # this one let go as such, so that it is counted once (rejected), not missed.
                if piece.state != PieceState.REJECTED:
                    piece.enter(PieceState.REJECTED, t_s, f"{TOUCHING}: merged into piece {into}")
                self.leave(piece, t_s)
                continue
            # Beside a tracked piece, its region may have merged into the tracked one's: not missed, held.
            piece.beside = self._beside_a_tracked(piece)
            if not piece.beside:
                piece.missed_looks += 1
                if piece.missed_looks >= MISSED_LOOKS and not piece.driven_out:
                    if piece.state != PieceState.REJECTED:  # a reject waiting for its way keeps its reason
                        piece.enter(PieceState.REJECTED, t_s, LOST_FROM_VIEW)
                    self.leave(piece, t_s)

    def _apart_from_tracked(self, regions: list[ClothRegion]) -> list[tuple[ClothRegion, bool]]:
        """Each region with what of it is a tracked piece's taken out (pieces touching come as one region):
        (region, whether it touched a tracked piece)."""
        tracked = Tracked.of([p.outline_m for p in self.pieces if p.tracking], self.camera_model)
        apart: list[tuple[ClothRegion, bool]] = []
        for region in regions:
            parts = outside_tracked(region, tracked) if tracked.outlines_px else None
            apart += [(region, False)] if parts is None else [(part, True) for part in parts]
        return apart

    def _start(self, piece: Piece, region: ClothRegion, outline_m: np.ndarray, t_s: float) -> None:
        """Start its tracking on the region, unless the region is larger than one piece: pieces touching,
        which no tracker can tell apart, are rejected (and driven out as they are)."""
        size = larger_than(outline_m, self.cfg.piece_max_m)
        if size is None:
            if self._free_slot_for(piece):
                piece.region = region
        elif piece.state != PieceState.REJECTED:
            long_mm, short_mm = (round(v * 1e3) for v in size)
            reason = f"{TOUCHING}: {long_mm} x {short_mm} mm, more than one piece"
            piece.enter(PieceState.REJECTED, t_s, reason)

    def _beside_a_tracked(self, piece: Piece) -> bool:
        """Its last outline touches a tracked piece's (their convex hulls overlap)."""
        hull = cv2.convexHull(piece.outline_m.astype(np.float32))
        return any(
            cv2.intersectConvexConvex(hull, cv2.convexHull(other.outline_m.astype(np.float32)))[0] > 0.0
            for other in self.pieces
            if other is not piece and other.tracking
        )

    def _owner(self, centre_m: np.ndarray, taken: set[int], outline_m: np.ndarray) -> Piece | None:
        """The tracked piece whose outline holds the region's centre, else the nearest untracked piece
        within MATCH_M, or whose last centre the region holds (pieces touching merge and part again)."""
        for piece in self.pieces:
            if piece.slot is not None and piece.id not in taken and contains(piece.outline_m, centre_m):
                return piece
        near = [
            (float(np.linalg.norm(p.centre_m - centre_m)), k)
            for k, p in enumerate(self.pieces)
            if p.slot is None and p.id not in taken
        ]
        if not near:
            return None
        distance, k = min(near)
        piece = self.pieces[k]
        return piece if distance < MATCH_M or contains(outline_m, piece.centre_m) else None

    def _free_slot_for(self, piece: Piece) -> bool:
        """Give the piece a tracker, started on its region in this frame; False when none is free."""
        if self._free:
            slot = self._free.pop()
        elif len(self._trackers) < self.max_pieces:
            self._trackers.append(self._make_tracker())
            slot = len(self._trackers) - 1
        else:
            return False
        tracker = self._trackers[slot]
        tracker.reset()
        tracker.find_region = lambda _image: piece.region
        piece.slot = slot
        return True

    def _release(self, piece: Piece) -> None:
        if piece.slot is not None:
            self._trackers[piece.slot].reset()
            self._free.append(piece.slot)
        piece.slot, piece.estimate, piece.region = None, None, None
        piece.last_centre_m, piece.still = None, False


def _touches_border(corners_px: np.ndarray, width: int, height: int, margin_px: float = 2.0) -> bool:
    """The region reaches the frame's edge: part of the piece may lie out of view."""
    x, y = corners_px[:, 0], corners_px[:, 1]
    return bool(
        (x.min() < margin_px)
        | (y.min() < margin_px)
        | (x.max() > width - 1 - margin_px)
        | (y.max() > height - 1 - margin_px)
    )
