"""Shi–Tomasi detection and pyramidal Lucas–Kanade tracking with a forward–backward check.

Each frame is prepared once (`FeatureEngine.prepare`) and serves as the current frame of one tick's
forward pass and as the previous frame of the next tick's. The forward–backward check (Kalal et al.
2010) tracks each point back from where it landed: a point that does not come home within
`fb_max_error_px` was mistracked (a belt edge sliding under the cloth's edge, a repeating twill).
The check is blind to a point whose patch was replaced (an arm over it, a glint): the offset where
the new patch best matches the old one is a local optimum both ways, so LK finds it forward and comes
home backward. On hwsim frames with noise pasted over the patch, a quarter of such points passed.
So a point must also still look like itself: the zero-mean normalised cross-correlation of the centre
of its LK window (`ncc_window_px`) in the two frames must reach `lk_min_ncc`. The 9 x 9 centre costs
two thirds of the 11 x 11 window and tracks compress, occlude, translate and rotate as well (clothd
bench accuracy); 7 x 7 let one of tests/test_features.py's 20 noise-covered points through.

Why the prepared frame holds no pyramid levels: OpenCV's Python binding cannot pass prebuilt levels
from cv2.buildOpticalFlowPyramid to cv2.calcOpticalFlowPyrLK (opencv/opencv#4777, still so in the
installed OpenCV: "prevImg is not a numerical tuple"), so every LK call builds its own. That costs
~0.4 ms per pass at 640x480 against ~6 ms to track 1000 points; levels nobody can use would only add
to it. The grey conversion, the part that can be shared, is done once per frame.

Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from clothd.config import FeatureConfig

# cornerSubPix may slide off the Shi–Tomasi maximum onto another saddle of the weave when its window
# holds no single corner; a jump larger than this is not a sub-pixel correction, so the integer corner
# is kept (it is as good a feature for LK).
_MAX_SUBPIX_SHIFT_PX = 1.0
# Ask Shi–Tomasi for this many more corners than wanted: spares for those the exact spacing check drops.
_SPARE_FRACTION = 0.125
# A grid cell counts as cloth when more than this fraction of its in-image pixels are in the mask.
_CELL_INSIDE_FRACTION = 0.5


@dataclass(frozen=True)
class GrayFrame:
    """One frame as detection and LK use it: gray (h, w) uint8."""

    gray: np.ndarray


@dataclass(frozen=True)
class TrackResult:
    """px: (n, 2) float32 tracked positions in the current frame, pixels (meaningless where not ok).
    ok: (n,) bool. fb_error_px: (n,) float64 forward–backward distance, pixels; inf where a pass failed.
    ncc: (n,) float32 zero-mean normalised cross-correlation of the LK window at px in the previous
    frame and at the tracked position in the current one, in [-1, 1]; nan where a pass failed."""

    px: np.ndarray
    ok: np.ndarray
    fb_error_px: np.ndarray
    ncc: np.ndarray


class FeatureEngine:
    """Detection and tracking with the parameters of one FeatureConfig."""

    def __init__(self, cfg: FeatureConfig) -> None:
        self.cfg = cfg
        self._win = (cfg.lk_window_px, cfg.lk_window_px)
        self._criteria = (
            cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
            cfg.lk_max_iterations,
            cfg.lk_epsilon_px,
        )
        # Sub-pixel refinement over the neighbourhood the corner response was measured on.
        half = max(1, cfg.block_size_px // 2)
        self._subpix_win = (half, half)
        self._subpix_criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
        self._crop_margin_px = cfg.block_size_px + 2 * half + 8  # past what either reads, and any slide
        # Rounding an avoided point to its pixel moves it up to 0.71 px: pad the exclusion disc by 1.
        r = int(np.ceil(cfg.min_distance_px)) + 1
        self._avoid_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))

    def prepare(self, image: np.ndarray) -> GrayFrame:
        """BGR (h, w, 3) or grey (h, w) uint8 -> the prepared frame."""
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        return GrayFrame(np.ascontiguousarray(gray, dtype=np.uint8))

    def detect(
        self, frame: GrayFrame, mask: np.ndarray, max_count: int, avoid_px: np.ndarray | None = None
    ) -> np.ndarray:
        """Shi–Tomasi corners (m, 2) float32 pixels, m <= max_count, strongest first, refined to sub-pixel,
        inside `mask` (uint8 (h, w), 255 = allowed), at least min_distance_px from each other and from
        every point of avoid_px (k, 2)."""
        c = self.cfg
        empty = np.zeros((0, 2), np.float32)
        if max_count <= 0:
            return empty
        allowed = mask
        avoid = np.zeros((0, 2), np.float32)
        if avoid_px is not None and len(avoid_px):
            avoid = np.asarray(avoid_px, np.float32).reshape(-1, 2)
            avoid = avoid[np.isfinite(avoid).all(axis=1)]
            # Keep Shi–Tomasi from spending its budget next to the existing points (exact check below).
            h, w = mask.shape
            ij = np.round(avoid).astype(np.int64)
            on = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
            seeds = np.zeros((h, w), np.uint8)
            seeds[ij[on, 1], ij[on, 0]] = 255
            allowed = cv2.bitwise_and(mask, cv2.bitwise_not(cv2.dilate(seeds, self._avoid_kernel)))
        # Only the mask's bounding box, with the margin the corner response and the sub-pixel window
        # read: a piece covers a fraction of the frame, and the response costs per pixel. The corners are
        # the whole frame's (the quality level is relative to the best corner in the mask).
        x, y, bw, bh = cv2.boundingRect(allowed)
        if bw == 0:
            return empty
        m = self._crop_margin_px
        x0, y0 = max(x - m, 0), max(y - m, 0)
        x1, y1 = min(x + bw + m, mask.shape[1]), min(y + bh + m, mask.shape[0])
        gray = frame.gray[y0:y1, x0:x1]
        corners = cv2.goodFeaturesToTrack(
            gray,
            maxCorners=max_count + int(np.ceil(_SPARE_FRACTION * max_count)),
            qualityLevel=c.quality_level,
            minDistance=c.min_distance_px,
            mask=allowed[y0:y1, x0:x1],
            blockSize=c.block_size_px,
            useHarrisDetector=False,
        )
        if corners is None:
            return empty
        corners = np.asarray(corners, np.float32).reshape(-1, 1, 2)
        refined = cv2.cornerSubPix(gray, corners.copy(), self._subpix_win, (-1, -1), self._subpix_criteria)
        jumped = np.linalg.norm(refined - corners, axis=2) > _MAX_SUBPIX_SHIFT_PX
        pts = np.where(jumped[:, :, None], corners, refined).reshape(-1, 2) + np.array([x0, y0], np.float32)
        ij = np.round(pts).astype(np.int64)
        h, w = mask.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        inside[inside] = mask[ij[inside, 1], ij[inside, 0]] > 0
        pts = pts[inside]
        keep = _spaced(np.concatenate([avoid, pts]), len(avoid), c.min_distance_px)
        return np.ascontiguousarray(pts[keep][:max_count], dtype=np.float32)

    def track(
        self, prev: GrayFrame, cur: GrayFrame, px: np.ndarray, guess_px: np.ndarray | None = None
    ) -> TrackResult:
        """Pyramidal LK prev -> cur from px (n, 2) pixels, starting at guess_px (n, 2) (the filter's
        predicted pixels) when given, then cur -> prev back. A point is ok when both passes converged,
        it came back within fb_max_error_px of where it started, it landed inside the image, and its
        window's centre still looks the same (NCC >= lk_min_ncc over ncc_window_px)."""
        n = len(px)
        if n == 0:
            none = np.zeros(0, np.float32)
            return TrackResult(np.zeros((0, 2), np.float32), np.zeros(0, bool), np.zeros(0), none)
        p0 = np.ascontiguousarray(px, dtype=np.float32).reshape(-1, 2)
        # A start near the answer (the filter's prediction) converges in fewer iterations and does not
        # lock onto the neighbouring wale of a twill when the cloth moves by about a wale per frame.
        guess = None if guess_px is None else np.asarray(guess_px, np.float32).reshape(-1, 2)
        p1, ok1 = self._lk(prev.gray, cur.gray, p0, guess)
        # The backward pass gets the same prior motion, reversed: from p1 - (guess - p0), not from p0.
        # Started at the answer it is checking, LK could stay there and pass a mistracked point; with
        # no prior at all it could not come back from a motion only the guess made reachable.
        back, ok2 = self._lk(cur.gray, prev.gray, p1, None if guess is None else p1 - (guess - p0))
        converged = ok1 & ok2 & np.isfinite(p1).all(axis=1) & np.isfinite(back).all(axis=1)
        fb = np.full(n, np.inf)
        miss = back[converged] - p0[converged]
        if self.cfg.aperture_max_ratio > 1.0:
            # Along a wale LK has nothing to hold on to, so there the way back lands anywhere near the
            # start: only the miss across the patch's edge tells a mistracked point (the LK covariance's
            # whitening, as the estimator weighs the measurement).
            c = self.cfg
            W = aperture_whitening(prev.gray, p0[converged], c.lk_window_px, c.aperture_max_ratio)
            miss = np.einsum("kab,kb->ka", W, miss)
        fb[converged] = np.linalg.norm(miss, axis=1)
        h, w = cur.gray.shape
        inside = (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        ok = converged & (fb <= self.cfg.fb_max_error_px) & inside
        ncc = np.full(n, np.nan, np.float32)
        ncc[converged] = _patch_ncc(prev.gray, cur.gray, p0[converged], p1[converged], self.cfg.ncc_window_px)
        ok[converged] &= ncc[converged] >= self.cfg.lk_min_ncc
        return TrackResult(p1, ok, fb, ncc)

    def refine_to_anchor(
        self, anchor: GrayFrame, cur: GrayFrame, anchor_px: np.ndarray, tracked_px: np.ndarray, max_px: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """LK from the points anchor_px (n, 2) of the anchor frame into cur, started at tracked_px (n, 2),
        the frame-to-frame answer: positions (n, 2) float32, and (n,) bool where the pass converged within
        max_px of tracked_px and the patch there still looks like the anchor's (NCC >= lk_min_ncc)."""
        p0 = np.ascontiguousarray(anchor_px, dtype=np.float32).reshape(-1, 2)
        start = np.ascontiguousarray(tracked_px, dtype=np.float32).reshape(-1, 2)
        p1, converged = self._lk(anchor.gray, cur.gray, p0, start)
        converged &= np.isfinite(p1).all(axis=1)
        agrees = converged.copy()
        agrees[converged] = np.linalg.norm(p1[converged] - start[converged], axis=1) <= max_px
        if agrees.any():
            ncc = _patch_ncc(anchor.gray, cur.gray, p0[agrees], p1[agrees], self.cfg.ncc_window_px)
            agrees[agrees] = ncc >= self.cfg.lk_min_ncc
        return p1, agrees

    def track_from_rest(
        self, prev: GrayFrame, cur: GrayFrame, px: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One LK pass prev -> cur from px (n, 2), started where each point was (no motion assumed):
        positions (n, 2) float32 and converged (n,) bool. On a repeating pattern the prediction's start
        and this one land on different look-alikes when the prediction was off by half a period or
        more (clothd/core/tracker.py)."""
        p0 = np.ascontiguousarray(px, dtype=np.float32).reshape(-1, 2)
        if len(p0) == 0:
            return np.zeros((0, 2), np.float32), np.zeros(0, bool)
        p1, ok = self._lk(prev.gray, cur.gray, p0, None)
        return p1, ok & np.isfinite(p1).all(axis=1)

    def _lk(
        self, a: np.ndarray, b: np.ndarray, pts: np.ndarray, start: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """One LK pass a -> b from pts (n, 2), from start (n, 2) if given: positions (n, 2) float32 and
        converged (n,) bool."""
        flags = 0 if start is None else cv2.OPTFLOW_USE_INITIAL_FLOW
        guess = pts.copy() if start is None else np.array(start, dtype=np.float32)
        out, status, _ = cv2.calcOpticalFlowPyrLK(
            a,
            b,
            pts.reshape(-1, 1, 2),
            guess.reshape(-1, 1, 2),
            winSize=self._win,
            maxLevel=self.cfg.lk_levels,
            criteria=self._criteria,
            flags=flags,
        )
        return np.asarray(out, np.float32).reshape(-1, 2), np.asarray(status).ravel() == 1


def _spaced(px: np.ndarray, n_fixed: int, min_distance_px: float) -> np.ndarray:
    """Which of px[n_fixed:] (in priority order) to keep so that every kept point is at least
    min_distance_px from each fixed point px[:n_fixed] and from every kept point before it: (n - n_fixed,)
    bool. Sweep over the points sorted by x: x[i + o] - x[i] only grows with the offset o, so the sweep
    stops at the first offset where no pair is within min_distance_px in x."""
    n = len(px)
    order = np.argsort(px[:, 0], kind="stable")
    s = px[order]
    pairs: list[np.ndarray] = []
    for o in range(1, n):
        dx = s[o:, 0] - s[:-o, 0]
        near = dx < min_distance_px
        if not near.any():
            break
        close = near & (np.hypot(dx, s[o:, 1] - s[:-o, 1]) < min_distance_px)
        a, b = order[:-o][close], order[o:][close]
        pairs.append(np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1))
    keep = np.ones(n, bool)
    if pairs:
        conflicts = np.concatenate(pairs)
        conflicts = conflicts[conflicts[:, 1] >= n_fixed]  # two fixed points may be close: not ours
        # In priority order: by the time point i is reached, whether it is kept is final.
        for i, j in conflicts[np.lexsort((conflicts[:, 1], conflicts[:, 0]))]:
            if keep[i]:
                keep[j] = False
    return keep[n_fixed:]


def _patch_ncc(a: np.ndarray, b: np.ndarray, pa: np.ndarray, pb: np.ndarray, size_px: int) -> np.ndarray:
    """Zero-mean NCC (n,) float32 of the size_px x size_px patches of grey images a and b centred on
    pa and pb (n, 2), pixels, sampled bilinearly: all patches with one remap per image."""
    if len(pa) == 0:
        return np.zeros(0, np.float32)
    d = np.arange(size_px, dtype=np.float32) - (size_px - 1) / 2.0
    dx, dy = (g.ravel() for g in np.meshgrid(d, d))

    def patches(img: np.ndarray, p: np.ndarray) -> np.ndarray:
        mx = np.ascontiguousarray(p[:, :1] + dx, dtype=np.float32)
        my = np.ascontiguousarray(p[:, 1:] + dy, dtype=np.float32)
        return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float32)

    pa_, pb_ = patches(a, pa), patches(b, pb)
    m = float(size_px * size_px)
    # Zero-mean sums from raw ones, without centred copies of the patches.
    sa, sb = pa_.sum(axis=1), pb_.sum(axis=1)
    cov = np.einsum("ij,ij->i", pa_, pb_) - sa * sb / m
    var_a = np.einsum("ij,ij->i", pa_, pa_) - sa * sa / m
    var_b = np.einsum("ij,ij->i", pb_, pb_) - sb * sb / m
    denom = np.sqrt(np.maximum(var_a, 0.0) * np.maximum(var_b, 0.0))
    # A flat patch (no texture in either frame) correlates with nothing: 0, as in hwsim.verify.
    return np.where(denom > 1e-6, cov / np.maximum(denom, 1e-6), 0.0).astype(np.float32)


def structure_ratios(gray: np.ndarray, px: np.ndarray, window_px: int) -> tuple[np.ndarray, np.ndarray]:
    """λ1/λ2 (n,) of the structure tensor G (the sum of ∇I ∇Iᵀ, central differences) over the window around
    each rounded pixel px (n, 2), and the weak direction e2 (n, 2); ratio inf where the patch has texture in
    one direction only, nan where none at all. A woven stripe gives a large ratio, a corner about 1."""
    n = len(px)
    if n == 0:
        return np.zeros(0), np.zeros((0, 2))
    h, w = gray.shape
    half = window_px // 2 + 1
    d = np.arange(-half, half + 1)
    ij = np.round(np.nan_to_num(np.asarray(px, np.float64).reshape(-1, 2))).astype(np.int64)
    cols = np.clip(ij[:, 0, None] + d, 0, w - 1)  # (n, m)
    rows = np.clip(ij[:, 1, None] + d, 0, h - 1)
    patch = gray[rows[:, :, None], cols[:, None, :]].astype(np.float32)  # (n, m, m)
    gx = patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2]
    gy = patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1]
    a = np.einsum("kij,kij->k", gx, gx, dtype=np.float64)
    b = np.einsum("kij,kij->k", gx, gy, dtype=np.float64)
    c = np.einsum("kij,kij->k", gy, gy, dtype=np.float64)
    # Eigen-decomposition of [[a, b], [b, c]] in closed form: λ1 >= λ2, e2 the weak direction.
    mean, half_gap = (a + c) / 2.0, np.sqrt(((a - c) / 2.0) ** 2 + b**2)
    l1, l2 = mean + half_gap, mean - half_gap
    angle = 0.5 * np.arctan2(2.0 * b, a - c)  # direction of e1
    e2 = np.stack([-np.sin(angle), np.cos(angle)], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(l1 > 1e-9, l1 / np.maximum(l2, 0.0), np.nan)
    return ratio, e2


def self_similarity(gray: np.ndarray, px: np.ndarray, window_px: int, reach_px: int = 8) -> np.ndarray:
    """(n,) the best normalised correlation of the window around each rounded pixel px (n, 2) with the
    same window shifted 3 to reach_px pixels away, within LK's reach: near 1 where a pattern repeats (a
    check: every corner like its neighbours; hwsim's gingham 0.94-0.96), ~0.65 on denim and where a
    twill meets the table (the first features of the shipped recordings); nan where the search would
    leave the image."""
    half = window_px // 2
    r = half + reach_px
    h, w = gray.shape
    dy, dx = np.mgrid[-reach_px : reach_px + 1, -reach_px : reach_px + 1]
    near = np.hypot(dx, dy) < 3.0
    out = np.full(len(px), np.nan)
    image = np.asarray(gray, np.float32)
    for k, (x, y) in enumerate(np.round(np.asarray(px, np.float64).reshape(-1, 2)).astype(np.int64)):
        if x - r < 0 or y - r < 0 or x + r >= w or y + r >= h:
            continue
        search = image[y - r : y + r + 1, x - r : x + r + 1]
        ncc = cv2.matchTemplate(
            search, image[y - half : y + half + 1, x - half : x + half + 1], cv2.TM_CCOEFF_NORMED
        )
        ncc[near] = -1.0
        out[k] = float(ncc.max())
    return out


def aperture_whitening(gray: np.ndarray, px: np.ndarray, window_px: int, max_ratio: float) -> np.ndarray:
    """(n, 2, 2) float64 W per point px (n, 2): the map that whitens an LK measurement there, relative to
    one of a corner that is equally sharp in every direction.

    LK's error covariance is sigma_n² G⁻¹ (G the structure tensor: the sum over its window of ∇I ∇Iᵀ), so
    where the patch has an edge and little else (a twill's wale, the aperture problem) the position along
    the edge is barely measured: LK leaves it near its start (the filter's prediction) plus noise. The
    measurement covariance is taken as sigma² λ1 G⁻¹ = sigma² (e1 e1ᵀ + (λ1/λ2) e2 e2ᵀ): the meas_sigma
    across the edge, λ1/λ2 (at most max_ratio) times its variance along it. W = R^(-1/2) sigma =
    e1 e1ᵀ + sqrt(λ2/λ1) e2 e2ᵀ. Gradients: central differences on the window around the rounded pixel."""
    out = np.tile(np.eye(2), (len(px), 1, 1))
    if len(px) == 0:
        return out
    ratio, e2 = structure_ratios(gray, px, window_px)
    flat = np.isnan(ratio)  # no texture at all: leave it isotropic, the gate judges it
    ratio = np.clip(np.nan_to_num(ratio, nan=1.0, posinf=max_ratio), 1.0, max_ratio)
    shrink = 1.0 / np.sqrt(ratio) - 1.0
    shrink[flat] = 0.0
    out += shrink[:, None, None] * np.einsum("ki,kj->kij", e2, e2)
    return out


def coverage_holes(mask: np.ndarray, px: np.ndarray, cell_px: int) -> np.ndarray:
    """uint8 (h, w) mask, 255 where the tracker should resample: the cells of a cell_px x cell_px grid
    from the top-left corner that are mostly (> 50 % of their in-image pixels) inside `mask` but hold
    no point of px (n, 2) pixels, intersected with `mask` so that it can be passed to `detect` as is."""
    h, w = mask.shape
    rows, cols = np.arange(0, h, cell_px), np.arange(0, w, cell_px)
    # Each cell's count of mask pixels from the summed-area table at its corners (4x faster than summing
    # the image twice with np.add.reduceat).
    corners = cv2.integral((mask > 0).view(np.uint8))[np.ix_(np.append(rows, h), np.append(cols, w))]
    inside = corners[1:, 1:] - corners[:-1, 1:] - corners[1:, :-1] + corners[:-1, :-1]
    area = np.outer(np.diff(np.append(rows, h)), np.diff(np.append(cols, w)))
    occupied = np.zeros(inside.shape, bool)
    pts = np.asarray(px, np.float64).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    cells = np.floor(pts / cell_px).astype(np.int64)
    on = (cells[:, 0] >= 0) & (cells[:, 0] < len(cols)) & (cells[:, 1] >= 0) & (cells[:, 1] < len(rows))
    occupied[cells[on, 1], cells[on, 0]] = True
    holes = (inside > _CELL_INSIDE_FRACTION * area) & ~occupied
    if not holes.any():
        return np.zeros((h, w), np.uint8)
    full = np.repeat(np.repeat(holes, cell_px, axis=0), cell_px, axis=1)[:h, :w]
    return np.where(full & (mask > 0), np.uint8(255), np.uint8(0))


SELF_SIMILARITY_SAMPLE = 200  # the first features whose windows tell a repeating pattern


def classify_texture(gray: np.ndarray, px: np.ndarray, cfg: FeatureConfig) -> tuple[bool, bool]:
    """(periodic, repetitive) from a cloth's first features px (n, 2). A periodic weave: stripes
    everywhere, so their structure tensors are nearly rank one (the aperture problem); it takes a wider LK
    window and the outline as a measurement. A repeating pattern with corners (a check): its windows match
    themselves a few pixels away; LK takes no coarser level."""
    ratios, _ = structure_ratios(gray, px, cfg.lk_window_px)
    periodic = len(px) > 0 and float(np.nanmedian(np.nan_to_num(ratios, posinf=1e12))) >= cfg.periodic_ratio
    if periodic:
        return True, False
    similar = self_similarity(gray, px[:SELF_SIMILARITY_SAMPLE], cfg.lk_window_px)
    return False, bool(np.isfinite(similar).any()) and float(np.nanmedian(similar)) >= cfg.repetitive_ncc
