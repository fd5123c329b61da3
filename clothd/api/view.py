"""The annotated live view (GET /api/v1/view.mjpg): the camera frame with what the tracker believes, in
the original's figure style (clothd/overlay.py), plus the pose arrow and the setpoint as a ghost outline.

Frames are drawn and JPEG-encoded on their own thread at `view_fps`, and only while someone watches,
so the view never costs the loop a tick.
"""

from __future__ import annotations

import math
import threading
from typing import TYPE_CHECKING

import cv2
import numpy as np

from clothd.overlay import draw_estimate

if TYPE_CHECKING:
    from clothd.daemon import Daemon

ARROW_BGR, GHOST_BGR = (255, 255, 255), (200, 120, 255)
ARROW_M = 0.08


class ViewPublisher:
    def __init__(self, daemon: Daemon, fps: float) -> None:
        self.daemon = daemon
        self.period_s = 1.0 / fps
        self.viewers = 0
        self.cond = threading.Condition()
        self.jpeg: bytes | None = None
        self.index = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start drawing; the app's lifespan may run more than once (tests), so this restarts cleanly."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="view", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            if self.viewers == 0:
                continue
            jpeg = self.render()
            if jpeg is None:
                continue
            with self.cond:
                self.jpeg, self.index = jpeg, self.index + 1
                self.cond.notify_all()

    def render(self) -> bytes | None:
        d = self.daemon
        frame, result = d.latest_frame, d.latest
        if frame is None:
            return None
        img = frame.image
        est = result.estimate if result else None
        tracker = d.tracker
        if est is not None and est.status == "tracking":
            node_px = None if est.nodes_m is None else d.camera_model.project(est.nodes_m.reshape(-1, 3))
            img = draw_estimate(img, est, tracker.mesh_shape, node_px)
            self._arrow(img, est.pose)
        else:
            img = img.copy()
        if d.setpoint.pose is not None and tracker.mesh is not None:
            self._ghost(img, d.setpoint.pose, tracker.mesh.width_m, tracker.mesh.height_m)
        ok, jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
        return jpeg.tobytes() if ok else None

    def _project(self, xy: np.ndarray) -> np.ndarray:
        return self.daemon.camera_model.project(np.column_stack([xy, np.zeros(len(xy))]))

    def _arrow(self, img: np.ndarray, pose: np.ndarray) -> None:
        tip = pose[:2] + ARROW_M * np.array([math.cos(pose[2]), math.sin(pose[2])])
        a, b = self._project(np.stack([pose[:2], tip])).round().astype(int)
        cv2.arrowedLine(
            img, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), ARROW_BGR, 2, cv2.LINE_AA, 0, 0.25
        )

    def _ghost(self, img: np.ndarray, pose: np.ndarray, width_m: float, height_m: float) -> None:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        w, h = width_m / 2, height_m / 2
        body = np.array([[-w, -h], [w, -h], [w, h], [-w, h]])
        world = body @ np.array([[c, s], [-s, c]]) + pose[:2]
        px = self._project(world).round().astype(np.int32)
        cv2.polylines(img, [px.reshape(-1, 1, 2)], True, GHOST_BGR, 2, cv2.LINE_AA)
