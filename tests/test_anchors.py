"""Drift correction (clothd/core/anchors.py): a still texture under fresh sensor noise every frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from clothd.config import FeatureConfig
from clothd.core.anchors import AnchorFrames
from clothd.core.feature_set import NO_ANCHOR, FeatureSet
from clothd.core.features import FeatureEngine, GrayFrame
from clothd.core.mesh import QuadMesh

pytestmark = pytest.mark.clock_free

NOISE_GREY = 4.0


def _texture(seed: int) -> np.ndarray:
    tex = cv2.GaussianBlur(
        np.random.default_rng(seed).uniform(0, 255, (240, 320)).astype(np.float32), (0, 0), 1.5
    )
    return np.asarray(cv2.normalize(tex, None, 20, 235, cv2.NORM_MINMAX))


def _frame(engine: FeatureEngine, tex: np.ndarray, k: int) -> GrayFrame:
    noise = np.random.default_rng([1, k]).normal(0.0, NOISE_GREY, tex.shape)
    return engine.prepare(np.clip(tex + noise, 0, 255).astype(np.uint8))


def _features(engine: FeatureEngine, frame: GrayFrame, n: int) -> FeatureSet:
    mask = np.zeros(frame.gray.shape, np.uint8)
    mask[20:-20, 20:-20] = 255
    px = engine.detect(frame, mask, n)
    features = FeatureSet(QuadMesh.covering(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]), 4, 4))
    features.add(px, np.full((len(px), 2), 0.5), np.ones(len(px), bool))
    return features


def _still_cloth_error_px(anchor: bool, frames: int) -> list[float]:
    """Mean distance of the features from where they were born, every 100 frames."""
    cfg = FeatureConfig(anchor=anchor)
    engine = FeatureEngine(cfg)
    tex = _texture(0)
    prev = _frame(engine, tex, 0)
    features = _features(engine, prev, 200)
    born = features.px.copy()
    anchors = AnchorFrames(cfg)
    anchors.adopt(prev, features)
    errors = []
    for k in range(1, frames + 1):
        cur = _frame(engine, tex, k)
        result = engine.track(prev, cur, features.px)
        measured = anchors.refine(engine, cur, features, result.px, result.ok)[0] if anchor else result.px
        features.keep(result.ok, measured)
        anchors.adopt(cur, features)
        prev = cur
        if k % 100 == 0:
            errors.append(float(np.linalg.norm(features.px - born[features.ids], axis=1).mean()))
    return errors


def test_a_still_feature_stays_where_its_anchor_puts_it() -> None:
    drifting = _still_cloth_error_px(anchor=False, frames=400)
    anchored = _still_cloth_error_px(anchor=True, frames=400)
    # Frame to frame, the error is a random walk; held to an anchor, it is one frame's noise, for good.
    assert drifting[-1] > 1.5 * drifting[0]
    assert anchored[-1] < 0.08 and anchored[-1] <= anchored[0] + 0.02
    assert anchored[-1] < 0.6 * drifting[-1]


def test_an_anchor_that_no_longer_looks_like_its_feature_is_released() -> None:
    cfg = FeatureConfig()
    engine = FeatureEngine(cfg)
    first = _frame(engine, _texture(0), 0)
    features = _features(engine, first, 100)
    anchors = AnchorFrames(cfg)
    anchors.adopt(first, features)
    assert (features.anchor_frame != NO_ANCHOR).all()
    # The same texture: every anchor agrees with the frame-to-frame answer.
    same = _frame(engine, _texture(0), 1)
    _, stats = anchors.refine(engine, same, features, features.px, np.ones(len(features), bool))
    assert stats.anchored == len(features) and stats.released == 0
    # Another texture where the frame-to-frame tracker claims the points still are: no anchor agrees.
    other = _frame(engine, _texture(5), 2)
    measured, stats = anchors.refine(engine, other, features, features.px, np.ones(len(features), bool))
    assert stats.released > 0.9 * len(features)
    released = features.anchor_frame == NO_ANCHOR
    np.testing.assert_array_equal(measured[released], features.px[released])


def test_a_feature_the_cloth_carried_off_its_anchor_is_released_untouched() -> None:
    cfg = FeatureConfig()
    engine = FeatureEngine(cfg)
    tex = _texture(0)
    first = _frame(engine, tex, 0)
    features = _features(engine, first, 100)
    anchors = AnchorFrames(cfg)
    anchors.adopt(first, features)
    shifted = np.roll(tex, 2, axis=1)  # the cloth moved 2 px right, and the tracker followed it
    carried = features.px + np.float32([2.0, 0.0])
    measured, stats = anchors.refine(
        engine, _frame(engine, shifted, 1), features, carried, np.ones(len(features), bool)
    )
    assert stats.released == len(features) and stats.anchored == 0
    np.testing.assert_array_equal(measured, carried)
    assert (features.anchor_frame == NO_ANCHOR).all()


def test_loose_features_are_anchored_together_and_too_many_frames_start_afresh() -> None:
    cfg = FeatureConfig(anchor_adopt_frames=3, anchor_max_frames=2)
    engine = FeatureEngine(cfg)
    tex = _texture(0)
    frame = _frame(engine, tex, 0)
    features = _features(engine, frame, 60)
    anchors = AnchorFrames(cfg)
    anchors.adopt(frame, features)  # no anchor frame yet: at once
    assert len(anchors.frames) == 1
    for k in range(1, 3):  # loose features wait for anchor_adopt_frames frames
        features.anchor_frame[k] = NO_ANCHOR
        anchors.adopt(_frame(engine, tex, k), features)
        assert len(anchors.frames) == 1
    anchors.adopt(_frame(engine, tex, 3), features)
    assert len(anchors.frames) == 2 and not (features.anchor_frame == NO_ANCHOR).any()
    assert len(set(features.anchor_frame[1:3].tolist())) == 1
    for k in range(4, 7):  # a third frame is one too many: everything is anchored in the newest
        features.anchor_frame[10] = NO_ANCHOR
        anchors.adopt(_frame(engine, tex, k), features)
    assert len(anchors.frames) == 1
    assert len(set(features.anchor_frame.tolist())) == 1
    np.testing.assert_array_equal(features.anchor_px, features.px)
    # Frames no feature uses any more are forgotten.
    features.keep(np.zeros(len(features), bool), features.px)
    anchors.adopt(_frame(engine, tex, 7), features)
    assert anchors.frames == {}
