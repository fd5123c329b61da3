import numpy as np
import pytest

from hwsim.scenario import Miscalibration, ModuleSelector, TableSpec
from hwsim.table import Table

pytestmark = pytest.mark.clock_free


def test_layout_is_centred_and_row_major() -> None:
    t = Table(TableSpec(modules_x=8, modules_y=6, pitch_m=0.075))
    assert t.n_modules == 48
    np.testing.assert_allclose(t.centres_m[0], [-0.2625, -0.1875])
    np.testing.assert_allclose(t.centres_m[1], [-0.1875, -0.1875])  # next column
    np.testing.assert_allclose(t.centres_m[8], [-0.2625, -0.1125])  # next row
    np.testing.assert_allclose(t.centres_m.mean(axis=0), [0, 0], atol=1e-12)


def test_selectors() -> None:
    t = Table(TableSpec())
    assert len(t.select(ModuleSelector(all=True))) == 48
    assert list(t.select(ModuleSelector(ids=[3, 5]))) == [3, 5]
    left = t.select(ModuleSelector(region_m=(-1, -1, -0.01, 1)))
    assert len(left) == 24 and np.all(t.centres_m[left, 0] < 0)


def test_acceleration_and_steering_limits() -> None:
    spec = TableSpec(accel_limit_m_s2=1.0, steer_rate_limit_rad_s=2.0, max_speed_m_s=0.5)
    t = Table(spec)
    t.command(np.array([0]), 0.3, 1.0)
    t.step(0.1)
    assert abs(t.speed_m_s[0]) == np.float64(0.1) or np.isclose(abs(t.speed_m_s[0]), 0.1)
    assert np.isclose(t.heading_rad[0], 0.2)
    for _ in range(10):
        t.step(0.1)
    assert np.isclose(t.speed_m_s[0], 0.3) and np.isclose(t.heading_rad[0], 1.0)
    np.testing.assert_allclose(t.surface_velocity_m_s()[0], 0.3 * np.array([np.cos(1.0), np.sin(1.0)]))


def test_half_turn_reverses_the_belt_instead_of_steering() -> None:
    t = Table(TableSpec())
    t.command(np.array([0]), 0.1, 0.0)
    for _ in range(20):
        t.step(0.05)
    t.command(np.array([0]), 0.1, np.pi)
    for _ in range(20):
        t.step(0.05)
    assert np.isclose(t.heading_rad[0], 0.0)  # never steered
    np.testing.assert_allclose(t.surface_velocity_m_s()[0], [-0.1, 0.0], atol=1e-12)


def test_speed_is_clipped_to_the_module_maximum() -> None:
    t = Table(TableSpec(max_speed_m_s=0.2))
    t.command(np.array([1]), 5.0, 0.0)
    assert t.cmd_speed_m_s[1] == 0.2


def test_a_miscalibrated_module_turns_and_scales_what_it_is_told() -> None:
    wrong = Miscalibration(module=2, reversed=True, heading_offset_deg=10.0, speed_scale=0.8)
    t = Table(TableSpec(miscalibrated=[wrong]))
    t.command(np.arange(t.n_modules), 0.1, 0.5)
    for _ in range(40):
        t.step(0.05)
    v = t.surface_velocity_m_s()
    actual = 0.5 + np.radians(10.0) + np.pi
    np.testing.assert_allclose(v[2], 0.08 * np.array([np.cos(actual), np.sin(actual)]), atol=1e-12)
    np.testing.assert_allclose(v[3], 0.1 * np.array([np.cos(0.5), np.sin(0.5)]), atol=1e-12)
    assert t.cmd_heading_rad[2] == 0.5 and t.cmd_speed_m_s[2] == 0.1  # the command stays as told
