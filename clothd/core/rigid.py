"""The rigid plate model: the cloth as a flat rigid body on the table.

State x = [X, Y, θ, Ẋ, Ẏ, θ̇] (m, m, rad, m/s, m/s, rad/s): the pose of the cloth's body frame, whose
origin is the cloth's centre at initialisation. A feature has fixed body coordinates q (2,); its world
point is R(θ) q + [X, Y] on the table (z = 0) and its predicted pixel the camera projection of that
(the original report's h_i, with a calibrated camera).

Prediction: with the conveyor input, the body velocity relaxes towards the rigid velocity the belts
under the cloth impose (friction drags the cloth towards the belt speed with time constant τ); without
it, constant velocity. Both are linear in x, so F is exact.
"""

from __future__ import annotations

import math

import numpy as np

from clothd.config import EkfConfig
from clothd.core.camera_model import CameraModel

N_STATES = 6


def rotation(theta_rad: float) -> np.ndarray:
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, -s], [s, c]])


def body_coordinates(world_xy: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Body coordinates (n, 2) of world points (n, 2) for pose [X, Y, θ]."""
    return np.asarray((world_xy - pose[:2]) @ rotation(float(pose[2])))


def world_points(x: np.ndarray, q_body: np.ndarray) -> np.ndarray:
    """World points (n, 3) on the table of body coordinates (n, 2) for state x."""
    xy = q_body @ rotation(float(x[2])).T + x[:2]
    return np.column_stack([xy, np.zeros(len(xy))])


def transition(dt_s: float, tau_s: float | None) -> np.ndarray:
    """F (6, 6). With input, v⁺ = α v + (1 − α) v_belt with α = exp(−dt/τ); the pose integrates the
    new velocity (semi-implicit Euler). Without input (tau None), α = 1: constant velocity."""
    alpha = 1.0 if tau_s is None else math.exp(-dt_s / tau_s)
    F = np.eye(N_STATES)
    F[3:, 3:] *= alpha
    F[:3, 3:] = dt_s * alpha * np.eye(3)
    return F


def predict_mean(
    x: np.ndarray, dt_s: float, tau_s: float | None, belt_twist: np.ndarray | None
) -> np.ndarray:
    """x⁻ = F x + G u, u = the belts' rigid twist [vx, vy, ω] (or none)."""
    x_pred = transition(dt_s, tau_s) @ x
    if tau_s is not None and belt_twist is not None:
        pull = (1.0 - math.exp(-dt_s / tau_s)) * belt_twist
        x_pred[3:] += pull
        x_pred[:3] += dt_s * pull
    x_pred[2] = math.remainder(float(x_pred[2]), 2 * math.pi)
    return x_pred


def process_noise(cfg: EkfConfig, dt_s: float) -> np.ndarray:
    """Q (6, 6): independent per-tick random walks on pose and rates; θ scaled by a 0.1 m lever."""
    q_pos, q_vel = cfg.process_pos_sigma_m**2, cfg.process_vel_sigma_m_s**2
    lever_m = 0.1
    return np.diag([q_pos, q_pos, q_pos / lever_m**2, q_vel, q_vel, q_vel / lever_m**2])


def initial_covariance(cfg: EkfConfig) -> np.ndarray:
    p, v = cfg.initial_pos_sigma_m**2, cfg.initial_vel_sigma_m_s**2
    lever_m = 0.1
    return np.diag([p, p, p / lever_m**2, v, v, v / lever_m**2])


def measure(camera: CameraModel, x: np.ndarray, q_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted pixels h(x) (n, 2) and the Jacobian H (n, 2, 6): ∂h/∂[X, Y] = J_π[:, :, :2],
    ∂h/∂θ = J_π[:, :, :2] · dR/dθ q; the rates do not enter the measurement."""
    px, J = camera.project_jacobian(world_points(x, q_body))
    c, s = math.cos(float(x[2])), math.sin(float(x[2]))
    dR_q = q_body @ np.array([[-s, -c], [c, -s]]).T  # dR/dθ · q, (n, 2)
    H = np.zeros((len(q_body), 2, N_STATES))
    H[:, :, 0:2] = J[:, :, :2]
    H[:, :, 2] = np.einsum("nij,nj->ni", J[:, :, :2], dR_q)
    return px, H
