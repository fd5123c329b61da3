"""`hwsim verify`: do the pixels agree with the ground truth?

Take 200 random material points that are visible and face the camera in frame 0. For every 10th frame
k, compare the 15x15 patch at each point's true pixel in frame k-10 with the patch at its true pixel in
frame k; the zero-mean normalised cross-correlation must be >= 0.9 for at least 95 % of the pairs.
A point is left out at a frame where it is occluded or tilted past 30 degrees. Because a 15x15 patch
sees the point's surroundings too, "occluded or tilted" is judged over the truth nodes within
`PATCH_RADIUS_M` of the point, and points are drawn at least that far inside the cloth's edge.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from hwsim.camera import Camera
from hwsim.paths import frame_path
from hwsim.truth import Truth, surface_normals, surface_points, surface_weights

N_POINTS = 200
FRAME_GAP = 10
PATCH_PX = 15
NCC_MIN = 0.9
PASS_FRACTION = 0.95
MAX_TILT_RAD = math.radians(30.0)
PATCH_RADIUS_M = 0.009  # ~half the patch at ~0.9 px/mm, rounded up
SEED = 0


@dataclass(frozen=True)
class VerifyResult:
    points: int
    pairs: int
    passed: int
    ncc_median: float
    ncc_p05: float

    @property
    def pass_fraction(self) -> float:
        return self.passed / self.pairs if self.pairs else 0.0

    @property
    def ok(self) -> bool:
        return self.pairs > 0 and self.pass_fraction >= PASS_FRACTION

    def to_json(self) -> dict[str, object]:
        return {**asdict(self), "pass_fraction": self.pass_fraction, "ok": self.ok}


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Zero-mean normalised cross-correlation of two equal-shape patches; 0 for a flat patch."""
    a = a - a.mean()
    b = b - b.mean()
    denom = math.sqrt(float((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / denom) if denom > 1e-12 else 0.0


def _usable(
    truth: Truth, camera: Camera, k: int, idx: np.ndarray, w: np.ndarray, near: list[np.ndarray]
) -> np.ndarray:
    """(n,) bool: each point and the nodes around it visible at frame k, and facing the camera."""
    nodes = truth.nodes_m[k]
    points = surface_points(nodes, idx, w)
    view = camera.centre_m - points
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    facing = np.abs(np.sum(surface_normals(nodes, idx) * view, axis=1)) >= math.cos(MAX_TILT_RAD)
    node_n = _node_normals(nodes)
    ok = np.empty(len(idx), bool)
    for p, nbrs in enumerate(near):
        js, is_ = nbrs[:, 0], nbrs[:, 1]
        to_cam = camera.centre_m - nodes[js, is_]
        to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
        tilt_ok = np.all(np.abs(np.sum(node_n[js, is_] * to_cam, axis=1)) >= math.cos(MAX_TILT_RAD))
        ok[p] = facing[p] and tilt_ok and bool(truth.visible[k][js, is_].all())
    return ok


def _node_normals(nodes: np.ndarray) -> np.ndarray:
    n = np.cross(np.gradient(nodes, axis=1), np.gradient(nodes, axis=0))
    return np.asarray(n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-15))


def _gray(recording: Path, k: int) -> np.ndarray:
    img = cv2.imread(str(frame_path(recording, k)), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise FileNotFoundError(f"missing frame {frame_path(recording, k)}")
    return img.astype(np.float32)


def verify(recording: Path) -> VerifyResult:
    truth = Truth.load(recording)
    camera = Camera.load(recording / "camera.json")
    rng = np.random.default_rng(SEED)
    w_m, h_m = truth.size_m
    shape = truth.st_m.shape[:2]
    # Draw candidates well inside the edge, keep the first N_POINTS usable in frame 0.
    cand = np.stack(
        [
            rng.uniform(PATCH_RADIUS_M, w_m - PATCH_RADIUS_M, 20 * N_POINTS),
            rng.uniform(PATCH_RADIUS_M, h_m - PATCH_RADIUS_M, 20 * N_POINTS),
        ],
        axis=1,
    )
    idx, w = surface_weights(cand, truth.spacing_m, shape)
    st_nodes = truth.st_m.reshape(-1, 2)
    grid_ji = np.stack(np.unravel_index(np.arange(len(st_nodes)), shape), axis=1)
    near = [grid_ji[np.linalg.norm(st_nodes - c, axis=1) <= PATCH_RADIUS_M] for c in cand]
    usable0 = _usable(truth, camera, 0, idx, w, near)
    keep = np.flatnonzero(usable0)[:N_POINTS]
    idx, w, near = idx[keep], w[keep], [near[i] for i in keep]
    pixels = camera.project(surface_points(truth.nodes_m, idx, w))  # (F, n, 2)
    scores: list[float] = []
    prev_img = _gray(recording, 0)
    prev_ok = _usable(truth, camera, 0, idx, w, near)
    for k in range(FRAME_GAP, len(truth.t_s), FRAME_GAP):
        img = _gray(recording, k)
        ok = _usable(truth, camera, k, idx, w, near)
        for p in np.flatnonzero(ok & prev_ok):
            a = cv2.getRectSubPix(prev_img, (PATCH_PX, PATCH_PX), tuple(map(float, pixels[k - FRAME_GAP, p])))
            b = cv2.getRectSubPix(img, (PATCH_PX, PATCH_PX), tuple(map(float, pixels[k, p])))
            scores.append(ncc(a, b))
        prev_img, prev_ok = img, ok
    arr = np.asarray(scores)
    return VerifyResult(
        points=len(keep),
        pairs=len(arr),
        passed=int((arr >= NCC_MIN).sum()),
        ncc_median=float(np.median(arr)) if len(arr) else float("nan"),
        ncc_p05=float(np.percentile(arr, 5)) if len(arr) else float("nan"),
    )
