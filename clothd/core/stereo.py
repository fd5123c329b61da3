"""The cloth's surface measured through two calibrated views: features of the first view found in the
second along their epipolar lines, triangulated, and a smooth height field fitted through the points.

Matching: a feature on the table (z = 0) would be seen in the second view where the table-plane point
under it projects; a feature at height h lies further along its epipolar line, by about f·b·h/Z² pixels
(b the baseline, Z the distance). The first view is first warped into the second through the table plane,
so that a patch of nearly flat cloth looks the same in both and LK's only motion is the height's shift:
matched as seen, each view's own perspective biased each feature's height by its own amount (0.26 mm
sigma on the default cell, 0.97 mm on the flow cell's). Pyramidal Lucas–Kanade starts at the
table-plane guess and searches the rest; the match must come back to where it started
(forward–backward), and lie on the epipolar line: a match off the line is a look-alike, whatever LK says.

Triangulation: the midpoint of the shortest segment between the two viewing rays (their undistorted
directions through each camera's centre).

The height field: node heights on a regular grid over the cloth's footprint, in the footprint mesh's
own axes, fitted to the points by least squares with a curvature penalty (second differences), so that
the field runs smoothly through the gaps between features and a stray point cannot spike it. Points
the first fit leaves far out are dropped and the field fitted again.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.spatial import cKDTree

from clothd.config import StereoConfig
from clothd.core.banded import gram_band, solve_band, transpose_times
from clothd.core.camera_model import CameraModel
from clothd.core.mesh import QuadMesh
from clothd.core.messages import PairedView

MATCH_WINDOW_PX = 21  # wider than tracking's: the two views see a patch from different angles
MATCH_LEVELS = 3  # pyramid levels: a match up to ~60 px along its line from the table-plane guess
TRACKING_LEVELS = 1  # from where the estimate puts a point: a few pixels to find
TRACKING_WINDOW_PX = 11  # ... in a window as tracking's own
# Forward-backward, searching or not: the match must lead back within this. The epipolar check alone let
# a look-alike on the line through (0.2 px per mm of height): a flat cloth's feature read 3.3 mm high.
MATCH_FB_MAX_PX = 1.0
SEARCH_BLUR_PX = 1.5  # Gaussian sigma: a weave period of ~5 px is cut to a fifth of its contrast
WARP_MARGIN_PX = 80  # the first view is warped this far around the features' guesses: LK's search and window
FIELD_PITCH_M = 0.004  # the height field's grid spacing, finer than a ridge (hwsim's σ is 12 mm)
POINT_SIGMA_M = 0.001  # one triangulated height, about (0.2 px at the default cell's geometry)
# A second difference over FIELD_PITCH_M: a 20 mm ridge of σ 12 mm has ~2.2 mm at its crest. Held to 1.5 mm
# the field cut a 17 mm crest to 15 mm and laid out two thirds of its slack.
CURVATURE_SIGMA_M = 0.004
ZERO_SIGMA_M = 0.05  # far from any point the field settles to the table
OUTLIER_SIGMA = 4.0  # the refit drops points this many robust sigmas off the first fit
MIN_OUTLIER_M = 0.0015  # ... but never tighter than this
# A quad measured this high has risen (folds.py): a flat cloth's quads read 0.8 mm at most.
CREST_ABOVE_M = 0.002
# A quad measured this high, backed by a neighbour as high, is read from the surface through the points as
# well (`crest_heights`). Flatness is decided at 1 mm, where the two highest points of a crease's quads
# read 0.3-0.5 mm for 0.8-0.9 mm (the flatten regulator let go of a 1.15 mm crease it read at 0.85 mm).
CREST_READ_ABOVE_M = 0.0005
CREST_SAMPLES = 5  # along each side of a risen quad, where the surface is read for its highest
# ... at most this far from a point: points lie about 7 mm apart, and past the last one at an edge the field
# runs on along its slope (an edge quad of an 11.3 mm ridge read 13.7 mm).
CREST_SUPPORT_M = 0.0045
# The surface is fitted through the points this far round the risen quads only: a crest is read from the
# points near it, and a fit over the whole of a 500 x 360 mm panel took 50 ms.
CREST_FIELD_MARGIN_M = 0.02
CREST_MIN_POINTS = 8


def epipolar_distance_px(
    cam0: CameraModel, px0: np.ndarray, cam1: CameraModel, px1: np.ndarray, reach_m: float
) -> np.ndarray:
    """(n,): how far each px1 lies from the epipolar line of px0 in the second view, the line through the
    projections of the ray's points on the table and reach_m above it (lens distortion bends the line a
    fraction of a pixel over that span)."""
    lo = cam1.project(cam0.backproject_to_plane(px0, 0.0))
    hi = cam1.project(cam0.backproject_to_plane(px0, reach_m))
    d = hi - lo
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    r = px1 - lo
    return np.asarray(np.abs(r[:, 0] * d[:, 1] - r[:, 1] * d[:, 0]))


@lru_cache(maxsize=16)
def table_warp(cam0: CameraModel, cam1: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the second view, the first view's pixel that sees the same table point: the maps
    (h, w) float32 of cv2.remap that warp the first view into the second through the table plane.
    Cameras are fixed: made once for a pair (CameraModel hashes by identity)."""
    u, v = np.meshgrid(np.arange(cam1.width, dtype=np.float64), np.arange(cam1.height, dtype=np.float64))
    px1 = np.column_stack([u.ravel(), v.ravel()])
    px0 = cam0.project(cam1.backproject_to_plane(px1, 0.0))
    px0 = np.nan_to_num(px0, nan=-1.0).astype(np.float32)
    shape = (cam1.height, cam1.width)
    return px0[:, 0].reshape(shape), px0[:, 1].reshape(shape)


def _warped_first_view(
    gray0: np.ndarray, gray1: np.ndarray, cam0: CameraModel, cam1: CameraModel, around_px: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first view warped into the second through the table plane, and the second view, both cut to
    the rectangle WARP_MARGIN_PX around pixels around_px (n, 2) of the second view, and that rectangle's
    top-left corner (2,)."""
    map_x, map_y = table_warp(cam0, cam1)
    h, w = gray1.shape[:2]
    finite = around_px[np.isfinite(around_px).all(axis=1)]
    lo = np.clip(np.floor(finite.min(axis=0)) - WARP_MARGIN_PX, 0, [w - 1, h - 1]).astype(int)
    hi = np.clip(np.ceil(finite.max(axis=0)) + WARP_MARGIN_PX + 1, 1, [w, h]).astype(int)
    rows, cols = slice(lo[1], hi[1]), slice(lo[0], hi[0])
    warped = cv2.remap(gray0, map_x[rows, cols], map_y[rows, cols], cv2.INTER_LINEAR)
    return warped, np.ascontiguousarray(gray1[rows, cols]), lo.astype(np.float64)


def match_across(
    gray0: np.ndarray,
    gray1: np.ndarray,
    px0: np.ndarray,
    cam0: CameraModel,
    cam1: CameraModel,
    cfg: StereoConfig,
    guess_m: np.ndarray | None = None,
    seen_px0: np.ndarray | None = None,
    wide: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels px0 (n, 2) of the first view found in the second: (px1 (n, 2), ok (n,)). guess_m (n, 3):
    where the points are believed to be when the second view saw them; None: on the table. LK starts
    there; the points `wide` (n,) bool (None: all) are searched for over MATCH_LEVELS pyramid levels (the
    whole height), the others only a few pixels about the guess (TRACKING_LEVELS). seen_px0: where the
    first view would have seen them then (a skew between the captures); None: px0."""
    n = len(px0)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    on_table = cam1.project(cam0.backproject_to_plane(px0, 0.0))  # px0's content in the warped view
    guess = on_table if guess_m is None else cam1.project(guess_m)
    if not np.isfinite(on_table).all(axis=1).any():
        return np.full((n, 2), np.nan), np.zeros(n, bool)
    warped, gray1_cut, corner = _warped_first_view(gray0, gray1, cam0, cam1, np.vstack([on_table, guess]))
    p0 = np.nan_to_num(on_table - corner, nan=-1.0).astype(np.float32).reshape(-1, 1, 2)
    g = np.nan_to_num(guess - corner, nan=-1.0).astype(np.float32).reshape(-1, 1, 2)
    ok = np.isfinite(guess).all(axis=1) & np.isfinite(on_table).all(axis=1)
    wide = np.ones(n, bool) if wide is None else wide
    if wide.any():
        # The search's wide window spans a ridge's whole rise at the coarse levels, and at the finest the
        # weave repeats every few pixels: it ended a weave period off on a third to a half of a 17 mm
        # ridge's points (10-14 mm low). So the search runs on both views blurred past the weave, and
        # only brings each point near; a small window finds it from there.
        b0, b1 = (cv2.GaussianBlur(view, (0, 0), SEARCH_BLUR_PX) for view in (warped, gray1_cut))
        g[wide], searched = _lk_both_ways(b0, b1, p0[wide], g[wide], MATCH_WINDOW_PX, MATCH_LEVELS)
        ok[wide] &= searched
    p1, found = _lk_both_ways(warped, gray1_cut, p0, g, TRACKING_WINDOW_PX, TRACKING_LEVELS)
    px1 = p1.reshape(-1, 2).astype(np.float64) + corner
    h, w = gray1.shape[:2]
    inside = (px1[:, 0] >= 0) & (px1[:, 0] <= w - 1) & (px1[:, 1] >= 0) & (px1[:, 1] <= h - 1)
    ok &= found & inside
    line_px0 = px0 if seen_px0 is None else seen_px0
    ok &= epipolar_distance_px(cam0, line_px0, cam1, px1, cfg.max_height_m) < cfg.epipolar_max_px
    return px1, ok


def _lk_both_ways(
    view0: np.ndarray, view1: np.ndarray, p0: np.ndarray, guess: np.ndarray, side_px: int, levels: int
) -> tuple[np.ndarray, np.ndarray]:
    """Points p0 (n, 1, 2) of view0 found in view1 by LK from guess (n, 1, 2): where (n, 1, 2), and
    whether (n,) LK found them and found its way back from there to within MATCH_FB_MAX_PX of p0."""
    window, criteria = (side_px, side_px), (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        view0, view1, p0, guess.copy(), winSize=window, maxLevel=levels, criteria=criteria, flags=flags
    )
    back, st2, _ = cv2.calcOpticalFlowPyrLK(
        view1, view0, p1, p0.copy(), winSize=window, maxLevel=levels, criteria=criteria, flags=flags
    )
    led_back = np.linalg.norm(back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1) < MATCH_FB_MAX_PX
    return p1, st1.ravel().astype(bool) & st2.ravel().astype(bool) & led_back


def measure_surface(
    gray0: np.ndarray,
    px0: np.ndarray,
    t_s: float,
    cam0: CameraModel,
    cameras: Sequence[CameraModel],
    views: Sequence[PairedView | None],
    cfg: StereoConfig,
    guess_m: np.ndarray | None = None,
    velocity_m_s: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Points of the surface (m, 3) at the first view's features px0 (n, 2) (its frame gray0, taken at
    t_s) and which features they are (n,) bool, through the first further view paired within
    cfg.max_skew_ms that finds at least cfg.min_matches of them; None when none does. guess_m: as
    match_across's, at t_s; a row of NaN: that point's height is not known, and it is searched for from
    the table plane over the whole height, as every point is with None. velocity_m_s (n, 2): how the
    points move on the table, so that a view taken skew_s apart is matched and triangulated where they
    were then (v·skew_s), and the points moved back to t_s; None: still."""
    for camera, view in zip(cameras, views, strict=False):
        skew_s = 0.0 if view is None else view.t_s - t_s
        if view is None or abs(skew_s) > cfg.max_skew_ms * 1e-3:
            continue
        image = view.image
        gray1 = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        shift_m = np.zeros((len(px0), 3))
        if velocity_m_s is not None:
            shift_m[:, :2] = velocity_m_s * skew_s
        table_m = cam0.backproject_to_plane(px0, 0.0)
        known = np.zeros(len(px0), bool) if guess_m is None else np.isfinite(guess_m).all(axis=1)
        base_m = table_m if guess_m is None else np.where(known[:, None], guess_m, table_m)
        seen_px0 = px0 + cam0.project(base_m + shift_m) - cam0.project(base_m)
        px1, ok = match_across(gray0, gray1, px0, cam0, camera, cfg, base_m + shift_m, seen_px0, ~known)
        if ok.sum() >= cfg.min_matches:
            return triangulate(cam0, seen_px0[ok], camera, px1[ok]) - shift_m[ok], ok
    return None


def triangulate(cam0: CameraModel, px0: np.ndarray, cam1: CameraModel, px1: np.ndarray) -> np.ndarray:
    """World points (n, 3): the midpoints of the shortest segments between the rays through px0 and px1."""
    c0, c1 = cam0.centre_m, cam1.centre_m
    d0 = _rays(cam0, px0)
    d1 = _rays(cam1, px1)
    w = c0 - c1
    a, b, c = (d0 * d0).sum(1), (d0 * d1).sum(1), (d1 * d1).sum(1)
    d, e = d0 @ w, d1 @ w
    den = np.maximum(a * c - b * b, 1e-18)
    s = (b * e - c * d) / den
    t = (a * e - b * d) / den
    return np.asarray(0.5 * ((c0 + s[:, None] * d0) + (c1 + t[:, None] * d1)))


def _rays(cam: CameraModel, px: np.ndarray) -> np.ndarray:
    xy = cam.undistort(px)
    return np.asarray(np.column_stack([xy, np.ones(len(xy))]) @ cam.T_cam_world[:3, :3])


@dataclass(frozen=True)
class HeightField:
    """Heights z (gy, gx), metres, on a grid over a footprint mesh's rectangle: node (j, i) at the mesh's
    origin + i·pitch along its first axis + j·pitch along its second."""

    footprint: QuadMesh
    pitch_m: float
    z_m: np.ndarray

    def at(self, xy_m: np.ndarray) -> np.ndarray:
        """Heights (n,) at table points xy_m (n, 2), bilinear; points off the grid take its border's."""
        w, b = _grid_weights(self.footprint, self.pitch_m, self.z_m.shape, xy_m)
        return np.asarray((w * self.z_m.ravel()[b]).sum(axis=1))


def _grid_shape(footprint: QuadMesh, pitch_m: float) -> tuple[int, int]:
    return (
        max(2, int(np.ceil(footprint.height_m / pitch_m)) + 1),
        max(2, int(np.ceil(footprint.width_m / pitch_m)) + 1),
    )


def _grid_weights(
    footprint: QuadMesh, pitch_m: float, shape: tuple[int, int], xy_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear weights (n, 4) and flat grid indices (n, 4) of table points (n, 2)."""
    gy, gx = shape
    f = (np.asarray(xy_m, float).reshape(-1, 2) - footprint.origin_m) @ footprint.axes.T / pitch_m
    f = np.clip(f, 0.0, [gx - 1, gy - 1])
    cell = np.minimum(np.floor(f), [gx - 2, gy - 2]).astype(np.int64)
    u, v = (f - cell).T
    i, j = cell.T
    base = j * gx + i
    idx = np.stack([base, base + 1, base + gx, base + gx + 1], axis=1)
    w = np.stack([(1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v], axis=1)
    return w, idx


def fit_height_field(
    points_m: np.ndarray, footprint: QuadMesh, pitch_m: float = FIELD_PITCH_M
) -> HeightField:
    """The smooth height field through triangulated points (n, 3) over the footprint's rectangle."""
    shape = _grid_shape(footprint, pitch_m)
    gy, gx = shape
    w, idx = _grid_weights(footprint, pitch_m, shape, points_m[:, :2])
    z = _solve_field(w, idx, points_m[:, 2], shape)
    residual = (w * z[idx]).sum(axis=1) - points_m[:, 2]
    spread = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
    keep = np.abs(residual) < max(OUTLIER_SIGMA * spread, MIN_OUTLIER_M)
    if not keep.all():  # the refit of the same points would only repeat the fit (the usual case)
        z = _solve_field(w[keep], idx[keep], points_m[keep, 2], shape)
    return HeightField(footprint, pitch_m, z.reshape(gy, gx))


def _solve_field(w: np.ndarray, idx: np.ndarray, z_m: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    # Symmetric positive definite and banded: a grid node couples to nodes up to two rows away. Numbered
    # column by column when the rows are the longer, the band is the narrower (the solve's cost goes
    # with its square).
    gy, gx = shape
    n = gy * gx
    renumber = np.arange(n).reshape(gy, gx).T.ravel().argsort() if gx > gy else np.arange(n)
    short = min(gy, gx)
    cols = renumber[idx]
    ab = _prior_band(n // short, short) + gram_band(cols, w / POINT_SIGMA_M, n, 2 * short)
    return solve_band(ab, transpose_times(cols, w / POINT_SIGMA_M, z_m / POINT_SIGMA_M, n))[renumber]


@lru_cache(maxsize=8)
def _prior_band(gy: int, gx: int) -> np.ndarray:
    """The field's prior in band storage: smooth (the grid's second differences along both axes, each
    within CURVATURE_SIGMA_M) and, far from any point, on the table (ZERO_SIGMA_M). Read-only: shared."""
    grid = np.arange(gy * gx).reshape(gy, gx)
    along_x = np.stack([grid[:, :-2], grid[:, 1:-1], grid[:, 2:]], axis=-1).reshape(-1, 3)
    along_y = np.stack([grid[:-2], grid[1:-1], grid[2:]], axis=-1).reshape(-1, 3)
    cols = np.concatenate([along_x, along_y])
    values = np.broadcast_to(np.array([1.0, -2.0, 1.0]) / CURVATURE_SIGMA_M, cols.shape)
    ab = gram_band(cols, values, gy * gx, 2 * gx)
    ab[-1] += 1.0 / ZERO_SIGMA_M**2
    ab.flags.writeable = False
    return ab


def quad_highest(quads: np.ndarray, z_m: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Each quad's highest point (shape), from heights z_m (m,) measured at points in quads (m,) (flat
    indices): the mean of its two highest points' (one: that one's). The highest alone let a flat cloth
    read 1.3 mm; the second highest alone read an 11 mm crest 1.3 mm low. A quad with none takes the
    highest of the quads around it, and 0 where they have none either."""
    n = shape[0] * shape[1]
    if len(quads) == 0:
        return np.zeros(shape)
    order = np.lexsort((z_m, quads))
    q, z = quads[order], z_m[order]
    last = np.flatnonzero(np.r_[q[1:] != q[:-1], True])  # each quad's highest
    first = np.r_[0, last[:-1] + 1]
    second = np.where(last > first, last - 1, last)
    out = np.full(n, np.nan)
    out[q[last]] = 0.5 * (z[last] + z[second])
    grid = out.reshape(shape)
    padded = np.pad(grid, 1, constant_values=np.nan)
    around = np.stack(
        [
            padded[1 + dy : 1 + dy + shape[0], 1 + dx : 1 + dx + shape[1]]
            for dy in (-1, 0, 1)
            for dx in (-1, 0, 1)
        ]
    )
    with np.errstate(all="ignore"):
        filled = np.where(
            np.isnan(grid), np.nanmax(np.where(np.isnan(around), -np.inf, around), axis=0), grid
        )
    return np.asarray(np.where(np.isfinite(filled), filled, 0.0))


def backed_heights(quad_height_m: np.ndarray) -> np.ndarray:
    """Each quad's height (ny-1, nx-1) as far as its highest neighbour backs it: a ridge runs over several
    quads, while a flat cloth's noise rises in one. Past the cloth's edge nothing backs it (a flat cloth's
    edge quad, one point 1.7 mm high in it, read 1.0 mm backed by itself)."""
    ring = np.ones((3, 3), np.uint8)
    ring[1, 1] = 0
    backing = cv2.dilate(
        quad_height_m.astype(np.float32), ring, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf
    )
    return np.asarray(np.minimum(quad_height_m, backing))


def crest_heights(quad_height_m: np.ndarray, points_m: np.ndarray, nodes_m: np.ndarray) -> np.ndarray:
    """Quad heights (ny-1, nx-1) as `quad_highest` gives them, each quad past CREST_ABOVE_M, or backed past
    CREST_READ_ABOVE_M (`backed_heights`), raised to the highest of the smooth surface through the points
    (m, 3) over it, the quad's corners nodes_m (ny, nx, 3). A crest lies between points ~7 mm apart: on 20
    laid ridges the two highest points of its quad read 0.6-1.7 mm below it, the surface 0.1-1.1 mm. Only
    risen quads, and only near a point: on a flat cloth the surface runs on past an edge's last point (one
    read 1.6 mm), where the points themselves read 0.8 mm at most."""
    risen = (quad_height_m > CREST_ABOVE_M) | (backed_heights(quad_height_m) > CREST_READ_ABOVE_M)
    if not risen.any():
        return quad_height_m
    j, i = np.nonzero(risen)
    corners = [nodes_m[j, i, :2], nodes_m[j, i + 1, :2], nodes_m[j + 1, i, :2], nodes_m[j + 1, i + 1, :2]]
    near = _points_around(points_m, np.concatenate(corners), CREST_FIELD_MARGIN_M)
    if near is None:
        return quad_height_m
    field = fit_height_field(*near)
    u, v = (g.ravel() for g in np.meshgrid(*2 * [np.linspace(0.0, 1.0, CREST_SAMPLES)]))
    weights = [(1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v]  # bilinear over each quad
    xy = sum(w[None, :, None] * c[:, None, :] for w, c in zip(weights, corners, strict=True))
    samples = np.reshape(xy, (-1, 2))
    supported = cKDTree(near[0][:, :2]).query(samples, distance_upper_bound=CREST_SUPPORT_M)[0] < np.inf
    on_surface = np.where(supported, field.at(samples), -np.inf).reshape(len(j), -1)
    out = quad_height_m.copy()
    out[j, i] = np.maximum(out[j, i], on_surface.max(axis=1))
    return out


def _points_around(
    points_m: np.ndarray, xy_m: np.ndarray, margin_m: float
) -> tuple[np.ndarray, QuadMesh] | None:
    """The points (m, 3) within the smallest rectangle round xy_m (k, 2) grown by margin_m on every side,
    and that rectangle; None when fewer than CREST_MIN_POINTS lie in it."""
    centre, size, angle = cv2.minAreaRect(xy_m.astype(np.float32))
    grown = (size[0] + 2.0 * margin_m, size[1] + 2.0 * margin_m)
    area = QuadMesh.covering(cv2.boxPoints((centre, grown, angle)), 2, 2)
    local = (points_m[:, :2] - area.origin_m) @ area.axes.T
    inside = np.all((local >= 0.0) & (local <= [area.width_m, area.height_m]), axis=1)
    return (points_m[inside], area) if inside.sum() >= CREST_MIN_POINTS else None
