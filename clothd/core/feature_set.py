"""The features the tracker follows: an identity each, the pixel where LK last measured it, its
material point: cloth-space (s, t) and where that sits on the rest mesh (its binding), and its anchor: the
frame and pixel it is held to against drift (clothd/core/anchors.py), or none yet.

Identities are never reused: a feature keeps its id from detection until it is dropped (forward–backward
check, the filter's gate, or leaving the cloth), and a set made after a loss numbers on from the last
(`first_id`), so an id names one patch for the whole run.
"""

from __future__ import annotations

import numpy as np

from clothd.core.mesh import Binding, QuadMesh

NO_ANCHOR = -1  # anchor_frame of a feature not (yet, or no longer) anchored


class FeatureSet:
    def __init__(self, mesh: QuadMesh, first_id: int = 0) -> None:
        self.mesh = mesh
        self.ids = np.zeros(0, np.int64)
        self.px = np.zeros((0, 2), np.float32)
        self.cloth_st = np.zeros((0, 2))
        self.binding: Binding = mesh.bind(self.cloth_st)
        self.anchor_frame = np.zeros(0, np.int64)
        self.anchor_px = np.zeros((0, 2), np.float32)
        self.next_id = first_id

    def __len__(self) -> int:
        return len(self.ids)

    def add(self, px: np.ndarray, cloth_st: np.ndarray, on_cloth: np.ndarray) -> None:
        """New features at pixels px (m, 2) with cloth coordinates (m, 2); those not on_cloth (m,) or off
        the mesh are left out."""
        on = on_cloth & self.mesh.bind(np.nan_to_num(cloth_st)).inside
        px, cloth_st = px[on], cloth_st[on]
        self.ids = np.concatenate([self.ids, self.next_id + np.arange(len(px))])
        self.next_id += len(px)
        self.px = np.concatenate([self.px, px.astype(np.float32)])
        self.cloth_st = np.concatenate([self.cloth_st, cloth_st])
        self.binding = self.mesh.bind(self.cloth_st)
        self.anchor_frame = np.concatenate([self.anchor_frame, np.full(len(px), NO_ANCHOR)])
        self.anchor_px = np.concatenate([self.anchor_px, np.full((len(px), 2), np.nan, np.float32)])

    def keep(self, keep: np.ndarray, measured_px: np.ndarray) -> None:
        """Keep the features selected by the mask keep (n,), now measured at measured_px (n, 2)."""
        self.ids, self.cloth_st = self.ids[keep], self.cloth_st[keep]
        self.binding = self.binding.subset(np.flatnonzero(keep))
        self.px = measured_px[keep].astype(np.float32)
        self.anchor_frame, self.anchor_px = self.anchor_frame[keep], self.anchor_px[keep]
