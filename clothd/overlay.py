"""Drawing what the tracker believes over a frame, in the original report's figure style: predicted
features as green crosses, measured ones red, a yellow line between each pair, and the mesh."""

from __future__ import annotations

import cv2
import numpy as np

from clothd.core.messages import Estimate

GREEN, RED, YELLOW, MESH_BGR = (0, 220, 0), (0, 0, 255), (0, 230, 255), (255, 160, 40)
_SHIFT = 2  # fractional bits for sub-pixel drawing
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


def draw_estimate(
    image: np.ndarray, est: Estimate, mesh_shape: tuple[int, int] | None, node_px: np.ndarray | None = None
) -> np.ndarray:
    """A copy of `image` (BGR) with the estimate drawn on. node_px (ny*nx, 2): the mesh nodes projected
    (given by the caller, who knows the camera); without it the mesh is not drawn."""
    img = image.copy()
    if node_px is not None and mesh_shape is not None:
        g = _fixed(node_px.reshape(*mesh_shape, 2))
        lines = [np.ascontiguousarray(g[j]) for j in range(g.shape[0])]
        lines += [np.ascontiguousarray(g[:, i]) for i in range(g.shape[1])]
        cv2.polylines(img, lines, False, MESH_BGR, 1, cv2.LINE_AA, _SHIFT)
    ok = ~np.isnan(est.meas_px[:, 0]) if len(est.meas_px) else np.zeros(0, bool)
    _segments(img, est.meas_px[ok], est.pred_px[ok], YELLOW)
    _crosses(img, est.meas_px[ok], RED)
    _crosses(img, est.pred_px, GREEN)
    label = f"t {est.t_s:6.2f} s  {est.status}  features {len(est.feature_id)}"
    cv2.putText(img, label, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img
