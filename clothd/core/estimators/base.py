"""What every estimator offers the tracker, whatever it believes the cloth to be.

An estimator owns its state (a rigid pose, or mesh nodes, or nothing) and answers in the table's world
frame. The tracker owns the features and the frames; it hands the estimator the control input, the
features' material points and their measurements, and asks it where the features and the cloth are.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from clothd.core.conveyor import BeltField
from clothd.core.ekf import UpdateStats
from clothd.core.feature_set import FeatureSet
from clothd.core.mesh import QuadMesh
from clothd.core.outline_edges import EdgeMeasurements


@dataclass(frozen=True)
class Measurements:
    """This frame's LK result: features (n), measured pixels (n, 2), and which LK kept (n,) bool.
    whiten: (n, 2, 2) each measurement's whitening relative to meas_sigma_px (features.aperture_whitening),
    None for isotropic measurements."""

    features: FeatureSet
    px: np.ndarray
    ok: np.ndarray
    whiten: np.ndarray | None = None
    # The cloth's outline measured against node positions (n, 3) (clothd/core/outline_edges.py), or None.
    edges: Callable[[np.ndarray], EdgeMeasurements] | None = None
    # How closely the mesh's edges keep their rest length (NodeBelief.correct), where the features alone
    # cannot hold the shape (a periodic weave); 0: not held.
    shape_sigma_m: float = 0.0
    # Each mesh quad's highest point (ny-1, nx-1) as a further view last measured it (folds.py), or None.
    quad_height_m: np.ndarray | None = None


@dataclass(frozen=True)
class StateEstimate:
    """pose (3,) [X_m, Y_m, theta_rad] with covariance (3, 3) (NaN where the estimator has none); nodes_m
    (ny, nx, 3) and outline_m (k, 2) on the table, or None without a model of the cloth."""

    pose: np.ndarray
    pose_cov: np.ndarray
    nodes_m: np.ndarray | None
    outline_m: np.ndarray | None


class Estimator(Protocol):
    def start(self, mesh: QuadMesh, pose0: np.ndarray, nodes_m: np.ndarray | None = None) -> None:
        """Begin from the rest mesh, the cloth at pose0 [X_m, Y_m, theta_rad]. nodes_m (n, 3): where the
        mesh's nodes lie now, when a measured surface says (clothd/core/unfold.py); None: the rest mesh is
        the first frame's footprint, and the nodes lie on it, flat."""

    def predict(self, u: BeltField | None, dt_s: float) -> None:
        """Advance the state by dt_s under the belts u (None: no input known)."""

    def feature_pixels(self, features: FeatureSet) -> np.ndarray | None:
        """Where the state places each feature (n, 2), px; None without a model (features are where LK
        measured them)."""

    def correct(self, m: Measurements) -> tuple[UpdateStats, np.ndarray]:
        """Gate and correct with the measurements LK kept; the statistics and the gate's verdict (n,)."""

    def cloth_coordinates(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cloth-space (s, t) (m, 2) of new features at pixels px (m, 2), and which lie on the cloth."""

    def outline_px(self) -> np.ndarray | None:
        """The cloth's outline in the image (k, 2), or None without a model."""

    def estimate(self) -> StateEstimate:
        """The state as pose, nodes and outline."""


def boundary(grid: np.ndarray) -> np.ndarray:
    """The outer ring of a (ny, nx, d) grid, in order around it, (k, d)."""
    return np.concatenate([grid[0, :], grid[1:, -1], grid[-1, -2::-1], grid[-2:0:-1, 0]])


def uncorrected(m: Measurements) -> tuple[UpdateStats, np.ndarray]:
    """The answer of an estimator that takes no correction: every kept measurement stands."""
    return UpdateStats(int(m.ok.sum()), 0, 0.0), np.ones(len(m.ok), bool)
