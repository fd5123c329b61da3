"""clothd.core.camera_model: projection against OpenCV, the analytic Jacobian, back-projection."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from clothd.core.camera_model import CameraModel
from clothd.errors import InputError
from clothd.formats import read_camera

pytestmark = pytest.mark.clock_free

DIST = np.array([-0.12, 0.03, 0.001, -0.0015, 0.002])


def _tilted_camera(dist: np.ndarray = DIST) -> CameraModel:
    """Looking down from (0.05, -0.2, 1.1), tilted 0.2 rad about x and yawed 0.3 rad, non-square pixels."""
    tilt, yaw = 0.2, 0.3
    rx = np.array([[1, 0, 0], [0, math.cos(tilt), -math.sin(tilt)], [0, math.sin(tilt), math.cos(tilt)]])
    rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    R_world_cam = rz @ rx @ np.diag([1.0, -1.0, -1.0])
    centre = np.array([0.05, -0.2, 1.1])
    T = np.eye(4)
    T[:3, :3] = R_world_cam.T
    T[:3, 3] = -R_world_cam.T @ centre
    K = np.array([[910.0, 0.0, 322.3], [0.0, 905.0, 241.7], [0.0, 0.0, 1.0]])
    return CameraModel(K, dist, T, 640, 480)


def _table_points(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.2, 0.2, n), rng.uniform(0, 0.08, n)])


def test_project_matches_opencv_with_distortion_tilt_and_pose() -> None:
    cam = _tilted_camera()
    pts = _table_points(200, seed=1)
    rvec, _ = cv2.Rodrigues(cam.T_cam_world[:3, :3])
    expected, _ = cv2.projectPoints(pts, rvec, cam.T_cam_world[:3, 3], cam.K, cam.dist)
    np.testing.assert_allclose(cam.project(pts), expected.reshape(-1, 2), rtol=0, atol=1e-9)
    # Any leading shape is kept.
    assert cam.project(pts.reshape(10, 20, 3)).shape == (10, 20, 2)


def test_centre_is_where_the_pose_puts_it() -> None:
    np.testing.assert_allclose(_tilted_camera().centre_m, [0.05, -0.2, 1.1], atol=1e-12)


def test_project_jacobian_matches_central_differences() -> None:
    cam = _tilted_camera()
    pts = _table_points(40, seed=2)
    pixels, J = cam.project_jacobian(pts)
    np.testing.assert_allclose(pixels, cam.project(pts), rtol=0, atol=1e-12)
    h = 1e-6
    numeric = np.empty_like(J)
    for c in range(3):
        step = np.zeros(3)
        step[c] = h
        numeric[:, :, c] = (cam.project(pts + step) - cam.project(pts - step)) / (2 * h)
    # ~1e-6 relative to the Jacobian's scale (about 800 px/m here).
    np.testing.assert_allclose(J, numeric, rtol=0, atol=1e-6 * np.abs(J).max())
    assert np.abs(J).max() > 500


@pytest.mark.parametrize("z_m", [0.0, 0.07, -0.03])
def test_backproject_round_trips_with_project(z_m: float) -> None:
    cam = _tilted_camera(np.array([-0.25, 0.08, 0.002, -0.001, -0.01]))  # strong barrel distortion
    rng = np.random.default_rng(3)
    pixels = np.column_stack([rng.uniform(0, 639, 300), rng.uniform(0, 479, 300)])
    world = cam.backproject_to_plane(pixels, z_m)
    np.testing.assert_allclose(world[:, 2], z_m, atol=1e-12)
    np.testing.assert_allclose(cam.project(world), pixels, rtol=0, atol=1e-8)
    # And the other way: world point -> pixel -> the same world point.
    pts = _table_points(50, seed=4)
    pts[:, 2] = z_m
    np.testing.assert_allclose(cam.backproject_to_plane(cam.project(pts), z_m), pts, rtol=0, atol=1e-10)


def test_backproject_gives_nan_where_the_ray_misses_the_plane() -> None:
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    # A plane above the camera is behind every ray of a downward-looking camera.
    assert np.isnan(cam.backproject_to_plane(np.array([[100.0, 50.0]]), z_m=2.0)).all()
    # A camera looking along the horizon: the top half of the image looks up, away from the table.
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # camera z = world +y, camera y = world -z
    T[:3, 3] = -T[:3, :3] @ np.array([0.0, 0.0, 1.0])
    side = CameraModel(cam.K, np.zeros(5), T, 640, 480)
    out = side.backproject_to_plane(np.array([[320.0, 100.0], [320.0, 400.0]]))
    assert np.isnan(out[0]).all()
    assert np.isfinite(out[1]).all() and out[1, 1] > 0


def test_ideal_camera() -> None:
    cam = CameraModel.ideal(640, 480, 900.0, 1.25)
    np.testing.assert_allclose(cam.centre_m, [0.0, 0.0, 1.25])
    centre_px = np.array([319.5, 239.5])
    # On the optical axis: the image centre, whatever the height.
    np.testing.assert_allclose(cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.4]])), [centre_px] * 2)
    # 0.1 m along world +x lands f 0.1 / d px to the right; world +y goes up the image.
    shift = 900 * 0.1 / 1.25
    np.testing.assert_allclose(cam.project(np.array([0.1, 0.0, 0.0])), centre_px + np.array([shift, 0.0]))
    np.testing.assert_allclose(cam.project(np.array([0.0, 0.1, 0.0])), centre_px - np.array([0.0, shift]))


def test_load_reads_camera_json(tmp_path: Path) -> None:
    cam = _tilted_camera()
    d = {
        "K": cam.K.tolist(),
        "dist": cam.dist.tolist(),
        "width": 640,
        "height": 480,
        "T_cam_world": cam.T_cam_world.tolist(),
    }
    (tmp_path / "camera.json").write_text(json.dumps(d))
    back = read_camera(tmp_path / "camera.json")
    np.testing.assert_array_equal(back.K, cam.K)
    np.testing.assert_array_equal(back.dist, cam.dist)
    np.testing.assert_array_equal(back.T_cam_world, cam.T_cam_world)
    assert (back.width, back.height) == (640, 480)


@pytest.mark.parametrize("key", ["K", "dist", "T_cam_world", "width", "height"])
def test_load_names_a_missing_key_and_the_file(tmp_path: Path, key: str) -> None:
    cam = CameraModel.ideal(64, 48, 90.0, 1.0)
    d = {
        "K": cam.K.tolist(),
        "dist": cam.dist.tolist(),
        "width": 64,
        "height": 48,
        "T_cam_world": cam.T_cam_world.tolist(),
    }
    del d[key]
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError, match=key) as info:
        read_camera(path)
    assert str(path) in str(info.value)


def test_load_refuses_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot read"):
        read_camera(tmp_path / "absent.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        read_camera(tmp_path / "bad.json")
    (tmp_path / "shape.json").write_text(
        json.dumps(
            {
                "K": [[1, 0], [0, 1]],
                "dist": [0] * 5,
                "width": 1,
                "height": 1,
                "T_cam_world": np.eye(4).tolist(),
            }
        )
    )
    with pytest.raises(InputError, match="K"):
        read_camera(tmp_path / "shape.json")
