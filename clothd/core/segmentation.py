"""Finding the cloth in a frame, against the conveyor background.

The conveyors (belts, deck) are grey: low colour saturation. Cloth is coloured and textured. The
score of a pixel is its colour distance from the background's colour, measured in CIE Lab on the
chroma plane (a*, b*) so that shading and the belts' light-dark ribs do not count; the background
colour is the median over the image border, which the cloth does not fill. Otsu's threshold on the
(blurred) score separates the two, morphology removes belt specks and closes the cloth's dark twill
lines, and the largest component, holes filled, is the cloth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

_MIN_AREA_FRACTION = 0.005  # smaller than this is not a cloth
_MAX_AREA_FRACTION = 0.9  # larger: the "cloth" is the whole view; use the full-frame ROI instead
_MIN_CHROMA_CONTRAST = 6.0  # Lab units between the two Otsu classes; below it nothing stands out
_BORDER_PX = 8


@dataclass(frozen=True)
class ClothRegion:
    mask: np.ndarray  # uint8 (h, w), 255 on the cloth
    corners_px: np.ndarray  # (4, 2) float32, minimum-area rectangle around the cloth
    area_px: int


def _chroma_score(image_bgr: np.ndarray) -> np.ndarray:
    lab = cv2.cvtColor(cv2.GaussianBlur(image_bgr, (5, 5), 0), cv2.COLOR_BGR2LAB).astype(np.float32)
    border = np.concatenate(
        [
            lab[:_BORDER_PX].reshape(-1, 3),
            lab[-_BORDER_PX:].reshape(-1, 3),
            lab[:, :_BORDER_PX].reshape(-1, 3),
            lab[:, -_BORDER_PX:].reshape(-1, 3),
        ]
    )
    background_ab = np.median(border[:, 1:], axis=0)
    return np.asarray(np.linalg.norm(lab[..., 1:] - background_ab, axis=-1))


def find_cloth(image_bgr: np.ndarray) -> ClothRegion | None:
    """The cloth in a BGR frame, or None when no plausible cloth is in view."""
    h, w = image_bgr.shape[:2]
    score = _chroma_score(image_bgr)
    score8 = np.clip(score * 4.0, 0, 255).astype(np.uint8)  # 1 Lab unit = 4 grey levels
    _, mask = cv2.threshold(score8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    fg, bg = score8[mask > 0], score8[mask == 0]
    if len(fg) == 0 or len(bg) == 0 or (float(fg.mean()) - float(bg.mean())) / 4.0 < _MIN_CHROMA_CONTRAST:
        return None
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel, iterations=2)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return None
    biggest = max(contours, key=cv2.contourArea)
    area = cv2.contourArea(biggest)
    if not _MIN_AREA_FRACTION * h * w <= area <= _MAX_AREA_FRACTION * h * w:
        return None
    filled = np.zeros((h, w), np.uint8)
    cv2.drawContours(filled, [biggest], -1, 255, thickness=cv2.FILLED)
    corners = cv2.boxPoints(cv2.minAreaRect(biggest)).astype(np.float32)
    return ClothRegion(filled, corners, int(area))


def full_frame_region(width: int, height: int, margin_px: int = 8) -> ClothRegion:
    """For footage where only cloth is in view: the whole frame less a margin."""
    m = margin_px
    corners = np.array(
        [[m, m], [width - 1 - m, m], [width - 1 - m, height - 1 - m], [m, height - 1 - m]], np.float32
    )
    mask = np.zeros((height, width), np.uint8)
    mask[m : height - m, m : width - m] = 255
    return ClothRegion(mask, corners, int((width - 2 * m) * (height - 2 * m)))


def cloth_mask_from_outline(outline_px: np.ndarray, width: int, height: int, erode_px: int) -> np.ndarray:
    """uint8 mask of the polygon outline (k, 2), eroded by erode_px: where features may be detected
    without their window reaching past the cloth's edge."""
    mask = np.zeros((height, width), np.uint8)
    pts = np.round(np.asarray(outline_px) * 4).astype(np.int32)  # 2 fractional bits
    cv2.fillPoly(mask, [pts], 255, lineType=cv2.LINE_8, shift=2)
    if erode_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1, 2 * erode_px + 1))
        return np.asarray(cv2.erode(mask, k))
    return mask
