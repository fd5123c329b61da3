"""find_cloth on hwsim frames, graded against the projected truth outline; the ROI masks."""

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from clothd.core.segmentation import ClothColour, cloth_mask_from_outline, find_cloth, full_frame_region
from hwsim.camera import Camera
from hwsim.paths import frame_path
from hwsim.truth import Truth

pytestmark = pytest.mark.clock_free

Recorder = Callable[[str], Path]


def _outline_px(rec: Path, k: int) -> np.ndarray:
    """The truth cloth's boundary nodes at frame k, projected, in order around the cloth: (m, 2)."""
    g = Camera.load(rec / "camera.json").project(Truth.load(rec).nodes_m[k])
    return np.concatenate([g[0, :], g[1:, -1], g[-1, -2::-1], g[-2:0:-1, 0]])


def _frame(rec: Path, k: int) -> np.ndarray:
    img = cv2.imread(str(frame_path(rec, k)), cv2.IMREAD_COLOR)
    assert img is not None
    return img


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.logical_and(a > 0, b > 0).sum() / np.logical_or(a > 0, b > 0).sum())


def _truth_mask(rec: Path, k: int) -> np.ndarray:
    return cloth_mask_from_outline(_outline_px(rec, k), 640, 480, 0)


def _paint_out(
    img: np.ndarray, truth_mask: np.ndarray, seed: int, tint_bgr: tuple[float, float, float] = (0, 0, 0)
) -> np.ndarray:
    """The frame with the cloth (and a 4-px rim) replaced by a textured grey of the background's colour,
    plus `tint_bgr`."""
    rng = np.random.default_rng(seed)
    cover = cv2.dilate(truth_mask, np.ones((9, 9), np.uint8)) > 0
    grey = np.median(img[~cover], axis=0) + np.asarray(tint_bgr)
    fill = grey + rng.normal(0.0, 8.0, (*img.shape[:2], 1))
    out = img.copy()
    out[cover] = np.clip(fill, 0, 255).astype(np.uint8)[cover]
    return out


@pytest.mark.parametrize("k", [0, 12])
def test_find_cloth_matches_the_true_outline(short_recording: Recorder, k: int) -> None:
    rec = short_recording("translate")
    region = find_cloth(_frame(rec, k))
    assert region is not None
    truth = _truth_mask(rec, k)
    assert _iou(region.mask, truth) >= 0.95
    assert region.area_px == int(np.count_nonzero(region.mask))
    # The rectangle hugs the (rectangular) cloth: each corner within 2 px of a true corner.
    true_corners = _outline_px(rec, k)[[0, 50, 90, 140]]  # 51 x 41 nodes: the four corner nodes
    d = np.linalg.norm(region.corners_px[:, None] - true_corners[None], axis=-1)
    assert region.corners_px.shape == (4, 2) and region.corners_px.dtype == np.float32
    assert d.min(axis=1).max() < 2.0


def test_find_cloth_ignores_a_smooth_coloured_object(short_recording: Recorder) -> None:
    """An operator's arm is coloured but smooth: it must neither be taken for the cloth nor merge
    with it, even when it is bigger than the cloth."""
    rec = short_recording("translate")
    img = _frame(rec, 0).astype(np.float32)
    yy, xx = np.mgrid[0:480, 0:640]
    arm = (yy >= 10) & (yy < 160)  # an arm across the top of the view, bigger than the cloth
    assert not np.any(arm & (cv2.dilate(_truth_mask(rec, 0), np.ones((31, 31), np.uint8)) > 0))
    shade = (0.6 + 0.4 * (xx / 640.0))[..., None]  # lit from the right, no texture
    noise = np.random.default_rng(4).normal(0.0, 1.5, img.shape)  # the sensor's, as hwsim's
    img[arm] = (np.array([70.0, 110.0, 150.0]) * shade + noise)[arm]  # brown, BGR
    region = find_cloth(np.clip(np.round(img), 0, 255).astype(np.uint8))
    assert region is not None
    assert _iou(region.mask, _truth_mask(rec, 0)) >= 0.95


def test_find_cloth_is_none_when_the_cloth_is_painted_out(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    img, truth = _frame(rec, 0), _truth_mask(rec, 0)
    assert find_cloth(img) is not None
    assert find_cloth(_paint_out(img, truth, seed=1)) is None
    # A faint colour cast (~3 Lab units: a warmer belt, uneven light) is not cloth either.
    assert find_cloth(_paint_out(img, truth, seed=1, tint_bgr=(-2.0, 0.0, 3.0))) is None


def test_find_cloth_is_none_without_anything_coloured() -> None:
    rng = np.random.default_rng(2)
    assert find_cloth(np.full((480, 640, 3), 90, np.uint8)) is None
    noisy_grey = np.clip(90 + rng.normal(0, 10, (480, 640, 1)), 0, 255).astype(np.uint8).repeat(3, axis=2)
    assert find_cloth(noisy_grey) is None


def test_find_cloth_is_none_for_a_speck_of_cloth(short_recording: Recorder) -> None:
    """A piece of cloth under 0.5 % of the frame (here 0.3 %) is no plausible cloth."""
    rec = short_recording("translate")
    img, truth = _frame(rec, 0), _truth_mask(rec, 0)
    ys, xs = np.nonzero(cv2.erode(truth, np.ones((31, 31), np.uint8)))
    y, x = int(ys.mean()), int(xs.mean())
    speck = _paint_out(img, truth, seed=3)
    speck[40:70, 40:70] = img[y : y + 30, x : x + 30]
    assert find_cloth(speck) is None


def test_find_cloth_is_none_when_cloth_fills_the_frame(short_recording: Recorder) -> None:
    """Mostly cloth: the dominant colour is the cloth's, so colour says nothing about where it ends."""
    rec = short_recording("translate")
    img, truth = _frame(rec, 0), _truth_mask(rec, 0)
    ys, xs = np.nonzero(cv2.erode(truth, np.ones((31, 31), np.uint8)))
    patch = img[ys.min() : ys.max(), xs.min() : xs.max()]
    tiled = np.tile(patch, (480 // patch.shape[0] + 1, 640 // patch.shape[1] + 1, 1))[:480, :640]
    framed = img.copy()
    framed[60:420, 60:580] = tiled[60:420, 60:580]  # 61 % of the frame
    assert find_cloth(framed) is None


def test_full_frame_region() -> None:
    r = full_frame_region(64, 48, margin_px=4)
    assert r.mask.shape == (48, 64) and r.mask.dtype == np.uint8
    assert r.mask[4, 4] == 255 and r.mask[43, 59] == 255 and r.mask[3, 4] == 0 and r.mask[4, 60] == 0
    assert r.area_px == 56 * 40
    assert r.corners_px.shape == (4, 2) and r.corners_px.dtype == np.float32
    corners = sorted(map(tuple, np.round(r.corners_px, 3).tolist()))
    assert corners == [(4, 4), (4, 43), (59, 4), (59, 43)]
    with pytest.raises(ValueError):
        full_frame_region(10, 10, margin_px=5)


def test_cloth_mask_from_outline_fills_and_erodes() -> None:
    square = np.array([[20.0, 10.0], [79.0, 10.0], [79.0, 69.0], [20.0, 69.0]])
    full = cloth_mask_from_outline(square, 100, 80, 0)
    assert full.dtype == np.uint8 and full.shape == (80, 100)
    assert np.count_nonzero(full) == 60 * 60 and full[10, 20] == 255 and full[9, 20] == 0
    eroded = cloth_mask_from_outline(square, 100, 80, 5)
    assert np.count_nonzero(eroded) == 50 * 50 and eroded[15, 25] == 255 and eroded[14, 25] == 0
    assert np.all(full[eroded > 0] > 0)
    # The frame's border counts as outside: a polygon running off the frame is eroded from it too.
    off = cloth_mask_from_outline(np.array([[-50.0, -50.0], [50, -50], [50, 50], [-50, 50]]), 100, 80, 3)
    assert off[3, 3] == 255 and off[2, 3] == 0 and off[3, 2] == 0


def test_is_cloth_judges_each_patch_by_its_mean_colour() -> None:
    """Blue cloth on a grey table: a patch is cloth when its mean colour's chroma is far enough from the
    table's; a patch half on each, or leaving the frame, goes by its mean, or is not cloth."""
    image = np.full((60, 80, 3), 128, np.uint8)
    image[:, 40:] = (160, 90, 60)  # BGR: blue denim from x = 40 on
    rng = np.random.default_rng(3)
    image = np.clip(image + rng.integers(-6, 7, image.shape), 0, 255).astype(np.uint8)
    lab = cv2.cvtColor(image[:1, :1], cv2.COLOR_BGR2Lab).reshape(3).astype(float)
    colour = ClothColour((lab[1], lab[2]), 12.0)
    points = np.array([[10.0, 30.0], [60.0, 30.0], [40.4, 30.0], [37.6, 30.0], [78.0, 30.0], [60.0, 0.5]])
    seen = colour.is_cloth(image, points)
    # The 5 x 5 patch at x = 40 holds three cloth columns of five, the one at x = 38 only one.
    assert seen.tolist() == [False, True, True, False, False, False]
    # Against the definition, patch by patch, on noise whose patch means straddle the threshold.
    noise = rng.integers(0, 256, (60, 80, 3)).astype(np.uint8)
    points = rng.uniform(-2, 82, (300, 2))
    seen = colour.is_cloth(noise, points)
    for (x, y), s in zip(np.round(points).astype(int), seen, strict=True):
        if not (2 <= x < 78 and 2 <= y < 58):
            assert not s
            continue
        mean = noise[y - 2 : y + 3, x - 2 : x + 3].reshape(-1, 3).mean(axis=0).astype(np.uint8)
        a, b = cv2.cvtColor(mean.reshape(1, 1, 3), cv2.COLOR_BGR2Lab).reshape(3)[1:].astype(float)
        assert s == (np.hypot(a - colour.background_ab[0], b - colour.background_ab[1]) > 12.0)
    assert 0.1 < seen.mean() < 0.9
