"""`clothd replay`: run the tracker over recorded footage and write what it believed.

DIR/estimates.npz   t_s (F,), pose (F, 3), nodes_m (F, ny, nx, 3) for the rigid and mesh models,
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
from clothd.core.messages import Estimate
from clothd.formats import write_estimates
from clothd.outputs.view import draw_estimate
from clothd.tools.offline import OfflineTracking

TIMED_STAGES = ("prepare", "predict", "klt", "update", "estimate", "resample", "tick", "heights")


# Start-up (kernel compilation, initialisation) falls in the first ticks; the steady rate leaves them out.
_STARTUP_TICKS = 3
_OVERLAYS_AHEAD = 4  # frames queued for the drawing thread before tracking waits for it


@dataclass(frozen=True)
class ReplayResult:
    camera: str  # the camera.json used, or the ideal camera assumed
    views: dict[str, int]  # each further camera's name: how many frames had a view of it
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


def replay(
    source: Path,
    out_dir: Path,
    cfg: TrackerConfig,
    roi: str = "auto",
    camera_json: Path | None = None,
    commands_csv: Path | None = None,
    write_video: bool = True,
    cameras: int | None = None,
) -> ReplayResult:
    """cameras: a recording's first this many (None: every one it holds)."""
    progress = f"replaying {source.name}"
    run = OfflineTracking(source, cfg, camera_json, commands_csv, roi, progress=progress, cameras=cameras)
    fps = run.footage.fps
    out_dir.mkdir(parents=True, exist_ok=True)
    video = None
    if write_video:
        h, w = run.frame_shape
        video = cv2.VideoWriter(str(out_dir / "overlay.mp4"), cv2.VideoWriter.fourcc(*"mp4v"), fps, (w, h))
    estimates: list[Estimate] = []
    # The overlay is drawn and encoded on a second thread (OpenCV releases the GIL), in frame order.
    drawer = ThreadPoolExecutor(max_workers=1)
    pending: deque[Future[None]] = deque()
    start = steady_start = time.perf_counter()
    try:
        for _, image, est in run:
            estimates.append(est)
            if len(estimates) == _STARTUP_TICKS:
                steady_start = time.perf_counter()
            if video is not None:
                pending.append(drawer.submit(_write_overlay, video, image, est, run.camera_model))
                while len(pending) > _OVERLAYS_AHEAD:
                    pending.popleft().result()
    finally:
        for fut in pending:
            fut.result()
        drawer.shutdown()
        if video is not None:
            video.release()
    end = time.perf_counter()
    write_estimates(out_dir / "estimates.npz", estimates)
    steady_frames = max(len(estimates) - _STARTUP_TICKS, 0)
    result = ReplayResult(
        run.camera_source,
        run.views_given,
        len(estimates),
        end - start,
        len(estimates) / fps,
        end - steady_start,
        steady_frames / fps,
    )
    _write_summary(out_dir / "summary.json", estimates, result, cfg)
    return result


def _write_overlay(
    video: cv2.VideoWriter, image: np.ndarray, est: Estimate, camera_model: CameraModel
) -> None:
    video.write(draw_estimate(image, est, camera_model))


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
                "t_s": e.frame_t_s,
                "status": e.status,
                "flatness_basis": e.flatness_basis.value,
                "features": len(e.feature_id),
                "accepted": e.stats.accepted,
                "rejected": e.stats.rejected,
                "nis_per_measurement": e.stats.nis_per_measurement,
                "residual_mean_px": float(r.mean()) if len(r) else None,
                "residual_worst_px": float(r.max()) if len(r) else None,
            }
        )
    summary = {
        "camera": result.camera,
        "cameras": 1 + len(result.views),
        "views": result.views,
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
