"""Regions that are not one piece (docs/flow.md, "Pieces touching").

Segmentation cannot part two pieces that touch: they come as one region. Where one of them is tracked,
its estimated outline (this frame's, as the segmentation is) is taken out of the region, widened by
`TRACKED_MARGIN_M` for the estimate's and the edge's error; what is left is the other piece. Where
neither is tracked, nothing tells where one ends: a region larger than the largest piece the line lays
(`flow.piece_max_m`) is taken for pieces touching.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from clothd.core.camera_model import CameraModel
from clothd.core.segmentation import ClothRegion

# A tracked outline is within ~2 mm of the piece's edge, the segmentation's edge within a pixel (~1 mm):
# 6 mm leaves no strip of the tracked piece to pass for a piece of its own.
TRACKED_MARGIN_M = 0.006
_OPEN_PX = 9
# A remainder smaller than find_cloths' smallest piece is a sliver of the tracked piece's edge.
_MIN_AREA_FRACTION = 0.005


def tracked_mask(outlines_m: Sequence[np.ndarray], model: CameraModel) -> np.ndarray | None:
    """uint8 (h, w), 255 where a tracked piece lies (its outline widened by the margin); None if none."""
    if not outlines_m:
        return None
    mask = np.zeros((model.height, model.width), np.uint8)
    for outline in outlines_m:
        pts = np.column_stack([outline, np.zeros(len(outline))])
        px = model.project(pts)
        cv2.fillPoly(mask, [np.round(px).astype(np.int32).reshape(-1, 1, 2)], 255)
    centre = np.array([[0.0, 0.0, 0.0], [TRACKED_MARGIN_M, 0.0, 0.0]])
    margin_px = float(np.linalg.norm(np.diff(model.project(centre), axis=0)))
    size = 2 * max(1, round(margin_px)) + 1
    return cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))


def outside_tracked(region: ClothRegion, tracked: np.ndarray | None) -> list[ClothRegion] | None:
    """What of the region lies off the tracked pieces, a region per part (none: all of it is theirs); None
    when the region touches no tracked piece."""
    if tracked is None or not cv2.countNonZero(cv2.bitwise_and(region.mask, tracked)):
        return None
    rest = cv2.bitwise_and(region.mask, cv2.bitwise_not(tracked))
    # A strip along the tracked piece's edge (where its estimate fell short by more than the margin) is
    # not a piece: opened away.
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (_OPEN_PX, _OPEN_PX))
    rest = cv2.morphologyEx(rest, cv2.MORPH_OPEN, k)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(rest, connectivity=8)
    min_area = _MIN_AREA_FRACTION * rest.shape[0] * rest.shape[1]
    parts = []
    for label in range(1, n):
        if stats[label, cv2.CC_STAT_AREA] < min_area:
            continue
        mask = np.where(labels == label, np.uint8(255), np.uint8(0))
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        points = np.concatenate(contours).astype(np.float32)
        corners = np.asarray(cv2.boxPoints(cv2.minAreaRect(points)), np.float32)
        parts.append(ClothRegion(mask, corners, int(stats[label, cv2.CC_STAT_AREA]), region.colour))
    return parts


def larger_than(outline_m: np.ndarray, max_m: tuple[float, float]) -> tuple[float, float] | None:
    """The region's (long, short) sides in metres, from its rectangle's corners (4, 2), when either is
    past the largest piece's; else None."""
    sides = np.linalg.norm(np.diff(outline_m[:3], axis=0), axis=1)
    long_m, short_m = float(sides.max()), float(sides.min())
    big_long, big_short = max(max_m), min(max_m)
    return (long_m, short_m) if long_m > big_long or short_m > big_short else None
