"""The rigid plate EKF (clothd/core/rigid.py): state [X, Y, θ, Ẋ, Ẏ, θ̇], dense 6 x 6 covariance.

A feature's body coordinates are its cloth-space point relative to the pose at initialisation, pose0.
With the conveyor input, the body velocity relaxes towards the rigid twist that the belts under the
cloth impose (a least-squares fit of the belt velocities at the rest mesh's nodes); without it, it keeps
a constant velocity.
"""

from __future__ import annotations

import numpy as np

from clothd.config import EkfConfig, PhysicsConfig
from clothd.core import rigid
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import BeltField, rigid_velocity_fit
from clothd.core.ekf import UpdateStats, gate, predict, update_information
from clothd.core.estimators.base import Measurements, StateEstimate
from clothd.core.feature_set import FeatureSet
from clothd.core.mesh import QuadMesh
from clothd.core.physics import stick_time_s


class RigidEstimator:
    """The Estimator of a flat rigid plate: x (6,) and P (6, 6), corrected in information form."""

    def __init__(
        self, camera_model: CameraModel, ekf: EkfConfig, physics: PhysicsConfig, use_input: bool
    ) -> None:
        self.camera_model = camera_model
        self.ekf = ekf
        self.physics = physics
        self.use_input = use_input
        self.pose0 = np.zeros(3)
        self.x = np.zeros(rigid.N_STATES)
        self.P = rigid.initial_covariance(ekf)
        self._corners_body = np.zeros((4, 2))
        self._rest_body = np.zeros((0, 2))
        self._mesh_shape = (0, 0)

    def start(self, mesh: QuadMesh, pose0: np.ndarray, nodes_m: np.ndarray | None = None) -> None:
        """nodes_m, a measured layout, is for a mesh of the cloth's own shape: a rigid body has none."""
        self.pose0 = pose0
        self.x = np.concatenate([pose0, np.zeros(3)])
        self.P = rigid.initial_covariance(self.ekf)
        w, h = mesh.width_m / 2, mesh.height_m / 2
        self._corners_body = np.array([[-w, -h], [w, -h], [w, h], [-w, h]])
        self._rest_body = rigid.body_coordinates(mesh.rest_nodes_m().reshape(-1, 2), pose0)
        self._mesh_shape = (mesh.ny, mesh.nx)

    def _body(self, cloth_st: np.ndarray) -> np.ndarray:
        return rigid.body_coordinates(cloth_st, self.pose0)

    def predict(self, u: BeltField | None, dt_s: float) -> None:
        tau_s = twist = None
        if u is not None and self.use_input:
            # The plate follows the belts as a node does: friction's stick time plus the damping's.
            tau_s = stick_time_s(self.physics) + 1.0 / self.physics.damping_1_s
            probe = rigid.world_points(self.x, self._rest_body)
            vel, on = u.velocity_at(probe)
            twist = rigid_velocity_fit(probe[on], vel[on], self.x[:2]) if on.any() else np.zeros(3)
        x_pred = rigid.predict_mean(self.x, dt_s, tau_s, twist)
        self.x, self.P = predict(
            self.x, self.P, x_pred, rigid.transition(dt_s, tau_s), rigid.process_noise(self.ekf, dt_s)
        )

    def feature_pixels(self, features: FeatureSet) -> np.ndarray | None:
        return rigid.measure(self.camera_model, self.x, self._body(features.cloth_st))[0]

    def correct(self, m: Measurements) -> tuple[UpdateStats, np.ndarray]:
        R_px2 = self.ekf.meas_sigma_px**2
        accepted = np.ones(len(m.ok), bool)
        idx = np.flatnonzero(m.ok)
        pred, H = rigid.measure(self.camera_model, self.x, self._body(m.features.cloth_st[idx]))
        nu = m.px[idx] - pred
        S = np.einsum("nij,jk,nlk->nil", H, self.P, H) + R_px2 * np.eye(2)
        inside, d2 = gate(nu, S, self.ekf.gate_chi2)
        accepted[idx[~inside]] = False
        if inside.any():
            Hs = H[inside].reshape(-1, rigid.N_STATES)
            self.x, self.P = update_information(self.x, self.P, nu[inside].ravel(), Hs, R_px2)
        return UpdateStats(int(inside.sum()), int((~inside).sum()), float(d2[inside].sum())), accepted

    def cloth_coordinates(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Back to the table, into the body frame of the current pose, out through pose0."""
        world = self.camera_model.backproject_to_plane(px)[:, :2]
        st = (
            rigid.body_coordinates(world, self.x[:3]) @ rigid.rotation(float(self.pose0[2])).T
            + self.pose0[:2]
        )
        return st, np.ones(len(px), bool)

    def _outline_m(self) -> np.ndarray:
        return rigid.world_points(self.x, self._corners_body)[:, :2]

    def outline_px(self) -> np.ndarray | None:
        outline = self._outline_m()
        return self.camera_model.project(np.column_stack([outline, np.zeros(len(outline))]))

    def estimate(self) -> StateEstimate:
        nodes = rigid.world_points(self.x, self._rest_body).reshape(*self._mesh_shape, 3)
        return StateEstimate(self.x[:3].copy(), self.P[:3, :3].copy(), nodes, self._outline_m())
