"""The tracker's own models: conveyor input, mass-spring prediction, mesh EKF correction, rebinding."""

import numpy as np
import pytest

from clothd.config import PhysicsConfig
from clothd.core.binding import cloth_coordinates, invert_bilinear
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout, ModuleModel, rigid_velocity_fit
from clothd.core.mesh import QuadMesh, blend, measurement_jacobian, shape_functions
from clothd.core.mesh_ekf import NodeBelief
from clothd.core.nanmedian import nanmedian
from clothd.core.physics import MassSpring, spring_pairs
from clothd.taichi_runtime import start_taichi

pytestmark = pytest.mark.clock_free

LAYOUT = ConveyorLayout(8, 6, 0.075, 0.065)


@pytest.fixture(scope="module", autouse=True)
def _taichi() -> None:
    start_taichi("cpu")


def _mesh() -> QuadMesh:
    return QuadMesh.covering(np.array([[-0.125, -0.1], [0.125, -0.1], [0.125, 0.1], [-0.125, 0.1]]), 12, 12)


def test_belt_velocity_lookup_and_rigid_fit() -> None:
    speed, heading = np.zeros(48), np.zeros(48)
    speed[LAYOUT.modules_x * 2 + 3] = 0.05  # module (col 3, row 2), centre (-0.0375, -0.0375)
    heading[LAYOUT.modules_x * 2 + 3] = np.pi / 2
    pts = np.array([[-0.0375, -0.0375], [-0.0375 + 0.034, -0.0375], [0.0, 0.0], [5.0, 5.0]])
    vel, on = LAYOUT.belt_velocity(pts, speed, heading)
    assert list(on) == [
        True,
        False,
        False,
        False,
    ]  # the second is past the belt's edge, the last off the table
    np.testing.assert_allclose(vel[0], [0.0, 0.05], atol=1e-12)
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.1, 0.1, (30, 2))
    twist = np.array([0.02, -0.01, 0.3])
    v = twist[:2] + twist[2] * np.stack([-(p[:, 1] - 0.01), p[:, 0] - 0.02], axis=1)
    np.testing.assert_allclose(rigid_velocity_fit(p, v, np.array([0.02, 0.01])), twist, atol=1e-12)


def test_spring_families() -> None:
    fam = spring_pairs(4, 3)
    assert len(fam["structural"]) == 3 * 3 + 2 * 4
    assert len(fam["shear"]) == 2 * 3 * 2
    assert len(fam["flexion"]) == 3 * 2 + 1 * 4


def _sim(cfg: PhysicsConfig, mesh: QuadMesh) -> MassSpring:
    sim = MassSpring(cfg, mesh.nx, mesh.ny)
    sim.set_rest(mesh.rest_nodes_m())
    return sim


def test_a_relaid_model_behaves_as_a_new_one() -> None:
    """Re-initialising tracking lays a new rest mesh into the same fields (nothing allocated, nothing
    compiled); mass and rest lengths follow the new mesh."""
    small, large = _mesh(), QuadMesh(12, 12, np.array([-0.2, -0.1]), 0.3, 0.4, 0.25)
    reused = _sim(PhysicsConfig(), small)
    reused.set_rest(large.rest_nodes_m())
    fresh = _sim(PhysicsConfig(), large)
    x0 = _rest_state(large) * np.array([1.02, 0.96, 1.0])
    belts = np.tile([0.02, 0.01], (large.n_nodes, 1)), np.ones(large.n_nodes, bool)
    for sim in (reused, fresh):
        sim.set_state(x0, np.zeros_like(x0))
        for _ in range(3):
            sim.step(1 / 30, *belts)
    assert reused.mass_kg == fresh.mass_kg
    np.testing.assert_array_equal(reused.state()[0], fresh.state()[0])
    assert np.abs(fresh.state()[0] - x0).max() > 1e-3  # it moved: the comparison means something


def test_mass_spring_rests_and_is_carried_by_belts() -> None:
    mesh = _mesh()
    sim = _sim(PhysicsConfig(), mesh)
    rest = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(mesh.n_nodes)])
    sim.set_state(rest, np.zeros_like(rest))
    still = np.zeros(48)
    for _ in range(10):
        vel, on = LAYOUT.belt_velocity(sim.state()[0], still, still)
        sim.step(1 / 30, vel, on)
    x, v = sim.state()
    assert np.abs(x - rest).max() < 1e-6 and np.abs(v).max() < 1e-4
    speed, heading = np.full(48, 0.03), np.full(48, np.pi / 2)
    for _ in range(30):
        vel, on = LAYOUT.belt_velocity(sim.state()[0], speed, heading)
        sim.step(1 / 30, vel, on)
    x, v = sim.state()
    np.testing.assert_allclose(v[:, :2].mean(axis=0), [0.0, 0.03], atol=0.002)
    assert x[:, 2].min() >= 0.0


def test_strain_limiting_holds_a_stretched_mesh() -> None:
    mesh = _mesh()
    cfg = PhysicsConfig(strain_limit=0.05)
    sim = _sim(cfg, mesh)
    rest = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(mesh.n_nodes)])
    stretched = rest.copy()
    stretched[:, 0] *= 1.3
    sim.set_state(stretched, np.zeros_like(rest))
    for _ in range(5):
        sim.step(1 / 30, np.zeros((mesh.n_nodes, 2)), np.zeros(mesh.n_nodes, bool))
    x = sim.state()[0].reshape(mesh.ny, mesh.nx, 3)
    dx = np.linalg.norm(np.diff(x, axis=1), axis=-1) / mesh.spacing_m[0]
    assert dx.max() < 1.0 + cfg.strain_limit + 0.01  # from 1.30: Provot's correction holds the limit


def _rest_state(mesh: QuadMesh) -> np.ndarray:
    return np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(mesh.n_nodes)])


def _edge_strain(x: np.ndarray, mesh: QuadMesh) -> np.ndarray:
    g = x.reshape(mesh.ny, mesh.nx, 3)
    return np.linalg.norm(np.diff(g, axis=1), axis=-1) / mesh.spacing_m[0] - 1.0


def test_woven_springs_are_slack_up_to_the_crimp_and_soft_in_compression() -> None:
    """A mesh 3 % long or short, on still belts, stays about where the features put it; Hookean springs
    spring it back further than friction holds in one tick."""
    mesh = _mesh()
    still = np.zeros((mesh.n_nodes, 2)), np.ones(mesh.n_nodes, bool)
    woven, hookean = PhysicsConfig(), PhysicsConfig(slack_strain=0.0, compression_k_ratio=1.0)
    moved_mm = {}
    for name, cfg in (("woven", woven), ("hookean", hookean)):
        for scale in (1.03, 0.97):
            sim = _sim(cfg, mesh)
            start = _rest_state(mesh) * np.array([scale, 1.0, 1.0])
            sim.set_state(start, np.zeros_like(start))
            sim.step(1 / 30, *still)
            moved_mm[name, scale] = np.abs(sim.state()[0] - start).max() * 1e3
    assert moved_mm["woven", 1.03] < 1e-6  # within the crimp: no force at all
    assert moved_mm["woven", 0.97] < 1.0
    assert moved_mm["hookean", 1.03] > 2.0 and moved_mm["hookean", 0.97] > 2.0


def test_cloth_up_in_a_fold_bends_rather_than_push_but_still_pulls() -> None:
    """Between two nodes up in a fold the cloth arches over the straight line, so a spring short between
    them pushes nothing; one stretched between them still pulls. Pushing, it drove the compress fold's top
    nodes apart and past their neighbours on the table."""
    mesh = _mesh()
    still = np.zeros((mesh.n_nodes, 2)), np.ones(mesh.n_nodes, bool)
    moved_mm = {}
    for scale in (0.9, 1.1):
        for height_m in (0.0, 0.01):
            sim = _sim(PhysicsConfig(), mesh)
            start = _rest_state(mesh) * np.array([scale, 1.0, 1.0])
            start[:, 2] = height_m
            sim.set_state(start, np.zeros_like(start))
            sim.step(1 / 30, *still)
            moved_mm[scale, height_m] = np.abs(sim.state()[0] - start).max() * 1e3
    assert moved_mm[0.9, 0.01] == 0.0  # a short mesh all up in a fold: no push, and nothing else
    assert moved_mm[0.9, 0.0] > 0.01  # on the table the same mesh pushes (and friction holds it)
    assert moved_mm[1.1, 0.01] > 1.0  # stretched, up in a fold, with no belt to hold it: pulled in


def test_height_is_kinematic_and_cloth_up_in_a_fold_feels_no_belt() -> None:
    mesh = _mesh()
    belts = np.tile([0.03, 0.0], (mesh.n_nodes, 1)), np.ones(mesh.n_nodes, bool)
    for height_m, carried in ((0.0, True), (0.01, False)):
        sim = _sim(PhysicsConfig(), mesh)
        x0 = _rest_state(mesh)
        x0[:, 2] = height_m
        sim.set_state(x0, np.zeros_like(x0))
        for _ in range(3):
            sim.step(1 / 30, *belts)
        x, v = sim.state()
        np.testing.assert_array_equal(x[:, 2], height_m)  # no node fell
        assert np.all(v[:, 0] > 0.025) if carried else np.all(v == 0.0)


def test_a_spring_steeper_than_it_is_long_leaves_its_ends_where_they_are() -> None:
    """Heights are given, not simulated, and the folds can give a node more height over its neighbour
    than the edge between them is long. No move in the plane can make such a spring whole: its strain
    limit dragged the two ends together and past each other, and the mesh folded over itself (the
    tracker was lost while a hand pushed a second ridge into the cloth, docs/benchmarks.md)."""
    mesh = _mesh()
    sim = _sim(PhysicsConfig(), mesh)
    x0 = _rest_state(mesh)
    column = np.arange(mesh.n_nodes) % mesh.nx == 5
    x0[column, 2] = 1.5 * mesh.spacing_m[0]  # one column of nodes high above its neighbours
    sim.set_state(x0, np.zeros_like(x0))
    for _ in range(3):
        sim.step(1 / 15, np.zeros((mesh.n_nodes, 2)), np.ones(mesh.n_nodes, bool))
    x = sim.state()[0].reshape(mesh.ny, mesh.nx, 3)
    assert np.all(np.diff(x[..., 0], axis=1) > 0)  # every row still in order: no quad folded over
    # Only the longer flexion springs still pull (they can be whole in 3-D): less than half a quad.
    assert np.abs(x[..., :2] - x0.reshape(mesh.ny, mesh.nx, 3)[..., :2]).max() < mesh.spacing_m[0] / 2


def test_set_heights_takes_height_out_of_the_filter() -> None:
    rng = np.random.default_rng(5)
    A = rng.normal(0, 1e-3, (4, 6, 6))
    P = A @ A.transpose(0, 2, 1) + 1e-8 * np.eye(6)
    belief = NodeBelief(rng.normal(0, 0.01, (4, 6)), P, np.array([[0, 1, 3, 2]]))
    belief.set_heights(np.array([0.0, 0.01, 0.02, 0.0]), 0.002, 0.01)
    np.testing.assert_array_equal(belief.x[:, 2], [0.0, 0.01, 0.02, 0.0])
    np.testing.assert_array_equal(belief.x[:, 5], 0.0)
    np.testing.assert_array_equal(belief.P[:, 2, [0, 1, 3, 4, 5]], 0.0)
    np.testing.assert_allclose(belief.P[:, 2, 2], 0.002**2)
    assert np.all(np.linalg.eigvalsh(belief.P) > 0)


def test_mesh_ekf_update_is_the_exact_information_form_update() -> None:
    """For a block-diagonal prior, the sparse update equals the dense textbook EKF update."""
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    mesh = QuadMesh.covering(np.array([[-0.05, -0.05], [0.05, -0.05], [0.05, 0.05], [-0.05, 0.05]]), 3, 3)
    rng = np.random.default_rng(3)
    n = mesh.n_nodes
    pos = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(n)])
    # Node blocks with position-velocity correlation, so the velocity update is exercised too.
    A = rng.normal(0, 1e-3, (n, 6, 6))
    P_blocks = A @ A.transpose(0, 2, 1) + np.diag([1e-6] * 3 + [1e-5] * 3)
    belief = NodeBelief(np.column_stack([pos, np.zeros_like(pos)]), P_blocks.copy(), mesh.quad_nodes())
    binding = mesh.bind(rng.uniform(-0.045, 0.045, (12, 2)))
    _, J = measurement_jacobian(cam, pos, binding)
    nu = rng.normal(0, 0.5, (12, 2))
    belief.correct(binding.quad, binding.nodes, J, nu, 0.25, gate_chi2=1e9)
    H = np.zeros((24, 6 * n))
    for i in range(12):
        for c in range(4):
            H[2 * i : 2 * i + 2, 6 * binding.nodes[i, c] : 6 * binding.nodes[i, c] + 3] = J[i, c]
    P = np.zeros((6 * n, 6 * n))
    for k in range(n):
        P[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] = P_blocks[k]
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + 0.25 * np.eye(24))
    x_ref = np.column_stack([pos, np.zeros_like(pos)]).ravel() + K @ nu.ravel()
    np.testing.assert_allclose(belief.x.ravel(), x_ref, atol=1e-12)
    for k in range(n):  # the localised blocks are SPD and no larger than the prior
        assert np.all(np.linalg.eigvalsh(belief.P[k]) > 0)
        assert np.all(np.diag(belief.P[k]) <= np.diag(P_blocks[k]) + 1e-15)


def test_planar_update_is_the_full_update_when_heights_are_outside_the_filter() -> None:
    """With no height column in J and z, v_z uncorrelated with the rest (set_heights), the x, y solve of a
    planar belief gives the 3-D solve's mean and covariance, heights untouched, and the same gate."""
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    mesh = QuadMesh.covering(np.array([[-0.05, -0.05], [0.05, -0.05], [0.05, 0.05], [-0.05, 0.05]]), 4, 3)
    rng = np.random.default_rng(6)
    n = mesh.n_nodes
    pos = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), rng.uniform(0, 0.01, n)])
    A = rng.normal(0, 1e-3, (n, 6, 6))
    P_blocks = A @ A.transpose(0, 2, 1) + np.diag([1e-6] * 3 + [1e-5] * 3)
    binding = mesh.bind(rng.uniform(-0.045, 0.045, (20, 2)))
    _, J = measurement_jacobian(cam, pos, binding)
    J[..., 2] = 0.0
    nu = rng.normal(0, 0.5, (20, 2))
    beliefs = []
    for planar in (False, True):
        belief = NodeBelief(
            np.column_stack([pos, np.zeros_like(pos)]), P_blocks.copy(), mesh.quad_nodes(), planar
        )
        belief.set_heights(pos[:, 2], 0.002, 0.01)
        # The gate's S: the planar filter's 2 x 2 blocks written out, the 3-D one's by matmul. (J with all
        # entries non-zero: this camera looks straight down, so its du/dy and dv/dx are 0.)
        J_any = rng.normal(0, 1e3, J.shape) * [1.0, 1.0, 0.0]
        S = belief.innovation_covariances(binding.nodes, J_any[..., : 2 if planar else 3], 0.25)
        Pc = belief.P[binding.nodes][:, :, :3, :3]
        S_direct = np.einsum("kcia,kcab,kcjb->kij", J_any, Pc, J_any) + 0.25 * np.eye(2)
        np.testing.assert_allclose(S, S_direct, rtol=1e-12, atol=0)
        belief.correct(binding.quad, binding.nodes, J, nu, 0.25, gate_chi2=1e9, smoothness_m=0.005)
        beliefs.append(belief)
    full, planar_belief = beliefs
    np.testing.assert_allclose(planar_belief.x, full.x, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(planar_belief.x[:, 2], pos[:, 2])
    np.testing.assert_allclose(planar_belief.P, full.P, rtol=1e-9, atol=1e-20)
    assert planar_belief.pattern.band < full.pattern.band


def test_smoothness_prior_carries_corrections_to_nodes_without_features() -> None:
    """With the smoothness prior the sparse update is the exact solve with the mesh's Laplacian added to
    the prior information; a corner node no feature touches is then corrected with its neighbours."""
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    mesh = QuadMesh.covering(np.array([[-0.05, -0.05], [0.05, -0.05], [0.05, 0.05], [-0.05, 0.05]]), 3, 3)
    n = mesh.n_nodes
    pos = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(n)])
    P_blocks = np.tile(np.diag([1e-6] * 3 + [1e-5] * 3), (n, 1, 1))
    rng = np.random.default_rng(4)
    binding = mesh.bind(rng.uniform(-0.045, -0.005, (8, 2)))  # all in the quad of nodes 0, 1, 3, 4
    _, J = measurement_jacobian(cam, pos, binding)
    nu = np.tile([2.0, 0.0], (8, 1))  # the features all moved 2 px along x
    moved = {}
    for sigma in (None, 0.005):
        belief = NodeBelief(np.column_stack([pos, np.zeros_like(pos)]), P_blocks.copy(), mesh.quad_nodes())
        belief.correct(binding.quad, binding.nodes, J, nu, 0.25, gate_chi2=1e9, smoothness_m=sigma)
        moved[sigma] = belief.x[:, 0] - pos[:, 0]
    away = [2, 5, 6, 7, 8]  # the nodes of the quads with no feature
    assert np.all(moved[None][away] == 0.0) and np.all(moved[0.005][away] > 0.0)
    assert moved[0.005][2] > 0.02 * moved[0.005][1]  # next to a corrected node: a share of its correction
    # The exact solve: (P⁻¹ + L/σ² + HᵀR⁻¹H) Δp = HᵀR⁻¹ν over the positions.
    Hp = np.zeros((16, 3 * n))
    for i in range(8):
        for c in range(4):
            Hp[2 * i : 2 * i + 2, 3 * binding.nodes[i, c] : 3 * binding.nodes[i, c] + 3] = J[i, c]
    L = np.zeros((n, n))
    for a, b in [(j * 3 + i, j * 3 + i + 1) for j in range(3) for i in range(2)] + [
        (j * 3 + i, (j + 1) * 3 + i) for j in range(2) for i in range(3)
    ]:
        L[[a, b], [a, b]] += 1.0
        L[a, b] -= 1.0
        L[b, a] -= 1.0
    info = np.kron(np.eye(n), np.linalg.inv(P_blocks[0, :3, :3])) + np.kron(L, np.eye(3)) / 0.005**2
    dp = np.linalg.solve(info + Hp.T @ Hp / 0.25, Hp.T @ nu.ravel() / 0.25)
    np.testing.assert_allclose(moved[0.005], dp.reshape(n, 3)[:, 0], rtol=1e-9, atol=1e-15)


def _shape_prior_step(
    scale: float, sigma_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 3 x 3 mesh at rest, then scaled along x about its centre; 40 features that measure y only (a
    stripe's aperture) and agree with it. Rest positions (n, 2), the scaled ones, the corrected ones, and
    the features' corner nodes (40, 4) and Jacobian blocks (40, 4, 2, 3)."""
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    mesh = QuadMesh.covering(np.array([[-0.05, -0.05], [0.05, -0.05], [0.05, 0.05], [-0.05, 0.05]]), 3, 3)
    n = mesh.n_nodes
    rest = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(n)])
    belief = NodeBelief(
        np.column_stack([rest, np.zeros_like(rest)]),
        np.tile(np.diag([1e-6] * 6), (n, 1, 1)),
        mesh.quad_nodes(),
        True,
    )
    scaled = rest * [scale, 1.0, 1.0]
    belief.x[:, :3] = scaled
    binding = mesh.bind(np.random.default_rng(5).uniform(-0.045, 0.045, (40, 2)))
    _, J = measurement_jacobian(cam, scaled, binding)
    J[..., 2] = 0.0
    J[:, :, 0, :] = 0.0  # across the stripes only: no say along x
    belief.correct(binding.quad, binding.nodes, J, np.zeros((40, 2)), 0.25, 1e9, shape_sigma_m=sigma_m)
    return rest[:, :2], scaled[:, :2], belief.x[:, :2], binding.nodes, J


def test_the_shape_prior_pulls_a_stretched_mesh_back_and_lets_a_compressed_one_buckle() -> None:
    """Where the features cannot tell (here: along x), the shape prior holds the mesh's edges to their
    rest lengths: tightly when stretched, three times more loosely when compressed."""
    width = {}
    for scale in (1.01, 0.99):
        rest, scaled, held, _, _ = _shape_prior_step(scale, 0.0)
        np.testing.assert_array_equal(held, scaled)  # without the prior nothing says where x lies
        rest, scaled, held, _, _ = _shape_prior_step(scale, 0.0002)
        width[scale] = (np.ptp(held[:, 0]) - np.ptp(rest[:, 0])) / (np.ptp(scaled[:, 0]) - np.ptp(rest[:, 0]))
        np.testing.assert_allclose(held[:, 1], scaled[:, 1], atol=5e-5)  # y was measured where it is
    assert width[1.01] < 0.1  # a 1 % stretch is taken back
    assert width[0.99] > 3 * width[1.01]  # more of a 1 % compression stays: the cloth may be buckling


def test_the_shape_prior_is_the_exact_information_form_step() -> None:
    """One correction with the shape prior is the Gauss–Newton step of the prior, the features and every
    edge's length (sides and diagonals) as pseudo-measurements, solved densely."""
    sigma = 0.0002
    rest, scaled, held, nodes, J = _shape_prior_step(1.01, sigma)
    edges = [(0, 1), (1, 2), (3, 4), (4, 5), (6, 7), (7, 8), (0, 3), (3, 6), (1, 4), (4, 7), (2, 5), (5, 8)]
    edges += [(0, 4), (1, 3), (1, 5), (2, 4), (3, 7), (4, 6), (4, 8), (5, 7)]
    n = len(rest)
    H = np.zeros((2 * len(J), 2 * n))  # the features: agreeing with the prior, they add information only
    for i in range(len(J)):
        for c in range(4):
            H[2 * i : 2 * i + 2, 2 * nodes[i, c] : 2 * nodes[i, c] + 2] = J[i, c, :, :2]
    info = np.eye(2 * n) / 1e-6 + H.T @ H / 0.25
    vec = np.zeros(2 * n)
    for a, b in edges:
        d = scaled[a] - scaled[b]
        u = d / np.linalg.norm(d)
        h = np.zeros(2 * n)
        h[2 * a : 2 * a + 2], h[2 * b : 2 * b + 2] = u, -u
        stretched = np.linalg.norm(d) > np.linalg.norm(rest[a] - rest[b]) + 1e-12
        s2 = (sigma if stretched else 3 * sigma) ** 2
        info += np.outer(h, h) / s2
        vec += h * (np.linalg.norm(rest[a] - rest[b]) - np.linalg.norm(d)) / s2
    dp = np.linalg.solve(info, vec).reshape(n, 2)
    np.testing.assert_allclose(held - scaled, dp, atol=1e-12)


def test_a_quad_in_a_fold_is_not_taken_for_an_occluder() -> None:
    """A quad whose features all move unlike its neighbours' is rejected as a patch an occluder carries,
    unless a node of it is up in a fold: a fold's sides climb while the cloth around them slides."""
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    mesh = QuadMesh.covering(np.array([[-0.06, -0.06], [0.06, -0.06], [0.06, 0.06], [-0.06, 0.06]]), 4, 4)
    n = mesh.n_nodes
    pos = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(n)])
    rng = np.random.default_rng(6)
    binding = mesh.bind(rng.uniform(-0.058, 0.058, (400, 2)))
    _, J = measurement_jacobian(cam, pos, binding)
    middle = binding.quad == 4  # the quad of nodes 5, 6, 9, 10
    nu = rng.normal(0.0, 0.1, (len(binding.quad), 2))
    nu[middle] += [3.0, 0.0]  # the middle quad's features moved 3 px more than the rest
    accepted = {}
    for lifted_m in (0.0, 0.01):
        x = np.column_stack([pos, np.zeros_like(pos)])
        x[5, 2] = lifted_m
        belief = NodeBelief(x, np.tile(np.diag([1e-6] * 3 + [1e-5] * 3), (n, 1, 1)), mesh.quad_nodes(), True)
        _, accepted[lifted_m] = belief.correct(binding.quad, binding.nodes, J, nu, 0.25, gate_chi2=9.21)
    assert middle.sum() > 10
    assert not accepted[0.0][middle].any() and accepted[0.0][~middle].mean() > 0.95
    assert accepted[0.01][middle].mean() > 0.95


def test_a_feature_no_neighbours_can_judge_is_judged_against_the_prediction() -> None:
    """A feature alone in its quad, with no featured quad around (the rest hidden under an arm), is its
    quad's mean: neither level of the neighbours' gate can see it move off the cloth. The prediction
    can, while a well-surrounded quad moving with its neighbours (a model error) still passes."""
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    mesh = QuadMesh.covering(np.array([[-0.07, -0.07], [0.07, -0.07], [0.07, 0.07], [-0.07, 0.07]]), 8, 8)
    n = mesh.n_nodes
    pos = np.column_stack([mesh.rest_nodes_m().reshape(-1, 2), np.zeros(n)])
    rng = np.random.default_rng(7)
    points = rng.uniform(-0.068, 0.068, (1500, 2))
    hidden = (points[:, 0] > 0.01) & (points[:, 1] > 0.01)  # 3 x 3 of the 7 x 7 quads under an arm
    dragged = np.array([[0.06, 0.06]])  # one feature left there, on the arm's edge
    binding = mesh.bind(np.concatenate([points[~hidden], dragged]))
    _, J = measurement_jacobian(cam, pos, binding)
    noise = rng.normal(0.0, 0.1, (len(binding.quad), 2))
    # The lone feature 15 px off, or 0.3 px; then every feature 3 px off the prediction alike (a model
    # error: corrected, not rejected), the lone one with them.
    for offset_px, lone_px, kept in ((0.0, 15.0, False), (0.0, 0.3, True), (3.0, 0.0, None)):
        nu = noise + np.array([offset_px, 0.0])
        nu[-1] += [lone_px, 0.0]
        belief = NodeBelief(
            np.column_stack([pos, np.zeros_like(pos)]),
            np.tile(np.diag([1e-6] * 3 + [1e-5] * 3), (n, 1, 1)),
            mesh.quad_nodes(),
            True,
        )
        _, accepted = belief.correct(binding.quad, binding.nodes, J, nu, 0.25, gate_chi2=13.8)
        assert kept is None or bool(accepted[-1]) is kept
        assert accepted[:-1].mean() > 0.95


def test_rebinding_through_a_moved_mesh() -> None:
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    mesh = _mesh()
    rest = mesh.rest_nodes_m().reshape(-1, 2)
    moved = np.column_stack([rest + np.array([0.02, -0.01]), np.zeros(len(rest))])
    rng = np.random.default_rng(4)
    st_true = rng.uniform([-0.1, -0.08], [0.1, 0.08], (20, 2))
    px = cam.project(blend(moved, mesh.bind(st_true)))
    st, found = cloth_coordinates(mesh, cam.project(moved), px)
    assert found.all()
    np.testing.assert_allclose(st, st_true, atol=1e-6)
    corners = np.array([[[0.0, 0.0], [2.0, 0.2], [2.2, 2.0], [-0.1, 1.8]]])
    xe = np.array([[0.3, -0.6]])
    np.testing.assert_allclose(invert_bilinear(corners, shape_functions(xe) @ corners[0]), xe, atol=1e-9)


def test_module_model_follows_the_stepper_limits() -> None:
    modules = ModuleModel(2, accel_limit_m_s2=1.0, steer_rate_limit_rad_s=2.0)
    speed, heading = np.array([0.3, 0.1]), np.array([1.0, 0.0])
    mid_speed, mid_heading = modules.advance(speed, heading, 0.1)
    np.testing.assert_allclose(mid_speed, [0.05, 0.05])  # mid-tick, 0.05 s at 1 m/s²
    np.testing.assert_allclose(mid_heading, [0.1, 0.0])  # 0.05 s at 2 rad/s
    for _ in range(20):
        modules.advance(speed, heading, 0.1)
    np.testing.assert_allclose(modules.speed_m_s, speed)
    np.testing.assert_allclose(modules.heading_rad, heading)
    # A half-turn command reverses the belt instead of steering round.
    for _ in range(10):
        modules.advance(np.array([0.3, 0.1]), np.array([1.0, np.pi]), 0.1)
    np.testing.assert_allclose(modules.heading_rad[1], 0.0)
    np.testing.assert_allclose(modules.speed_m_s[1], -0.1)


def test_nanmedian_matches_numpy() -> None:
    rng = np.random.default_rng(11)
    a = rng.normal(size=(40, 8, 2))
    a[rng.random((40, 8)) < 0.5] = np.nan
    a[:, 0] = rng.normal(size=(40, 2))  # every row holds a number
    np.testing.assert_allclose(nanmedian(a, axis=1), np.nanmedian(a, axis=1))
    b = rng.normal(size=(5, 12, 11))
    b[rng.random(b.shape) < 0.6] = np.nan
    b[:, 3, 4] = np.nan  # a slice with no number: NaN, as numpy's
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
        expected = np.nanmedian(b, axis=0)
    np.testing.assert_allclose(nanmedian(b, axis=0), expected)
