"""Messages between the tracker and its callers: the control input and the estimate of one tick."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from clothd.core.ekf import UpdateStats


@dataclass(frozen=True)
class ModuleCommands:
    """The control input u: each module's commanded belt speed and heading, indexed by module id."""

    speed_m_s: np.ndarray
    heading_rad: np.ndarray


@dataclass(frozen=True)
class Estimate:
    """What the tracker believes after a tick. Feature arrays are indexed like feature_id; pred_px is
    where the estimate places each feature, meas_px where LK measured it this tick (NaN if not)."""

    t_s: float
    status: str  # "tracking" or "lost"
    pose: np.ndarray  # (3,) X_m, Y_m, theta_rad; NaN when lost
    pose_cov: np.ndarray  # (3, 3)
    nodes_m: np.ndarray | None  # (ny, nx, 3) for the mesh-based modes
    feature_id: np.ndarray  # (n,)
    meas_px: np.ndarray  # (n, 2)
    pred_px: np.ndarray  # (n, 2)
    stats: UpdateStats
    timing_s: dict[str, float] = field(default_factory=dict)

    @property
    def residual_px(self) -> np.ndarray:
        ok = ~np.isnan(self.meas_px[:, 0])
        return np.asarray(np.linalg.norm(self.meas_px[ok] - self.pred_px[ok], axis=1))
