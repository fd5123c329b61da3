"""`hwsim charuco`: the pictures an integrator takes to calibrate a cell, rendered through a scenario's
camera, with the truth beside them.

DIR/flat.png          the board flat on the table, ChArUco corner id 0 at world (X, Y, 0), board x along
                      world +x and board y along world -y (its printed side up, facing the camera)
DIR/view_NN.png       the board held over the table in tilted poses, spread over the image
DIR/camera.json       the true camera (as `hwsim record` writes it)
DIR/board.json        the board's geometry, the flat view's origin and every view's true T_cam_board

Held poses are drawn from a seeded generator: the board's centre on the ray of a point near one of
nine places in the picture (12, 50 or 88 % across and down, taken in turn, jittered by 6 %), 60-90 % of
the camera's height away, tilted 20-45° about an in-plane axis whose direction turns from view to view,
and turned about its normal by up to 30°. So boards run off every edge and corner, where the lens
bends most. A pose is kept when the whole sheet is above the table and at least 35 % of the corners
are in the picture.
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
from hwsim.scenario import Scenario

FLAT_NAME = "flat.png"
SUPERSAMPLE = 4
_MIN_VISIBLE = 0.35
_AIM = (0.12, 0.5, 0.88)  # where in the picture a view's board centre goes, per axis (then jittered)
_EDGE_PX = 8.0
_MAX_TRIES = 1000


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


def held_poses(camera: Camera, spec: BoardSpec, count: int, rng: np.random.Generator) -> list[np.ndarray]:
    """T_cam_board of `count` tilted views of the board held over the table (see the module's notes)."""
    height_m = float(camera.centre_m[2])
    centre_board = np.array([*np.asarray(spec.size_m) / 2, 0.0])
    poses: list[np.ndarray] = []
    for _ in range(_MAX_TRIES):
        if len(poses) == count:
            return poses
        k = len(poses)
        cell_x, cell_y = k % 3, (k // 3) % 3
        target = np.array(
            [
                (_AIM[cell_x] + rng.uniform(-0.06, 0.06)) * camera.width,
                (_AIM[cell_y] + rng.uniform(-0.06, 0.06)) * camera.height,
            ]
        )
        xy = cv2.undistortPoints(target.reshape(1, 1, 2), camera.K, camera.dist).reshape(2)
        ray = np.array([*xy, 1.0]) / np.linalg.norm([*xy, 1.0])
        distance_m = rng.uniform(0.6, 0.9) * height_m
        axis_rad = 2 * math.pi * k / count + rng.uniform(-0.3, 0.3)
        tilt = _axis_angle(np.array([math.cos(axis_rad), math.sin(axis_rad), 0.0]), rng.uniform(0.35, 0.8))
        R = tilt @ _axis_angle(np.array([0.0, 0.0, 1.0]), rng.uniform(-0.5, 0.5))  # board faces the camera
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = distance_m * ray - R @ centre_board
        if _acceptable(camera, spec, T):
            poses.append(T)
    raise ValueError(f"could not place {count} board views in this camera's picture")


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
    """Render the flat view and `views` held views through the scenario's camera; returns the names.

    extra_flat_origins_m: more views flat on the table (flat_2.png, ...), instead of held ones when
    `views` is 0: a set whose planes are all parallel, which cannot fix the focal length."""
    camera = Camera.from_spec(scenario.camera)
    rng = np.random.default_rng(seed)
    T_world_cam = np.linalg.inv(camera.T_cam_world)
    named = {FLAT_NAME: camera.T_cam_world @ flat_pose(spec, flat_origin_m)}
    for k, origin in enumerate(extra_flat_origins_m, start=2):
        named[f"flat_{k}.png"] = camera.T_cam_world @ flat_pose(spec, origin)
    for k, T in enumerate(held_poses(camera, spec, views, rng), start=1):
        named[f"view_{k:02d}.png"] = T
    out_dir.mkdir(parents=True, exist_ok=True)
    pattern = BoardPattern(spec)
    rays = corner_rays(camera)
    for name, T_cam_board in named.items():
        image = render_board(
            pattern, rays, T_cam_board, SUPERSAMPLE, _light(scenario, T_world_cam @ T_cam_board)
        )
        cv2.imwrite(str(out_dir / name), to_grey8(image, scenario.noise.sigma, rng))
    camera.save(out_dir / "camera.json")
    board = {
        "board": asdict(spec),
        "flat": FLAT_NAME,
        "flat_origin_m": list(flat_origin_m),
        "T_cam_board": {name: T.tolist() for name, T in named.items()},
    }
    (out_dir / "board.json").write_text(json.dumps(board, indent=2) + "\n")
    return list(named)
