"""The mesh EKF: node positions and velocities, corrected by features through FEM shape functions.

State: for each of the n mesh nodes x_i = [p_i, v_i] (m, m/s), world frame; 6n states in all.

Why this structure (the measured costs are in docs/architecture.md and docs/benchmarks.md):
- A dense EKF costs O(m³) per tick: 864 states (12 x 12 nodes) is already ~30 ms, 20 x 20 seconds.
- The spring couplings are far stiffer than a tick: linearising them across 33 ms (F ≈ I + A·dt) gives
  dt²·k/m ≫ 1, an unstable covariance propagator. The mean is predicted by the nonlinear Taichi model
  (springs, strain limiting, contact, friction), which holds the mesh together; the covariance is
  propagated per node with F_i from the node's own friction/damping dynamics (covariance localisation
  with radius zero, as a local EKF does).
- The correction is exact for that node-block prior, in information form. Features see positions
  only, and a node's velocity is correlated with its own position only, so the velocities drop out:
  (P_pp⁻¹ + Hᵀ R⁻¹ H) Δp = Hᵀ R⁻¹ ν, a sparse 3n system (nodes couple when they share a quad), then
  Δv_i = P_vp,i P_pp,i⁻¹ Δp_i. Its sparsity pattern is fixed by the mesh, so it is built once, and it
  is banded, so a banded Cholesky solves it.
- The posterior is localised back to node blocks: node i's 6x6 information gains the diagonal 3x3
  block of Hᵀ R⁻¹ H that falls on its position (the node-decoupled EKF). Every block stays symmetric
  positive definite. The cost grows about linearly with the node count.
- Optionally a smoothness prior on the correction (the mesh's edge Laplacian added to the information
  matrix) puts back some of the spatial correlation the localisation dropped; it has the quads'
  sparsity, so the solve is unchanged. So has the optional shape prior: every quad's sides and
  diagonals held near their rest lengths, for a cloth whose features cannot hold its shape alone.
  The camera corrects in the table plane only: the tracker zeroes the height column of H, and heights
  come from folds.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps

from clothd.core.ekf import UpdateStats, gate
from clothd.core.nanmedian import nanmedian

# A compressed edge is held this many times more loosely than a stretched one: yarns do not stretch, but
# cloth pushed together buckles into folds (folds.py). Looser lets a prediction that pushes part of the
# mesh into the rest pass as a fold to be: at 10, belts dragging the gingham's corner a check ahead of
# the cloth put it 4 px off; at 3 every weave met its bar (docs/benchmarks.md, "Repeating checks").
COMPRESSED_SHAPE_SIGMA_FACTOR = 3.0


class InformationPattern:
    """The fixed sparsity of Hᵀ R⁻¹ H over the d position components of every node (dn x dn; d = 3, or
    2 for x, y alone) for a mesh's quads (q, 4), and where each quad's 4d x 4d block of corner-position
    entries lands in it."""

    def __init__(self, quad_nodes: np.ndarray, n_nodes: int, d: int = 3) -> None:
        comp = np.arange(d)
        w = 4 * d  # a quad's corner coordinates
        # Global position index of each quad's 4d corner coordinates, (q, 4d), corner-major.
        dof = (d * quad_nodes[:, :, None] + comp[None, None, :]).reshape(len(quad_nodes), w)
        rows = np.broadcast_to(dof[:, :, None], (len(dof), w, w)).ravel()
        cols = np.broadcast_to(dof[:, None, :], (len(dof), w, w)).ravel()
        diag_r = np.repeat(np.arange(d * n_nodes), d)
        diag_c = (d * (np.arange(d * n_nodes) // d))[:, None].repeat(d, 1).ravel() + np.tile(
            comp, d * n_nodes
        )
        keys = np.concatenate([cols * (d * n_nodes) + rows, diag_c * (d * n_nodes) + diag_r])
        unique, inverse = np.unique(keys, return_inverse=True)  # sorted by column, then row: CSC order
        self._keys = unique
        self.d = d
        self.size = d * n_nodes
        self.quad_slots = inverse[: len(rows)].reshape(len(dof), w * w)
        self.diag_slots = inverse[len(rows) :].reshape(n_nodes, d * d)
        self.nnz = len(unique)
        # Nodes are numbered row by row, so a quad couples dofs at most d·(nx + 2) - 1 apart: the matrix
        # is banded, and a banded Cholesky (LAPACK pbsv) solves it in O(size · band²) with no fill-in
        # search. At 32 x 32 nodes that beat SuperLU (scipy.sparse.linalg.splu, COLAMD or minimum-degree
        # ordering) 3-5x (docs/benchmarks.md, "Speed and scaling").
        row, col = unique % self.size, unique // self.size
        upper = row <= col
        self.band = int((col - row)[upper].max())
        self._upper_slots = np.flatnonzero(upper)
        self._band_rows = self.band + row[upper] - col[upper]
        self._band_cols = col[upper]

    def slots(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Where the entries (rows[i], cols[i]) of the pattern are stored (all must be in it)."""
        return np.asarray(np.searchsorted(self._keys, cols * self.size + rows))

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """Solve A x = rhs for the symmetric positive definite A with these entries (nnz,)."""
        ab = np.zeros((self.band + 1, self.size))
        ab[self._band_rows, self._band_cols] = data[self._upper_slots]
        return np.asarray(sla.solveh_banded(ab, rhs, check_finite=False))


@dataclass(frozen=True)
class HeldEdges:
    """Mesh edges (e, 2) whose in-plane length is held at a bound (e,) m, σ sigma_m: from above where upper
    (e,) is True, from below where it is False."""

    edges: np.ndarray
    bound_m: np.ndarray
    upper: np.ndarray
    sigma_m: float


def _quad_mean(quads: np.ndarray, residual_px: np.ndarray) -> np.ndarray:
    """Each feature's quad's mean residual (k, 2)."""
    count = np.maximum(np.bincount(quads), 1)
    mean = np.stack([np.bincount(quads, residual_px[:, i]) / count for i in range(2)], axis=1)
    return np.asarray(mean[quads])


class NodeBelief:
    """Mean x (n, 6) and covariance blocks P (n, 6, 6) of the nodes of a mesh with quads (q, 4). The
    nodes as first given are the mesh at rest (the shape prior's rest lengths).

    planar: the correction moves x and y only. For a filter whose heights are set from outside
    (`set_heights` after every correction, as the mesh estimator does) and whose camera Jacobian has no
    height column, z and v_z are uncorrelated with the rest and unobserved, so the 3n-position solve
    splits into a 2n one for x, y and a trivial one (Δz = 0) for the heights: the same answer, with a
    band of 2·(nx + 2) - 1 instead of 3·(nx + 2) - 1, about a third of the work."""

    def __init__(self, x: np.ndarray, P: np.ndarray, quad_nodes: np.ndarray, planar: bool = False) -> None:
        self.x = x
        self.P = P
        self.planar = planar
        d = 2 if planar else 3
        self.pattern = InformationPattern(quad_nodes, len(x), d)
        # Quads that share a node are neighbours (at most 8; a quad is not its own): (q, 8), -1 padded.
        # Sparse: the dense quad-node incidence product took 27 ms at 32 x 32 nodes, in the first tick.
        n_quads = len(quad_nodes)
        incidence = sps.csr_matrix(
            (np.ones(quad_nodes.size), (np.repeat(np.arange(n_quads), 4), quad_nodes.ravel())),
            shape=(n_quads, len(x)),
        )
        adjacent = (incidence @ incidence.T).tocoo()
        pairs = np.unique(np.stack([adjacent.row, adjacent.col], axis=1), axis=0)  # sorted by quad
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        rank = np.arange(len(pairs)) - np.searchsorted(pairs[:, 0], pairs[:, 0])  # place among its row's
        self.quad_nodes = quad_nodes
        self.quad_neighbours = np.full((n_quads, 8), -1)
        self.quad_neighbours[pairs[:, 0], rank] = pairs[:, 1]
        # The graph Laplacian of the mesh's edges on node positions, as entries of the pattern.
        sides = np.concatenate([quad_nodes[:, [k, (k + 1) % 4]] for k in range(4)])
        edges = np.unique(np.sort(sides, axis=1), axis=0)
        a = (d * edges[:, :1] + np.arange(d)).ravel()
        b = (d * edges[:, 1:] + np.arange(d)).ravel()
        slot = self.pattern.slots
        self._laplacian_slots = np.concatenate([slot(a, a), slot(b, b), slot(a, b), slot(b, a)])
        self._laplacian_values = np.concatenate([np.ones(2 * len(a)), -np.ones(2 * len(a))])
        # The shape prior's edges: every quad's sides and diagonals, with their rest lengths; the 2d
        # position components of each edge's two nodes, and where its 2d x 2d block lands in the pattern.
        diagonals = np.concatenate([quad_nodes[:, [0, 2]], quad_nodes[:, [1, 3]]])
        self._shape_edges = np.concatenate([edges, np.unique(np.sort(diagonals, axis=1), axis=0)])
        ends = self.x[self._shape_edges, :d]
        self._rest_lengths_m = np.linalg.norm(ends[:, 0] - ends[:, 1], axis=1)
        self._shape_dofs = np.concatenate(
            [d * self._shape_edges[:, :1] + np.arange(d), d * self._shape_edges[:, 1:] + np.arange(d)], axis=1
        )
        w = 2 * d
        self._shape_slots = slot(
            np.repeat(self._shape_dofs, w, axis=1).ravel(), np.tile(self._shape_dofs, (1, w)).ravel()
        ).reshape(len(self._shape_edges), w * w)

    @property
    def positions_m(self) -> np.ndarray:
        return self.x[:, :3]

    def set_heights(self, z_m: np.ndarray, sigma_z_m: float, sigma_vz_m_s: float) -> None:
        """Heights (n,) given from outside the filter (folds.py): the camera does not estimate them, so
        height and vertical speed leave the filter with fixed variances, uncorrelated with the rest."""
        self.x[:, 2] = z_m
        self.x[:, 5] = 0.0
        for i, var in ((2, sigma_z_m**2), (5, sigma_vz_m_s**2)):
            self.P[:, i, :] = 0.0
            self.P[:, :, i] = 0.0
            self.P[:, i, i] = var

    def predict(self, x_pred: np.ndarray, F: np.ndarray, Q: np.ndarray) -> None:
        """x⁻ = f(x, u) from the model; P_i⁻ = F_i P_i F_iᵀ + Q_i. F, Q: (n, 6, 6)."""
        self.x = x_pred
        P = F @ self.P @ F.transpose(0, 2, 1) + Q
        self.P = 0.5 * (P + P.transpose(0, 2, 1))

    def innovation_covariances(self, nodes: np.ndarray, J: np.ndarray, R_px2: float) -> np.ndarray:
        """S_i (k, 2, 2) = Σ_corners J_ic P_c,pp J_icᵀ + R for features with corner nodes (k, 4) and
        Jacobian blocks J (k, 4, 2, d) (d = 2 or 3 position components); corners are uncorrelated under
        the localised prior."""
        d = J.shape[-1]
        Pc = self.P[:, :d, :d][nodes]  # (k, 4, d, d)
        if d == 3:
            S = (J @ Pc @ J.transpose(0, 1, 3, 2)).sum(axis=1)
            return S + R_px2 * np.eye(2)
        # The planar filter's symmetric 2 x 2 blocks, written out: 2.5x faster than batched matmul on
        # 2 x 2 matrices (0.33 against 0.84 ms at 2000 features).
        a, b, c = Pc[..., 0, 0], Pc[..., 0, 1], Pc[..., 1, 1]
        u0, u1, v0, v1 = J[..., 0, 0], J[..., 0, 1], J[..., 1, 0], J[..., 1, 1]
        S = np.empty((len(J), 2, 2))
        S[:, 0, 0] = (u0 * (a * u0 + 2.0 * b * u1) + c * u1 * u1).sum(axis=1) + R_px2
        S[:, 1, 1] = (v0 * (a * v0 + 2.0 * b * v1) + c * v1 * v1).sum(axis=1) + R_px2
        S[:, 0, 1] = S[:, 1, 0] = (u0 * (a * v0 + b * v1) + u1 * (b * v0 + c * v1)).sum(axis=1)
        return S

    def _odd_quads(
        self, quads: np.ndarray, quad_mean: np.ndarray, S: np.ndarray, gate_chi2: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(k,) bool each: the feature's quad moves unlike the quads around it (the median of their mean
        innovations), as a patch carried by an occluder does, while a model error is smooth; and whether
        its quad had featured quads enough around it to be judged so. A quad with a node up in a fold is
        never odd: a fold's sides climb while the cloth around them slides, so its quads move unlike their
        neighbours by nature (the test threw out the compress fold's whole side in one frame, and its top
        went unseen)."""
        n_quads = len(self.quad_neighbours)
        mean = np.full((n_quads + 1, 2), np.nan)  # the last row stands for "no neighbour"
        mean[quads] = quad_mean
        around = mean[self.quad_neighbours]  # (q, 8, 2); index -1 reads the NaN row
        enough = (~np.isnan(around[:, :, 0])).sum(axis=1) >= 3
        d = np.zeros((n_quads, 2))
        d[enough] = mean[:n_quads][enough] - nanmedian(around[enough], axis=1)
        # The quad's typical innovation variance: the mean of its features' S diagonals.
        s = np.bincount(quads, S[:, 0, 0] + S[:, 1, 1], minlength=n_quads) / np.maximum(
            2 * np.bincount(quads, minlength=n_quads), 1
        )
        odd = (d**2).sum(axis=1) > gate_chi2 * np.maximum(s, 1e-12)  # NaN (a quad without features) is False
        odd &= ~np.any(self.x[self.quad_nodes, 2] > 0.0, axis=1)
        return np.asarray(odd[quads]), np.asarray(enough[quads])

    def _gate(
        self, quads: np.ndarray, residual_px: np.ndarray, S: np.ndarray, gate_chi2: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Which features (k,) pass, and their d² against their quad's mean innovation (`correct`)."""
        quad_mean = _quad_mean(quads, residual_px)
        accepted, d2 = gate(residual_px - quad_mean, S, gate_chi2)
        odd, judged = self._odd_quads(quads, quad_mean, S, gate_chi2)
        accepted &= ~odd
        # A quad with too few featured quads around to judge it by has only the prediction to be judged
        # against. An arm's edge, hiding the quads around, dragged a feature alone in its quad 36 px off
        # the cloth, a few pixels a frame, each frame its quad's mean and so never odd.
        unjudged = ~judged
        if unjudged.any():
            accepted[unjudged] &= gate(quad_mean[unjudged], S[unjudged], gate_chi2)[0]
        return accepted, d2

    def _shape_information(self, sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
        """The shape prior in information form: each edge's length |p_a − p_b| a pseudo-measurement of its
        rest length, linearised at the prior mean, σ sigma_m while stretched and
        COMPRESSED_SHAPE_SIGMA_FACTOR times that while compressed. Its entries on the pattern, and its
        information vector."""
        d, e = self.pattern.d, self._shape_edges
        diff = self.x[e[:, 0], :d] - self.x[e[:, 1], :d]
        length = np.linalg.norm(diff, axis=1)
        u = diff / np.maximum(length, 1e-12)[:, None]
        sigma = np.where(length > self._rest_lengths_m, sigma_m, COMPRESSED_SHAPE_SIGMA_FACTOR * sigma_m)
        h = np.concatenate([u, -u], axis=1) / sigma[:, None]  # whitened ∂|p_a − p_b| / ∂(p_a, p_b)
        info = np.einsum("ea,eb->eab", h, h).reshape(len(e), -1)
        vector = h * ((self._rest_lengths_m - length) / sigma)[:, None]
        pat = self.pattern
        return (
            np.bincount(self._shape_slots.ravel(), info.ravel(), minlength=pat.nnz),
            np.bincount(self._shape_dofs.ravel(), vector.ravel(), minlength=pat.size),
        )

    def _edge_priors(
        self, shape_sigma_m: float, held: HeldEdges | None
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """The shape prior and the held edges, those asked for, each in information form."""
        out = [self._shape_information(shape_sigma_m)] if shape_sigma_m > 0.0 else []
        return out if held is None else [*out, self._held_information(held)]

    def _held_information(self, held: HeldEdges) -> tuple[np.ndarray, np.ndarray]:
        """HeldEdges in information form, linearised at the prior mean: each edge past its bound (shorter
        than a lower one, longer than an upper one) a pseudo-measurement of its length at the bound."""
        d, pat, e = self.pattern.d, self.pattern, held.edges
        diff = self.x[e[:, 0], :d] - self.x[e[:, 1], :d]
        length = np.linalg.norm(diff, axis=1)
        past = np.where(held.upper, length > held.bound_m, length < held.bound_m)
        u = diff / np.maximum(length, 1e-12)[:, None]
        h = np.where(past[:, None], np.concatenate([u, -u], axis=1), 0.0) / held.sigma_m
        info = np.einsum("ea,eb->eab", h, h).reshape(len(e), -1)
        vector = h * ((held.bound_m - length) / held.sigma_m)[:, None]
        dofs = np.concatenate([d * e[:, :1] + np.arange(d), d * e[:, 1:] + np.arange(d)], axis=1)
        w = 2 * d
        slots = pat.slots(np.repeat(dofs, w, axis=1).ravel(), np.tile(dofs, (1, w)).ravel())
        return (
            np.bincount(slots, info.ravel(), minlength=pat.nnz),
            np.bincount(dofs.ravel(), vector.ravel(), minlength=pat.size),
        )

    def correct(
        self,
        quads: np.ndarray,
        nodes: np.ndarray,
        J: np.ndarray,
        residual_px: np.ndarray,
        R_px2: float,
        gate_chi2: float,
        smoothness_m: float | None = None,
        shape_sigma_m: float = 0.0,
        held: HeldEdges | None = None,
    ) -> tuple[UpdateStats, np.ndarray]:
        """Gate, then correct with the accepted features. quads (k,) each feature's quad, nodes (k, 4) its
        corner nodes, J (k, 4, 2, 3) ∂h/∂p blocks, residual ν = z − h(x⁻) (k, 2). Returns the statistics
        and the accepted mask (k,). A planar belief reads J's x, y columns only (its z column must be 0).

        smoothness_m: how far the corrections of two nodes joined by a mesh edge are expected to differ
        (a zero-mean Gaussian prior on each difference). Localising the prior to node blocks dropped
        the spatial correlation a cloth has; this puts a sparse part of it back, in information form,
        so that a node no feature reaches (at the cloth's edge, in a fold, under an arm) is corrected
        with its neighbours instead of not at all.

        held: edges whose in-plane length is held to a bound (`HeldEdges`), like the shape prior.

        shape_sigma_m: how closely each edge keeps its rest length (_shape_information; 0: not held). On a
        periodic weave the features measure across its stripes only: along them, nothing but this and the
        outline keeps the nodes from wandering apart (docs/architecture.md, "Periodic weaves"). Like the
        smoothness prior it shapes the correction and leaves the covariance as the measurements make it:
        a prior restated every frame is not new information.

        The gate (and the NIS it reports) judges each feature against its quad's mean innovation: an
        outlier (an arm, a glint) disagrees with its neighbours, while a model error (the cloth slipping
        on the belts, turning faster than predicted) moves all of them alike and must be corrected, not
        rejected. Gating the raw innovation rejected whole regions in fast moves, and features re-bound
        through the lagging estimate locked its error in (docs/architecture.md). Only a quad with too few
        featured quads around to be judged by them (under an arm, at a bare corner) has its mean
        innovation gated against the prediction itself."""
        d = self.pattern.d
        J = J[..., :d]
        S = self.innovation_covariances(nodes, J, R_px2)
        accepted, d2 = self._gate(quads, residual_px, S, gate_chi2)
        if not accepted.any():
            return UpdateStats(0, len(accepted), 0.0), accepted
        n, pat, w = len(self.x), self.pattern, 4 * d
        Ja = J[accepted].transpose(0, 2, 1, 3).reshape(-1, 2, w)  # (k, 2, 4d): corner-major columns
        # Hᵀ R⁻¹ H: each feature's 4d x 4d outer product, summed into the pattern's slots by its quad.
        outer = np.einsum("kia,kib->kab", Ja, Ja).reshape(-1, w * w) / R_px2
        q = quads[accepted]
        data = np.bincount(pat.quad_slots[q].ravel(), outer.ravel(), minlength=pat.nnz)
        gain_diag = data[pat.diag_slots].reshape(n, d, d)  # measurement information on each node alone
        Ppp = self.P[:, :d, :d]
        Ppp_inv = np.linalg.inv(Ppp)
        data += np.bincount(pat.diag_slots.ravel(), Ppp_inv.ravel(), minlength=pat.nnz)
        if smoothness_m is not None:
            data += np.bincount(
                self._laplacian_slots, self._laplacian_values / smoothness_m**2, minlength=pat.nnz
            )
        # Hᵀ R⁻¹ ν on the corner positions.
        g = np.bincount(
            (d * nodes[accepted][:, :, None] + np.arange(d)).ravel(),
            np.einsum("kia,ki->ka", Ja, residual_px[accepted]).ravel() / R_px2,
            minlength=d * n,
        )
        for prior_data, prior_vector in self._edge_priors(shape_sigma_m, held):
            data += prior_data
            g += prior_vector
        dp = pat.solve(data, g).reshape(n, d)
        dv = np.einsum("nij,njk,nk->ni", self.P[:, 3:, :d], Ppp_inv, dp)
        self.x = self.x + np.concatenate([dp, np.zeros((n, 3 - d)), dv], axis=1)
        # The localised posterior P⁺ = (P⁻¹ + E G Eᵀ)⁻¹, G the node's own measurement information on its
        # positions E: by the push-through identity P⁺ = P − P E W Eᵀ P with W = (I + G Ppp)⁻¹ G (d x d,
        # symmetric), one small solve per node instead of inverting two 6 x 6 matrices.
        W = np.linalg.solve(np.eye(d) + gain_diag @ Ppp, gain_diag)
        PE = self.P[:, :, :d]
        P = self.P - PE @ W @ PE.transpose(0, 2, 1)
        self.P = 0.5 * (P + P.transpose(0, 2, 1))
        return UpdateStats(int(accepted.sum()), int((~accepted).sum()), float(d2[accepted].sum())), accepted
