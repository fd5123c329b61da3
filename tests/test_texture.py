from pathlib import Path

import cv2
import numpy as np
import pytest

from hwsim.texture import belt_texture, cloth_texture, deck_texture, image_texture, mip_level_for, mip_pyramid

SIZE_M = (0.25, 0.20)


def _gray_at_camera_scale(tex: np.ndarray, texels_per_m: float, px_per_mm: float = 0.9) -> np.ndarray:
    h, w = tex.shape[:2]
    scale = px_per_mm * 1000.0 / texels_per_m
    small = cv2.resize(tex, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    return np.asarray(cv2.cvtColor(small, cv2.COLOR_BGR2GRAY))


def test_denim_is_seeded_and_shaped() -> None:
    a = cloth_texture("denim", 7, SIZE_M, 2000.0)
    assert a.shape == (400, 500, 3) and a.dtype == np.float32
    assert a.min() >= 0.0 and a.max() <= 1.0
    np.testing.assert_array_equal(a, cloth_texture("denim", 7, SIZE_M, 2000.0))
    assert np.abs(a - cloth_texture("denim", 8, SIZE_M, 2000.0)).mean() > 0.01
    b, _, r = a.reshape(-1, 3).mean(axis=0)
    assert b > r + 0.1  # indigo


def test_denim_has_many_distinct_corners_and_plain_twill_repeats() -> None:
    tpm = 4000.0
    denim = _gray_at_camera_scale(cloth_texture("denim", 7, SIZE_M, tpm), tpm)
    plain = _gray_at_camera_scale(cloth_texture("plain_twill", 7, SIZE_M, tpm), tpm)
    corners = cv2.goodFeaturesToTrack(denim, 2000, 0.01, 5)
    assert corners is not None and len(corners) >= 400
    assert denim.std() >= 0.08
    rng = np.random.default_rng(0)

    def max_ncc_between_random_patches(img: np.ndarray) -> float:
        best = -1.0
        for _ in range(50):
            (y0, x0), (y1, x1) = rng.integers(10, np.array(img.shape) - 25, size=(2, 2))
            p, q = img[y0 : y0 + 15, x0 : x0 + 15], img[y1 : y1 + 15, x1 : x1 + 15]
            p, q = p - p.mean(), q - q.mean()
            best = max(best, float((p * q).sum() / np.sqrt((p * p).sum() * (q * q).sum() + 1e-12)))
        return best

    # Some pair of plain-twill patches matches closely (same wale phase); denim patches do not.
    assert max_ncc_between_random_patches(plain) > max_ncc_between_random_patches(denim) + 0.1


def test_belt_tiles_along_its_length() -> None:
    belt = belt_texture(3, 0.2, 0.065, 2000.0)
    assert belt.shape == (130, 400, 3)
    seam = np.abs(belt[:, -1] - belt[:, 0]).mean()
    adjacent = np.abs(np.diff(belt, axis=1)).mean()
    assert seam < 2.0 * adjacent


def test_deck_and_mips() -> None:
    deck = deck_texture(1, (0.3, 0.3), 1000.0)
    assert deck.shape == (300, 300, 3) and deck.mean() < 0.4
    pyr = mip_pyramid(np.zeros((100, 64, 3), np.float32), 10)
    assert [p.shape[:2] for p in pyr] == [(100, 64), (50, 32), (25, 16), (13, 8)]
    assert mip_level_for(4000.0, 1800.0) == 1  # 2000 texels/m still >= 1800 px/m
    assert mip_level_for(4000.0, 2500.0) == 0
    assert mip_level_for(4000.0, 400.0) == 3
    assert mip_level_for(1000.0, 5000.0) == 0


def test_image_texture(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"missing\.png"):
        image_texture(tmp_path / "missing.png", SIZE_M, 1000.0)
    img = np.zeros((40, 50, 3), np.uint8)
    img[:, 25:] = 255
    cv2.imwrite(str(tmp_path / "t.png"), img)
    tex = image_texture(tmp_path / "t.png", SIZE_M, 1000.0)
    assert tex.shape == (200, 250, 3) and tex[:, :100].max() < 0.05 and tex[:, 150:].min() > 0.95
