"""The mesh EKF: node positions and velocities, corrected by features through FEM shape functions.

State: for each of the n mesh nodes x_i = [p_i, v_i] (m, m/s), world frame; 6n states in all.

Why this structure (the measured costs are in docs/benchmarks.md):
- A dense EKF costs O(m³) per tick: 864 states (12 x 12 nodes) is already ~30 ms, 20 x 20 seconds.
- The spring couplings are far stiffer than a tick: linearising them across 33 ms (F ≈ I + A·dt) gives
  dt²·k/m ≫ 1, an unstable covariance propagator. The mean is predicted by the nonlinear Taichi model
  (springs, strain limiting, contact, friction), which holds the mesh together; the covariance is
  propagated per node with F_i from the node's own friction/damping dynamics (covariance localisation
  with radius zero, as a local EKF does).
- The correction is exact for that block-diagonal prior, in information form: each feature touches the
  positions of 4 nodes, so Λ = P⁻¹ + Hᵀ R⁻¹ H is sparse (nodes sharing a quad) and one sparse solve
  gives the new mean. The posterior is localised back to 6x6 node blocks by inverting the diagonal
  blocks of Λ (the node-decoupled EKF). Cost grows about linearly with the node count.
- P stays symmetric positive definite: every block is an inverse of a symmetric positive definite
  information block, re-symmetrised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from clothd.core.ekf import UpdateStats, gate


@dataclass
class NodeBelief:
    """Mean x (n, 6) and covariance blocks P (n, 6, 6) of the nodes."""

    x: np.ndarray
    P: np.ndarray

    @property
    def positions_m(self) -> np.ndarray:
        return self.x[:, :3]

    def predict(self, x_pred: np.ndarray, F: np.ndarray, Q: np.ndarray) -> None:
        """x⁻ = f(x, u) from the model; P_i⁻ = F_i P_i F_iᵀ + Q_i. F, Q: (n, 6, 6)."""
        self.x = x_pred
        P = F @ self.P @ F.transpose(0, 2, 1) + Q
        self.P = 0.5 * (P + P.transpose(0, 2, 1))

    def innovation_covariances(self, nodes: np.ndarray, J: np.ndarray, R_px2: float) -> np.ndarray:
        """S_i (k, 2, 2) = Σ_corners J_ic P_c,pp J_icᵀ + R for features with corner nodes (k, 4) and
        Jacobian blocks J (k, 4, 2, 3); corners are uncorrelated under the localised prior."""
        Ppp = self.P[nodes][:, :, :3, :3]  # (k, 4, 3, 3)
        S = np.einsum("kcij,kcjl,kcml->kim", J, Ppp, J)
        return S + R_px2 * np.eye(2)

    def correct(
        self, nodes: np.ndarray, J: np.ndarray, residual_px: np.ndarray, R_px2: float, gate_chi2: float
    ) -> tuple[UpdateStats, np.ndarray]:
        """Gate, then the information-form update with the accepted features. nodes (k, 4) corner node
        indices, J (k, 4, 2, 3) ∂h/∂p blocks, residual ν = z − h(x⁻) (k, 2). Returns the statistics and
        the accepted mask (k,)."""
        S = self.innovation_covariances(nodes, J, R_px2)
        accepted, d2 = gate(residual_px, S, gate_chi2)
        n = len(self.x)
        if not accepted.any():
            return UpdateStats(0, len(accepted), 0.0), accepted
        nodes_a, J_a, nu = nodes[accepted], J[accepted], residual_px[accepted]
        info_prior = np.linalg.inv(self.P)  # (n, 6, 6)
        # Hᵀ R⁻¹ H: for each feature, the 3x3 block J_cᵀ J_d / R between its corners c and d.
        blocks = np.einsum("kcij,kdil->kcdjl", J_a, J_a) / R_px2  # (k, 4, 4, 3, 3)
        rows = 6 * nodes_a[:, :, None, None, None] + np.arange(3)[None, None, None, :, None]
        cols = 6 * nodes_a[:, None, :, None, None] + np.arange(3)[None, None, None, None, :]
        rows, cols = np.broadcast_to(rows, blocks.shape), np.broadcast_to(cols, blocks.shape)
        prior_r = 6 * np.arange(n)[:, None, None] + np.arange(6)[None, :, None]
        prior_c = 6 * np.arange(n)[:, None, None] + np.arange(6)[None, None, :]
        prior_r, prior_c = (
            np.broadcast_to(prior_r, info_prior.shape),
            np.broadcast_to(prior_c, info_prior.shape),
        )
        Lam = sp.csc_matrix(
            (
                np.concatenate([blocks.ravel(), info_prior.ravel()]),
                (
                    np.concatenate([rows.ravel(), prior_r.ravel()]),
                    np.concatenate([cols.ravel(), prior_c.ravel()]),
                ),
            ),
            shape=(6 * n, 6 * n),
        )
        # Hᵀ R⁻¹ ν, scattered onto the corner positions.
        g = np.zeros((n, 6))
        np.add.at(g[:, :3], nodes_a, np.einsum("kcij,ki->kcj", J_a, nu) / R_px2)
        dx = spla.spsolve(Lam, g.ravel())
        self.x = self.x + dx.reshape(n, 6)
        # Localise the posterior: the inverse of each node's 6x6 diagonal block of Λ.
        diag = np.zeros((n, 6, 6))
        Lam_coo = Lam.tocoo()
        same = (Lam_coo.row // 6) == (Lam_coo.col // 6)
        np.add.at(
            diag, (Lam_coo.row[same] // 6, Lam_coo.row[same] % 6, Lam_coo.col[same] % 6), Lam_coo.data[same]
        )
        P = np.linalg.inv(diag)
        self.P = 0.5 * (P + P.transpose(0, 2, 1))
        return UpdateStats(int(accepted.sum()), int((~accepted).sum()), float(d2[accepted].sum())), accepted
