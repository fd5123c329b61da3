"""Shi–Tomasi detection and LK tracking on hwsim frames, graded against hwsim's truth."""

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from clothd.config import FeatureConfig
from clothd.core.features import FeatureEngine, coverage_holes, self_similarity
from clothd.core.segmentation import cloth_mask_from_outline
from hwsim.camera import Camera
from hwsim.paths import frame_path
from hwsim.truth import Truth, surface_points, surface_weights

pytestmark = pytest.mark.clock_free

Recorder = Callable[[str], Path]

K = 12  # translate: at 0.4 s every belt has run at 30 mm/s for a while, about 0.9 px per frame


def _frame(rec: Path, k: int) -> np.ndarray:
    img = cv2.imread(str(frame_path(rec, k)), cv2.IMREAD_COLOR)
    assert img is not None
    return img


def _cloth_mask(rec: Path, k: int, erode_px: float) -> np.ndarray:
    g = Camera.load(rec / "camera.json").project(Truth.load(rec).nodes_m[k])
    outline = np.concatenate([g[0, :], g[1:, -1], g[-1, -2::-1], g[-2:0:-1, 0]])
    return cloth_mask_from_outline(outline, 640, 480, erode_px)


def _true_next_px(rec: Path, k: int, px: np.ndarray) -> np.ndarray:
    """Where the material points seen at px (n, 2) in frame k truly are in frame k + 1, pixels (n, 2).

    Each pixel's material coordinates (s, t) come from inverting s, t -> truth surface -> camera: a
    fixed-point iteration px = f(s, t) with the least-squares affine fit of f as the step, exact on each
    (flat, nearly affinely imaged) truth triangle after a few steps; the residual is checked."""
    truth, cam = Truth.load(rec), Camera.load(rec / "camera.json")
    shape = truth.st_m.shape[:2]
    st, g = truth.st_m.reshape(-1, 2), cam.project(truth.nodes_m[k]).reshape(-1, 2)
    fit = np.linalg.lstsq(np.column_stack([st, np.ones(len(st))]), g, rcond=None)[0]  # px = [s t 1] fit
    step = np.linalg.inv(fit[:2])
    s_t = (px - fit[2]) @ step
    for _ in range(20):
        idx, w = surface_weights(np.clip(s_t, 0.0, truth.size_m), truth.spacing_m, shape)
        s_t = s_t + (px - cam.project(surface_points(truth.nodes_m[k], idx, w))) @ step
    idx, w = surface_weights(np.clip(s_t, 0.0, truth.size_m), truth.spacing_m, shape)
    assert np.abs(cam.project(surface_points(truth.nodes_m[k], idx, w)) - px).max() < 1e-3
    return np.asarray(cam.project(surface_points(truth.nodes_m[k + 1], idx, w)))


@pytest.fixture(scope="module")
def engine() -> FeatureEngine:
    return FeatureEngine(FeatureConfig())


def _min_distance(a: np.ndarray, b: np.ndarray | None = None) -> float:
    d = np.linalg.norm(a[:, None] - (a if b is None else b)[None], axis=-1)
    if b is None:
        d += np.diag(np.full(len(a), np.inf))
    return float(d.min())


def test_detect_respects_mask_spacing_and_existing_points(
    short_recording: Recorder, engine: FeatureEngine
) -> None:
    rec = short_recording("translate")
    pyr = engine.prepare(_frame(rec, K))
    mask = _cloth_mask(rec, K, 6)
    d_min = engine.cfg.min_distance_px
    pts = engine.detect(pyr, mask, 300)
    assert pts.shape == (300, 2) and pts.dtype == np.float32
    ij = np.round(pts).astype(int)
    assert np.all(mask[ij[:, 1], ij[:, 0]] > 0)
    assert _min_distance(pts) >= d_min
    assert np.any(pts != np.round(pts))  # refined to sub-pixel
    more = engine.detect(pyr, mask, 1000, avoid_px=pts)
    assert 100 < len(more) <= 1000
    ij = np.round(more).astype(int)
    assert np.all(mask[ij[:, 1], ij[:, 0]] > 0)
    assert _min_distance(more) >= d_min and _min_distance(more, pts) >= d_min
    # A point to avoid counts even where the mask already excludes it, and off the image.
    edge = np.array([[-3.0, -3.0], [1e4, 1e4], [np.nan, 1.0]], np.float32)
    assert _min_distance(engine.detect(pyr, mask, 50, avoid_px=np.concatenate([pts, edge])), pts) >= d_min


def test_detect_stays_inside_a_small_mask(short_recording: Recorder, engine: FeatureEngine) -> None:
    rec = short_recording("translate")
    pyr = engine.prepare(_frame(rec, K))
    mask = np.zeros((480, 640), np.uint8)
    mask[250:280, 300:340] = 255
    pts = engine.detect(pyr, mask, 1000)
    assert 10 < len(pts) < 60
    assert np.all((pts[:, 0] > 299.5) & (pts[:, 0] < 339.5) & (pts[:, 1] > 249.5) & (pts[:, 1] < 279.5))
    assert engine.detect(pyr, np.zeros_like(mask), 100).shape == (0, 2)
    assert engine.detect(pyr, mask, 0).shape == (0, 2)
    assert engine.detect(engine.prepare(np.full((480, 640), 90, np.uint8)), mask, 100).shape == (0, 2)


def test_lk_lands_on_the_truth(short_recording: Recorder, engine: FeatureEngine) -> None:
    rec = short_recording("translate")
    prev, cur = engine.prepare(_frame(rec, K)), engine.prepare(_frame(rec, K + 1))
    pts = engine.detect(prev, _cloth_mask(rec, K, 10), 1000)
    truth = _true_next_px(rec, K, pts.astype(np.float64))
    assert np.median(np.linalg.norm(truth - pts, axis=1)) > 0.5  # the cloth really moves
    res = engine.track(prev, cur, pts)
    assert res.px.shape == (len(pts), 2) and res.ok.shape == (len(pts),) and res.ok.mean() > 0.95
    err = np.linalg.norm(res.px[res.ok] - truth[res.ok], axis=1)
    assert np.median(err) < 0.3 and np.percentile(err, 95) < 0.5
    assert np.all(res.fb_error_px[res.ok] <= engine.cfg.fb_max_error_px)
    # Started from a prediction 1.5 px off (the filter's guess), LK lands on the same answer.
    guess = truth + np.array([1.0, -1.1])
    res_g = engine.track(prev, cur, pts, guess_px=guess)
    err_g = np.linalg.norm(res_g.px[res_g.ok] - truth[res_g.ok], axis=1)
    assert res_g.ok.mean() > 0.95 and np.median(err_g) < 0.3


def test_fb_check_rejects_corrupted_patches(short_recording: Recorder, engine: FeatureEngine) -> None:
    rec = short_recording("translate")
    img0, img1 = _frame(rec, K), _frame(rec, K + 1)
    prev = engine.prepare(img0)
    pts = engine.detect(prev, _cloth_mask(rec, K, 10), 1000)
    # 20 points at least 40 px apart get a patch of noise over them in the second frame.
    rng = np.random.default_rng(5)
    bad: list[int] = []
    for i in rng.permutation(len(pts)):
        if len(bad) < 20 and all(np.linalg.norm(pts[i] - pts[j]) > 40 for j in bad):
            bad.append(i)
    corrupted = img1.copy()
    for x, y in np.round(pts[bad]).astype(int):
        corrupted[y - 10 : y + 11, x - 10 : x + 11] = rng.integers(0, 256, (21, 21, 3), dtype=np.uint8)
    res = engine.track(prev, engine.prepare(corrupted), pts)
    assert not res.ok[bad].any()
    # The forward-backward check alone catches most of them; the rest came home consistently to a
    # wrong match, and the appearance check (NCC) catches those.
    fb_failed = res.fb_error_px[bad] > engine.cfg.fb_max_error_px
    assert np.mean(fb_failed) > 0.5
    assert np.all(res.ncc[bad][~fb_failed] < 0.6)
    # Points whose LK window (15 px) never overlaps a corrupted patch are tracked as before.
    far = np.linalg.norm(pts[:, None] - pts[bad][None], axis=-1).min(axis=1) > 10 + 8 + 2
    assert far.sum() > 200 and res.ok[far].mean() > 0.95


def test_track_a_known_shift_and_points_leaving_the_image(engine: FeatureEngine) -> None:
    rng = np.random.default_rng(6)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640)).astype(np.float32), (0, 0), 2.0)
    img0 = (255 * (tex - tex.min()) / (tex.max() - tex.min())).astype(np.uint8)
    shift = np.array([2.3, -1.6])
    move = np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]])
    img1 = cv2.warpAffine(img0, move, (640, 480), flags=cv2.INTER_CUBIC)
    pts = np.array([[320.0, 240.0], [100.5, 400.25], [500.0, 60.0], [638.5, 200.0]], np.float32)
    res = engine.track(engine.prepare(img0), engine.prepare(img1), pts)
    assert res.ok[:3].all() and np.abs(res.px[:3] - (pts[:3] + shift)).max() < 0.1
    assert not res.ok[3]  # landed at x ~ 640.8: off the image
    # Without pyramid levels LK cannot reach a 15 px motion on its own; from a guess 0.5 px off it can.
    flat = FeatureEngine(FeatureConfig(lk_levels=0))
    far = np.array([15.0, -4.0])
    img2 = cv2.warpAffine(img0, np.array([[1.0, 0.0, far[0]], [0.0, 1.0, far[1]]]), (640, 480))
    p0, p2 = flat.prepare(img0), flat.prepare(img2)
    blind = flat.track(p0, p2, pts[:3])
    assert not np.any(blind.ok & (np.abs(blind.px - (pts[:3] + far)).max(axis=1) < 0.5))
    guided = flat.track(p0, p2, pts[:3], guess_px=pts[:3] + far + 0.5)
    assert guided.ok.all() and np.abs(guided.px - (pts[:3] + far)).max() < 0.1
    empty = engine.track(engine.prepare(img0), engine.prepare(img1), np.zeros((0, 2), np.float32))
    assert empty.px.shape == (0, 2) and empty.ok.shape == (0,) and empty.fb_error_px.shape == (0,)


def test_coverage_holes_finds_the_empty_cells() -> None:
    mask = np.zeros((100, 150), np.uint8)
    mask[:, :125] = 255  # cells of 48 px: columns 96-143 are 29/48 inside, 144-149 all outside
    pts = np.array([[10.0, 10.0], [60.0, 10.0], [10.0, 60.0], [np.nan, np.nan], [-5.0, 500.0]])
    holes = coverage_holes(mask, pts, 48)
    assert holes.shape == mask.shape and holes.dtype == np.uint8
    assert holes[48:96, 48:96].min() == 255  # the empty cell inside the cloth
    assert holes[10, 10] == 0 and holes[10, 60] == 0 and holes[60, 10] == 0  # cells holding a point
    assert holes[10, 100] == 255 and holes[10, 124] == 255  # mostly inside and empty
    assert np.all(holes[:, 125:] == 0)  # never outside the mask
    assert holes[98, 60] == 255  # the 4-px bottom cells are judged by their in-image pixels
    half = np.zeros((100, 150), np.uint8)
    half[:, :120] = 255  # columns 96-143: exactly half inside, not mostly
    assert not coverage_holes(half, pts, 48)[:, 96:].any()
    grid = np.array([[x, y] for x in range(0, 150, 40) for y in range(0, 100, 40)], np.float32)
    assert not coverage_holes(mask, grid, 48)[:96].any()  # every cell of the top two rows holds one


def test_self_similarity_tells_a_repeating_check_from_a_texture_that_does_not_repeat() -> None:
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:120, 0:160]
    check = (((xx // 3) + (yy // 3)) % 2 * 200 + 30).astype(np.uint8)  # a 6 px check
    check = cv2.GaussianBlur(check, (0, 0), 0.7)
    noise = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160)).astype(np.float32), (0, 0), 1.5).astype(np.uint8)
    px = np.array([[60.0, 50.0], [80.0, 70.0], [100.0, 40.0], [5.0, 5.0]])
    on_check, on_noise = self_similarity(check, px, 11), self_similarity(noise, px, 11)
    assert np.all(on_check[:3] > 0.95) and np.all(on_noise[:3] < 0.7)
    assert np.isnan(on_check[3])  # the search would leave the image
