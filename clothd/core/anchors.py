"""Drift correction: each feature is held to its appearance in an anchor frame, not only to the last frame.

Frame-to-frame LK adds a little error every frame, and nothing takes it back: on a still cloth the
residual grew from 0.005 px to 0.9 px in 5 minutes. Following Zinsser et al. (tracking
features against a reference template, as the report's own smart-camera tracker does) and Matthews et
al. 2004 ("The template update problem"), every frame-to-frame result is refined by one more LK pass from
the feature's anchor, the frame and pixel where it was anchored, started at the frame-to-frame answer.
Where the two agree within `anchor_max_px` and the patch still looks like its anchor
(`lk_min_ncc`), the anchored position is the measurement, so a still feature stays where its anchor puts
it however long it is tracked. Where they disagree, the feature keeps the frame-to-frame answer and
loses its anchor. So does a feature that moved more than `anchor_still_px` off its anchor: the cloth
carried it, and turned or deformed it on the way, so the anchor's look no longer fits it (anchored
through every move, the shipped scenarios' feature error grew by up to 20 %: clothd bench accuracy). The
anchor is for the cloth at rest, where drift builds up unseen; a moving feature is renewed anyway.

Features without an anchor (new ones, and those that lost theirs) are anchored together in the current
frame once every `anchor_adopt_frames` frames, so that all features share a few anchor frames and the
extra pass costs a few LK calls a tick, not one per feature. When more than `anchor_max_frames` would be
in use, every feature is anchored afresh in the current frame: a moving cloth thus takes a new keyframe
every so often, and drifts only by what accumulates between keyframes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clothd.config import FeatureConfig
from clothd.core.feature_set import NO_ANCHOR, FeatureSet
from clothd.core.features import FeatureEngine, GrayFrame


@dataclass(frozen=True)
class AnchorStats:
    """How the last refinement went: features held to an anchor, and those that lost theirs."""

    anchored: int
    released: int
    frames: int


class AnchorFrames:
    """The anchor frames in use, by id, and when features were last anchored."""

    def __init__(self, cfg: FeatureConfig) -> None:
        self.cfg = cfg
        self.frames: dict[int, GrayFrame] = {}
        self._next_id = 0
        self._since_adopt = 0

    def reset(self) -> None:
        self.frames.clear()
        self._since_adopt = 0

    def refine(
        self,
        engine: FeatureEngine,
        cur: GrayFrame,
        features: FeatureSet,
        tracked_px: np.ndarray,
        ok: np.ndarray,
    ) -> tuple[np.ndarray, AnchorStats]:
        """The measurements (n, 2) float32: tracked_px (the frame-to-frame answer), replaced by the anchored
        position where it agrees, refined with the tracker's engine (it changes with the weave). Features
        whose anchor disagrees are released (their anchor dropped)."""
        px = np.array(tracked_px, np.float32, copy=True)
        anchored = released = 0
        for frame_id, anchor in self.frames.items():
            members = np.flatnonzero(ok & (features.anchor_frame == frame_id))
            # A feature that moved off its anchor has turned or deformed with the cloth since: the anchor's
            # look no longer fits it, and a translational LK from it would pull it aside.
            offset_px = np.linalg.norm(px[members] - features.anchor_px[members], axis=1)
            moved = offset_px > self.cfg.anchor_still_px
            features.anchor_frame[members[moved]] = NO_ANCHOR
            released += int(moved.sum())
            members = members[~moved]
            if len(members) == 0:
                continue
            refined, agrees = engine.refine_to_anchor(
                anchor, cur, features.anchor_px[members], px[members], self.cfg.anchor_max_px
            )
            px[members[agrees]] = refined[agrees]
            features.anchor_frame[members[~agrees]] = NO_ANCHOR
            anchored += int(agrees.sum())
            released += int((~agrees).sum())
        return px, AnchorStats(anchored, released, len(self.frames))

    def adopt(self, cur: GrayFrame, features: FeatureSet) -> None:
        """After the tick's features are final: anchor those without one in the current frame, every
        anchor_adopt_frames frames (or all of them when that would need too many frames), and forget frames
        no feature uses."""
        self._since_adopt += 1
        in_use = set(np.unique(features.anchor_frame[features.anchor_frame != NO_ANCHOR]).tolist())
        for frame_id in list(self.frames):
            if frame_id not in in_use:
                del self.frames[frame_id]
        loose = features.anchor_frame == NO_ANCHOR
        if not loose.any() or (self.frames and self._since_adopt < self.cfg.anchor_adopt_frames):
            return
        if len(self.frames) >= self.cfg.anchor_max_frames:
            self.frames.clear()
            loose[:] = True
        frame_id = self._next_id
        self._next_id += 1
        self.frames[frame_id] = cur
        features.anchor_frame[loose] = frame_id
        features.anchor_px[loose] = features.px[loose]
        self._since_adopt = 0
