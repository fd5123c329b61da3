"""The mesh EKF's held edges (mesh_ekf.HeldEdges): an edge past its bound is pulled to it, one within it
is left alone."""

from __future__ import annotations

import numpy as np

from clothd.core.camera_model import CameraModel
from clothd.core.mesh import QuadMesh, measurement_jacobian
from clothd.core.mesh_ekf import HeldEdges, NodeBelief


def _held_step(held: HeldEdges) -> tuple[np.ndarray, np.ndarray]:
    """A 3 x 3 mesh at rest whose 40 features measure y only and agree with it, corrected with `held`.
    The nodes' x, y (n, 2) before and after."""
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    mesh = QuadMesh.covering(np.array([[-0.05, -0.05], [0.05, -0.05], [0.05, 0.05], [-0.05, 0.05]]), 3, 3)
    n = mesh.n_nodes
    rest = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(n)])
    P = np.tile(np.diag([1e-6] * 6), (n, 1, 1))
    belief = NodeBelief(np.column_stack([rest, np.zeros_like(rest)]), P, mesh.quad_nodes(), True)
    binding = mesh.bind(np.random.default_rng(5).uniform(-0.045, 0.045, (40, 2)))
    _, J = measurement_jacobian(cam, rest, binding)
    J[..., 2] = 0.0
    J[:, :, 0, :] = 0.0  # no say along x
    belief.correct(binding.quad, binding.nodes, J, np.zeros((40, 2)), 0.25, 1e9, held=held)
    return rest[:, :2], belief.x[:, :2].copy()


def test_an_edge_past_its_bound_is_pulled_to_it_and_one_within_is_left_alone() -> None:
    length = 0.05  # the 3 x 3 mesh's edges
    edges = np.array([[0, 1], [3, 4], [6, 7], [1, 2]])
    # (0, 1) held 2 mm longer from below and (6, 7) 2 mm shorter from above: both past their bounds.
    # (3, 4) and (1, 2) within theirs.
    bound = np.array([length + 0.002, length - 0.002, length - 0.002, length + 0.002])
    upper = np.array([False, False, True, True])
    before, after = _held_step(HeldEdges(edges, bound, upper, 0.0002))
    span = np.linalg.norm(after[edges[:, 0]] - after[edges[:, 1]], axis=1)
    assert span[0] > length + 0.0019  # σ 0.2 mm against the nodes' 1 mm: nearly to the bound
    assert span[2] < length - 0.0019
    np.testing.assert_allclose(after[[3, 4, 5, 2]], before[[3, 4, 5, 2]], atol=1e-12)
