import numpy as np
import pytest

from hwsim.camera import Camera
from hwsim.scenario import CameraSpec

pytestmark = pytest.mark.clock_free


def test_straight_down_camera_projects_by_k_and_pose() -> None:
    cam = Camera.from_spec(CameraSpec(f_px=900.0, position_m=(0.0, 0.0, 1.0)))
    cx, cy = 319.5, 239.5
    # The origin is under the optical centre; +x world is +u, +y world is -v (image y points down).
    np.testing.assert_allclose(cam.project(np.array([0.0, 0.0, 0.0])), [cx, cy])
    np.testing.assert_allclose(cam.project(np.array([0.1, 0.0, 0.0])), [cx + 90.0, cy])
    np.testing.assert_allclose(cam.project(np.array([0.0, 0.1, 0.0])), [cx, cy - 90.0])
    # A point 0.2 m above the table is 0.8 m from the camera: 0.1 m off-axis is 112.5 px.
    np.testing.assert_allclose(cam.project(np.array([0.1, 0.0, 0.2])), [cx + 112.5, cy])


def test_projection_matches_opencv_with_distortion_and_tilt() -> None:
    import cv2

    spec = CameraSpec(
        dist=(-0.12, 0.03, 0.001, -0.0015, 0.0), tilt_rad=0.2, yaw_rad=0.3, position_m=(0.05, -0.2, 1.1)
    )
    cam = Camera.from_spec(spec)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.3, 0.3, 50), rng.uniform(-0.2, 0.2, 50), rng.uniform(0, 0.05, 50)])
    rvec, _ = cv2.Rodrigues(cam.T_cam_world[:3, :3])
    expected, _ = cv2.projectPoints(pts, rvec, cam.T_cam_world[:3, 3], cam.K, cam.dist)
    np.testing.assert_allclose(cam.project(pts), expected.reshape(-1, 2), atol=1e-9)


def test_table_points_invert_projection() -> None:
    cam = Camera.from_spec(
        CameraSpec(dist=(-0.05, 0.01, 0.0, 0.0, 0.0), tilt_rad=0.1, width=160, height=120, f_px=225)
    )
    table = cam.table_points()
    v, u = 37, 101
    world = np.array([*table[v, u], 0.0])
    np.testing.assert_allclose(cam.project(world), [u, v], atol=1e-4)


@pytest.mark.parametrize("factor", [2, 3])
def test_supersampled_camera_keeps_pixel_centres(factor: int) -> None:
    cam = Camera.from_spec(CameraSpec())
    hi = cam.scaled(factor)
    p = np.array([0.07, -0.04, 0.0])
    u, v = cam.project(p)
    # Pixel u's centre is the mean of hi-res centres factor*u .. factor*u + factor - 1.
    np.testing.assert_allclose(hi.project(p), [factor * u + (factor - 1) / 2, factor * v + (factor - 1) / 2])


def test_camera_json_round_trip(tmp_path) -> None:  # type: ignore[no-untyped-def]
    cam = Camera.from_spec(CameraSpec(tilt_rad=0.1))
    cam.save(tmp_path / "camera.json")
    back = Camera.load(tmp_path / "camera.json")
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.T_cam_world, cam.T_cam_world)
    assert (back.width, back.height) == (640, 480)
