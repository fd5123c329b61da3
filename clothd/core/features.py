"""Shi–Tomasi detection and pyramidal Lucas–Kanade tracking with a forward–backward check.

Each frame is converted to grey once and serves the forward pass (previous -> current) and, on the
next tick, the backward pass of the next pair. (OpenCV's Python binding cannot take a prebuilt pyramid
in calcOpticalFlowPyrLK, so each call rebuilds its pyramids: about 0.5 ms at 640x480, small next to
tracking 1000 points.) The forward–backward check (Kalal et al. 2010) tracks each point back
from where it landed; a point that does not come home within `fb_max_error_px` was mistracked
(occlusion, a moving belt edge, a repeating pattern).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from clothd.config import FeatureConfig


@dataclass(frozen=True)
class GrayFrame:
    """One frame ready for detection and LK."""

    gray: np.ndarray


@dataclass(frozen=True)
class TrackResult:
    px: np.ndarray  # (n, 2) float32 positions in the current frame (meaningless where not ok)
    ok: np.ndarray  # (n,) bool
    fb_error_px: np.ndarray  # (n,) forward-backward distance, inf where a pass failed


class FeatureEngine:
    def __init__(self, cfg: FeatureConfig) -> None:
        self.cfg = cfg
        win = (cfg.lk_window_px, cfg.lk_window_px)
        self._win = win
        self._criteria = (
            cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
            cfg.lk_max_iterations,
            cfg.lk_epsilon_px,
        )

    def prepare(self, image: np.ndarray) -> GrayFrame:
        """BGR or grey uint8 (h, w[, 3]) -> the frame as the tracker uses it."""
        return GrayFrame(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image)

    def detect(
        self, frame: GrayFrame, mask: np.ndarray, max_count: int, avoid_px: np.ndarray | None = None
    ) -> np.ndarray:
        """Shi–Tomasi corners (m, 2) float32, m <= max_count, inside mask (uint8, 255 = allowed), at least
        min_distance_px from each other and from every point of avoid_px (k, 2). Not refined to sub-pixel:
        a feature is the patch LK follows, wherever its centre sits, and refinement can merge corners."""
        c = self.cfg
        if max_count <= 0:
            return np.zeros((0, 2), np.float32)
        allowed = mask.copy()
        if avoid_px is not None and len(avoid_px):
            radius = max(1, round(c.min_distance_px))
            for x, y in np.round(avoid_px).astype(int):
                cv2.circle(allowed, (int(x), int(y)), radius, 0, -1)
        pts = cv2.goodFeaturesToTrack(
            frame.gray,
            maxCorners=max_count,
            qualityLevel=c.quality_level,
            minDistance=c.min_distance_px,
            mask=allowed,
            blockSize=c.block_size_px,
            useHarrisDetector=False,
        )
        if pts is None:
            return np.zeros((0, 2), np.float32)
        return np.asarray(pts.reshape(-1, 2), dtype=np.float32)

    def track(
        self, prev: GrayFrame, cur: GrayFrame, px: np.ndarray, guess_px: np.ndarray | None = None
    ) -> TrackResult:
        """LK prev -> cur from px (n, 2), starting from guess_px (the filter's prediction) when given,
        then cur -> prev back to check. A point is ok when both passes converged, it came back within
        fb_max_error_px, and it lies inside the image."""
        n = len(px)
        if n == 0:
            empty = np.zeros((0, 2), np.float32)
            return TrackResult(empty, np.zeros(0, bool), np.zeros(0))
        p0 = np.ascontiguousarray(px, dtype=np.float32).reshape(-1, 1, 2)
        # Start LK at the filter's prediction when there is one: a better start converges faster and
        # is less likely to lock onto the next twill wale.
        start = p0 if guess_px is None else np.ascontiguousarray(guess_px, dtype=np.float32).reshape(-1, 1, 2)
        p1_init = start.copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(
            prev.gray,
            cur.gray,
            p0,
            p1_init,
            winSize=self._win,
            maxLevel=self.cfg.lk_levels,
            criteria=self._criteria,
            flags=flags,
        )
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            cur.gray,
            prev.gray,
            p1,
            p0.copy(),
            winSize=self._win,
            maxLevel=self.cfg.lk_levels,
            criteria=self._criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        p1, back = p1.reshape(-1, 2), back.reshape(-1, 2)
        converged = (st1.ravel() == 1) & (st2.ravel() == 1)
        fb = np.where(converged, np.linalg.norm(back - p0.reshape(-1, 2), axis=1), np.inf)
        h, w = cur.gray.shape
        inside = (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        ok = converged & (fb <= self.cfg.fb_max_error_px) & inside
        return TrackResult(p1.astype(np.float32), ok, fb)


def coverage_holes(mask: np.ndarray, px: np.ndarray, cell_px: int) -> np.ndarray:
    """uint8 mask (255) of the cell_px x cell_px grid cells that are mostly inside `mask` but hold no
    point of px (n, 2): the parts of the cloth the tracker has lost sight of."""
    h, w = mask.shape
    gh, gw = -(-h // cell_px), -(-w // cell_px)
    padded = np.zeros((gh * cell_px, gw * cell_px), np.uint8)
    padded[:h, :w] = mask > 0
    inside_frac = padded.reshape(gh, cell_px, gw, cell_px).mean(axis=(1, 3))
    occupied = np.zeros((gh, gw), bool)
    if len(px):
        cells = np.floor(np.asarray(px) / cell_px).astype(int)
        good = (cells[:, 0] >= 0) & (cells[:, 0] < gw) & (cells[:, 1] >= 0) & (cells[:, 1] < gh)
        occupied[cells[good, 1], cells[good, 0]] = True
    holes = (inside_frac > 0.75) & ~occupied
    out = np.kron(holes.astype(np.uint8), np.ones((cell_px, cell_px), np.uint8))[:h, :w] * 255
    return np.asarray(out & mask)
