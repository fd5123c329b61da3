"""Features and segmentation on real hwsim frames, graded against hwsim's truth."""

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from clothd.config import FeatureConfig
from clothd.core.features import FeatureEngine, coverage_holes
from clothd.core.segmentation import cloth_mask_from_outline, find_cloth, full_frame_region
from hwsim.camera import Camera
from hwsim.paths import frame_path
from hwsim.truth import Truth

Recorder = Callable[[str], Path]


def _truth_outline_px(rec: Path, k: int) -> np.ndarray:
    truth, cam = Truth.load(rec), Camera.load(rec / "camera.json")
    g = cam.project(truth.nodes_m[k])
    return np.concatenate([g[0, :], g[1:, -1], g[-1, -2::-1], g[-2:0:-1, 0]])


def test_find_cloth_matches_the_true_outline(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    img = cv2.imread(str(frame_path(rec, 0)))
    region = find_cloth(img)
    assert region is not None
    truth_mask = cloth_mask_from_outline(_truth_outline_px(rec, 0), img.shape[1], img.shape[0], 0)
    inter = np.logical_and(region.mask > 0, truth_mask > 0).sum()
    union = np.logical_or(region.mask > 0, truth_mask > 0).sum()
    assert inter / union >= 0.95


def test_find_cloth_says_none_without_a_cloth(short_recording: Recorder) -> None:
    img = cv2.imread(str(frame_path(short_recording("translate"), 0)))
    assert find_cloth(np.full_like(img, 90)) is None
    hidden = img.copy()
    region = find_cloth(img)
    assert region is not None
    hidden[region.mask > 0] = (60, 60, 60)  # paint the cloth out with a deck-like grey
    assert find_cloth(hidden) is None


def test_full_frame_region() -> None:
    r = full_frame_region(64, 48, margin_px=4)
    assert r.mask[4, 4] == 255 and r.mask[3, 4] == 0 and r.area_px == 56 * 40


def test_detect_respects_mask_spacing_and_existing_points(short_recording: Recorder) -> None:
    img = cv2.imread(str(frame_path(short_recording("translate"), 0)))
    cfg = FeatureConfig()
    eng = FeatureEngine(cfg)
    frame = eng.prepare(img)
    region = find_cloth(img)
    assert region is not None
    mask = cloth_mask_from_outline(region.corners_px, img.shape[1], img.shape[0], 6)
    pts = eng.detect(frame, mask, 500)
    assert 300 <= len(pts) <= 500
    ij = np.round(pts).astype(int)
    assert np.all(mask[ij[:, 1], ij[:, 0]] > 0)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(len(pts)) * 1e9
    assert d.min() >= cfg.min_distance_px - 1.0
    more = eng.detect(frame, mask, 200, avoid_px=pts)
    assert len(more) > 0
    assert np.linalg.norm(more[:, None] - pts[None], axis=-1).min() >= cfg.min_distance_px - 1.0


def _true_next(rec: Path, k: int, px: np.ndarray) -> np.ndarray:
    """Where the cloth points seen at px in frame k truly are in frame k + 1 (flat cloth: bilinear
    interpolation of the projected truth grid, inverted by a lookup on a fine map)."""
    truth, cam = Truth.load(rec), Camera.load(rec / "camera.json")
    g0, g1 = cam.project(truth.nodes_m[k]), cam.project(truth.nodes_m[k + 1])
    # For a rigidly translating flat cloth, the image motion is the same everywhere up to perspective;
    # use the motion of the nearest truth node, exact to far below a pixel at 5 mm node spacing.
    flat0, flat1 = g0.reshape(-1, 2), g1.reshape(-1, 2)
    nearest = np.argmin(np.linalg.norm(px[:, None] - flat0[None], axis=-1), axis=1)
    return np.asarray(px + (flat1[nearest] - flat0[nearest]))


def test_lk_tracks_to_the_truth_and_the_fb_check_rejects_corruption(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    k = 15  # the cloth is moving at about 30 mm/s
    img0, img1 = cv2.imread(str(frame_path(rec, k))), cv2.imread(str(frame_path(rec, k + 1)))
    eng = FeatureEngine(FeatureConfig())
    f0 = eng.prepare(img0)
    region = find_cloth(img0)
    assert region is not None
    pts = eng.detect(f0, cloth_mask_from_outline(region.corners_px, 640, 480, 10), 400)
    res = eng.track(f0, eng.prepare(img1), pts)
    assert res.ok.mean() > 0.95
    err = np.linalg.norm(res.px[res.ok] - _true_next(rec, k, pts[res.ok]), axis=1)
    assert np.median(err) < 0.3
    # Corrupt the patch around the first 20 points in the second frame: they must be rejected.
    bad = img1.copy()
    rng = np.random.default_rng(0)
    for x, y in np.round(pts[:20]).astype(int):
        bad[y - 8 : y + 9, x - 8 : x + 9] = rng.integers(0, 255, (17, 17, 3), dtype=np.uint8)
    res_bad = eng.track(f0, eng.prepare(bad), pts)
    assert res_bad.ok[:20].mean() < 0.3
    # Points whose LK window stays clear of every corrupted patch are unaffected.
    far = np.linalg.norm(pts[:, None] - pts[None, :20], axis=-1).min(axis=1) > 8 + 8 + 2
    assert far.sum() > 50 and res_bad.ok[far].mean() > 0.95


def test_coverage_holes_finds_an_empty_cell() -> None:
    mask = np.zeros((96, 96), np.uint8)
    mask[:, :] = 255
    pts = np.array([[10.0, 10.0], [60.0, 10.0], [10.0, 60.0]])
    holes = coverage_holes(mask, pts, 48)
    assert holes[70, 70] == 255 and holes[10, 10] == 0 and holes[10, 60] == 0
