"""No model: each feature is where Lucas–Kanade measured it, and the pose stays where the cloth was found.
The original report's model-free baseline."""

from __future__ import annotations

import numpy as np

from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import BeltField
from clothd.core.ekf import UpdateStats
from clothd.core.estimators.base import Measurements, StateEstimate, uncorrected
from clothd.core.feature_set import FeatureSet
from clothd.core.mesh import QuadMesh


class NoModel:
    """The Estimator with no state: no prediction, no correction, the pose where the cloth was found."""

    def __init__(self, camera_model: CameraModel) -> None:
        self.camera_model = camera_model
        self.pose0 = np.zeros(3)

    def start(self, mesh: QuadMesh, pose0: np.ndarray, nodes_m: np.ndarray | None = None) -> None:
        """nodes_m, a measured layout, is for a mesh of the cloth's own shape: a rigid body has none."""
        self.pose0 = pose0

    def predict(self, u: BeltField | None, dt_s: float) -> None:
        """Nothing to advance."""

    def feature_pixels(self, features: FeatureSet) -> np.ndarray | None:
        return None

    def correct(self, m: Measurements) -> tuple[UpdateStats, np.ndarray]:
        return uncorrected(m)

    def cloth_coordinates(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The table point under each pixel: without a model, cloth space is where the cloth lay."""
        return self.camera_model.backproject_to_plane(px)[:, :2], np.ones(len(px), bool)

    def outline_px(self) -> np.ndarray | None:
        return None

    def estimate(self) -> StateEstimate:
        return StateEstimate(self.pose0.copy(), np.full((3, 3), np.nan), None, None)
