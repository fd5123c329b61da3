"""Drawing what the tracker believes over a frame, in the original report's figure style: predicted
features as green crosses, measured ones red, a yellow line between each pair, and the mesh, its edges
that have risen off the table coloured by height (yellow at 1 mm to red at 15 mm and above).

`draw_estimate` serves `clothd replay`'s overlay video, `draw_tracking` (what it draws, from arrays)
`clothd export`'s /camera/annotated channel; `ViewRenderer` the live annotated view
(GET /api/v1/view.mjpg), which adds the pose arrow, the setpoint as a ghost outline, and each ridge the
flatness finds as a magenta line along it, labelled with its height. The live view is
drawn in the compute process, only on ticks when someone watches, at `api.view_fps`."""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Iterator

import cv2
import numpy as np

from clothd.core.camera_model import CameraModel
from clothd.core.control import Setpoint
from clothd.core.flatness import Flatness, Ridge
from clothd.core.messages import Estimate
from clothd.core.workspace import cloth_corners_m

GREEN, RED, YELLOW, MESH_BGR = (0, 220, 0), (0, 0, 255), (0, 230, 255), (255, 160, 40)
ARROW_BGR, GHOST_BGR, RIDGE_BGR = (255, 255, 255), (200, 120, 255), (255, 0, 255)
ARROW_M = 0.08
JPEG_QUALITY = 80
_SHIFT = 2  # fractional bits for sub-pixel drawing
RAISED_M, RAISED_FULL_M = 0.001, 0.015  # edges this high are drawn yellow, this high and more red
_CROSS_PX = 3


def _fixed(px: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(px) * (1 << _SHIFT)).astype(np.int32)


def _segments(img: np.ndarray, starts: np.ndarray, ends: np.ndarray, colour: tuple[int, int, int]) -> None:
    """Draw n line segments (n, 2) -> (n, 2) in one call (OpenCV draws them without the GIL)."""
    if len(starts):
        segments = list(np.stack([_fixed(starts), _fixed(ends)], axis=1))
        cv2.polylines(img, segments, False, colour, 1, cv2.LINE_AA, _SHIFT)


def _crosses(img: np.ndarray, px: np.ndarray, colour: tuple[int, int, int]) -> None:
    p = px[~np.isnan(px[:, 0])] if len(px) else px
    d = np.array([_CROSS_PX, _CROSS_PX], float)
    _segments(img, np.concatenate([p - d, p + d * [-1, 1]]), np.concatenate([p + d, p + d * [1, -1]]), colour)


def _raised_edges(img: np.ndarray, px: np.ndarray, z_m: np.ndarray) -> None:
    """Over the mesh (px (ny, nx, 2), fixed point), its row and column edges higher than RAISED_M at
    either end, thicker, coloured from yellow to red by that height."""
    for a, b, za, zb in (
        (px[:, :-1], px[:, 1:], z_m[:, :-1], z_m[:, 1:]),
        (px[:-1], px[1:], z_m[:-1], z_m[1:]),
    ):
        height = np.maximum(za, zb)
        for j, i in zip(*np.nonzero(height > RAISED_M), strict=True):
            f = min(1.0, (height[j, i] - RAISED_M) / (RAISED_FULL_M - RAISED_M))
            colour = (0, round(230 * (1.0 - f)), 255)
            p0, p1 = (int(a[j, i, 0]), int(a[j, i, 1])), (int(b[j, i, 0]), int(b[j, i, 1]))
            cv2.line(img, p0, p1, colour, 2, cv2.LINE_AA, _SHIFT)


def draw_estimate(
    image: np.ndarray, est: Estimate, camera_model: CameraModel, when: str | None = None
) -> np.ndarray:
    """A copy of `image` (BGR) with the estimate drawn on, the mesh projected through camera_model.
    `when` labels the frame's time (default: its time in the footage, seconds)."""
    label = f"{when or f't {est.frame_t_s:6.2f} s'}  {est.status}  features {len(est.feature_id)}"
    return draw_tracking(image, est.nodes_m, est.meas_px, est.pred_px, camera_model, label)


def draw_tracking(
    image: np.ndarray,
    nodes_m: np.ndarray | None,
    meas_px: np.ndarray,
    pred_px: np.ndarray,
    camera_model: CameraModel,
    label: str,
) -> np.ndarray:
    """A copy of `image` (BGR) with the mesh nodes_m (ny, nx, 3) projected through camera_model, its
    risen edges coloured by height, the features where the estimate places them (pred_px (n, 2), green)
    and where they were measured (meas_px (n, 2), red, NaN where not) joined by their residual, and a
    label in the corner."""
    img = image.copy()
    if nodes_m is not None:
        ny, nx = nodes_m.shape[:2]
        g = _fixed(camera_model.project(nodes_m.reshape(-1, 3)).reshape(ny, nx, 2))
        lines = [np.ascontiguousarray(g[j]) for j in range(ny)]
        lines += [np.ascontiguousarray(g[:, i]) for i in range(nx)]
        cv2.polylines(img, lines, False, MESH_BGR, 1, cv2.LINE_AA, _SHIFT)
        _raised_edges(img, g, nodes_m[..., 2])
    ok = ~np.isnan(meas_px[:, 0]) if len(meas_px) else np.zeros(0, bool)
    _segments(img, meas_px[ok], pred_px[ok], YELLOW)
    _crosses(img, meas_px[ok], RED)
    _crosses(img, pred_px, GREEN)
    cv2.putText(img, label, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def wall_clock_label(t_mono_s: float) -> str:
    """A capture time on the host's monotonic clock as the wall-clock time an operator reads."""
    t_unix_s = time.time() - (time.monotonic() - t_mono_s)
    return time.strftime("%H:%M:%S", time.localtime(t_unix_s)) + f".{int(t_unix_s * 10) % 10}"


class ViewRenderer:
    def __init__(self, camera_model: CameraModel) -> None:
        self.camera_model = camera_model

    def render(
        self, image: np.ndarray, est: Estimate | None, setpoint: Setpoint, flatness: Flatness | None = None
    ) -> bytes | None:
        if est is not None and est.tracking:
            img = draw_estimate(image, est, self.camera_model, wall_clock_label(est.frame_t_s))
            self._arrow(img, est.pose)
            for ridge in flatness.ridges if flatness is not None else ():
                self._ridge(img, ridge)
        else:
            img = image.copy()
        if setpoint.pose is not None and est is not None and est.cloth_size_m is not None:
            self._ghost(img, setpoint.pose, est.cloth_size_m)
        ok, jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        return jpeg.tobytes() if ok else None

    def _project(self, xy: np.ndarray) -> np.ndarray:
        return self.camera_model.project(np.column_stack([xy, np.zeros(len(xy))]))

    def _arrow(self, img: np.ndarray, pose: np.ndarray) -> None:
        tip = pose[:2] + ARROW_M * np.array([math.cos(pose[2]), math.sin(pose[2])])
        a, b = self._project(np.stack([pose[:2], tip])).round().astype(int)
        start, end = (int(a[0]), int(a[1])), (int(b[0]), int(b[1]))
        cv2.arrowedLine(img, start, end, ARROW_BGR, 2, cv2.LINE_AA, 0, 0.25)

    def _ridge(self, img: np.ndarray, ridge: Ridge) -> None:
        along = np.array([math.cos(ridge.direction_rad), math.sin(ridge.direction_rad)])
        middle = ridge.quad_centres_m.mean(axis=0)
        reach = (ridge.quad_centres_m - middle) @ along
        ends = middle + np.outer([reach.min(), reach.max()], along)
        a, b = self._project(ends).round().astype(int)
        cv2.line(img, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), RIDGE_BGR, 3, cv2.LINE_AA)
        label = f"{ridge.height_m * 1e3:.1f} mm"
        cv2.putText(
            img, label, (int(b[0]) + 6, int(b[1])), cv2.FONT_HERSHEY_SIMPLEX, 0.5, RIDGE_BGR, 1, cv2.LINE_AA
        )

    def _ghost(self, img: np.ndarray, pose: np.ndarray, size_m: tuple[float, float]) -> None:
        px = self._project(cloth_corners_m(pose, size_m)).round().astype(np.int32)
        cv2.polylines(img, [px.reshape(-1, 1, 2)], True, GHOST_BGR, 2, cv2.LINE_AA)


class ViewBoard:
    """The annotated view between the loop's thread, which asks the compute to draw it only while someone
    watches and posts each one, and the daemon's end of the API process's channel (api/process.py), which
    sends each new one while the API process says someone watches. Three values behind a lock, never held
    for more than a copy."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._watchers = 0
        self._jpeg: bytes | None = None
        self._index = 0

    @contextlib.contextmanager
    def watching(self) -> Iterator[None]:
        with self._lock:
            self._watchers += 1
        try:
            yield
        finally:
            with self._lock:
                self._watchers -= 1

    @property
    def watched(self) -> bool:
        with self._lock:
            return self._watchers > 0

    def post(self, jpeg: bytes) -> None:
        with self._lock:
            self._jpeg, self._index = jpeg, self._index + 1

    def latest(self) -> tuple[bytes | None, int]:
        """The newest view and its number (0 before the first)."""
        with self._lock:
            return self._jpeg, self._index
