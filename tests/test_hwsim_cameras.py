"""hwsim with several cameras: the scenario's `cameras`, `hwsim record`'s cameras/NAME/, the height
precision of a pair, every camera seeing the same patterns where they lie, and `hwsim serve`'s stream per
camera."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys
import urllib.request
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from small_scenarios import SMALL_OBLIQUE, SMALL_TOP, two_cameras

from hwsim import scenario as scenarios
from hwsim.camera import Camera
from hwsim.recording import record, render_frame
from hwsim.renderer_spares import make_renderer
from hwsim.stereo import height_precision_mm, oblique_spec, sees_table
from hwsim.streams import frame_intervals
from hwsim.taichi_runtime import ensure_taichi
from hwsim.world import World

pytestmark = pytest.mark.clock_free

TABLE_HALF_M = (0.3, 0.225)  # the default 8 x 6 modules at 75 mm


def test_two_cameras_validate_and_camera_stays_one() -> None:
    sc = scenarios.parse(two_cameras())
    assert [c.name for c in sc.camera_specs] == ["cam0", "side"]
    assert sc.camera == sc.cameras[0]  # `camera` is the first camera, for every one-camera reader
    assert scenarios.parse(sc.model_dump(mode="json")) == sc  # scenario.yaml reloads
    one = scenarios.parse({"name": "x", "duration_s": 1, "camera": {"f_px": 800}})
    assert [(c.name, c.f_px) for c in one.camera_specs] == [("cam0", 800.0)]
    assert len(scenarios.load("cell").camera_specs) == 2
    assert scenarios.load("cell").camera == scenarios.CameraSpec()  # the top camera exactly as before


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"cameras": [SMALL_TOP, {**SMALL_OBLIQUE, "capture_skew_s": 0.5}]}, "cameras.1.capture_skew_s"),
        ({"cameras": [{**SMALL_TOP, "capture_skew_s": 0.01}, SMALL_OBLIQUE]}, "cameras.0.capture_skew_s"),
        ({"cameras": [SMALL_TOP, {**SMALL_OBLIQUE, "name": "cam0"}]}, "cameras.1.name"),
        ({"cameras": [SMALL_TOP, {**SMALL_OBLIQUE, "name": "Side/1"}]}, "cameras.1.name"),
        ({"cameras": [SMALL_TOP] * 5}, "cameras"),
        ({"camera": {"f_px": 800}}, "camera: give camera"),
    ],
)
def test_bad_cameras_are_refused_naming_the_key(change: dict[str, Any], key: str) -> None:
    with pytest.raises(scenarios.ScenarioError, match=key):
        scenarios.parse(two_cameras(**change))


def _cloth_blue(image: np.ndarray, px: np.ndarray) -> bool:
    """The denim (indigo: blue well above red) around pixel px."""
    u, v = np.round(px).astype(int)
    patch = image[v - 2 : v + 3, u - 2 : u + 3].astype(float)
    return bool(np.median(patch[..., 0] - patch[..., 2]) > 25)


def test_record_writes_every_camera_and_each_sees_the_cloth_where_it_projects(tmp_path: Path) -> None:
    record(scenarios.parse(two_cameras()), tmp_path)
    truth = np.load(tmp_path / "truth.npz")
    nodes = truth["nodes_m"][0]
    centre_m = nodes[nodes.shape[0] // 2, nodes.shape[1] // 2]
    off_cloth_m = centre_m + np.array([0.0, 0.16, 0.0])  # past the cloth's 0.1 m half height, on belts
    for cam_dir in (tmp_path, tmp_path / "cameras" / "side"):
        camera = Camera.load(cam_dir / "camera.json")
        frames = sorted((cam_dir / "frames").glob("*.png"))
        assert len(frames) == len(truth["t_s"]) == 4
        image = cv2.imread(str(frames[0]))
        assert image.shape == (120, 160, 3)
        assert _cloth_blue(image, camera.project(centre_m)), cam_dir
        assert not _cloth_blue(image, camera.project(off_cloth_m)), cam_dir
    assert not (tmp_path / "cameras" / "cam0").exists()  # the first camera keeps today's layout
    top, side = (Camera.load(p / "camera.json") for p in (tmp_path, tmp_path / "cameras" / "side"))
    assert side.centre_m[1] == pytest.approx(-0.423)
    assert not np.allclose(top.T_cam_world, side.T_cam_world)


def test_height_precision_grows_as_the_baseline_shrinks() -> None:
    base = scenarios.CameraSpec()
    top = Camera.from_spec(base)
    angles = [5, 10, 15, 20, 25]
    sigma_mm = [
        height_precision_mm(top, Camera.from_spec(oblique_spec(base, math.radians(a), 1.0, 900.0, "b")), 0.3)
        for a in angles
    ]
    assert all(a > b for a, b in itertools.pairwise(sigma_mm)), sigma_mm
    # The live cell's pair: about a third of a millimetre from 0.1 px, linear in the pixel noise.
    first, second = (Camera.from_spec(c) for c in scenarios.load("cell").camera_specs)
    assert 0.25 < height_precision_mm(first, second, 0.1) < 0.5
    assert height_precision_mm(first, second, 0.3) == pytest.approx(
        3 * height_precision_mm(first, second, 0.1)
    )
    assert sees_table(first, TABLE_HALF_M) and sees_table(second, TABLE_HALF_M)


def _one_jpeg(url: str) -> np.ndarray:
    """The first JPEG of a multipart MJPEG stream, decoded."""
    with urllib.request.urlopen(url, timeout=30) as stream:
        length = 0
        while True:
            line = stream.readline().strip()
            if line.lower().startswith(b"content-length:"):
                length = int(line.split(b":")[1])
            elif not line and length:
                break
        image = cv2.imdecode(np.frombuffer(stream.read(length), np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return np.asarray(image)


def test_serve_streams_every_camera(tmp_path: Path) -> None:
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(two_cameras(duration_s=600.0)))
    state = tmp_path / "state"
    cmd = [sys.executable, "-m", "hwsim.cli", "serve", "--scenario", str(path), "--state-dir", str(state)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        assert proc.stdout is not None
        line = b""
        while not line.startswith(b"{"):  # Taichi announces itself on stdout first
            line = proc.stdout.readline()
            assert line, "hwsim serve exited before it was ready"
        ready = json.loads(line)
        cams = ready["cameras"]
        assert [c["name"] for c in cams] == ["cam0", "side"]
        assert cams[0]["camera_json"] == ready["camera_json"] == str(state / "camera.json")
        assert cams[1]["camera_json"] == str(state / "camera-side.json")
        assert [c["capture_skew_s"] for c in cams] == [0.0, 0.0]
        assert Camera.load(Path(cams[1]["camera_json"])).centre_m[1] == pytest.approx(-0.423)
        for url in (ready["video_url"], cams[0]["video_url"], cams[1]["video_url"]):
            assert _one_jpeg(url).shape == (120, 160, 3)
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_a_skewed_camera_shows_the_world_later(tmp_path: Path) -> None:
    """Two identical top cameras, the second capturing 50 ms later, over belts carrying the cloth +x at
    0.2 m/s: its cloth lies 10 mm (2.25 px at f 225 from 1 m) further along."""
    drive = {"t_s": 0.0, "modules": {"all": True}, "speed_m_s": 0.2, "heading_rad": 0.0}
    late = {**SMALL_TOP, "name": "late", "capture_skew_s": 0.05}
    scenario = two_cameras(duration_s=0.4, cameras=[SMALL_TOP, late], timeline=[drive])
    record(scenarios.parse(scenario), tmp_path)

    def cloth_centroid_u(cam_dir: Path) -> float:
        image = cv2.imread(str(sorted((cam_dir / "frames").glob("*.png"))[-1])).astype(float)
        us = np.nonzero(image[..., 0] - image[..., 2] > 25)[1]
        return float(us.mean())

    shift_px = cloth_centroid_u(tmp_path / "cameras" / "late") - cloth_centroid_u(tmp_path)
    assert shift_px == pytest.approx(2.25, abs=0.5)


def test_other_cameras_frames_coincide_with_the_first_cameras() -> None:
    assert frame_intervals(30.0, 2, 15.0, None) == [2, 2]
    assert frame_intervals(30.0, 2, 15.0, 7.5) == [2, 4]
    assert frame_intervals(30.0, 3, 15.0, 10.0) == [2, 4, 4]  # every 3 steps would miss the first camera
    assert frame_intervals(30.0, 1, 15.0, 5.0) == [2]


def _top_down_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One world rendered by two cameras straight down from 1 m, f 450 and f 900 (different mip levels of
    every texture): their images (grey), and the homography that takes the first's pixels to the second's."""
    near = {"width": 640, "height": 480, "f_px": 900.0}
    far = {"width": 320, "height": 240, "f_px": 450.0}
    sc = scenarios.parse({**two_cameras(), "cameras": [far, {**near, "name": "near"}]})
    world = World(sc, log_commands=False)
    world.step()
    images = []
    for spec in sc.camera_specs:
        renderer = make_renderer(sc, Camera.from_spec(spec), world.cloth.grid, world)
        image, _ = render_frame(world, renderer, 0.0)
        images.append(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
    K = [Camera.from_spec(spec).K for spec in sc.camera_specs]
    return images[0], images[1], K[1] @ np.linalg.inv(K[0])


def test_every_camera_sees_the_same_cloth_and_belts_where_they_lie() -> None:
    """Two cameras, each texture sampled at its own mip level: the pattern lies in the same place on the
    cloth and on the belts in both (no disparity where there is no height)."""
    ensure_taichi()
    far, near, H = _top_down_pair()
    far_in_near = cv2.warpPerspective(far, H, (near.shape[1], near.shape[0]), flags=cv2.INTER_CUBIC)
    window = cv2.createHanningWindow((128, 128), cv2.CV_32F)
    for name, (x, y) in {"cloth": (320, 240), "belt": (560, 80)}.items():
        a, b = (img[y - 64 : y + 64, x - 64 : x + 64].astype(np.float32) for img in (far_in_near, near))
        (dx, dy), response = cv2.phaseCorrelate(a, b, window)
        assert math.hypot(dx, dy) < 0.1 and response > 0.3, name
