"""`clothd replay`: run the tracker over recorded footage and write what it believed.

DIR/estimates.npz   t_s (F,), pose (F, 3), nodes_m (F, ny, nx, 3) for the mesh-based models,
                    feature_id (n,), meas_px (F, n, 2), pred_px (F, n, 2) (NaN where a feature is not alive)
DIR/summary.json    per-frame residuals and counts, per-stage timing, real-time factor
DIR/overlay.mp4     the original's figure style: predicted features green, measured red, a yellow line
                    between them, and the mesh
The format is documented in docs/replay-format.md.
"""

from __future__ import annotations

import json
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from clothd.config import TrackerConfig
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout
from clothd.core.messages import Estimate
from clothd.core.tracker import Tracker
from clothd.drivers.footage import CommandSchedule, Footage, open_footage
from clothd.overlay import draw_estimate

TIMED_STAGES = ("prepare", "predict", "klt", "update", "resample", "tick")


# Start-up (kernel compilation, initialisation) falls in the first ticks; the steady rate leaves them out.
_STARTUP_TICKS = 3


@dataclass(frozen=True)
class ReplayResult:
    frames: int
    wall_s: float
    footage_s: float
    steady_wall_s: float  # wall time after the first _STARTUP_TICKS ticks
    steady_footage_s: float

    @property
    def realtime_factor(self) -> float:
        return self.footage_s / self.wall_s if self.wall_s > 0 else float("inf")

    @property
    def steady_realtime_factor(self) -> float:
        return self.steady_footage_s / self.steady_wall_s if self.steady_wall_s > 0 else float("inf")


def _camera(footage: Footage, override: Path | None, cfg: TrackerConfig, first: np.ndarray) -> CameraModel:
    path = override or footage.camera_json
    if path is not None:
        return CameraModel.load(path)
    h, w = first.shape[:2]
    return CameraModel.ideal(w, h, cfg.camera.f_px, cfg.camera.distance_m)


def replay(
    source: Path,
    out_dir: Path,
    cfg: TrackerConfig,
    roi: str = "auto",
    camera_json: Path | None = None,
    commands_csv: Path | None = None,
    write_video: bool = True,
) -> ReplayResult:
    footage = open_footage(source)
    frames = footage.frames()
    try:
        t0_s, first = next(frames)
    except StopIteration:
        raise ValueError(f"{source}: no frames") from None
    camera = _camera(footage, camera_json, cfg, first)
    conveyor = ConveyorLayout.load(footage.table_json) if footage.table_json else None
    cmd_path = commands_csv or footage.commands_csv
    schedule = CommandSchedule(cmd_path, conveyor.n_modules) if (cmd_path and conveyor) else None
    tracker = Tracker(cfg, camera, conveyor, roi=roi, clock=time.perf_counter)
    out_dir.mkdir(parents=True, exist_ok=True)
    video = None
    if write_video:
        h, w = first.shape[:2]
        video = cv2.VideoWriter(
            str(out_dir / "overlay.mp4"), cv2.VideoWriter.fourcc(*"mp4v"), footage.fps, (w, h)
        )
    estimates: list[Estimate] = []
    # The overlay is drawn and encoded on a second thread (OpenCV releases the GIL), in frame order.
    drawer = ThreadPoolExecutor(max_workers=1)
    pending: deque[Future[None]] = deque()
    start = steady_start = time.perf_counter()
    t_s, image = t0_s, first
    try:
        while True:
            est = tracker.step(image, t_s, schedule.at(t_s) if schedule else None)
            estimates.append(est)
            if len(estimates) == _STARTUP_TICKS:
                steady_start = time.perf_counter()
            if video is not None:
                nodes_px = camera.project(est.nodes_m.reshape(-1, 3)) if est.nodes_m is not None else None
                pending.append(drawer.submit(_write_overlay, video, image, est, tracker.mesh_shape, nodes_px))
                while len(pending) > 4:
                    pending.popleft().result()
            try:
                t_s, image = next(frames)
            except StopIteration:
                break
    finally:
        for fut in pending:
            fut.result()
        drawer.shutdown()
        if video is not None:
            video.release()
    end = time.perf_counter()
    wall = end - start
    write_estimates(out_dir / "estimates.npz", estimates)
    steady_frames = max(len(estimates) - _STARTUP_TICKS, 0)
    result = ReplayResult(
        len(estimates), wall, len(estimates) / footage.fps, end - steady_start, steady_frames / footage.fps
    )
    _write_summary(out_dir / "summary.json", estimates, result, cfg)
    return result


def _write_overlay(
    video: cv2.VideoWriter,
    image: np.ndarray,
    est: Estimate,
    mesh_shape: tuple[int, int] | None,
    nodes_px: np.ndarray | None,
) -> None:
    video.write(draw_estimate(image, est, mesh_shape, nodes_px))


def write_estimates(path: Path, estimates: list[Estimate]) -> None:
    ids = np.unique(np.concatenate([e.feature_id for e in estimates])) if estimates else np.zeros(0, np.int64)
    col = {int(i): k for k, i in enumerate(ids)}
    F, n = len(estimates), len(ids)
    meas = np.full((F, n, 2), np.nan, np.float32)
    pred = np.full((F, n, 2), np.nan, np.float32)
    for f, e in enumerate(estimates):
        cols = np.array([col[int(i)] for i in e.feature_id], dtype=np.int64)
        if len(cols):
            meas[f, cols] = e.meas_px
            pred[f, cols] = e.pred_px
    arrays: dict[str, np.ndarray] = {
        "t_s": np.array([e.t_s for e in estimates]),
        "pose": np.array([e.pose for e in estimates]),
        "feature_id": ids,
        "meas_px": meas,
        "pred_px": pred,
    }
    shapes = {e.nodes_m.shape for e in estimates if e.nodes_m is not None}
    if len(shapes) == 1:
        shape = shapes.pop()
        arrays["nodes_m"] = np.array(
            [e.nodes_m if e.nodes_m is not None else np.full(shape, np.nan) for e in estimates], np.float32
        )
    np.savez_compressed(path, allow_pickle=False, **arrays)


def _stage_stats(estimates: list[Estimate]) -> dict[str, dict[str, float]]:
    out = {}
    for stage in TIMED_STAGES:
        vals = np.array([e.timing_s[stage] for e in estimates[1:] if stage in e.timing_s]) * 1e3
        if len(vals):
            out[stage] = {
                "p50_ms": float(np.median(vals)),
                "p99_ms": float(np.percentile(vals, 99)),
                "max_ms": float(vals.max()),
            }
    return out


def _write_summary(path: Path, estimates: list[Estimate], result: ReplayResult, cfg: TrackerConfig) -> None:
    per_frame = []
    for e in estimates:
        r = e.residual_px
        per_frame.append(
            {
                "t_s": e.t_s,
                "status": e.status,
                "features": len(e.feature_id),
                "accepted": e.stats.accepted,
                "rejected": e.stats.rejected,
                "nis_per_measurement": e.stats.nis_per_measurement,
                "residual_mean_px": float(r.mean()) if len(r) else None,
                "residual_worst_px": float(r.max()) if len(r) else None,
            }
        )
    summary = {
        "model": cfg.model,
        "use_input": cfg.use_input,
        "frames": result.frames,
        "wall_s": result.wall_s,
        "realtime_factor": result.realtime_factor,
        "steady_realtime_factor": result.steady_realtime_factor,
        "timing": _stage_stats(estimates),
        "per_frame": per_frame,
    }
    path.write_text(json.dumps(summary, indent=1) + "\n")
