"""Binding new features to cloth space through the current mesh estimate.

A feature found mid-run is seen at a pixel; its cloth-space position is where the current estimate
says that pixel's cloth point came from. The projected mesh nodes (ny, nx, 2) give each quad's image;
a pixel inside a projected quad is inverted to the quad's (ξ, η) by Newton's method on the bilinear
map, and (ξ, η) taken back to the rest (cloth-space) quad.
"""

from __future__ import annotations

import numpy as np

from clothd.core.mesh import QuadMesh, shape_functions

_NEWTON_STEPS = 8


def invert_bilinear(corners: np.ndarray, px: np.ndarray) -> np.ndarray:
    """(ξ, η) (m, 2) with Σ N_k(ξ, η) c_k = px for quads with corners (m, 4, 2) in FEM order N1..N4."""
    xe = np.zeros((len(px), 2))
    for _ in range(_NEWTON_STEPS):
        xi, eta = xe[:, 0], xe[:, 1]
        r = np.einsum("mk,mkd->md", shape_functions(xe), corners) - px
        # ∂N/∂ξ and ∂N/∂η of N1..N4.
        dxi = 0.25 * np.stack([-(1 - eta), (1 - eta), (1 + eta), -(1 + eta)], axis=1)
        deta = 0.25 * np.stack([-(1 - xi), -(1 + xi), (1 + xi), (1 - xi)], axis=1)
        Jm = np.stack([np.einsum("mk,mkd->md", dxi, corners), np.einsum("mk,mkd->md", deta, corners)], axis=2)
        det = Jm[:, 0, 0] * Jm[:, 1, 1] - Jm[:, 0, 1] * Jm[:, 1, 0]
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        step = np.stack(
            [
                (Jm[:, 1, 1] * r[:, 0] - Jm[:, 0, 1] * r[:, 1]) / det,
                (-Jm[:, 1, 0] * r[:, 0] + Jm[:, 0, 0] * r[:, 1]) / det,
            ],
            axis=1,
        )
        xe = np.clip(xe - step, -1.5, 1.5)
    return xe


def cloth_coordinates(mesh: QuadMesh, nodes_px: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cloth-space positions (m, 2) of pixels (m, 2) under the projected mesh nodes_px (n_nodes, 2), and
    whether each pixel lies on the mesh (m,) bool. Each pixel is tried against the quads whose projected
    bounding box holds it; the first with (ξ, η) in [-1, 1]² wins."""
    quads = mesh.quad_nodes()  # (n_quads, 4)
    corners = nodes_px[quads]  # (n_quads, 4, 2)
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    rest = mesh.rest_nodes_m().reshape(-1, 2)
    st = np.full((len(px), 2), np.nan)
    found = np.zeros(len(px), bool)
    cand_px, cand_q = np.nonzero(
        (px[:, None, 0] >= lo[None, :, 0])
        & (px[:, None, 0] <= hi[None, :, 0])
        & (px[:, None, 1] >= lo[None, :, 1])
        & (px[:, None, 1] <= hi[None, :, 1])
    )
    if len(cand_px) == 0:
        return st, found
    xe = invert_bilinear(corners[cand_q], px[cand_px])
    good = np.all(np.abs(xe) <= 1.0 + 1e-6, axis=1)
    p, q, e = cand_px[good], cand_q[good], xe[good]
    p, first = np.unique(p, return_index=True)  # candidates come in pixel, then quad order
    st[p] = np.einsum("mk,mkd->md", shape_functions(e[first]), rest[quads[q[first]]])
    found[p] = True
    return st, found
