"""Grading estimates against hwsim's ground truth (benchmarks and tests only; the tracker never reads
truth). A tracker node or feature is a material point: where it lay on the table at initialisation.
Its true position at frame k is the same material point on the truth surface (docs/recording-format.md).
"""

from __future__ import annotations

import numpy as np

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
