"""`hwsim preview`: a video of a recording, with the truth mesh drawn over it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from hwsim.camera import Camera
from hwsim.paths import frame_path
from hwsim.truth import Truth

MESH_STRIDE = 5  # draw every 5th truth row and column
MESH_BGR = (80, 220, 255)


def write_preview(recording: Path, out: Path | None = None, fps: float | None = None) -> Path:
    truth = Truth.load(recording)
    camera = Camera.load(recording / "camera.json")
    out = out or recording / "preview.mp4"
    if fps is None:
        fps = 1.0 / float(truth.t_s[1] - truth.t_s[0]) if len(truth.t_s) > 1 else 30.0
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter.fourcc(*"mp4v"), fps, (camera.width, camera.height))
    if not writer.isOpened():
        raise OSError(f"cannot open a video writer for {out}")
    try:
        for k, t_s in enumerate(truth.t_s):
            img = cv2.imread(str(frame_path(recording, k)))
            if img is None:
                raise FileNotFoundError(frame_path(recording, k))
            px = camera.project(truth.nodes_m[k])
            lines = [px[j, ::1] for j in range(0, px.shape[0], MESH_STRIDE)]
            lines += [px[:, i] for i in range(0, px.shape[1], MESH_STRIDE)]
            poly = [np.round(line * 4).astype(np.int32) for line in lines]  # 2 fractional bits
            cv2.polylines(img, poly, False, MESH_BGR, 1, cv2.LINE_AA, shift=2)
            height_mm = truth.nodes_m[k][..., 2].max() * 1e3
            label = f"t {t_s:5.2f} s   max height {height_mm:4.1f} mm"
            cv2.putText(img, label, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
            writer.write(img)
    finally:
        writer.release()
    return out
