import numpy as np
import pytest

from hwsim.truth import surface_normals, surface_points, surface_weights

pytestmark = pytest.mark.clock_free


def _grid(nx: int = 5, ny: int = 4, d: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    s, t = np.meshgrid(np.arange(nx) * d, np.arange(ny) * d)
    st = np.stack([s, t], -1)
    return st, np.concatenate([st, np.zeros((ny, nx, 1))], -1)


def test_weights_are_a_partition_of_unity_and_exact_at_nodes() -> None:
    st, nodes = _grid()
    rng = np.random.default_rng(1)
    q = rng.uniform(0, [0.04, 0.03], size=(100, 2))
    idx, w = surface_weights(q, (0.01, 0.01), st.shape[:2])
    np.testing.assert_allclose(w.sum(1), 1.0)
    assert (w >= -1e-12).all()
    # On a flat, unstretched sheet material coordinates are world x, y.
    np.testing.assert_allclose(surface_points(nodes, idx, w)[:, :2], q, atol=1e-12)
    at_nodes = st.reshape(-1, 2)
    idx, w = surface_weights(at_nodes, (0.01, 0.01), st.shape[:2])
    np.testing.assert_allclose(surface_points(nodes, idx, w), nodes.reshape(-1, 3), atol=1e-12)


def test_triangle_split_is_the_documented_diagonal() -> None:
    st, nodes = _grid()
    nodes[1, 1, 2] = 0.01  # lift node (j=1, i=1)
    idx, w = surface_weights(np.array([[0.007, 0.003], [0.003, 0.007]]), (0.01, 0.01), st.shape[:2])
    z = surface_points(nodes, idx, w)[:, 2]
    # a >= b: triangle (0,0),(0,1),(1,1) holds the lifted node with weight b = 0.3.
    np.testing.assert_allclose(z, [0.003, 0.003])


def test_flat_normals_point_up() -> None:
    st, nodes = _grid()
    idx, _ = surface_weights(np.array([[0.012, 0.017], [0.017, 0.012]]), (0.01, 0.01), st.shape[:2])
    np.testing.assert_allclose(surface_normals(nodes, idx), [[0, 0, 1], [0, 0, 1]], atol=1e-12)
