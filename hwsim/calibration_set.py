"""`hwsim charuco`: the pictures an integrator takes to calibrate a cell, rendered through a scenario's
camera, with the truth beside them.

DIR/flat.png          the board flat on the table, ChArUco corner id 0 at world (X, Y, 0), board x along
                      world +x and board y along world -y (its printed side up, facing the camera)
DIR/view_NN.png       the board held over the table in tilted poses, spread over the image
DIR/camera.json       the true camera (as `hwsim record` writes it)
DIR/board.json        the board's geometry, the flat view's origin, every view's true T_cam_board (the
                      first camera's) and T_world_board, and the cameras' names
DIR/cameras/NAME/     each further camera of the scenario: the same pictures (the board in the same
                      pose, at the same instant, under the same names) and its true camera.json, as
                      `hwsim record` lays out its cameras/NAME/

Held poses are drawn from a seeded generator: the board's centre on the ray of a point near one of
nine places in the picture (12, 50 or 88 % across and down, taken in turn, jittered by 6 %), 60-90 % of
the camera's height away, tilted 20-45° about an in-plane axis whose direction turns from view to view,
and turned about its normal by up to 30°. So boards run off every edge and corner, where the lens
bends most. A pose is kept when the whole sheet is above the table and at least 35 % of the corners
are in the picture. With several cameras the views aim through each camera in turn (view k through
camera k mod n, at place k div n), and a pose is kept only when every camera sees it so, its printed
side turned at most 60° from each further camera's line of sight (the detector's reach). One camera's
set is the same, picture for picture, as before further cameras existed.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from hwsim.camera import Camera
from hwsim.charuco import BoardPattern, BoardSpec, corner_rays, render_board, to_grey8
from hwsim.paths import camera_dir
from hwsim.scenario import Scenario

FLAT_NAME = "flat.png"
SUPERSAMPLE = 4
_MIN_VISIBLE = 0.35
_AIM = (0.12, 0.5, 0.88)  # where in the picture a view's board centre goes, per axis (then jittered)
_EDGE_PX = 8.0
_MAX_TRIES = 1000
_MAX_FACING_DEG = 60.0


def middle_on_table(camera: Camera) -> np.ndarray:
    """World x, y (2,) of the table point seen at the middle of the picture."""
    middle = np.array([[[(camera.width - 1) / 2, (camera.height - 1) / 2]]])
    xy = cv2.undistortPoints(middle, camera.K, camera.dist).reshape(2)
    ray = camera.T_cam_world[:3, :3].T @ np.array([*xy, 1.0])
    c = camera.centre_m
    return np.asarray(c[:2] - c[2] / ray[2] * ray[:2])


def centred_origin(camera: Camera, spec: BoardSpec) -> tuple[float, float]:
    """The flat view's origin (world x, y of corner id 0, to the centimetre) that centres the board on
    the table point seen at the middle of the picture."""
    seen = middle_on_table(camera)
    w, h = spec.size_m
    return round(seen[0] + spec.square_m - w / 2, 2), round(seen[1] + h / 2 - spec.square_m, 2)


def flat_pose(spec: BoardSpec, origin_m: tuple[float, float]) -> np.ndarray:
    """T_world_board, 4 x 4, of the board flat on the table with corner id 0 at (X, Y, 0): board x along
    world +x, board y along world -y, so board z points down into the table."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [origin_m[0] - spec.square_m, origin_m[1] + spec.square_m, 0.0]
    return T


def _axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(axis, dtype=np.float64) * angle_rad)
    return np.asarray(R)


def _sheet_corners_m(spec: BoardSpec) -> np.ndarray:
    w, h = spec.size_m
    return np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], dtype=np.float64)


def _acceptable(camera: Camera, spec: BoardSpec, T_cam_board: np.ndarray) -> bool:
    T_world_board = np.linalg.inv(camera.T_cam_world) @ T_cam_board
    sheet_world = _sheet_corners_m(spec) @ T_world_board[:3, :3].T + T_world_board[:3, 3]
    if np.any(sheet_world[:, 2] < 0.02):
        return False
    corners = spec.corners_m()
    in_front = (corners @ T_cam_board[:3, :3].T + T_cam_board[:3, 3])[:, 2] > 0.05
    px = camera.project(corners @ T_world_board[:3, :3].T + T_world_board[:3, 3])
    inside = (
        in_front
        & (px[:, 0] >= _EDGE_PX)
        & (px[:, 0] <= camera.width - 1 - _EDGE_PX)
        & (px[:, 1] >= _EDGE_PX)
        & (px[:, 1] <= camera.height - 1 - _EDGE_PX)
    )
    return bool(inside.mean() >= _MIN_VISIBLE)


def _faces(camera: Camera, spec: BoardSpec, T_cam_board: np.ndarray) -> bool:
    """The board's printed side is turned at most _MAX_FACING_DEG from the camera's line of sight."""
    centre = T_cam_board[:3, :3] @ np.array([*np.asarray(spec.size_m) / 2, 0.0]) + T_cam_board[:3, 3]
    cos = float(T_cam_board[:3, 2] @ centre / np.linalg.norm(centre))  # board z points away from its print
    return cos >= math.cos(math.radians(_MAX_FACING_DEG))


def held_poses(
    cameras: list[Camera], spec: BoardSpec, count: int, rng: np.random.Generator
) -> list[np.ndarray]:
    """T_cam_board, in the first camera's frame, of `count` tilted views of the board held over the
    table, every camera seeing each (see the module's notes)."""
    centre_board = np.array([*np.asarray(spec.size_m) / 2, 0.0])
    poses: list[np.ndarray] = []
    for _ in range(_MAX_TRIES):
        if len(poses) == count:
            return poses
        k = len(poses)
        aim, place = cameras[k % len(cameras)], k // len(cameras)
        cell_x, cell_y = place % 3, (place // 3) % 3
        target = np.array(
            [
                (_AIM[cell_x] + rng.uniform(-0.06, 0.06)) * aim.width,
                (_AIM[cell_y] + rng.uniform(-0.06, 0.06)) * aim.height,
            ]
        )
        xy = cv2.undistortPoints(target.reshape(1, 1, 2), aim.K, aim.dist).reshape(2)
        ray = np.array([*xy, 1.0]) / np.linalg.norm([*xy, 1.0])
        distance_m = rng.uniform(0.6, 0.9) * float(aim.centre_m[2])
        axis_rad = 2 * math.pi * k / count + rng.uniform(-0.3, 0.3)
        tilt = _axis_angle(np.array([math.cos(axis_rad), math.sin(axis_rad), 0.0]), rng.uniform(0.35, 0.8))
        R = tilt @ _axis_angle(np.array([0.0, 0.0, 1.0]), rng.uniform(-0.5, 0.5))  # board faces the camera
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = distance_m * ray - R @ centre_board
        if aim is not cameras[0]:
            T = cameras[0].T_cam_world @ np.linalg.inv(aim.T_cam_world) @ T
        T_world_board = np.linalg.inv(cameras[0].T_cam_world) @ T
        seen = [
            _acceptable(cam, spec, cam.T_cam_world @ T_world_board if i else T)
            and (cam is aim or _faces(cam, spec, cam.T_cam_world @ T_world_board))
            for i, cam in enumerate(cameras)
        ]
        if all(seen):
            poses.append(T)
    raise ValueError(f"could not place {count} board views in every camera's picture")


def _light(scenario: Scenario, T_world_board: np.ndarray) -> float:
    """Lambert plus ambient on the board's printed side, whose normal is -z of the board frame."""
    towards = np.asarray(scenario.light.direction, dtype=np.float64)
    towards /= np.linalg.norm(towards)
    facing = max(0.0, float(-T_world_board[:3, 2] @ towards))
    return scenario.light.ambient + (1.0 - scenario.light.ambient) * facing


def write_calibration_set(
    scenario: Scenario,
    out_dir: Path,
    spec: BoardSpec,
    views: int,
    flat_origin_m: tuple[float, float],
    seed: int,
    extra_flat_origins_m: tuple[tuple[float, float], ...] = (),
) -> list[str]:
    """Render the flat view and `views` held views through every camera of the scenario (the first into
    out_dir, each further one into out_dir/cameras/NAME/); returns the pictures' names.

    extra_flat_origins_m: more views flat on the table (flat_2.png, ...), instead of held ones when
    `views` is 0: a set whose planes are all parallel, which cannot fix the focal length."""
    specs = scenario.camera_specs
    cameras = [Camera.from_spec(s) for s in specs]
    camera = cameras[0]
    rng = np.random.default_rng(seed)
    named = {FLAT_NAME: camera.T_cam_world @ flat_pose(spec, flat_origin_m)}
    for k, origin in enumerate(extra_flat_origins_m, start=2):
        named[f"flat_{k}.png"] = camera.T_cam_world @ flat_pose(spec, origin)
    for k, T in enumerate(held_poses(cameras, spec, views, rng), start=1):
        named[f"view_{k:02d}.png"] = T
    T_world_board = {name: np.linalg.inv(camera.T_cam_world) @ T for name, T in named.items()}
    pattern = BoardPattern(spec)
    for i, (cam_spec, cam) in enumerate(zip(specs, cameras, strict=True)):
        # The first camera's noise follows its poses on one generator (a one-camera set as it always was).
        noise = rng if i == 0 else np.random.default_rng((seed, i))
        cam_dir = camera_dir(out_dir, i, str(cam_spec.name))
        cam_dir.mkdir(parents=True, exist_ok=True)
        rays = corner_rays(cam)
        for name, T_wb in T_world_board.items():
            T_cam_board = named[name] if i == 0 else cam.T_cam_world @ T_wb
            image = render_board(pattern, rays, T_cam_board, SUPERSAMPLE, _light(scenario, T_wb))
            cv2.imwrite(str(cam_dir / name), to_grey8(image, scenario.noise.sigma, noise))
        cam.save(cam_dir / "camera.json")
    board = {
        "board": asdict(spec),
        "flat": FLAT_NAME,
        "flat_origin_m": list(flat_origin_m),
        "cameras": [str(s.name) for s in specs],
        "T_cam_board": {name: T.tolist() for name, T in named.items()},
        "T_world_board": {name: T.tolist() for name, T in T_world_board.items()},
    }
    (out_dir / "board.json").write_text(json.dumps(board, indent=2) + "\n")
    return list(named)
