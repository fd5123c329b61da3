"""Hard footage in hwsim: the weave's relief under side light, and the scenarios that use it."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml

from hwsim import scenario as scenarios
from hwsim.camera import Camera
from hwsim.renderer_spares import make_renderer
from hwsim.texture import CHECK_PERIOD_M, TWILL_ANGLE_DEG, TWILL_PERIOD_M, cloth_texture, weave_slopes
from hwsim.world import World

pytestmark = pytest.mark.clock_free

WEAVES = ("twill-turn-left", "twill-turn-right", "twill-push", "twill-spin")
FAST = {
    "fast-050": 0.05,
    "fast-100": 0.10,
    "fast-150": 0.15,
    "fast-200": 0.20,
    "fast-300": 0.3,
    "fast-400": 0.4,
}


def test_weave_slopes_run_across_the_wales_with_the_relief_s_depth() -> None:
    relief = 0.0005
    # One-sided differences at the border; inside, central ones, true to the plane wave within 2 %.
    slopes = weave_slopes("plain_twill", 7, (0.05, 0.04), 4000.0, relief)[1:-1, 1:-1].reshape(-1, 2)
    a = math.radians(TWILL_ANGLE_DEG)
    across = np.array([math.sin(a), math.cos(a)])  # the phase's gradient: across the wales
    along = np.array([math.cos(a), -math.sin(a)])
    assert np.abs(slopes @ along).max() < 0.02 * np.abs(slopes @ across).max()
    # h = relief/2 cos(2 pi phase): steepest slope pi relief / period (less a little for the differences).
    steepest = np.abs(slopes @ across).max()
    assert 0.95 * math.pi * relief / TWILL_PERIOD_M < steepest <= math.pi * relief / TWILL_PERIOD_M
    # Denim's slopes come from its own wavy wales, drawn from the same seed as its colours.
    tex = cloth_texture("denim", 7, (0.05, 0.04), 4000.0)
    assert weave_slopes("denim", 7, (0.05, 0.04), 4000.0, relief).shape == (*tex.shape[:2], 2)


def test_relief_is_for_woven_textures_only() -> None:
    data = yaml.safe_load(scenarios.resolve_path("translate").read_text())
    data["texture"] = {"kind": "image", "path": "x.png", "relief_m": 0.0005}
    with pytest.raises(scenarios.ScenarioError, match="relief_m"):
        scenarios.parse(data)


@pytest.mark.parametrize("name", WEAVES)
def test_weave_scenarios_are_a_relieved_twill_under_low_side_light(name: str) -> None:
    sc = scenarios.load(name)
    assert sc.texture.kind == "plain_twill" and sc.texture.relief_m > 0
    light = np.asarray(sc.light.direction) / np.linalg.norm(sc.light.direction)
    assert math.degrees(math.asin(light[2])) <= 36.0  # low: at most 35 degrees above the table


def test_the_gingham_repeats_every_check_and_has_corners_everywhere() -> None:
    size, texels = (0.048, 0.036), 4000.0  # whole checks: 8 x 6
    tex = cloth_texture("gingham", 7, size, texels).mean(axis=2)
    period = round(CHECK_PERIOD_M * texels)
    # Strictly periodic: each check is the next, to float precision, with a strong contrast.
    assert np.abs(tex[:, period:] - tex[:, :-period]).max() < 1e-4
    assert np.abs(tex[period:, :] - tex[:-period, :]).max() < 1e-4 and np.ptp(tex) > 0.4
    # Corners everywhere: Shi-Tomasi, as a camera at 0.9 px/mm sees it, finds at least two a check.
    seen = cv2.resize(tex, None, fx=0.9 / 4.0, fy=0.9 / 4.0, interpolation=cv2.INTER_AREA)
    corners = cv2.goodFeaturesToTrack((seen * 255).astype(np.uint8), 500, 0.05, 2)
    assert corners is not None and len(corners) >= 2 * 8 * 6


@pytest.mark.parametrize("name", ["gingham-fast", "gingham-push"])
def test_gingham_scenarios_move_it_more_than_half_a_check_a_frame(name: str) -> None:
    sc = scenarios.load(name)
    assert sc.texture.kind == "gingham"
    px_per_m = sc.camera.f_px / sc.camera.position_m[2]
    speed = max(c.speed_m_s for c in sc.timeline)
    assert speed <= sc.table.max_speed_m_s
    assert speed / sc.fps > CHECK_PERIOD_M / 2 and CHECK_PERIOD_M * px_per_m < 6.0


@pytest.mark.parametrize("name", list(FAST))
def test_fast_scenarios_are_fast_blurred_noisy_and_stay_on_the_table(name: str) -> None:
    sc = scenarios.load(name)
    speed = max(c.speed_m_s for c in sc.timeline)
    assert speed == pytest.approx(FAST[name])
    assert speed <= sc.table.max_speed_m_s
    assert sc.noise.exposure_s == pytest.approx(0.012) and sc.noise.motion_blur_samples >= 4
    # Blur steps of at most half a pixel: a smooth streak, not a few ghosts.
    px_per_m = sc.camera.f_px / sc.camera.position_m[2]
    assert speed * sc.noise.exposure_s * px_per_m / (sc.noise.motion_blur_samples - 1) <= 0.5
    assert sc.noise.sigma >= 4 * 1.5
    # The belts run +x for (stop - start) s: the cloth's far edge stays on the table.
    start, stop = sc.timeline[0].t_s, sc.timeline[-1].t_s
    reach = sc.initial_pose.x_m + speed * (stop - start) + sc.cloth.size_m[0] / 2
    assert reach < sc.table.modules_x * sc.table.pitch_m / 2
    assert sc.duration_s > stop  # the stop is recorded


def _cloth_std(name: str, relief_m: float) -> float:
    """Grey-level std over the middle of the cloth in the first frame of a small render of `name`."""
    data = yaml.safe_load(scenarios.resolve_path(name).read_text())
    data.update(duration_s=0.01, settle_s=0.0, camera={"width": 200, "height": 150, "f_px": 281.25})
    data["texture"]["relief_m"] = relief_m
    data["noise"] = {"sigma": 0.0}
    data["cloth"] = {"vibration_m_s": 0.0}
    sc = scenarios.parse(data)
    world = World(sc)
    renderer = make_renderer(sc, Camera.from_spec(sc.camera), world.cloth.grid, world)
    image, _ = renderer.render([world.scene_state()])
    grey = image.mean(axis=2)
    return float(grey[60:90, 80:120].std())


def test_side_light_brings_out_the_relief() -> None:
    flat, relieved = _cloth_std("twill-spin", 0.0), _cloth_std("twill-spin", 0.0005)
    assert relieved > 1.2 * flat
