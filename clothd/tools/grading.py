"""Grading estimates against hwsim's ground truth (benchmarks and tests only; the tracker never reads
truth). A tracker node or feature is a material point: where it lay on the table at initialisation.
Its true position at frame k is the same material point on the truth surface (docs/recording-format.md).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from clothd.core.binding import cloth_coordinates
from clothd.core.camera_model import CameraModel
from clothd.core.mesh import QuadMesh
from hwsim.truth import Truth, surface_points, surface_weights


def material_coordinates(truth: Truth, world_xy0: np.ndarray, frame: int = 0) -> np.ndarray:
    """Material (s, t) (n, 2) of points that lay at world_xy0 (n, 2) in `frame`, where the truth cloth is
    flat: the least-squares affine map from the truth nodes' world x, y to their material coordinates."""
    xy = truth.nodes_m[frame][..., :2].reshape(-1, 2)
    st = truth.st_m.reshape(-1, 2)
    A = np.column_stack([xy, np.ones(len(xy))])
    coef, *_ = np.linalg.lstsq(A, st, rcond=None)
    out = np.column_stack([world_xy0, np.ones(len(world_xy0))]) @ coef
    w, h = truth.size_m
    return np.asarray(np.clip(out, 0.0, [w, h]))


def true_positions(truth: Truth, st_m: np.ndarray, frames: np.ndarray | None = None) -> np.ndarray:
    """World positions (F, n, 3) of material points (n, 2) in the given frames (all by default)."""
    idx, w = surface_weights(st_m, truth.spacing_m, truth.st_m.shape[:2])
    nodes = truth.nodes_m if frames is None else truth.nodes_m[frames]
    return surface_points(nodes, idx, w)


def truth_mesh(truth: Truth) -> QuadMesh:
    """The truth cloth's own grid as a quad mesh in material coordinates."""
    ny, nx = truth.st_m.shape[:2]
    w, h = truth.size_m
    return QuadMesh(nx, ny, np.zeros(2), 0.0, w, h)


def seen_nodes_m(truth: Truth, k: int, exposure_s: float) -> np.ndarray:
    """The truth's nodes (ny, nx, 3) as frame k shows them. hwsim smears a frame over its exposure up to
    the frame's time, so a moving cloth is seen where it was exposure_s / 2 earlier (the smear's middle),
    p − v·exposure_s/2; v from the neighbouring frames (central differences, one-sided at the ends)."""
    nodes = truth.nodes_m[k].astype(np.float64)
    if exposure_s <= 0.0 or len(truth.t_s) < 2:
        return nodes
    lo, hi = max(k - 1, 0), min(k + 1, len(truth.t_s) - 1)
    velocity = (truth.nodes_m[hi] - truth.nodes_m[lo]) / (truth.t_s[hi] - truth.t_s[lo])
    return np.asarray(nodes - 0.5 * exposure_s * velocity)


class FeatureTruth:
    """Each feature's true pixel in every frame of a recording: the material point under the pixel it
    was detected at (as the frame showed the cloth, in the middle of its exposure_s), projected through
    the recording's true camera."""

    def __init__(self, truth: Truth, camera: CameraModel, exposure_s: float = 0.0) -> None:
        self.truth = truth
        self.camera = camera
        self.exposure_s = exposure_s
        self._mesh = truth_mesh(truth)
        self.pixels: dict[int, np.ndarray] = {}  # feature id -> (F, 2) true pixel in every frame

    def learn_births(self, births: Mapping[int, tuple[int, np.ndarray]]) -> None:
        """Features by id -> (the frame each was detected in, its pixel (2,) there)."""
        by_frame: dict[int, list[tuple[int, np.ndarray]]] = {}
        for fid, (k, px) in births.items():
            by_frame.setdefault(k, []).append((fid, px))
        for k, items in by_frame.items():
            self.learn(k, [fid for fid, _ in items], np.array([px for _, px in items]))

    def learn(self, frame: int, ids: Sequence[int], px: np.ndarray) -> None:
        """Features `ids` detected in `frame` at px (n, 2). One detected off the true cloth stays unknown."""
        if not len(ids):
            return
        nodes_px = self.camera.project(seen_nodes_m(self.truth, frame, self.exposure_s).reshape(-1, 3))
        st, found = cloth_coordinates(self._mesh, nodes_px, np.asarray(px, dtype=np.float64).reshape(-1, 2))
        points = true_positions(self.truth, np.nan_to_num(st))
        pix = self.camera.project(points.reshape(-1, 3)).reshape(len(self.truth.t_s), -1, 2)
        for j, fid in enumerate(ids):
            if found[j]:
                self.pixels[int(fid)] = pix[:, j]
