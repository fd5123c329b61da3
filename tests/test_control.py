"""The pose controller: planned twists within the limits, and module commands from the rigid field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from clothd.config import CellConfig, ControlConfig
from clothd.core.control import PoseController
from clothd.core.conveyor import ConveyorLayout

pytestmark = pytest.mark.clock_free

CELL = CellConfig()
LAYOUT = ConveyorLayout(CELL.modules_x, CELL.modules_y, CELL.pitch_m, CELL.module_size_m)
DT = 1 / 30


def _controller(**kw: float) -> PoseController:
    return PoseController(ControlConfig(**kw), CELL, LAYOUT.centres_m)


def _cloth_outline(cx: float, cy: float, w: float = 0.25, h: float = 0.20) -> np.ndarray:
    return np.array(
        [
            [cx - w / 2, cy - h / 2],
            [cx + w / 2, cy - h / 2],
            [cx + w / 2, cy + h / 2],
            [cx - w / 2, cy + h / 2],
        ]
    )


def test_twist_ramps_within_the_limits_and_converges_on_the_target() -> None:
    c = _controller()
    cfg = c.cfg
    pose, target = np.zeros(3), np.array([0.1, 0.0, math.radians(30)])
    prev = np.zeros(3)
    for _ in range(int(8 / DT)):
        twist = c.plan_twist(pose, target, DT)
        assert np.linalg.norm(twist[:2] - prev[:2]) <= cfg.max_accel_m_s2 * DT + 1e-12
        assert abs(twist[2] - prev[2]) <= cfg.max_ang_accel_rad_s2 * DT + 1e-12
        assert (
            np.linalg.norm(twist[:2]) <= cfg.max_speed_m_s + 1e-12
            and abs(twist[2]) <= cfg.max_rate_rad_s + 1e-12
        )
        pose = pose + twist * DT  # a cloth that follows its belts exactly
        prev = twist
    assert np.linalg.norm(pose[:2] - target[:2]) < 1e-3 and abs(pose[2] - target[2]) < math.radians(0.1)


def test_modules_under_the_cloth_follow_the_rigid_field_and_the_rest_stop() -> None:
    c = _controller()
    pose = np.array([0.0, 0.0, 0.0])
    twist = np.array([0.02, 0.0, 0.3])
    under = c.modules_under(_cloth_outline(0.0, 0.0))
    cmd = c.module_commands(pose, twist, under)
    assert 0 < under.sum() < LAYOUT.n_modules
    rel = LAYOUT.centres_m[under]
    expected = twist[:2] + twist[2] * np.stack([-rel[:, 1], rel[:, 0]], axis=1)
    np.testing.assert_allclose(cmd.speed_m_s[under], np.linalg.norm(expected, axis=1))
    np.testing.assert_allclose(cmd.heading_rad[under], np.arctan2(expected[:, 1], expected[:, 0]))
    assert not cmd.speed_m_s[~under].any()


def test_a_field_too_fast_for_the_modules_is_scaled_down_whole() -> None:
    c = _controller()
    twist = np.array([0.5, 0.0, 2.0])
    under = c.modules_under(_cloth_outline(0.0, 0.0))
    cmd = c.module_commands(np.zeros(3), twist, under)
    assert math.isclose(cmd.speed_m_s.max(), CELL.max_speed_m_s)
    slow = c.module_commands(np.zeros(3), twist * CELL.max_speed_m_s / cmd.speed_m_s.max(), under)
    np.testing.assert_allclose(cmd.speed_m_s, slow.speed_m_s, atol=1e-12)


def test_stop_commands_zero_speed_and_keeps_headings() -> None:
    c = _controller()
    c.module_commands(np.zeros(3), np.array([0.0, 0.05, 0.0]), c.modules_under(_cloth_outline(0.0, 0.0)))
    stop = c.stop()
    assert not stop.speed_m_s.any()
    assert np.isclose(stop.heading_rad[c.modules_under(_cloth_outline(0, 0))], math.pi / 2).all()
