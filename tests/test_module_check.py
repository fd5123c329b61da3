"""The module check's measurement: a surface's shift between two pictures, the fitted velocity, and the
calibration that velocity implies."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from clothd.core.camera_model import CameraModel
from clothd.core.messages import ModuleCommands
from clothd.core.module_calibration import ModuleCalibration
from clothd.core.module_check import (
    PATCH_M_PER_PX,
    BeltPatch,
    ModuleCalibrationEntry,
    calibration_of,
    mean_velocity_m_s,
    surface_shift_m,
)
from clothd.errors import InputError
from clothd.formats import read_module_calibration, write_module_calibration

pytestmark = pytest.mark.clock_free


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


def test_the_velocity_is_the_shifts_over_their_time() -> None:
    dt = np.array([1 / 15, 1 / 15, 2 / 15])  # a frame pair dropped between the second and the third
    v = np.array([0.03, -0.01])
    np.testing.assert_allclose(mean_velocity_m_s(dt, dt[:, None] * v), v)


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


def test_the_commands_sent_undo_a_module_s_calibration() -> None:
    wrong = ModuleCalibrationEntry(module=1, reversed=True, heading_offset_deg=10.0, speed_scale=0.8)
    calibration = ModuleCalibration.of([wrong], 3)
    sent = calibration.to_send(ModuleCommands(np.array([0.04, 0.04, 0.0]), np.array([0.7, 0.7, 0.2])))
    # The module adds its error to what it is told: it then runs the wanted 0.04 m/s at 0.7 rad.
    done_heading = sent.heading_rad[1] + math.pi + math.radians(10.0)
    assert math.remainder(done_heading - 0.7, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
    assert sent.speed_m_s[1] * 0.8 == pytest.approx(0.04)
    np.testing.assert_allclose(sent.speed_m_s[[0, 2]], [0.04, 0.0])
    np.testing.assert_allclose(sent.heading_rad[[0, 2]], [0.7, 0.2])


def test_a_calibration_file_round_trips_and_refuses_nonsense(tmp_path: Path) -> None:
    path = tmp_path / "modules.yaml"
    found = [ModuleCalibrationEntry(9, True, 10.04, 0.8012), ModuleCalibrationEntry(10, False, -0.3, 1.0)]
    write_module_calibration(path, found, "clothd check-modules")
    assert read_module_calibration(path, 48) == [
        ModuleCalibrationEntry(9, True, 10.04, 0.8012),
        ModuleCalibrationEntry(10, False, -0.3, 1.0),
    ]
    path.write_text("modules:\n  - {module: 48, reversed: false, heading_offset_deg: 0, speed_scale: 1}\n")
    with pytest.raises(InputError, match=r"modules\[0\].module: 48 out of range"):
        read_module_calibration(path, 48)
    path.write_text("modules:\n  - {module: 1, reversed: false, heading_offset_deg: 0, speed: 1}\n")
    with pytest.raises(InputError, match="needs exactly"):
        read_module_calibration(path, 48)
