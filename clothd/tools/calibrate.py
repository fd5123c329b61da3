"""`clothd calibrate`: the camera (K, lens distortion) and the table's pose from pictures of a ChArUco board.

- Intrinsics: every picture where the board is found, the flat one included, goes to
  `cv2.calibrateCamera` (zero skew; k1, k2, p1, p2, and k3 only when asked: a sixth-order term that few
  views pin down bends the image's corners, where boards seldom reach). Then, REFINE_ROUNDS times, each
  corner is measured again in the board's plane through that solution (clothd/tools/corner_refinement.py)
  and the camera solved again from those measurements.
- Table: in the flat picture the board lies on the table, ChArUco corner id 0 at world (X, Y, 0),
  board x along world +x and board y along world -y. Its corners are world points, so `solvePnP`
  (IPPE, the planar solution, then Levenberg-Marquardt) with the intrinsics gives T_cam_world.

Refused, with the reason (InputError): the flat picture missing, or the board not in it; fewer than
MIN_HELD_VIEWS other pictures with the board; and a set of views whose boards are all parallel to one
another (within MIN_SPREAD_DEG), which leaves the focal length free: the same pictures come from a
longer lens further away. Parallel planes share their vanishing line l in the image, so their normals
K^T l agree whatever K is; the spread is measured with a nominal K (f = the image's larger side).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from clothd.core.camera_model import CameraModel
from clothd.drivers.footage import IMAGE_SUFFIXES, natural_key
from clothd.errors import InputError
from clothd.tools.charuco import MIN_CORNERS, Board, CornerFinder, Detection
from clothd.tools.corner_refinement import CLEAR_OF_MARKERS, refine_corners

MIN_HELD_VIEWS = 4
REFINE_ROUNDS = 2
MIN_SPREAD_DEG = 10.0
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass(frozen=True)
class View:
    name: str
    detection: Detection
    grey: np.ndarray  # the picture, for measuring the corners again


@dataclass(frozen=True)
class ViewFit:
    """A view's corners against the solved camera: detected pixels (n, 2) and detected minus projected."""

    name: str
    pixels: np.ndarray
    residual_px: np.ndarray

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residual_px**2, axis=1))))


@dataclass(frozen=True)
class Calibration:
    camera: CameraModel
    views: list[ViewFit]  # every view the intrinsics were solved from, the flat one included
    flat: ViewFit  # the flat view against the table's world points through T_cam_world
    skipped: list[tuple[str, str]]  # pictures not used, and why

    @property
    def rms_px(self) -> float:
        """RMS reprojection error over every corner of every view (what cv2.calibrateCamera minimises)."""
        r = np.concatenate([v.residual_px for v in self.views])
        return float(np.sqrt(np.mean(np.sum(r**2, axis=1))))


@dataclass(frozen=True)
class Pictures:
    """What a directory of pictures holds: the flat view, the others with the board, and the rest."""

    flat: View
    held: list[View]
    skipped: list[tuple[str, str]]
    width: int
    height: int


def read_pictures(images_dir: Path, board: Board, flat_name: str) -> Pictures:
    """Find the board in every picture of images_dir (natural order); InputError for the flat view missing
    or without the board, or pictures of different sizes."""
    if not images_dir.is_dir():
        raise InputError(f"{images_dir}: not a directory of pictures")
    paths = sorted((p for p in images_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
    if flat_name not in {p.name for p in paths}:
        raise InputError(f"flat view missing: no picture {flat_name!r} in {images_dir}")
    finder = CornerFinder(board)
    flat: View | None = None
    held: list[View] = []
    skipped: list[tuple[str, str]] = []
    size: tuple[int, int] | None = None
    # A bar on a terminal only (disable=None): the board is looked for in every picture, seconds each.
    for path in tqdm(paths, desc="finding the board", unit="picture", disable=None):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise InputError(f"{path}: not a readable image")
        h, w = image.shape
        if size is not None and (w, h) != size:
            raise InputError(f"{path}: {w}x{h} px, the pictures before it {size[0]}x{size[1]}")
        size = (w, h)
        found = finder.find(image)
        if path.name == flat_name:
            if found is None:
                raise InputError(f"{path}: board not found in the flat view (need {MIN_CORNERS} corners)")
            flat = View(path.name, found, image)
        elif found is None:
            skipped.append((path.name, f"board not found (fewer than {MIN_CORNERS} corners)"))
        else:
            held.append(View(path.name, found, image))
    assert flat is not None and size is not None
    return Pictures(flat, held, skipped, size[0], size[1])


def flat_world_points(board: Board, board_m: np.ndarray, flat_origin_m: tuple[float, float]) -> np.ndarray:
    """Board-frame points (n, 3) of the flat view -> world points (n, 3): corner id 0, at board
    (square, square), to (X, Y, 0); board x along world +x, board y along world -y."""
    s = board.square_m
    x, y = flat_origin_m
    return np.column_stack([x + board_m[:, 0] - s, y - (board_m[:, 1] - s), np.zeros(len(board_m))])


def plane_spread_deg(views: list[View], width: int, height: int) -> float:
    """The largest angle between two views' board planes, by a nominal K (module notes)."""
    f = float(max(width, height))
    K_inv = np.linalg.inv(np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]))
    normals = []
    for v in views:
        H, _ = cv2.findHomography(v.detection.board_m[:, :2], v.detection.pixels)
        if H is None:
            continue
        M = K_inv @ H
        n = np.cross(M[:, 0], M[:, 1])
        normals.append(n / np.linalg.norm(n) * np.sign(n[2]))
    if len(normals) < 2:
        return 0.0
    N = np.asarray(normals)
    return math.degrees(math.acos(float(np.clip((N @ N.T).min(), -1.0, 1.0))))


def _residual(
    pixels: np.ndarray,
    points_m: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
) -> np.ndarray:
    projected, _ = cv2.projectPoints(points_m, rvec, tvec, K, dist)
    return np.asarray(pixels - projected.reshape(-1, 2))


def _calibrate(
    detections: list[Detection], size: tuple[int, int], flags: int
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """cv2.calibrateCamera: K, dist (5,), and each view's rvec and tvec."""
    _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [d.board_m.astype(np.float32) for d in detections],
        [d.pixels.astype(np.float32) for d in detections],
        size,
        None,
        None,
        flags=flags,
        criteria=_CRITERIA,
    )
    return K, np.asarray(dist, dtype=np.float64).ravel()[:5], list(rvecs), list(tvecs)


def _enough_views(held: int) -> None:
    if held < MIN_HELD_VIEWS:
        raise InputError(
            f"too few views: the board was found in {held} pictures besides the flat one, "
            f"{MIN_HELD_VIEWS} needed (10-20 recommended)"
        )


@dataclass(frozen=True)
class Intrinsics:
    """One camera solved from its pictures: K, dist (5,), the views used (flat first) with their corners
    as last measured, each view's board pose in the camera (rvec, tvec), and the pictures not used."""

    K: np.ndarray
    dist: np.ndarray
    used: list[tuple[View, Detection]]
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]
    skipped: list[tuple[str, str]]


def solve_intrinsics(pictures: Pictures, board: Board, fit_k3: bool = False) -> Intrinsics:
    """K and distortion from every picture with the board, corners measured again REFINE_ROUNDS times
    (module notes); InputError for too few or all-parallel views."""
    _enough_views(len(pictures.held))
    views = [pictures.flat, *pictures.held]
    spread = plane_spread_deg(views, pictures.width, pictures.height)
    if spread < MIN_SPREAD_DEG:
        raise InputError(
            f"degenerate views: the boards are all parallel (at most {spread:.1f}° apart, "
            f"{MIN_SPREAD_DEG:.0f}° needed); tilt the board 20-45° in different directions"
        )
    flags = 0 if fit_k3 else cv2.CALIB_FIX_K3
    size = (pictures.width, pictures.height)
    used = [(v, v.detection) for v in views]
    skipped = list(pictures.skipped)
    K, dist, rvecs, tvecs = _calibrate([d for _, d in used], size, flags)
    half_width_m = CLEAR_OF_MARKERS * (board.square_m - board.marker_m) / 2
    for _ in range(REFINE_ROUNDS):
        refined = [
            (v, refine_corners(v.grey, v.detection, half_width_m, K, dist, r, t))
            for (v, _), r, t in zip(used, rvecs, tvecs, strict=True)
        ]
        used = [(v, d) for v, d in refined if len(d.ids) >= MIN_CORNERS]
        if used[0][0] is not pictures.flat:
            raise InputError(
                f"{pictures.flat.name}: fewer than {MIN_CORNERS} corners clear of the picture's edge"
            )
        skipped += [
            (v.name, f"fewer than {MIN_CORNERS} corners clear of the picture's edge")
            for v, d in refined
            if len(d.ids) < MIN_CORNERS
        ]
        _enough_views(len(used) - 1)
        K, dist, rvecs, tvecs = _calibrate([d for _, d in used], size, flags)
    return Intrinsics(K, dist, used, rvecs, tvecs, skipped)


def solve(
    pictures: Pictures, board: Board, flat_origin_m: tuple[float, float], fit_k3: bool = False
) -> Calibration:
    """The camera from the pictures; InputError for too few or all-parallel views."""
    solved = solve_intrinsics(pictures, board, fit_k3)
    K, dist, used = solved.K, solved.dist, solved.used
    fits = [
        ViewFit(v.name, d.pixels, _residual(d.pixels, d.board_m, r, t, K, dist))
        for (v, d), r, t in zip(used, solved.rvecs, solved.tvecs, strict=True)
    ]
    flat_detection = used[0][1]
    world_m = flat_world_points(board, flat_detection.board_m, flat_origin_m)
    flat_px = flat_detection.pixels
    _, rvec, tvec = cv2.solvePnP(world_m, flat_px, K, dist, flags=cv2.SOLVEPNP_IPPE)
    rvec, tvec = cv2.solvePnPRefineLM(world_m, flat_px, K, dist, rvec, tvec, criteria=_CRITERIA)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    camera = CameraModel(K, dist, T, pictures.width, pictures.height)
    flat = ViewFit(pictures.flat.name, flat_px, _residual(flat_px, world_m, rvec, tvec, K, dist))
    return Calibration(camera, fits, flat, solved.skipped)
