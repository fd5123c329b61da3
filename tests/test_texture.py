"""Tests for hwsim.texture: determinism, shapes, seamless belts, periodic vs distinctive cloth, mip levels."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from hwsim import texture
from hwsim.texture import (
    belt_texture,
    cloth_texture,
    deck_texture,
    image_texture,
    mip_level_for,
    mip_pyramid,
)

pytestmark = pytest.mark.clock_free

TEXELS_PER_M = 4000.0  # 4 texels per mm, the density the renderer uses for a 250 x 200 mm cloth
CLOTH_M = (0.25, 0.2)


@pytest.fixture(scope="module")
def denim() -> np.ndarray:
    return cloth_texture("denim", 7, CLOTH_M, TEXELS_PER_M)


@pytest.fixture(scope="module")
def twill() -> np.ndarray:
    return cloth_texture("plain_twill", 7, CLOTH_M, TEXELS_PER_M)


def _gray_at(tex: np.ndarray, px_per_mm: float) -> np.ndarray:
    """Gray image of a texture resampled with INTER_AREA to px_per_mm, as a camera would see it."""
    scale = px_per_mm * 1000.0 / TEXELS_PER_M
    size_px = (round(tex.shape[1] * scale), round(tex.shape[0] * scale))
    return cv2.resize(cv2.cvtColor(tex, cv2.COLOR_BGR2GRAY), size_px, interpolation=cv2.INTER_AREA)


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a.astype(np.float64).ravel() - a.mean()
    b = b.astype(np.float64).ravel() - b.mean()
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12))


def _max_patch_ncc(gray: np.ndarray, seed: int, pairs: int = 50, k_px: int = 15) -> float:
    rng = np.random.default_rng(seed)
    h_px, w_px = gray.shape
    best = -1.0
    for _ in range(pairs):
        r1, r2 = rng.integers(0, h_px - k_px, 2)
        c1, c2 = rng.integers(0, w_px - k_px, 2)
        best = max(best, _ncc(gray[r1 : r1 + k_px, c1 : c1 + k_px], gray[r2 : r2 + k_px, c2 : c2 + k_px]))
    return best


def _max_shift_ncc(gray: np.ndarray, min_shift_px: int, max_shift_px: int) -> float:
    """Best NCC between the image and a shifted copy of itself over shifts of at least min_shift_px."""
    best = -1.0
    h_px, w_px = gray.shape
    for dy in range(0, max_shift_px + 1):
        for dx in range(-max_shift_px, max_shift_px + 1):
            if dx * dx + dy * dy < min_shift_px**2:
                continue
            a = gray[dy:, max(dx, 0) : w_px + min(dx, 0)]
            b = gray[: h_px - dy, max(-dx, 0) : w_px + min(-dx, 0)]
            best = max(best, _ncc(a, b))
    return best


def test_denim_is_deterministic_per_seed(denim: np.ndarray) -> None:
    again = cloth_texture("denim", 7, CLOTH_M, TEXELS_PER_M)
    other = cloth_texture("denim", 8, CLOTH_M, TEXELS_PER_M)
    assert np.array_equal(denim, again)
    assert np.mean(np.abs(denim - other)) > 0.02


def test_plain_twill_ignores_seed(twill: np.ndarray) -> None:
    assert np.array_equal(twill, cloth_texture("plain_twill", 99, CLOTH_M, TEXELS_PER_M))


@pytest.mark.parametrize(
    ("make", "shape"),
    [
        (lambda: cloth_texture("denim", 1, (0.05, 0.03), 2000.0), (60, 100, 3)),
        (lambda: cloth_texture("plain_twill", 1, (0.05, 0.03), 2000.0), (60, 100, 3)),
        (lambda: belt_texture(1, 0.3, 0.1, 1000.0), (100, 300, 3)),
        (lambda: deck_texture(1, (0.08, 0.05), 1500.0), (75, 120, 3)),
    ],
)
def test_shape_dtype_and_range(make: object, shape: tuple[int, int, int]) -> None:
    assert callable(make)
    tex = make()
    assert tex.shape == shape
    assert tex.dtype == np.float32
    assert tex.flags.c_contiguous
    assert float(tex.min()) >= 0.0 and float(tex.max()) <= 1.0


def test_unknown_kind_and_empty_size_raise() -> None:
    with pytest.raises(ValueError, match="kind"):
        cloth_texture("corduroy", 0, CLOTH_M, TEXELS_PER_M)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="empty"):
        cloth_texture("denim", 0, (0.0001, 0.1), 1000.0)


def test_denim_contrast_and_brightness(denim: np.ndarray) -> None:
    gray = _gray_at(denim, 1.0)
    assert float(gray.std()) >= 0.08
    assert 0.2 < float(gray.mean()) < 0.7
    assert float(np.mean(gray > 0.98)) < 0.01  # not saturated
    bgr_mean = denim.reshape(-1, 3).mean(axis=0)
    assert bgr_mean[0] > bgr_mean[1] > bgr_mean[2]  # blue-dominant: indigo


def test_belt_tiles_along_columns() -> None:
    belt = belt_texture(3, 0.5, 0.2, 2000.0)
    adjacent = np.mean(np.abs(np.diff(belt, axis=1)))
    seam = np.mean(np.abs(belt[:, 0] - belt[:, -1]))
    assert seam < 1.5 * adjacent
    # Not trivially flat: the belt must carry structure for an optical-flow tracker.
    assert float(cv2.cvtColor(belt, cv2.COLOR_BGR2GRAY).std()) > 0.02


def test_belt_seam_check_can_fail() -> None:
    belt = belt_texture(3, 0.5, 0.2, 2000.0)
    cut = belt[:, : belt.shape[1] - 37]  # an arbitrary crop is no longer periodic
    seam = np.mean(np.abs(cut[:, 0] - cut[:, -1]))
    assert seam > 1.5 * np.mean(np.abs(np.diff(cut, axis=1)))


def test_plain_twill_is_periodic_denim_is_not(denim: np.ndarray, twill: np.ndarray) -> None:
    # Shifts of at least 10 mm: the twill matches itself along the wales, the denim nowhere.
    twill_gray, denim_gray = _gray_at(twill, 1.0), _gray_at(denim, 1.0)
    twill_best = _max_shift_ncc(twill_gray, 10, 16)
    denim_best = _max_shift_ncc(denim_gray, 10, 16)
    assert twill_best > 0.9
    assert denim_best < 0.6


def test_denim_patches_are_distinct(denim: np.ndarray, twill: np.ndarray) -> None:
    twill_max = _max_patch_ncc(_gray_at(twill, 1.0), seed=11)
    denim_max = _max_patch_ncc(_gray_at(denim, 1.0), seed=11)
    assert twill_max > 0.9
    assert denim_max < twill_max - 0.2


def test_denim_has_many_good_features(denim: np.ndarray) -> None:
    gray = _gray_at(denim, 0.9)
    corners = cv2.goodFeaturesToTrack(gray, maxCorners=5000, qualityLevel=0.01, minDistance=5)
    assert corners is not None and len(corners) >= 400
    # qualityLevel is relative to the strongest corner, so also demand absolute strength: a blurred or
    # washed-out texture still yields "corners" but with a tiny minimum eigenvalue.
    min_eig = cv2.cornerMinEigenVal(gray, 3)
    cols, rows = np.round(corners.reshape(-1, 2)).astype(int).T
    assert int(np.sum(min_eig[rows, cols] > 1e-3)) >= 400


def test_mip_pyramid_halves_and_stops_at_8_texels() -> None:
    tex = np.random.default_rng(0).random((100, 70, 3), dtype=np.float32)
    pyramid = mip_pyramid(tex, 10)
    assert [p.shape[:2] for p in pyramid] == [(100, 70), (50, 35), (25, 18), (13, 9)]
    assert pyramid[0] is tex
    assert all(p.dtype == np.float32 for p in pyramid)
    assert len(mip_pyramid(tex, 2)) == 2
    assert min(pyramid[-1].shape[:2]) >= texture.MIN_MIP_SIDE
    with pytest.raises(ValueError):
        mip_pyramid(tex, 0)


def test_mip_pyramid_low_passes() -> None:
    checker = (np.indices((64, 64)).sum(axis=0) % 2).astype(np.float32)  # Nyquist-rate content
    level1 = mip_pyramid(np.dstack([checker] * 3), 2)[1]
    assert float(level1.std()) < 0.05  # decimating without a low-pass would keep the full 0.5 contrast


@pytest.mark.parametrize(
    ("texels_per_m", "render_px_per_m", "level"),
    [
        (4000.0, 1800.0, 1),
        (4000.0, 2000.0, 1),
        (4000.0, 2000.0001, 0),
        (4000.0, 999.0, 2),
        (4000.0, 5000.0, 0),
        (4000.0, 250.0, 4),
        (4000.0, 0.9 * 2 * 1000.0 * 10 / 9, 1),
    ],
)
def test_mip_level_for(texels_per_m: float, render_px_per_m: float, level: int) -> None:
    assert mip_level_for(texels_per_m, render_px_per_m) == level
    assert texels_per_m / 2**level >= render_px_per_m * (1 - 1e-6) or level == 0


def test_image_texture_missing_file_names_path(tmp_path: Path) -> None:
    missing = tmp_path / "no_such_cloth.png"
    with pytest.raises(ValueError, match=re.escape(str(missing))):
        image_texture(missing, CLOTH_M, 1000.0)


def test_image_texture_loads_png(tmp_path: Path) -> None:
    img = np.zeros((40, 60, 3), np.uint8)
    img[:, :30] = (255, 0, 0)  # left half blue in BGR
    img[:, 30:] = (0, 0, 255)  # right half red
    path = tmp_path / "cloth.png"
    assert cv2.imwrite(str(path), img)
    tex = image_texture(str(path), (0.03, 0.02), 1000.0)  # 30 x 20 texels: a shrink
    assert tex.shape == (20, 30, 3) and tex.dtype == np.float32
    assert np.allclose(tex[10, 5], (1.0, 0.0, 0.0)) and np.allclose(tex[10, 25], (0.0, 0.0, 1.0))
    big = image_texture(path, (0.12, 0.08), 1000.0)  # enlarging works too
    assert big.shape == (80, 120, 3) and float(big.min()) >= 0.0 and float(big.max()) <= 1.0
