"""Finding the cloth in a frame, and the masks where features may be detected.

The background of the cell is grey: belts with ribs over a dark grey deck, all of low chroma. The cloth
is coloured (usually blue denim) and textured. `find_cloth` keeps the textured pixels whose chroma
(CIE Lab's (a, b) plane) is far from the frame's dominant, background colour; Otsu's method on those
distances finds the cloth's core and the edge is placed half-way between the cloth's and the
background's levels; then morphological cleanup, the largest connected component, holes filled.
Lab's (a, b) separates colour from brightness, so the dark deck, the bright ribs and the cloth's
shading do not move a pixel across the threshold; the texture test leaves out smooth coloured things
such as an operator's arm.

Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

# 5x5 Gaussian before the colour conversion: averages the sensor noise down ~4x; a symmetric blur does
# not move the half-way point of an edge.
_BLUR_PX = 5
# The dominant colour is the densest 5x5-unit patch of the (a, b) histogram.
_MODE_WINDOW = 5
# Chroma distances (Lab units) are scaled by this into 8 bits for Otsu and the medians: 0.25-unit
# bins, and the cloth's distances (~10-40 units) stay well below the clip at 255.
_CHROMA_SCALE = 4.0
# Otsu always splits, even a frame of pure background. The smoothed background's chroma noise stays
# under ~3 units (sensor noise sigma 1.5 grey levels); the faintest cloth pixels sit near 9. A split
# below 5 units is noise, not cloth.
_MIN_CHROMA = 5.0
# Texture: the local standard deviation of grey over 9x9 windows. A smooth surface under sensor noise
# (an arm, the shaded deck) stays under ~4 grey levels; woven cloth measures 14 and up (denim, twill).
_TEXTURE_PX = 9
_MIN_TEXTURE = 7.0
# Opening removes specks up to ~2 px (noise, coloured grit on the belts).
_OPEN_PX = 5
# Closing fills notches up to ~30 px across in the cloth's edge: faded, nearly white patches of denim
# have the background's chroma. It cannot round the cloth's (convex) corners.
_CLOSE_PX = 31
# A plausible cloth covers more than this fraction of the frame (smaller: specks, a stray object) ...
_MIN_AREA_FRACTION = 0.005
# ... and less than this: past it the background is hardly the dominant colour any more (footage of
# cloth only: use full_frame_region).
_MAX_AREA_FRACTION = 0.6


@dataclass(frozen=True)
class ClothColour:
    """How find_cloth told cloth from background in a frame: the background's colour (a, b) in 8-bit Lab
    and the chroma distance from it (Lab units) where cloth begins."""

    background_ab: tuple[float, float]
    edge_chroma: float

    def is_cloth(self, image_bgr: np.ndarray, points_px: np.ndarray, half_px: int = 2) -> np.ndarray:
        """Whether the mean colour of the (2 half_px + 1)² patch at each point (k, 2) is the cloth's, bool
        (k,); a patch that leaves the frame is not. Cheap: only the patches are converted."""
        h, w = image_bgr.shape[:2]
        c = np.round(np.asarray(points_px, np.float64)).astype(int)
        inside = np.all((c >= half_px) & (c < np.array([w, h]) - half_px), axis=1)
        seen = np.zeros(len(c), dtype=bool)
        if not inside.any():
            return seen
        cx, cy = c[inside, 0], c[inside, 1]
        # Summed pixel by pixel of the patch: gathering whole patches and averaging them cost twice as much.
        total = np.zeros((len(cx), 3), np.int32)
        for dy in range(-half_px, half_px + 1):
            for dx in range(-half_px, half_px + 1):
                total += image_bgr[cy + dy, cx + dx]
        mean = (total / (2 * half_px + 1) ** 2).astype(np.uint8)
        lab = cv2.cvtColor(mean.reshape(1, -1, 3), cv2.COLOR_BGR2Lab).reshape(-1, 3).astype(np.float32)
        a0, b0 = self.background_ab
        seen[inside] = np.hypot(lab[:, 1] - a0, lab[:, 2] - b0) > self.edge_chroma
        return seen


@dataclass(frozen=True)
class ClothRegion:
    """Where the cloth is in one frame.

    mask: uint8 (h, w), 255 on the cloth. corners_px: (4, 2) float32, the minimum-area rectangle around
    the cloth in cv2.boxPoints order, pixels. area_px: the number of cloth pixels. colour: how the cloth
    was told from the background (None when it was not: the whole frame taken as cloth).
    """

    mask: np.ndarray
    corners_px: np.ndarray
    area_px: int
    colour: ClothColour | None = None

    def outline_px(self) -> np.ndarray:
        """(k, 2) float64: the mask's largest outline, every boundary pixel in order around it."""
        contours, _ = cv2.findContours(self.mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        return np.asarray(max(contours, key=cv2.contourArea).reshape(-1, 2), dtype=np.float64)


def disk(diameter_px: int) -> np.ndarray:
    """A round structuring element that wide."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (diameter_px, diameter_px))


def _region(mask: np.ndarray, points_px: np.ndarray) -> ClothRegion:
    """A ClothRegion from its mask and the points (k, 2) whose minimum-area rectangle bounds it."""
    box = cv2.boxPoints(cv2.minAreaRect(points_px.reshape(-1, 1, 2).astype(np.float32)))
    return ClothRegion(mask, np.asarray(box, np.float32), int(cv2.countNonZero(mask)))


def _median_u8(channel: np.ndarray, mask: np.ndarray) -> float:
    """Median of a uint8 image (h, w) over a bool mask (h, w), from its histogram (fast, exact)."""
    hist = cv2.calcHist([channel], [0], mask.view(np.uint8), [256], [0, 256]).ravel()
    return float(np.searchsorted(np.cumsum(hist), 0.5 * hist.sum()))


def _dominant_ab(lab: np.ndarray) -> tuple[float, float]:
    """The frame's dominant colour (a, b) in 8-bit Lab: the peak of the (a, b) histogram, smoothed so
    that the peak is the densest patch and not one lucky bin. It is the background's colour as long as
    the background covers more of the frame than any one colour of the cloth."""
    hist = cv2.calcHist([lab], [1, 2], None, [256, 256], [0, 256, 0, 256])
    ia, ib = np.unravel_index(int(np.argmax(cv2.blur(hist, (_MODE_WINDOW, _MODE_WINDOW)))), hist.shape)
    # The patch's centroid: below the 1-unit quantisation, which would otherwise bias every distance.
    r = _MODE_WINDOW // 2
    lo_a, lo_b = max(int(ia) - r, 0), max(int(ib) - r, 0)
    patch = hist[lo_a : int(ia) + r + 1, lo_b : int(ib) + r + 1]
    wa, wb, total = patch.sum(axis=1), patch.sum(axis=0), float(patch.sum())
    return lo_a + float(wa @ np.arange(len(wa))) / total, lo_b + float(wb @ np.arange(len(wb))) / total


def _texture(gray: np.ndarray) -> np.ndarray:
    """Local standard deviation (h, w) float32 of a grey image over _TEXTURE_PX windows, grey levels."""
    g = gray.astype(np.float32)
    k = (_TEXTURE_PX, _TEXTURE_PX)
    mean = cv2.blur(g, k)
    return np.asarray(np.sqrt(np.maximum(cv2.blur(g * g, k) - mean * mean, 0.0)))


def find_cloth(image_bgr: np.ndarray) -> ClothRegion | None:
    """The cloth in a BGR uint8 frame (h, w, 3), or None when no plausible cloth is visible: the largest
    of `find_cloths`."""
    found = find_cloths(image_bgr)
    return found[0] if found else None


def find_cloths(image_bgr: np.ndarray) -> list[ClothRegion]:
    """Every piece of cloth in a BGR uint8 frame (h, w, 3), largest first; empty when none is visible.

    Empty when nothing textured differs in colour from the background by more than noise. A coloured,
    textured component is a piece when it covers between 0.5 % and 60 % of the frame and is not greyer
    than the dominant colour; when the largest is not, the dominant colour was the cloth's, not the
    background's, and nothing is found. Pieces a few millimetres apart stay apart: each component is
    closed alone.
    """
    if image_bgr.ndim != 3 or image_bgr.shape[2] != 3:
        raise ValueError(f"find_cloth needs a BGR image (h, w, 3), got shape {image_bgr.shape}")
    h, w = image_bgr.shape[:2]
    lab = cv2.cvtColor(cv2.GaussianBlur(image_bgr, (_BLUR_PX, _BLUR_PX), 0), cv2.COLOR_BGR2Lab)
    a0, b0 = _dominant_ab(lab)
    dist = np.hypot(lab[..., 1].astype(np.float32) - a0, lab[..., 2].astype(np.float32) - b0)
    scaled = np.clip(dist * _CHROMA_SCALE, 0, 255).astype(np.uint8)
    # Smooth coloured things (an arm, a painted part) are not cloth; leaving them out also keeps them
    # from pulling Otsu's split away from background-versus-cloth.
    textured = _texture(cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY)) > _MIN_TEXTURE
    if not textured.any():
        return []
    otsu, _ = cv2.threshold(scaled[textured].reshape(-1, 1), 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    core = textured & (scaled > max(otsu, _MIN_CHROMA * _CHROMA_SCALE))
    if not core.any():
        return []
    # Otsu's split finds the cloth's coloured core but sits above the middle of the edge's ramp when
    # the cloth's chroma spreads wide (denim: ~10 to 40 units), which would lose the rim. The edge is
    # where the chroma is half-way from the background's typical level to the cloth's.
    rest = textured & ~core
    bg_level = _median_u8(scaled, rest) if rest.any() else 0.0
    level = max(0.5 * (_median_u8(scaled, core) + bg_level), _MIN_CHROMA * _CHROMA_SCALE)
    above = np.where(textured & (scaled > level), np.uint8(255), np.uint8(0))
    mask = cv2.morphologyEx(above, cv2.MORPH_OPEN, disk(_OPEN_PX))
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    colour = ClothColour((a0, b0), level / _CHROMA_SCALE)
    background_chroma = math.hypot(a0 - 128.0, b0 - 128.0)
    regions = []
    for label in 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA]):
        if stats[label, cv2.CC_STAT_AREA] < _MIN_AREA_FRACTION * h * w:
            break
        region = _closed_component(labels, int(label), stats[label, :4], colour)
        on = region.mask > 0
        cloth_chroma = math.hypot(_median_u8(lab[..., 1], on) - 128.0, _median_u8(lab[..., 2], on) - 128.0)
        plausible = region.area_px <= _MAX_AREA_FRACTION * h * w and cloth_chroma > background_chroma
        if plausible:
            regions.append(region)
        elif not regions:  # the largest is no cloth: the background was not the dominant colour
            return []
    return regions


def _closed_component(labels: np.ndarray, label: int, box: np.ndarray, colour: ClothColour) -> ClothRegion:
    """One component closed alone (other coloured blobs must not merge into it), in its bounding box
    padded by the kernel, with its holes filled by filling its outer contour."""
    h, w = labels.shape
    x, y, bw, bh = (int(v) for v in box)
    x0, y0 = max(x - _CLOSE_PX, 0), max(y - _CLOSE_PX, 0)
    x1, y1 = min(x + bw + _CLOSE_PX, w), min(y + bh + _CLOSE_PX, h)
    component = np.where(labels[y0:y1, x0:x1] == label, np.uint8(255), np.uint8(0))
    component = cv2.morphologyEx(component, cv2.MORPH_CLOSE, disk(_CLOSE_PX))
    contours, _ = cv2.findContours(component, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE, offset=(x0, y0))
    outline = max(contours, key=cv2.contourArea)
    filled = np.zeros((h, w), np.uint8)
    cv2.drawContours(filled, [outline], -1, 255, thickness=cv2.FILLED)
    return replace(_region(filled, outline.reshape(-1, 2)), colour=colour)


def full_frame_region(width: int, height: int, margin_px: int = 8) -> ClothRegion:
    """The whole frame less a `margin_px` border, for footage that shows only cloth (--roi full)."""
    if width <= 2 * margin_px or height <= 2 * margin_px:
        raise ValueError(f"a {width}x{height} frame has nothing inside a {margin_px}-px margin")
    mask = np.zeros((height, width), np.uint8)
    lo_x, lo_y, hi_x, hi_y = margin_px, margin_px, width - 1 - margin_px, height - 1 - margin_px
    mask[lo_y : hi_y + 1, lo_x : hi_x + 1] = 255
    corners = np.array([[lo_x, lo_y], [hi_x, lo_y], [hi_x, hi_y], [lo_x, hi_y]], np.float32)
    return _region(mask, corners)


def cloth_mask_from_outline(outline_px: np.ndarray, width: int, height: int, erode_px: float) -> np.ndarray:
    """uint8 (height, width) mask, 255 inside the polygon `outline_px` (k, 2) pixels, shrunk by
    `erode_px` pixels: where new features may be detected (away from the edge, where a feature's
    patch would straddle cloth and moving background)."""
    shift = 4  # sub-pixel vertices: 1/16 px
    pts = np.round(np.asarray(outline_px, np.float64).reshape(-1, 1, 2) * (1 << shift)).astype(np.int32)
    mask = np.zeros((height, width), np.uint8)
    cv2.fillPoly(mask, [pts], 255, lineType=cv2.LINE_8, shift=shift)
    radius = math.ceil(erode_px)
    if radius <= 0:
        return mask
    # Outside the frame counts as off the cloth: a patch cut by the frame's edge tracks no better. Only
    # the polygon's bounding box is eroded: around it the mask is 0, as the border the box is eroded with.
    x, y, w, h = cv2.boundingRect(mask)
    if w == 0:
        return mask
    box = np.ascontiguousarray(mask[y : y + h, x : x + w])
    kernel = disk(2 * radius + 1)
    mask[y : y + h, x : x + w] = cv2.erode(box, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return mask
