"""`clothd calibrate` through several cameras: every camera's K, distortion and pose in the table frame
from the same ChArUco views, and how well the pair agrees (the epipolar error).

Pictures: DIR holds the first camera's (as for one camera), DIR/cameras/NAME/ each further camera's,
as `hwsim record` and `hwsim charuco` lay them out. A picture of the same name in two cameras is the
board in one pose, taken at one instant by both (a trigger, or the board held still while both take it).

- Each camera alone first: `calibrate.solve_intrinsics` (K, distortion, corners measured again in the
  board's plane) and its pose in the table frame from its flat view (IPPE, then Levenberg-Marquardt).
- Then one bundle adjustment over every corner of every camera: each camera's fx, fy, cx, cy, k1, k2,
  p1, p2 (and k3 with --k3) and T_cam_world, and each held view's board pose in the table frame, shared
  by the cameras that saw it; the flat view's board pose is the table frame's definition and stays
  fixed. A held view seen by two cameras ties their poses to each other. On hwsim's cell (bench
  calibrate --cameras 2, seeds 0-3) it halved the pair's epipolar error (median 0.056-0.075 px alone,
  0.033-0.040 px together; p95 0.15-0.18 px, 0.09-0.12 px) and took the worst camera position error
  from 0.48 to 0.43 mm; the worst angle went from 0.027° to 0.041° (docs/commissioning.md).
- Epipolar error of a pair: every corner id found in the same picture by both cameras, undistorted; its
  distance (px) from the epipolar line of its match, in each camera's image, through the solved poses.
  It measures the pair as the tracker uses it (matching along epipolar lines, triangulation).

A further camera is written beside the first's camera.json as NAME.json, the calibration `cameras:`
names for it (clothd/config/camera.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from clothd.config.camera import default_camera_name
from clothd.core.camera_model import CameraModel
from clothd.drivers.footage import natural_key
from clothd.errors import InputError
from clothd.tools.calibrate import (
    Calibration,
    Intrinsics,
    Pictures,
    View,
    ViewFit,
    flat_world_points,
    read_pictures,
    solve,
    solve_intrinsics,
)
from clothd.tools.charuco import Board, Detection

FURTHER_DIR = "cameras"
_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


@dataclass(frozen=True)
class Epipolar:
    """Two cameras' agreement: each matched corner's distance from its epipolar line, px, both ways."""

    cameras: tuple[str, str]
    distances_px: np.ndarray

    @property
    def median_px(self) -> float:
        return float(np.median(self.distances_px))

    @property
    def p95_px(self) -> float:
        return float(np.percentile(self.distances_px, 95))


@dataclass(frozen=True)
class Rig:
    """Every camera's calibration (the joint solution), first first, and each pair's epipolar error."""

    names: list[str]
    calibrations: list[Calibration]
    pairs: list[Epipolar]
    views_shared: int  # held views seen by two cameras or more


def camera_dirs(images_dir: Path) -> list[tuple[str, Path]]:
    """(name, directory) of every camera's pictures: the first in images_dir, named cam0, then each
    images_dir/cameras/NAME in natural order."""
    further = images_dir / FURTHER_DIR
    subdirs = [p for p in further.iterdir() if p.is_dir()] if further.is_dir() else []
    subdirs.sort(key=natural_key)
    return [(default_camera_name(0), images_dir), *((p.name, p) for p in subdirs)]


def further_out(first_out: Path, name: str) -> Path:
    """Where a further camera's camera.json goes: beside the first's, NAME.json."""
    return first_out.with_name(f"{name}.json")


def read_rig(images_dir: Path, board: Board, flat_name: str) -> list[tuple[str, Pictures]]:
    """Each camera's pictures (calibrate.read_pictures); InputError as it gives, naming the camera."""
    rig = []
    for name, path in camera_dirs(images_dir):
        try:
            rig.append((name, read_pictures(path, board, flat_name)))
        except InputError as err:
            raise InputError(f"camera {name}: {err}") from err
    return rig


def _vector(T: np.ndarray) -> np.ndarray:
    return np.concatenate([cv2.Rodrigues(T[:3, :3])[0].ravel(), T[:3, 3]])


def _pose(rt: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rt[:3], dtype=np.float64))[0]
    T[:3, 3] = rt[3:6]
    return T


def _flat_pose(board: Board, flat_origin_m: tuple[float, float]) -> np.ndarray:
    """The flat view's board frame in the table frame (calibrate.flat_world_points as a pose)."""
    s = board.square_m
    T = np.diag([1.0, -1.0, -1.0, 1.0])
    T[:3, 3] = [flat_origin_m[0] - s, flat_origin_m[1] + s, 0.0]
    return T


def _intrinsic_vector(K: np.ndarray, dist: np.ndarray, fit_k3: bool) -> np.ndarray:
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist[: 5 if fit_k3 else 4]])


def _lens(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
    dist = np.zeros(5)
    dist[: len(p) - 4] = p[4:]
    return K, dist


def _project(p_cam: np.ndarray, T_cam_board: np.ndarray, board_m: np.ndarray) -> np.ndarray:
    K, dist = _lens(p_cam)
    rvec = cv2.Rodrigues(T_cam_board[:3, :3])[0]
    px, _ = cv2.projectPoints(board_m, rvec, T_cam_board[:3, 3], K, dist)
    return np.asarray(px).reshape(-1, 2)


@dataclass(frozen=True)
class _Problem:
    """The bundle adjustment's layout: observations (camera, view or -1 for the flat one, detection)."""

    n_cam_params: int  # per camera: intrinsics, then T_cam_world's rvec and t
    n_intrinsics: int
    views: list[str]  # held views, in parameter order
    observations: list[tuple[int, int, Detection]]
    T_world_flat: np.ndarray

    def unpack(self, x: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray]:
        p = x[c * self.n_cam_params : (c + 1) * self.n_cam_params]
        return p[: self.n_intrinsics], _pose(p[self.n_intrinsics :])

    def board_pose(self, x: np.ndarray, n_cameras: int, v: int) -> np.ndarray:
        if v < 0:
            return self.T_world_flat
        start = n_cameras * self.n_cam_params + 6 * v
        return _pose(x[start : start + 6])

    def residuals(self, x: np.ndarray, n_cameras: int) -> np.ndarray:
        out = []
        for c, v, d in self.observations:
            intr, T_cw = self.unpack(x, c)
            projected = _project(intr, T_cw @ self.board_pose(x, n_cameras, v), d.board_m)
            out.append((projected - d.pixels).ravel())
        return np.concatenate(out)

    def sparsity(self, n_cameras: int, n_params: int) -> lil_matrix:
        rows = sum(2 * len(d.ids) for _, _, d in self.observations)
        S = lil_matrix((rows, n_params), dtype=int)
        r = 0
        for c, v, d in self.observations:
            n = 2 * len(d.ids)
            S[r : r + n, c * self.n_cam_params : (c + 1) * self.n_cam_params] = 1
            if v >= 0:
                start = n_cameras * self.n_cam_params + 6 * v
                S[r : r + n, start : start + 6] = 1
            r += n
        return S


def _start(
    solved: list[Intrinsics], flat_T: list[np.ndarray], fit_k3: bool
) -> tuple[list[str], list[tuple[int, int, Detection]], np.ndarray]:
    """Held views (union over cameras), observations, and the starting vector: each camera's own
    solution, each held view's board pose from the first camera that used it."""
    views: list[str] = []
    poses: list[np.ndarray] = []
    observations: list[tuple[int, int, Detection]] = []
    cam_params = []
    for c, (s, T_cw) in enumerate(zip(solved, flat_T, strict=True)):
        cam_params.append(np.concatenate([_intrinsic_vector(s.K, s.dist, fit_k3), _vector(T_cw)]))
        for k, ((view, d), rvec, tvec) in enumerate(zip(s.used, s.rvecs, s.tvecs, strict=True)):
            if k == 0:
                observations.append((c, -1, d))
                continue
            if view.name not in views:
                views.append(view.name)
                T_cb = _pose(np.concatenate([np.ravel(rvec), np.ravel(tvec)]))
                poses.append(_vector(np.linalg.inv(T_cw) @ T_cb))
            observations.append((c, views.index(view.name), d))
    return views, observations, np.concatenate([*cam_params, *poses])


def _pnp_flat(s: Intrinsics, board: Board, flat_origin_m: tuple[float, float]) -> np.ndarray:
    """T_cam_world from the flat view alone (as one camera's calibration finds it)."""
    d = s.used[0][1]
    world_m = flat_world_points(board, d.board_m, flat_origin_m)
    _, rvec, tvec = cv2.solvePnP(world_m, d.pixels, s.K, s.dist, flags=cv2.SOLVEPNP_IPPE)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rvec, tvec = cv2.solvePnPRefineLM(world_m, d.pixels, s.K, s.dist, rvec, tvec, criteria=crit)
    return _pose(np.concatenate([rvec.ravel(), tvec.ravel()]))


def _fits(
    problem: _Problem, x: np.ndarray, solved: list[Intrinsics], n_cameras: int
) -> list[tuple[list[ViewFit], ViewFit]]:
    """Each camera's views (flat first) and its flat view against the joint solution."""
    per_camera: list[tuple[list[ViewFit], ViewFit]] = []
    for c, s in enumerate(solved):
        intr, T_cw = problem.unpack(x, c)
        fits = []
        for view, d in s.used:
            v = problem.views.index(view.name) if view is not s.used[0][0] else -1
            projected = _project(intr, T_cw @ problem.board_pose(x, n_cameras, v), d.board_m)
            fits.append(ViewFit(view.name, d.pixels, d.pixels - projected))
        per_camera.append((fits, fits[0]))
    return per_camera


def solve_rig(
    rig: list[tuple[str, Pictures]], board: Board, flat_origin_m: tuple[float, float], fit_k3: bool = False
) -> Rig:
    """Every camera from the same views (module notes); one camera is `calibrate.solve`'s answer."""
    if len(rig) == 1:
        return Rig([rig[0][0]], [solve(rig[0][1], board, flat_origin_m, fit_k3)], [], 0)
    solved = []
    for name, pictures in rig:
        try:
            solved.append(solve_intrinsics(pictures, board, fit_k3))
        except InputError as err:
            raise InputError(f"camera {name}: {err}") from err
    flat_T = [_pnp_flat(s, board, flat_origin_m) for s in solved]
    views, observations, x0 = _start(solved, flat_T, fit_k3)
    n_intr = 9 if fit_k3 else 8
    problem = _Problem(n_intr + 6, n_intr, views, observations, _flat_pose(board, flat_origin_m))
    n = len(rig)
    fit = least_squares(
        problem.residuals,
        x0,
        jac_sparsity=problem.sparsity(n, len(x0)),
        x_scale="jac",
        method="trf",
        args=(n,),
    )
    calibrations = []
    for c, ((_, pictures), s, (fits, flat)) in enumerate(
        zip(rig, solved, _fits(problem, fit.x, solved, n), strict=True)
    ):
        intr, T_cw = problem.unpack(fit.x, c)
        K, dist = _lens(intr)
        camera = CameraModel(K, dist, T_cw, pictures.width, pictures.height)
        calibrations.append(Calibration(camera, fits, flat, s.skipped))
    seen = [[v.name for v, _ in s.used[1:]] for s in solved]
    shared = sum(1 for v in views if sum(v in names for names in seen) >= 2)
    names = [name for name, _ in rig]
    pairs = [
        epipolar((names[a], names[b]), calibrations[a], calibrations[b], solved[a].used, solved[b].used)
        for a in range(n)
        for b in range(a + 1, n)
    ]
    return Rig(names, calibrations, pairs, shared)


def _undistorted_px(camera: CameraModel, pixels: np.ndarray) -> np.ndarray:
    """Pixels with the lens's distortion taken out, in the same K."""
    xy = cv2.undistortPoints(
        pixels.reshape(-1, 1, 2).astype(np.float64), camera.K, camera.dist, P=camera.K, criteria=_UNDISTORT
    )
    return np.asarray(xy).reshape(-1, 2)


def _line_distances(F: np.ndarray, from_px: np.ndarray, to_px: np.ndarray) -> np.ndarray:
    """Distance of each to_px from the epipolar line F · from_px (homogeneous), px."""
    lines = np.column_stack([from_px, np.ones(len(from_px))]) @ F.T
    num = np.abs(np.sum(lines[:, :2] * to_px, axis=1) + lines[:, 2])
    return np.asarray(num / np.linalg.norm(lines[:, :2], axis=1))


def epipolar(
    names: tuple[str, str],
    a: Calibration,
    b: Calibration,
    used_a: list[tuple[View, Detection]],
    used_b: list[tuple[View, Detection]],
) -> Epipolar:
    """Matched corners' distances from their epipolar lines in both images (module notes)."""
    T_ba = b.camera.T_cam_world @ np.linalg.inv(a.camera.T_cam_world)
    t = T_ba[:3, 3]
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ T_ba[:3, :3]
    F = np.linalg.inv(b.camera.K).T @ E @ np.linalg.inv(a.camera.K)  # x_bᵀ F x_a = 0
    by_name_b = {v.name: d for v, d in used_b}
    distances = []
    for view, da in used_a:
        db = by_name_b.get(view.name)
        if db is None:
            continue
        common, ia, ib = np.intersect1d(da.ids, db.ids, return_indices=True)
        if len(common) == 0:
            continue
        pa = _undistorted_px(a.camera, da.pixels[ia])
        pb = _undistorted_px(b.camera, db.pixels[ib])
        distances += [_line_distances(F, pa, pb), _line_distances(F.T, pb, pa)]
    if not distances:
        raise InputError(f"cameras {names[0]} and {names[1]}: no corner seen in the same picture by both")
    return Epipolar(names, np.concatenate(distances))
