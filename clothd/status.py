"""The daemon's status as one JSON-ready dict: what GET /api/v1/status returns and /stream pushes.
Its shape is declared for the API in clothd/api/schemas.py (StatusResponse)."""

from __future__ import annotations

import math
import time
from dataclasses import asdict
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from clothd.daemon import Daemon


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _pose(p: np.ndarray | None) -> dict[str, float | None] | None:
    if p is None:
        return None
    return {"x_m": _num(p[0]), "y_m": _num(p[1]), "theta_rad": _num(p[2])}


def build_status(d: Daemon) -> dict[str, Any]:
    est = d.latest.estimate if d.latest else None
    tracking = est is not None and est.status == "tracking"
    pose = None
    mesh = None
    features = 0
    rejected = 0
    residual: dict[str, float | None] = {"mean_px": None, "worst_px": None}
    if est is not None and tracking:
        cov = [[_num(v) for v in row] for row in est.pose_cov.tolist()]
        pose = {**(_pose(est.pose) or {}), "cov": cov}
        if est.nodes_m is not None:
            ny, nx = est.nodes_m.shape[:2]
            mesh = {"nx": nx, "ny": ny, "nodes_m": np.round(est.nodes_m.reshape(-1, 3), 5).tolist()}
        features = int((~np.isnan(est.meas_px[:, 0])).sum()) if len(est.meas_px) else 0
        rejected = est.stats.rejected
        r = est.residual_px
        if len(r):
            residual = {"mean_px": float(r.mean()), "worst_px": float(r.max())}
    link = d.link
    cam = d.camera
    return {
        "t_unix_s": time.time(),
        "state": d.state,
        "mode": d.setpoint.mode,
        "setpoint": _pose(d.setpoint.pose),
        "estop": d.estopped,
        "pose": pose,
        "mesh": mesh,
        "features": features,
        "rejected_features": rejected,
        "residual": residual,
        "timing": d.stats.cached_summary(),
        "camera": {
            "state": cam.state,
            "healthy": cam.healthy,
            "source": d.cfg.camera.source,
            "last_error": cam.last_error,
            "reconnects": cam.reconnects,
        },
        "link": {
            "state": link.state,
            "port": d.cfg.stepper.port,
            "firmware": link.firmware,
            "last_error": link.last_error,
            "controller_estop": link.controller_estopped,
            "counters": link.counters.snapshot(),
        },
        "faults": list(d.faults),
        "recording": None if d.latest is None or d.latest.recording is None else asdict(d.latest.recording),
    }
