"""Regions that are not one piece (docs/flow.md, "Pieces touching").

Segmentation cannot part two pieces that touch: they come as one region. Where one of them is tracked,
its estimated outline (this frame's, as the segmentation is) is taken out of the region, widened by
`TRACKED_MARGIN_M` for the estimate's and the edge's error; what is left is the other piece. Where
neither is tracked, nothing tells where one ends: a region larger than the largest piece the line lays
(`flow.piece_max_m`) is taken for pieces touching.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from clothd.core.camera_model import CameraModel
from clothd.core.segmentation import ClothRegion, disk

# A tracked outline is within ~2 mm of the piece's edge, the segmentation's edge within a pixel (~1 mm):
# 6 mm leaves no strip of the tracked piece to pass for a piece of its own.
TRACKED_MARGIN_M = 0.006
_OPEN_PX = 9
# A remainder smaller than find_cloths' smallest piece is a sliver of the tracked piece's edge.
_MIN_AREA_FRACTION = 0.005


@dataclass(frozen=True)
class Tracked:
    """The tracked pieces' outlines in the frame, pixels, and the margin around them, pixels."""

    outlines_px: list[np.ndarray]  # each (k, 1, 2) int32
    margin_px: int

    @classmethod
    def of(cls, outlines_m: Sequence[np.ndarray], model: CameraModel) -> Tracked:
        px = [model.project(np.column_stack([o, np.zeros(len(o))])) for o in outlines_m]
        ends = model.project(np.array([[0.0, 0.0, 0.0], [TRACKED_MARGIN_M, 0.0, 0.0]]))
        margin = max(1, round(float(np.linalg.norm(ends[1] - ends[0]))))
        return cls([np.round(p).astype(np.int32).reshape(-1, 1, 2) for p in px], margin)


def outside_tracked(region: ClothRegion, tracked: Tracked) -> list[ClothRegion] | None:
    """What of the region lies off the tracked pieces, a region per part (none: all of it is theirs); None
    when the region touches no tracked piece. Worked in the region's box (0.5 ms a look; the whole frame
    and connected components cost 4.5)."""
    h, w = region.mask.shape
    x, y, bw, bh = cv2.boundingRect(region.corners_px.reshape(-1, 1, 2))
    m = tracked.margin_px
    x0, y0, x1, y1 = max(x - m, 0), max(y - m, 0), min(x + bw + m, w), min(y + bh + m, h)
    near = [o - np.array([x0, y0], np.int32) for o in tracked.outlines_px if _overlap(o, (x0, y0, x1, y1))]
    if not near:
        return None
    theirs = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillPoly(theirs, near, 255)
    theirs = cv2.dilate(theirs, disk(2 * m + 1))
    box = region.mask[y0:y1, x0:x1]
    if not cv2.countNonZero(cv2.bitwise_and(box, theirs)):
        return None
    # A strip along the tracked piece's edge (where its estimate fell short by more than the margin) is
    # not a piece: opened away.
    rest = cv2.morphologyEx(cv2.bitwise_and(box, cv2.bitwise_not(theirs)), cv2.MORPH_OPEN, disk(_OPEN_PX))
    contours, _ = cv2.findContours(rest, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE, offset=(x0, y0))
    parts = []
    for outline in contours:
        if cv2.contourArea(outline) < _MIN_AREA_FRACTION * h * w:
            continue
        mask = np.zeros((h, w), np.uint8)
        cv2.drawContours(mask, [outline], -1, 255, thickness=cv2.FILLED)
        corners = cv2.boxPoints(cv2.minAreaRect(outline.astype(np.float32)))
        parts.append(
            ClothRegion(mask, np.asarray(corners, np.float32), cv2.countNonZero(mask), region.colour)
        )
    return parts


def _overlap(outline_px: np.ndarray, box: tuple[int, int, int, int]) -> bool:
    x, y, w, h = cv2.boundingRect(outline_px)
    return x < box[2] and x + w > box[0] and y < box[3] and y + h > box[1]


def larger_than(outline_m: np.ndarray, max_m: tuple[float, float]) -> tuple[float, float] | None:
    """The region's (long, short) sides in metres, from its rectangle's corners (4, 2), when either is
    past the largest piece's; else None."""
    sides = np.linalg.norm(np.diff(outline_m[:3], axis=0), axis=1)
    long_m, short_m = float(sides.max()), float(sides.min())
    big_long, big_short = max(max_m), min(max_m)
    return (long_m, short_m) if long_m > big_long or short_m > big_short else None
