"""The filter steps against filterpy, the rigid model's Jacobian against finite differences, gating."""

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from clothd.config import EkfConfig
from clothd.core import ekf, rigid
from clothd.core.camera_model import CameraModel

pytestmark = pytest.mark.clock_free


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.standard_normal((n, n))
    return A @ A.T + n * np.eye(n)


def test_predict_and_update_match_filterpy() -> None:
    rng = np.random.default_rng(0)
    m, z = 6, 8
    x, P, F, Q = rng.standard_normal(m), _spd(rng, m), rng.standard_normal((m, m)), _spd(rng, m) * 0.1
    H, R = rng.standard_normal((z, m)), _spd(rng, z) * 0.5
    meas = rng.standard_normal(z)
    ref = ExtendedKalmanFilter(dim_x=m, dim_z=z)
    ref.x, ref.P, ref.F, ref.Q = x.copy()[:, None], P.copy(), F.copy(), Q.copy()
    ref.predict()
    x_pred, P_pred = ekf.predict(x, P, F @ x, F, Q)
    np.testing.assert_allclose(x_pred, ref.x.ravel(), atol=1e-9)
    np.testing.assert_allclose(P_pred, ref.P, atol=1e-9)
    ref.update(meas[:, None], lambda _x: H, lambda xx: H @ xx, R=R)
    x_new, P_new = ekf.update(x_pred, P_pred, meas - H @ x_pred, H, R)
    np.testing.assert_allclose(x_new, ref.x.ravel(), atol=1e-9)
    np.testing.assert_allclose(P_new, ref.P, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(P_new) > 0)
    # The information form gives the same answer for R = r·I.
    x_inf, P_inf = ekf.update_information(x_pred, P_pred, meas - H @ x_pred, H, 0.7)
    x_gain, P_gain = ekf.update(x_pred, P_pred, meas - H @ x_pred, H, 0.7 * np.eye(z))
    np.testing.assert_allclose(x_inf, x_gain, atol=1e-9)
    np.testing.assert_allclose(P_inf, P_gain, atol=1e-9)


def test_gate_rejects_outliers_by_mahalanobis_distance() -> None:
    S = np.tile(np.diag([1.0, 4.0]), (3, 1, 1))
    nu = np.array([[1.0, 1.0], [0.0, 7.0], [5.0, 0.0]])
    ok, d2 = ekf.gate(nu, S, chi2=13.8)
    np.testing.assert_allclose(d2, [1.25, 12.25, 25.0])
    assert list(ok) == [True, True, False]


def test_rigid_measurement_jacobian_matches_finite_differences() -> None:
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    rng = np.random.default_rng(1)
    q = rng.uniform(-0.1, 0.1, (5, 2))
    x = np.array([0.03, -0.02, 0.4, 0.01, 0.0, 0.1])
    _, H = rigid.measure(cam, x, q)
    eps = 1e-6
    for k in range(rigid.N_STATES):
        dx = np.zeros(rigid.N_STATES)
        dx[k] = eps
        num = (rigid.measure(cam, x + dx, q)[0] - rigid.measure(cam, x - dx, q)[0]) / (2 * eps)
        np.testing.assert_allclose(H[:, :, k], num, atol=1e-4)


def test_rigid_prediction_follows_the_belts() -> None:
    x = np.zeros(rigid.N_STATES)
    twist = np.array([0.03, 0.0, 0.1])
    for _ in range(60):
        x = rigid.predict_mean(x, 1 / 30, 0.05, twist)
    np.testing.assert_allclose(x[3:], twist, atol=1e-6)
    np.testing.assert_allclose(x[0], 0.03 * 2.0, atol=0.003)
    F = rigid.transition(1 / 30, 0.05)
    x0 = np.array([0.0, 0.0, 0.0, 0.02, 0.0, 0.0])
    # Without the belt pull, the linear part is exactly F.
    np.testing.assert_allclose(rigid.predict_mean(x0, 1 / 30, 0.05, None), F @ x0)


def test_rigid_ekf_recovers_a_pose_from_pixels() -> None:
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    rng = np.random.default_rng(2)
    q = rng.uniform(-0.1, 0.1, (40, 2))
    truth = np.array([0.012, -0.008, 0.05, 0.0, 0.0, 0.0])
    z = rigid.measure(cam, truth, q)[0] + rng.normal(0, 0.3, (40, 2))
    x, P = np.zeros(6), rigid.initial_covariance(EkfConfig(initial_pos_sigma_m=0.02))
    for _ in range(3):  # iterate the linearisation
        pred, H = rigid.measure(cam, x, q)
        x, P = ekf.update(x, P, (z - pred).ravel(), H.reshape(-1, 6), 0.09 * np.eye(80))
    assert np.abs(x[:2] - truth[:2]).max() < 3e-4, x
    assert abs(x[2] - truth[2]) < 3e-3, x
