"""The module check's measurement: a surface's shift between two pictures, the fitted velocity, and the
calibration that velocity implies."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from clothd.core.camera_model import CameraModel
from clothd.core.module_check import (
    PATCH_M_PER_PX,
    BeltPatch,
    calibration_of,
    fitted_velocity_m_s,
    surface_shift_m,
)


def _ribbed_texture(rng: np.random.Generator, n: int) -> np.ndarray:
    """A belt-like surface: ribs across x with speckle, smooth enough for sub-pixel shifts."""
    x = np.arange(n)
    ribs = 40 * np.sin(2 * np.pi * x / 17.0)[None, :]
    speckle = cv2.GaussianBlur(rng.normal(0, 40, (n, n)), (0, 0), 1.5)
    return np.asarray(120 + ribs + speckle)


@pytest.mark.parametrize("shift_px", [(2.3, -1.7), (-4.6, 0.4), (0.0, 3.1)])
def test_a_surface_shift_is_found_within_a_percent(shift_px: tuple[float, float]) -> None:
    big = _ribbed_texture(np.random.default_rng(1), 120)
    moved = cv2.warpAffine(big, np.array([[1, 0, shift_px[0]], [0, 1, shift_px[1]]]), (120, 120))
    before = np.clip(big[20:100, 20:100], 0, 255).astype(np.uint8)
    after = np.clip(moved[20:100, 20:100], 0, 255).astype(np.uint8)
    found = surface_shift_m(before, after, cv2.createHanningWindow((80, 80), cv2.CV_64F))
    assert found is not None
    np.testing.assert_allclose(found / PATCH_M_PER_PX, shift_px, atol=0.01 * math.hypot(*shift_px) + 0.02)


def test_the_velocity_is_the_slope_of_the_accumulated_shifts() -> None:
    t = np.arange(20) / 15.0
    v = np.array([0.03, -0.01])
    shifts = np.tile(v / 15.0, (19, 1)) + np.random.default_rng(2).normal(0, 1e-5, (19, 2))
    np.testing.assert_allclose(fitted_velocity_m_s(t, shifts), v, atol=2e-4)


def test_the_calibration_turns_the_command_into_what_was_measured() -> None:
    heading = 0.7
    actual = heading + math.pi + math.radians(10.0)
    velocity = 0.8 * 0.04 * np.array([math.cos(actual), math.sin(actual)])
    found = calibration_of(9, 0.04, heading, velocity)
    assert found.reversed and found.module == 9
    assert found.heading_offset_deg == pytest.approx(10.0) and found.speed_scale == pytest.approx(0.8)
    straight = calibration_of(3, 0.04, -3.0, 0.04 * np.array([math.cos(-3.05), math.sin(-3.05)]))
    assert not straight.reversed and straight.heading_offset_deg == pytest.approx(math.degrees(-0.05))


def test_the_patch_lies_on_the_table_where_the_camera_sees_it() -> None:
    camera = CameraModel.ideal(640, 480, 900.0, 1.0)
    patch = BeltPatch.of(camera, np.array([0.1, -0.05]), 0.04)
    assert patch.map_x.shape == (80, 80) and patch.inside(640, 480)
    centre_px = camera.project(np.array([[0.1, -0.05, 0.0]]))[0]
    np.testing.assert_allclose([patch.map_x.mean(), patch.map_y.mean()], centre_px, atol=0.1)
    assert not BeltPatch.of(camera, np.array([0.5, 0.0]), 0.04).inside(640, 480)
