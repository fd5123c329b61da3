"""The oracle: the tracker's features measured at their true pixels (clothd/tools/oracle.py), so that
`clothd bench accuracy --oracle` tells LK's error from the estimator's."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from clothd.config import load_config
from clothd.core.camera_model import CameraModel
from clothd.core.ekf import UpdateStats
from clothd.core.estimators import Measurements
from clothd.core.feature_set import FeatureSet
from clothd.core.mesh import QuadMesh
from clothd.taichi_runtime import start_taichi
from clothd.tools.bench_accuracy import grade
from clothd.tools.grading import FeatureTruth
from clothd.tools.oracle import OracleEstimator
from hwsim.truth import Truth

Recorder = Callable[[str], Path]


class _Recorded:
    """An estimator that keeps the measurements it is corrected with."""

    def __init__(self) -> None:
        self.seen: list[Measurements] = []

    def correct(self, m: Measurements) -> tuple[UpdateStats, np.ndarray]:
        self.seen.append(m)
        return UpdateStats(int(m.ok.sum()), 0, 0.0), m.ok.copy()


def test_the_oracle_measures_each_known_feature_at_its_true_pixel_in_the_frame_tracked() -> None:
    mesh = QuadMesh(3, 3, np.zeros(2), 0.0, 0.2, 0.2)
    features = FeatureSet(mesh)
    features.add(np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]]), np.full((3, 2), 0.1), np.ones(3, bool))
    st = np.stack(np.meshgrid([0.0, 0.2], [0.0, 0.2]), axis=-1)
    flat = Truth(np.zeros(1), np.zeros((1, 2, 2, 3)), st, np.ones((1, 2, 2), bool))
    truth = FeatureTruth(flat, CameraModel.ideal(640, 480, 900.0, 1.0))
    truth.pixels = {0: np.array([[1.0, 2.0], [3.0, 4.0]]), 2: np.array([[5.0, 6.0], [7.0, 8.0]])}
    inner = _Recorded()
    oracle = OracleEstimator(inner, truth)  # type: ignore[arg-type]  # only correct is asked of it
    oracle.frame = 1
    lk_px = np.array([[11.0, 11.0], [21.0, 21.0], [31.0, 31.0]])
    oracle.correct(Measurements(features, lk_px, np.array([True, True, False])))
    (m,) = inner.seen
    np.testing.assert_array_equal(m.px[0], [3.0, 4.0])  # the truth's, in frame 1
    assert m.ok.tolist() == [True, False, False]  # id 1: unknown to the truth; id 2: LK lost it


@pytest.mark.slow
def test_with_the_oracle_a_translating_cloth_is_placed_closer_than_with_lk(short_recording: Recorder) -> None:
    """On a flat cloth moving rigidly the mesh can place every feature exactly: with LK's noise gone the
    estimate puts the features nearer the truth. A wrong frame or a wrong pixel in the oracle would put
    them further off. (The nodes' error on this second of footage is the first frame's footprint's, the
    same with either.)"""
    start_taichi("cpu")
    rec = short_recording("translate")
    cfg = load_config(None).tracker
    lk = grade(rec, "translate", "mesh", cfg).row
    oracle = grade(rec, "translate", "mesh", cfg, oracle=True).row
    assert oracle.lost_frames == 0
    assert oracle.feat_mean_px < 0.5 * lk.feat_mean_px
