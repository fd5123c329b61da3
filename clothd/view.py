"""The annotated live view (GET /api/v1/view.mjpg): the camera frame with what the tracker believes, in
the original's figure style (clothd/overlay.py), plus the pose arrow and the setpoint as a ghost
outline. Drawn in the compute process, only on ticks when someone watches, at `api.view_fps`."""

from __future__ import annotations

import math

import cv2
import numpy as np

from clothd.core.camera_model import CameraModel
from clothd.core.control import Setpoint
from clothd.core.messages import Estimate
from clothd.core.tracker import Tracker
from clothd.overlay import draw_estimate

ARROW_BGR, GHOST_BGR = (255, 255, 255), (200, 120, 255)
ARROW_M = 0.08
JPEG_QUALITY = 80


class ViewRenderer:
    def __init__(self, camera: CameraModel) -> None:
        self.camera = camera

    def render(
        self, image: np.ndarray, est: Estimate | None, tracker: Tracker, setpoint: Setpoint
    ) -> bytes | None:
        if est is not None and est.status == "tracking":
            node_px = None if est.nodes_m is None else self.camera.project(est.nodes_m.reshape(-1, 3))
            img = draw_estimate(image, est, tracker.mesh_shape, node_px)
            self._arrow(img, est.pose)
        else:
            img = image.copy()
        if setpoint.pose is not None and tracker.mesh is not None:
            self._ghost(img, setpoint.pose, tracker.mesh.width_m, tracker.mesh.height_m)
        ok, jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        return jpeg.tobytes() if ok else None

    def _project(self, xy: np.ndarray) -> np.ndarray:
        return self.camera.project(np.column_stack([xy, np.zeros(len(xy))]))

    def _arrow(self, img: np.ndarray, pose: np.ndarray) -> None:
        tip = pose[:2] + ARROW_M * np.array([math.cos(pose[2]), math.sin(pose[2])])
        a, b = self._project(np.stack([pose[:2], tip])).round().astype(int)
        start, end = (int(a[0]), int(a[1])), (int(b[0]), int(b[1]))
        cv2.arrowedLine(img, start, end, ARROW_BGR, 2, cv2.LINE_AA, 0, 0.25)

    def _ghost(self, img: np.ndarray, pose: np.ndarray, width_m: float, height_m: float) -> None:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        w, h = width_m / 2, height_m / 2
        body = np.array([[-w, -h], [w, -h], [w, h], [-w, h]])
        world = body @ np.array([[c, s], [-s, c]]) + pose[:2]
        px = self._project(world).round().astype(np.int32)
        cv2.polylines(img, [px.reshape(-1, 1, 2)], True, GHOST_BGR, 2, cv2.LINE_AA)
