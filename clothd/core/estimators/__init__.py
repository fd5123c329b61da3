"""The estimators behind the tracker, one per model (docs/architecture.md): none, rigid, mesh (and the
mesh predicted only). `make_estimator` is the one place that turns the configured model into one."""

from __future__ import annotations

from collections.abc import Callable

from clothd.config import TrackerConfig
from clothd.core.camera_model import CameraModel
from clothd.core.estimators.base import Estimator, Measurements, StateEstimate
from clothd.core.estimators.mesh import MeshEstimator
from clothd.core.estimators.none import NoModel
from clothd.core.estimators.rigid import RigidEstimator

__all__ = ["Estimator", "Measurements", "StateEstimate", "make_estimator"]


def make_estimator(cfg: TrackerConfig, camera_model: CameraModel) -> Estimator:
    """The estimator for `cfg.model`. The mesh estimators need Taichi started (taichi_runtime)."""

    def mesh(corrects: bool) -> Estimator:
        return MeshEstimator(camera_model, cfg.mesh, cfg.physics, cfg.ekf, cfg.use_input, corrects)

    builders: dict[str, Callable[[], Estimator]] = {
        "none": lambda: NoModel(camera_model),
        "rigid": lambda: RigidEstimator(camera_model, cfg.ekf, cfg.physics, cfg.use_input),
        "mesh": lambda: mesh(corrects=True),
        "predict": lambda: mesh(corrects=False),
    }
    return builders[cfg.model]()
