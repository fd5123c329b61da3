"""clothd.core.mesh: shape functions, binding, covering a rectangle, the measurement Jacobian."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from clothd.core.camera_model import CameraModel
from clothd.core.mesh import QuadMesh, blend, measurement_jacobian, shape_functions

pytestmark = pytest.mark.clock_free

CORNERS_XI_ETA = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])  # N1..N4


def _mesh() -> QuadMesh:
    return QuadMesh(7, 5, np.array([-0.21, 0.13]), 0.4, 0.42, 0.28)


def test_shape_functions_partition_unity() -> None:
    rng = np.random.default_rng(10)
    N = shape_functions(rng.uniform(-1, 1, (500, 2)))
    assert N.shape == (500, 4)
    np.testing.assert_allclose(N.sum(axis=1), 1.0, atol=1e-15)
    assert (N >= 0).all()


def test_shape_functions_are_exact_at_the_nodes() -> None:
    np.testing.assert_allclose(shape_functions(CORNERS_XI_ETA), np.eye(4), atol=0)
    np.testing.assert_allclose(shape_functions(np.zeros((1, 2))), [[0.25] * 4])


def test_rest_nodes_follow_the_grid_axes() -> None:
    mesh = _mesh()
    nodes = mesh.rest_nodes_m()
    assert nodes.shape == (5, 7, 2)
    a1 = np.array([math.cos(0.4), math.sin(0.4)])
    a2 = np.array([-math.sin(0.4), math.cos(0.4)])
    np.testing.assert_allclose(nodes[0, 0], mesh.origin_m)
    np.testing.assert_allclose(nodes[0, 1] - nodes[0, 0], 0.07 * a1, atol=1e-15)
    np.testing.assert_allclose(nodes[1, 0] - nodes[0, 0], 0.07 * a2, atol=1e-15)
    np.testing.assert_allclose(nodes[4, 6], mesh.origin_m + 0.42 * a1 + 0.28 * a2, atol=1e-15)
    assert (mesh.n_nodes, mesh.n_quads) == (35, 24)


def test_binding_the_nodes_round_trips() -> None:
    mesh = _mesh()
    nodes = mesh.rest_nodes_m()
    b = mesh.bind(nodes.reshape(-1, 2))
    assert b.inside.all()
    assert ((b.quad >= 0) & (b.quad < mesh.n_quads)).all()
    assert (np.abs(b.xi_eta) <= 1).all()
    # Each node carries weight 1 for itself in whatever quad it landed in, and no other node any weight.
    own = b.nodes == np.arange(mesh.n_nodes)[:, None]
    assert own.sum(axis=1).tolist() == [1] * mesh.n_nodes
    np.testing.assert_allclose(b.weights[own], 1.0, atol=1e-9)
    np.testing.assert_allclose(b.weights[~own], 0.0, atol=1e-9)
    # Interior nodes take the cell they are the lowest corner of; the far edges take the last cell.
    j, i = 2, 3
    assert b.quad[j * 7 + i] == j * 6 + i
    np.testing.assert_allclose(b.xi_eta[j * 7 + i], [-1, -1], atol=1e-9)
    assert b.quad[4 * 7 + 6] == 3 * 6 + 5
    np.testing.assert_allclose(b.xi_eta[4 * 7 + 6], [1, 1], atol=1e-9)


def test_bind_corner_order_and_local_coordinates() -> None:
    mesh = _mesh()
    nodes = mesh.rest_nodes_m()
    # A point a quarter of the way along a₁ and three quarters along a₂ inside cell (j, i) = (1, 2).
    p = nodes[1, 2] + 0.25 * (nodes[1, 3] - nodes[1, 2]) + 0.75 * (nodes[2, 2] - nodes[1, 2])
    b = mesh.bind(p[None])
    assert b.quad[0] == 1 * 6 + 2
    np.testing.assert_allclose(b.xi_eta[0], [-0.5, 0.5], atol=1e-12)
    assert b.nodes[0].tolist() == [1 * 7 + 2, 1 * 7 + 3, 2 * 7 + 3, 2 * 7 + 2]


def test_blend_of_rest_nodes_reproduces_the_points_and_edges_are_bound() -> None:
    mesh = _mesh()
    rng = np.random.default_rng(11)
    nodes = mesh.rest_nodes_m()
    # Random points on the mesh, points on its edges, and points on the interior cell edges.
    fi, fj = rng.uniform(0, 1, 300), rng.uniform(0, 1, 300)
    st = mesh.origin_m + np.column_stack([fi * 0.42, fj * 0.28]) @ mesh.axes
    edges = np.concatenate(
        [
            nodes[0, :-1] + (nodes[0, 1:] - nodes[0, :-1]) * 0.3,
            nodes[-1, :-1] + (nodes[-1, 1:] - nodes[-1, :-1]) * 0.6,
            nodes[:-1, -1] + (nodes[1:, -1] - nodes[:-1, -1]) * 0.5,
            nodes[2, :-1] + (nodes[2, 1:] - nodes[2, :-1]) * 0.5,
        ]
    )
    pts = np.concatenate([st, edges])
    b = mesh.bind(pts)
    assert b.inside.all()
    assert ((b.quad >= 0) & (b.quad < mesh.n_quads)).all()
    world = np.concatenate([nodes, np.zeros((5, 7, 1))], axis=-1).reshape(-1, 3)
    out = blend(world, b)
    np.testing.assert_allclose(out[:, :2], pts, atol=1e-13)
    np.testing.assert_array_equal(out[:, 2], 0.0)


def test_points_outside_are_flagged_and_clamped() -> None:
    mesh = _mesh()
    nodes = mesh.rest_nodes_m()
    a1, a2 = mesh.axes
    outside = np.array([nodes[0, 0] - 0.01 * a1, nodes[4, 3] + 0.02 * a2, nodes[2, 6] + 0.5 * a1])
    b = mesh.bind(np.concatenate([outside, nodes[2, 3][None]]))
    assert b.inside.tolist() == [False, False, False, True]
    assert ((b.quad >= 0) & (b.quad < mesh.n_quads)).all()
    assert (np.abs(b.xi_eta) <= 1).all()
    # Clamped onto the nearest boundary point.
    np.testing.assert_allclose(blend(nodes, b)[:3], [nodes[0, 0], nodes[4, 3], nodes[2, 6]], atol=1e-13)
    assert len(b.subset(b.inside)) == 1


@pytest.mark.parametrize("angle_deg", [0.0, 27.0, -61.0, 90.0, 123.0])
def test_covering_a_rotated_rectangle_puts_nodes_on_its_corners(angle_deg: float) -> None:
    box = cv2.boxPoints(((0.12, -0.07), (0.18, 0.31), angle_deg))  # 0.31 m is the long side
    rng = np.random.default_rng(12)
    corners = box[rng.permutation(4)].astype(np.float64)
    mesh = QuadMesh.covering(corners, 9, 6)
    assert mesh.width_m == pytest.approx(0.31, abs=1e-6)
    assert mesh.height_m == pytest.approx(0.18, abs=1e-6)
    assert -math.pi / 2 < mesh.theta_rad <= math.pi / 2
    nodes = mesh.rest_nodes_m()
    grid_corners = np.array([nodes[0, 0], nodes[0, -1], nodes[-1, -1], nodes[-1, 0]])
    # Each grid corner is one of the rectangle's corners (float32 from boxPoints: ~1e-7).
    dist = np.linalg.norm(grid_corners[:, None] - corners[None], axis=-1)
    assert sorted(dist.argmin(axis=1).tolist()) == [0, 1, 2, 3]
    assert dist.min(axis=1).max() < 1e-6
    # The first axis runs along the long side and the second is it turned +90°.
    a1, a2 = mesh.axes
    assert a1[0] * a2[1] - a1[1] * a2[0] == pytest.approx(1.0)
    np.testing.assert_allclose(np.linalg.norm(nodes[0, -1] - nodes[0, 0]), 0.31, atol=1e-6)


def test_covering_a_square_prefers_the_axis_nearest_s() -> None:
    box = cv2.boxPoints(((0.0, 0.0), (0.2, 0.2), 70.0))
    mesh = QuadMesh.covering(box, 4, 4)
    assert mesh.theta_rad == pytest.approx(math.radians(-20.0), abs=1e-6)


def test_measurement_jacobian_matches_finite_differences() -> None:
    mesh = QuadMesh(4, 3, np.array([-0.15, -0.1]), 0.3, 0.3, 0.2)
    rng = np.random.default_rng(13)
    rest = mesh.rest_nodes_m().reshape(-1, 2)
    # A crumpled cloth: nodes lifted and pushed about, under a tilted camera with distortion.
    nodes = np.column_stack([rest + rng.normal(0, 0.01, rest.shape), rng.uniform(0, 0.05, len(rest))])
    camera = _tilted_camera()
    st = mesh.origin_m + rng.uniform(0, 1, (25, 2)) * [0.3, 0.2] @ mesh.axes
    b = mesh.bind(st)
    pixels, blocks = measurement_jacobian(camera, nodes, b)
    assert blocks.shape == (25, 4, 2, 3)
    np.testing.assert_allclose(pixels, camera.project(blend(nodes, b)), atol=1e-12)
    # The full dh/dx by central differences over every node coordinate.
    h = 1e-6
    numeric = np.empty((25, 2, mesh.n_nodes, 3))
    for n in range(mesh.n_nodes):
        for c in range(3):
            plus, minus = nodes.copy(), nodes.copy()
            plus[n, c] += h
            minus[n, c] -= h
            numeric[:, :, n, c] = (camera.project(blend(plus, b)) - camera.project(blend(minus, b))) / (2 * h)
    dense = np.zeros_like(numeric)
    for i in range(25):
        for k in range(4):
            dense[i, :, b.nodes[i, k], :] += blocks[i, k]
    np.testing.assert_allclose(dense, numeric, rtol=0, atol=1e-6 * np.abs(numeric).max())
    assert np.abs(numeric).max() > 100


def _tilted_camera() -> CameraModel:
    tilt = 0.25
    c, s = math.cos(tilt), math.sin(tilt)
    R_world_cam = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) @ np.diag([1.0, -1.0, -1.0])
    T = np.eye(4)
    T[:3, :3] = R_world_cam.T
    T[:3, 3] = -R_world_cam.T @ np.array([0.02, -0.3, 0.9])
    K = np.array([[880.0, 0.0, 318.0], [0.0, 884.0, 243.0], [0.0, 0.0, 1.0]])
    return CameraModel(K, np.array([-0.15, 0.05, 0.001, -0.002, 0.0]), T, 640, 480)
