"""The mesh EKF (clothd/core/mesh_ekf.py): every node's position and velocity, predicted by the Taichi
mass–spring driven by the belts under it, corrected by the features through the FEM shape functions.

With `corrects=False` it is the report's predict-only mode: the model driven by the conveyors, never
corrected. Without the input (`use_input=False`) the model takes the modules as stopped: the cloth rests
on still belts, and friction holds the mesh where the features last put it.
"""

from __future__ import annotations

import math

import numpy as np

from clothd.config import EkfConfig, MeshConfig, PhysicsConfig
from clothd.core.binding import cloth_coordinates
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import BeltField
from clothd.core.ekf import UpdateStats
from clothd.core.estimators.base import Measurements, StateEstimate, boundary, uncorrected
from clothd.core.feature_set import FeatureSet
from clothd.core.folds import FoldedEdges, even_slack_lengths_m, fold_heights_m, fold_reading, folds_across
from clothd.core.mesh import QuadMesh, blend, measurement_jacobian
from clothd.core.mesh_ekf import HeldEdges, NodeBelief
from clothd.core.physics import CONTACT_HEIGHT_M, MassSpring

# How closely an edge at a fold keeps its length in the plane (`MeshEstimator._held_edges`).
HELD_EDGE_SIGMA_M = 0.001


def _joined(a: HeldEdges | None, b: HeldEdges | None) -> HeldEdges | None:
    """Both sets of held edges as one (None: neither); both are held at HELD_EDGE_SIGMA_M."""
    if a is None or b is None:
        return a if b is None else b
    cat = np.concatenate
    return HeldEdges(
        cat([a.edges, b.edges]), cat([a.bound_m, b.bound_m]), cat([a.upper, b.upper]), HELD_EDGE_SIGMA_M
    )


class MeshEstimator:
    """The Estimator of the cloth as a mesh of nodes: NodeBelief (x (n, 6), node-block P (n, 6, 6)),
    predicted by the MassSpring allocated here once, corrected sparsely, heights from folds.py."""

    def __init__(
        self,
        camera_model: CameraModel,
        mesh_cfg: MeshConfig,
        physics: PhysicsConfig,
        ekf: EkfConfig,
        use_input: bool,
        corrects: bool = True,
    ) -> None:
        self.camera_model = camera_model
        self.mesh_cfg = mesh_cfg
        self.ekf = ekf
        self.use_input = use_input
        self.corrects = corrects
        self.sim = MassSpring(physics, mesh_cfg.nodes_x, mesh_cfg.nodes_y)
        n = mesh_cfg.nodes_x * mesh_cfg.nodes_y
        self._P0 = np.diag([ekf.initial_pos_sigma_m**2] * 3 + [ekf.initial_vel_sigma_m_s**2] * 3)
        Q = np.diag([ekf.process_pos_sigma_m**2] * 3 + [ekf.process_vel_sigma_m_s**2] * 3)
        self._Q = np.tile(Q, (n, 1, 1))
        self.mesh: QuadMesh | None = None
        self.belief: NodeBelief | None = None
        self._quad_height_m: np.ndarray | None = None  # as a further view last measured them
        self._folded: FoldedEdges | None = None  # the model's, at the last correction

    def start(self, mesh: QuadMesh, pose0: np.ndarray, nodes_m: np.ndarray | None = None) -> None:
        self.mesh = mesh
        self._quad_height_m = None
        self._folded = None
        rest = mesh.rest_nodes_m()
        self.sim.set_rest(rest)
        nodes = (
            np.column_stack([rest.reshape(-1, 2), np.zeros(mesh.n_nodes)])
            if nodes_m is None
            else np.array(nodes_m, float)
        )
        self.belief = NodeBelief(
            np.column_stack([nodes, np.zeros_like(nodes)]),
            np.tile(self._P0, (mesh.n_nodes, 1, 1)),
            mesh.quad_nodes(),
            planar=True,  # the camera corrects x, y; heights come from folds.py (correct, _lift_folds)
        )

    def _started(self) -> tuple[QuadMesh, NodeBelief]:
        assert self.mesh is not None and self.belief is not None, "start() comes first"
        return self.mesh, self.belief

    def predict(self, u: BeltField | None, dt_s: float) -> None:
        _, belief = self._started()
        pos, vel = belief.x[:, :3], belief.x[:, 3:]
        if u is None:
            belt_v, on_belt = np.zeros((len(pos), 2)), np.zeros(len(pos), bool)
        else:
            belt_v, on_belt = (u if self.use_input else u.stopped()).velocity_at(pos)
        self.sim.set_state(pos, vel)
        self.sim.step(dt_s, belt_v, on_belt)
        x_new, v_new = self.sim.state()
        in_contact = on_belt & (x_new[:, 2] <= CONTACT_HEIGHT_M)
        F = self.sim.transition_blocks(dt_s, in_contact)
        belief.predict(np.column_stack([x_new, v_new]), F, self._Q)

    def feature_pixels(self, features: FeatureSet) -> np.ndarray | None:
        _, belief = self._started()
        return self.camera_model.project(blend(belief.positions_m, features.binding))

    def correct(self, m: Measurements) -> tuple[UpdateStats, np.ndarray]:
        if not self.corrects:
            return uncorrected(m)
        _, belief = self._started()
        e = self.ekf
        accepted = np.ones(len(m.ok), bool)
        idx = np.flatnonzero(m.ok)
        sub = m.features.binding.subset(idx)
        seen_m = self._seen_positions_m()
        pred, J = measurement_jacobian(self.camera_model, seen_m, sub)
        # The camera corrects the nodes on the table plane only. From above, height barely moves a pixel,
        # and a filter free to use it explained in-plane model error with it: nodes floated 15-20 mm up
        # on flat cloth. Height comes from inextensibility instead (_lift_folds).
        residual = m.px[idx] - pred
        whiten = None if m.whiten is None else m.whiten[idx]
        quads, nodes = sub.quad, sub.nodes
        if m.edges is not None:
            # The outline's points join the features: same model, whitened to measure across the edge only.
            edges = m.edges(seen_m)
            on = np.flatnonzero(edges.ok)
            eb = edges.binding.subset(on)
            epred, eJ = measurement_jacobian(self.camera_model, seen_m, eb)
            ew = edges.whiten[on]
            whiten = np.concatenate([np.tile(np.eye(2), (len(idx), 1, 1)) if whiten is None else whiten, ew])
            residual = np.concatenate([residual, edges.px[on] - epred])
            J = np.concatenate([J, eJ])
            quads, nodes = np.concatenate([quads, eb.quad]), np.concatenate([nodes, eb.nodes])
        J[..., 2] = 0.0
        if whiten is not None:
            # An anisotropic R_i = sigma² W_i⁻² enters the isotropic correction as W_i ν and W_i J: the
            # information Jᵀ R⁻¹ J, Jᵀ R⁻¹ ν and the gate's Mahalanobis distance are then exactly R_i's.
            residual = np.einsum("kab,kb->ka", whiten, residual)
            J = np.einsum("kab,kcbd->kcad", whiten, J)
        held = None
        if m.quad_height_m is not None:
            held = _joined(self._held_edges(), self._even_slack_edges(m.quad_height_m))
        stats, inside = belief.correct(
            quads,
            nodes,
            J,
            residual,
            e.meas_sigma_px**2,
            e.gate_chi2,
            e.smoothness_sigma_m,
            m.shape_sigma_m,
            held,
        )
        inside = inside[: len(idx)]
        accepted[idx[~inside]] = False
        self._lift_folds()
        self._quad_height_m = m.quad_height_m
        return stats, accepted

    def _held_edges(self) -> HeldEdges | None:
        """The mesh edges with a node up in a fold, held in the plane: no longer than their rest length in
        3-D (the cloth does not stretch), and, where the fold does not lie across them (`folds_across`),
        no shorter than it (the cloth along a fold stands as long as it lies). The model's springs leave
        both loose in a fold, and neither camera sees a fold's flanks: on compress the springs from a node
        lifted beside one not yet lifted dragged an edge row's node 7 mm along the fold in one tick, and
        the features on a dying fold's flank pulled its node 3 mm into the crest, its outer edge 5 % over
        length, so that it read unfolded and 5.4 mm low. None while nothing is up."""
        mesh, belief = self._started()
        z = belief.x[:, 2].reshape(mesh.ny, mesh.nx)
        if self._folded is None or not (z > 0.0).any():
            return None
        idx = np.arange(mesh.n_nodes).reshape(mesh.ny, mesh.nx)
        rest = mesh.rest_nodes_m()
        across = folds_across(self._folded)
        edges, bounds, upper = [], [], []
        for sl_a, sl_b, folded in (
            ((slice(None), slice(None, -1)), (slice(None), slice(1, None)), across.rows),
            ((slice(None, -1), slice(None)), (slice(1, None), slice(None)), across.cols.T),
        ):
            at_fold = (z[sl_a] > 0.0) | (z[sl_b] > 0.0)
            pairs = np.stack([idx[sl_a][at_fold], idx[sl_b][at_fold]], axis=1)
            length = np.linalg.norm(rest[sl_a] - rest[sl_b], axis=-1)[at_fold]
            rise = (z[sl_a] - z[sl_b])[at_fold]
            along = ~folded[at_fold]
            edges += [pairs, pairs[along]]
            bounds += [np.sqrt(np.maximum(length**2 - rise**2, 0.0)), length[along]]
            upper += [np.ones(len(pairs), bool), np.zeros(int(along.sum()), bool)]
        cat = np.concatenate
        return HeldEdges(cat(edges), cat(bounds), cat(upper), HELD_EDGE_SIGMA_M)

    def _even_slack_edges(self, quad_height_m: np.ndarray) -> HeldEdges | None:
        """The edges of each measured fold's run held, from both sides, at an even share of its slack
        (folds.even_slack_lengths_m), σ HELD_EDGE_SIGMA_M; None where no run holds slack."""
        mesh, belief = self._started()
        xy = belief.positions_m[:, :2].reshape(mesh.ny, mesh.nx, 2)
        target = even_slack_lengths_m(xy, mesh.rest_nodes_m(), quad_height_m)
        idx = np.arange(mesh.n_nodes).reshape(mesh.ny, mesh.nx)
        edges, bounds = [], []
        for a, b, t in ((idx[:, :-1], idx[:, 1:], target.rows), (idx[:-1].T, idx[1:].T, target.cols)):
            on = ~np.isnan(t)
            edges.append(np.stack([a[on], b[on]], axis=1))
            bounds.append(t[on])
        e, bound = np.concatenate(edges), np.concatenate(bounds)
        if not len(e):
            return None
        both = np.repeat([True, False], len(e))
        return HeldEdges(np.concatenate([e, e]), np.concatenate([bound, bound]), both, HELD_EDGE_SIGMA_M)

    def _seen_positions_m(self) -> np.ndarray:
        """Node positions (n, 3) as the frame shows them: where they were in the middle of the exposure,
        p - v exposure_s / 2 (to first order; the velocity as predicted). With exposure_s 0, p. The
        Jacobian with respect to p is the same, so only where h(x) is evaluated changes."""
        _, belief = self._started()
        if self.ekf.exposure_s <= 0.0:
            return belief.positions_m
        return np.asarray(belief.positions_m - (0.5 * self.ekf.exposure_s) * belief.x[:, 3:6])

    def _lift_folds(self) -> None:
        """Set the node heights from how much shorter the cloth is on the table than at rest. The model's
        edges are straight, so each folded edge rises by its whole length: its springs stay at rest. A fold
        holds until its edges are nearly back to length (folds.HELD_TOLERANCE_FRACTION)."""
        mesh, belief = self._started()
        xy = belief.positions_m[:, :2].reshape(mesh.ny, mesh.nx, 2)
        tolerance = self.mesh_cfg.fold_tolerance_strain
        z, self._folded = fold_reading(xy, mesh.rest_nodes_m(), tolerance, None, self._folded)
        belief.set_heights(z.ravel(), self.ekf.initial_pos_sigma_m, self.ekf.initial_vel_sigma_m_s)

    def _measured_fold_heights_m(self, quad_height_m: np.ndarray) -> np.ndarray:
        mesh, belief = self._started()
        return fold_heights_m(
            belief.positions_m[:, :2].reshape(mesh.ny, mesh.nx, 2),
            mesh.rest_nodes_m(),
            self.mesh_cfg.fold_tolerance_strain,
            quad_height_m,
        )

    def cloth_coordinates(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mesh, _ = self._started()
        # px were found in this frame: bind them through the nodes as the frame shows them.
        return cloth_coordinates(mesh, self.camera_model.project(self._seen_positions_m()), px)

    def nodes_px(self) -> tuple[np.ndarray, np.ndarray]:
        """Where the nodes lie in the frame (n, 2) (as it shows them, as `cloth_coordinates` binds), and
        their heights (n,), metres."""
        _, belief = self._started()
        seen = self._seen_positions_m()
        return self.camera_model.project(seen), np.asarray(belief.positions_m[:, 2])

    def outline_px(self) -> np.ndarray | None:
        mesh, belief = self._started()
        return boundary(self.camera_model.project(belief.positions_m).reshape(mesh.ny, mesh.nx, 2))

    def estimate(self) -> StateEstimate:
        mesh, belief = self._started()
        nodes = belief.positions_m
        if self._quad_height_m is not None:
            # Where a further view measured the quads, the cloth's own points: a pleat's flank nodes lie
            # lower than the model's straight edges put them, and a low fold rises before its edges are
            # short enough for the model (folds.py). The model keeps its edges straight, springs at rest.
            nodes = nodes.copy()
            nodes[:, 2] = self._measured_fold_heights_m(self._quad_height_m).ravel()
        return StateEstimate(
            _best_fit_pose(mesh, nodes),
            _best_fit_pose_cov(nodes, belief.P),
            nodes.reshape(mesh.ny, mesh.nx, 3).copy(),
            boundary(nodes[:, :2].reshape(mesh.ny, mesh.nx, 2)),
        )


def _best_fit_pose(mesh: QuadMesh, nodes_m: np.ndarray) -> np.ndarray:
    """The rigid pose [X, Y, θ] that best maps the rest mesh onto the nodes' x, y (Kabsch in 2-D)."""
    rest = mesh.rest_nodes_m().reshape(-1, 2)
    cur = nodes_m[:, :2]
    rc, cc = rest.mean(axis=0), cur.mean(axis=0)
    M = (rest - rc).T @ (cur - cc)
    rot = math.atan2(M[0, 1] - M[1, 0], M[0, 0] + M[1, 1])
    return np.array([cc[0], cc[1], math.remainder(mesh.theta_rad + rot, 2 * math.pi)])


def _best_fit_pose_cov(nodes_m: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of the best-fit pose under the filter's independent node blocks P (n, 6, 6):
    the centre is the mean of the nodes, and a small rotation moves node i by θ ẑ × r_i, so to first
    order θ = Σ (r_i × Δp_i) / Σ |r_i|²."""
    r = nodes_m[:, :2] - nodes_m[:, :2].mean(axis=0)
    n = len(r)
    J = np.zeros((n, 3, 2))  # d pose / d p_i,xy
    J[:, 0, 0] = J[:, 1, 1] = 1.0 / n
    J[:, 2, :] = np.stack([-r[:, 1], r[:, 0]], axis=1) / float((r**2).sum())
    return np.asarray(np.einsum("nij,njk,nlk->il", J, P[:, :2, :2], J))
