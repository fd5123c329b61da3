"""Oracle features: the tracker run with every feature LK keeps measured at its true pixel.

The tracker's error has two sources: where LK puts a feature, and what the estimator can make of the
features (a quad mesh, bilinear inside each quad, its heights inferred from inextensibility and the
second view). With the oracle the first is gone, so what `clothd bench accuracy --oracle` still reports is
the estimator's own. A feature keeps LK's verdict (one LK lost, under an arm or off the frame, stays
unmeasured); its pixel is the truth's, the projection of the material point it was detected on
(grading.FeatureTruth). A feature the truth does not know yet is not measured: one found in a frame's
upkeep is first measured in the next frame, before the estimate that reports its detection.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from clothd.core.conveyor import BeltField
from clothd.core.ekf import UpdateStats
from clothd.core.estimators import Estimator, Measurements, StateEstimate
from clothd.core.feature_set import FeatureSet
from clothd.core.mesh import QuadMesh
from clothd.core.messages import Estimate
from clothd.tools.grading import FeatureTruth
from clothd.tools.offline import OfflineTracking


class OracleEstimator:
    """An estimator whose corrections see each feature at its true pixel in frame `frame`."""

    def __init__(self, inner: Estimator, truth: FeatureTruth) -> None:
        self.inner = inner
        self.truth = truth
        self.frame = 0  # the frame being tracked, an index into the truth's

    def correct(self, m: Measurements) -> tuple[UpdateStats, np.ndarray]:
        px = np.array(m.px, dtype=np.float64)
        known = np.zeros(len(px), bool)
        for j, fid in enumerate(m.features.ids.tolist()):
            track = self.truth.pixels.get(fid)
            if track is not None:
                px[j], known[j] = track[self.frame], True
        return self.inner.correct(replace(m, px=px, ok=m.ok & known))

    def start(self, mesh: QuadMesh, pose0: np.ndarray, nodes_m: np.ndarray | None = None) -> None:
        self.inner.start(mesh, pose0, nodes_m)

    def predict(self, u: BeltField | None, dt_s: float) -> None:
        self.inner.predict(u, dt_s)

    def feature_pixels(self, features: FeatureSet) -> np.ndarray | None:
        return self.inner.feature_pixels(features)

    def cloth_coordinates(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.inner.cloth_coordinates(px)

    def outline_px(self) -> np.ndarray | None:
        return self.inner.outline_px()

    def estimate(self) -> StateEstimate:
        return self.inner.estimate()


def track_with_oracle(run: OfflineTracking, truth: FeatureTruth) -> list[Estimate]:
    """Every frame's estimate of `run`, its tracker's features measured by the oracle. `truth` learns
    each feature as an estimate reports its detection."""
    oracle = OracleEstimator(run.tracker.estimator, truth)
    run.tracker.estimator = oracle
    frame_at: dict[float, int] = {}
    ests = []
    for k, (_, _, est) in enumerate(run):
        ests.append(est)
        frame_at[est.frame_t_s] = k
        d = est.detected
        for t_s in np.unique(d.t_s):
            if float(t_s) in frame_at:
                at = d.t_s == t_s
                truth.learn(frame_at[float(t_s)], d.ids[at].tolist(), d.px[at])
        oracle.frame = k + 1  # the generator tracks the next frame when asked for it
    return ests
