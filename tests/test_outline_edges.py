"""The outline as a measurement (clothd/core/outline_edges.py) and the aperture's whitening, on synthetic
frames whose truth is known exactly."""

from __future__ import annotations

import numpy as np
import pytest

from clothd.core.camera_model import CameraModel
from clothd.core.features import aperture_whitening
from clothd.core.mesh import QuadMesh
from clothd.core.outline_edges import OutlineEdges
from clothd.core.segmentation import ClothColour

pytestmark = pytest.mark.clock_free

W_PX, H_PX, F_PX = 320, 240, 450.0


def _frame(shift_px: tuple[float, float]) -> np.ndarray:
    """A blue rectangle (x 100..220, y 70..170 px, moved by shift_px) on a grey, noisy background; its
    edges are area-sampled (8x supersampled), so a sub-pixel shift moves them by exactly that much."""
    ss = 8
    ys, xs = np.mgrid[0 : H_PX * ss, 0 : W_PX * ss]
    x, y = (xs + 0.5) / ss - 0.5 - shift_px[0], (ys + 0.5) / ss - 0.5 - shift_px[1]
    inside = ((x >= 100) & (x < 220) & (y >= 70) & (y < 170)).astype(np.float32)
    cover = inside.reshape(H_PX, ss, W_PX, ss).mean(axis=(1, 3))[..., None]
    cloth, grey = np.array([150.0, 70.0, 30.0]), np.array([90.0, 90.0, 90.0])
    noise = np.random.default_rng(3).normal(0.0, 2.0, (H_PX, W_PX, 3))
    return np.clip(cover * cloth + (1 - cover) * grey + noise, 0, 255).astype(np.uint8)


def _setup() -> tuple[OutlineEdges, np.ndarray, CameraModel]:
    camera = CameraModel.ideal(W_PX, H_PX, F_PX, 1.0)
    corners_px = np.array([[99.5, 69.5], [219.5, 69.5], [219.5, 169.5], [99.5, 169.5]])
    corners_m = camera.backproject_to_plane(corners_px)[:, :2]
    mesh = QuadMesh.covering(corners_m, 6, 5)
    nodes = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(mesh.n_nodes)])
    # Lab (a, b) of the grey background: neutral, 128; the blue cloth is far from it.
    edges = OutlineEdges(mesh, ClothColour((128.0, 128.0), 15.0), camera, 4, 4.0, 100.0)
    first = edges.measure(_frame((0.0, 0.0)), nodes)
    assert not first.ok.any()  # the first frame only sets the offsets
    return edges, nodes, camera


def test_the_outline_measures_a_shift_across_each_edge_only() -> None:
    edges, nodes, camera = _setup()
    shift = np.array([1.3, -0.6])
    m = edges.measure(_frame((shift[0], shift[1])), nodes)
    assert m.ok.all()
    predicted = camera.project(_blend(nodes, edges))
    moved = m.px - predicted
    # Top and bottom sides see the y shift, left and right the x shift; along its edge a point stays.
    top_bottom, left_right = slice(0, 8), slice(8, 16)
    # Each point to within 0.3 px (the threshold's crossing depends a little on where the edge falls in a
    # pixel), their mean to within 0.1 px.
    np.testing.assert_allclose(moved[top_bottom, 1], shift[1], atol=0.3)
    np.testing.assert_allclose(moved[top_bottom, 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(moved[left_right, 0], shift[0], atol=0.3)
    assert abs(moved[top_bottom, 1].mean() - shift[1]) < 0.1
    assert abs(moved[left_right, 0].mean() - shift[0]) < 0.1
    np.testing.assert_allclose(moved[left_right, 1], 0.0, atol=1e-9)
    # Whitened, a measurement keeps its weight across the edge and next to none along it.
    normal = np.array([0.0, 1.0])
    np.testing.assert_allclose(m.whiten[0] @ normal, normal, atol=1e-9)
    assert np.linalg.norm(m.whiten[0] @ np.array([1.0, 0.0])) <= 0.1 + 1e-9


def test_an_edge_out_of_reach_is_not_measured() -> None:
    edges, nodes, _ = _setup()
    m = edges.measure(_frame((9.0, 0.0)), nodes)  # beyond the 4 px search on the left and right
    assert not m.ok[8:].any()


def _blend(nodes: np.ndarray, edges: OutlineEdges) -> np.ndarray:
    return np.einsum("nk,nkd->nd", edges.binding.weights, nodes[edges.binding.nodes])


def test_aperture_whitening_leaves_corners_and_discounts_along_stripes() -> None:
    ys, xs = np.mgrid[0:64, 0:64].astype(np.float64)
    rng = np.random.default_rng(0)
    stripes = (128 + 60 * np.cos(2 * np.pi * (xs + ys) / 6.0)).astype(np.uint8)  # wales along (1, -1)
    blobs = np.clip(128 + 40 * rng.standard_normal((64, 64)), 0, 255).astype(np.uint8)
    pt = np.array([[32.0, 32.0]])
    w_stripes = aperture_whitening(stripes, pt, 11, 100.0)[0]
    along, across = np.array([1.0, -1.0]) / np.sqrt(2), np.array([1.0, 1.0]) / np.sqrt(2)
    np.testing.assert_allclose(w_stripes @ across, across, atol=1e-6)
    assert np.linalg.norm(w_stripes @ along) <= 0.1 + 1e-6  # the cap: variance ratio 100
    w_blobs = aperture_whitening(blobs, pt, 11, 100.0)[0]
    assert np.linalg.eigvalsh(w_blobs).min() > 0.5  # texture in every direction: nearly isotropic
