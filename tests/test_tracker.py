"""The tracker in each mode on a short hwsim recording, graded against the truth."""

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from clothd.config import FeatureConfig, TrackerConfig
from clothd.core.messages import Estimate, feature_detections
from clothd.core.tracker import Tracker
from clothd.drivers.footage import open_footage
from clothd.formats import read_camera, write_estimates
from clothd.taichi_runtime import start_taichi
from clothd.tools.grading import material_coordinates, true_positions
from clothd.tools.offline import OfflineTracking
from hwsim.truth import Truth

pytestmark = pytest.mark.clock_free

Recorder = Callable[[str], Path]


@pytest.fixture(scope="module", autouse=True)
def _taichi() -> None:
    start_taichi("cpu")


def _run(rec: Path, cfg: TrackerConfig) -> list[Estimate]:
    return [est for _, _, est in OfflineTracking(rec, cfg)]


def _rest_xy(ests: list[Estimate]) -> np.ndarray:
    """Where the nodes lay at initialisation (the first estimate): their material points."""
    assert ests[0].nodes_m is not None
    return ests[0].nodes_m[..., :2].reshape(-1, 2)


def test_rigid_tracks_the_translating_cloth(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    ests = _run(rec, TrackerConfig(model="rigid"))
    truth = Truth.load(rec)
    assert all(e.status == "tracking" for e in ests)
    centre_true = truth.nodes_m[:, ..., :2].mean(axis=(1, 2))
    centre_est = np.array([e.pose[:2] for e in ests])
    moved = centre_true[-1] - centre_true[0]
    assert moved[1] > 0.015  # the cloth really moved
    # The segmented rectangle's centre is the cloth centre to within a pixel or so; motion is exact.
    np.testing.assert_allclose(centre_est[-1] - centre_est[0], moved, atol=0.0005)
    assert np.mean([e.residual_px.mean() for e in ests[5:]]) < 0.5


def test_mesh_nodes_follow_the_material_points(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    ests = _run(rec, TrackerConfig(model="mesh"))
    truth = Truth.load(rec)
    assert ests[-1].nodes_m is not None
    st = material_coordinates(truth, _rest_xy(ests))
    true_last = true_positions(truth, st, np.array([len(ests) - 1]))[0]
    err_mm = np.linalg.norm(ests[-1].nodes_m.reshape(-1, 3) - true_last, axis=1) * 1e3
    assert np.sqrt(np.mean(err_mm**2)) < 2.0
    assert ests[-1].stats.accepted > 300


@pytest.mark.parametrize("use_input", [True, False])
def test_mesh_follows_the_cloth_into_a_fold(short_recording: Recorder, use_input: bool) -> None:
    """compress: the two halves are pushed together and the middle buckles up. The mesh follows the
    halves and lifts its middle nodes by inextensibility (the camera barely sees height)."""
    rec = short_recording("compress")
    ests = _run(rec, TrackerConfig(model="mesh", use_input=use_input))
    truth = Truth.load(rec)
    assert all(e.status == "tracking" for e in ests)
    st = material_coordinates(truth, _rest_xy(ests))
    true_nodes = true_positions(truth, st, np.arange(len(ests)))
    est_nodes = np.array([e.nodes_m.reshape(-1, 3) for e in ests if e.nodes_m is not None])
    err_mm = np.linalg.norm(est_nodes - true_nodes, axis=2) * 1e3
    assert np.sqrt(np.mean(err_mm**2)) < 4.0 and err_mm.max() < 15.0  # the Hookean mesh: 11 / 36 mm
    folded = true_nodes[-1, :, 2] > 0.015
    assert folded.sum() >= 12  # the fold really rose (two columns of the mesh)
    assert np.all(est_nodes[-1, folded, 2] > 0.008)
    assert np.all(est_nodes[-1, true_nodes[-1, :, 2] < 0.001, 2] < 0.005)


def test_features_keep_their_identity_and_are_resampled(short_recording: Recorder) -> None:
    rec = short_recording("occlude")
    ests = _run(rec, TrackerConfig(model="mesh"))
    first = set(ests[0].feature_id.tolist())
    assert len(first) == len(ests[0].feature_id)  # unique
    # While the arm covers part of the cloth, features there are dropped; new ones appear elsewhere.
    ids_end = set(ests[-1].feature_id.tolist())
    assert ids_end - first, "no feature was ever resampled"
    assert len(first & ids_end) > 100, "identities must persist"


def test_the_estimates_say_where_each_feature_was_detected(short_recording: Recorder, tmp_path: Path) -> None:
    """A feature is detected where and when it joins the tracker's features: in a frame's first detection
    or in its upkeep (then the next frame's estimate is the first to carry it). estimates.npz says so per
    feature (detect_frame, detect_px), the material point `clothd bench accuracy` grades it as."""
    run = OfflineTracking(short_recording("occlude"), TrackerConfig(model="mesh"), read_ahead=False)
    joined: dict[int, tuple[int, np.ndarray]] = {}
    ests = []
    for k, (_, _, est) in enumerate(run):
        ests.append(est)
        assert run.tracker.features is not None
        for fid, px in zip(run.tracker.features.ids.tolist(), run.tracker.features.px, strict=True):
            joined.setdefault(fid, (k, px))
    detected = feature_detections(ests)
    assert set(detected) == set(np.concatenate([e.feature_id for e in ests]).tolist())
    assert any(k > 0 for k, _ in detected.values()), "no feature was detected after the first frame"
    for fid, (k, px) in detected.items():
        assert k == joined[fid][0]
        np.testing.assert_array_equal(px, joined[fid][1])
    write_estimates(tmp_path / "estimates.npz", ests)
    with np.load(tmp_path / "estimates.npz") as z:
        for fid, k, px in zip(z["feature_id"].tolist(), z["detect_frame"], z["detect_px"], strict=True):
            assert k == detected[fid][0]
            np.testing.assert_array_equal(px, detected[fid][1])


def test_a_budget_the_cloth_cannot_fill_is_not_detected_for_every_tick(short_recording: Recorder) -> None:
    """With max_features far above the cloth's corners the tracker would always be "short"; it judges
    "short" against what the first frame offered instead of detecting anew every tick, and still tracks
    every frame."""
    rec = short_recording("translate")
    run = OfflineTracking(rec, TrackerConfig(model="mesh", features=FeatureConfig(max_features=5000)))
    engine = run.tracker.engine
    detected: list[int] = []
    detect = engine.detect

    def counting(*args: Any, **kwargs: Any) -> np.ndarray:
        found = detect(*args, **kwargs)
        detected.append(len(found))
        return found

    engine.detect = counting  # type: ignore[method-assign]
    ests = [est for _, _, est in run]
    assert all(e.status == "tracking" for e in ests) and len(ests) > 20
    assert detected[0] > 300 and run.tracker.initial_features == detected[0]
    assert len(detected) < len(ests) // 2, f"detected {len(detected)} times in {len(ests)} frames"


def test_predict_mode_moves_with_the_belts_without_correction(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    ests = _run(rec, TrackerConfig(model="predict"))
    assert all(e.stats.nis == 0.0 for e in ests)
    dy = ests[-1].pose[1] - ests[0].pose[1]
    assert 0.01 < dy < 0.03  # the belts carried the model about 24 mm


def test_none_mode_reports_raw_features(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    ests = _run(rec, TrackerConfig(model="none"))
    last = ests[-1]
    ok = ~np.isnan(last.meas_px[:, 0])
    np.testing.assert_array_equal(last.meas_px[ok], last.pred_px[ok])
    assert ok.sum() > 300


def test_lost_cloth_is_reported_and_tracking_reinitialises(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    footage = open_footage(rec)
    frames = list(footage.frames())
    tracker = Tracker(TrackerConfig(model="rigid"), read_camera(rec / "camera.json"), None)
    first = tracker.step(frames[0][1], 0.0, None)
    assert first.status == "tracking"
    blank = np.full_like(frames[1][1], 70)
    assert tracker.step(blank, frames[1][0], None).status == "lost"
    assert tracker.step(blank, frames[2][0], None).status == "lost"
    again = tracker.step(frames[3][1], frames[3][0], None)
    assert again.status == "tracking"
    # The cloth found again gets new identities: an id names one patch for the whole run.
    assert len(again.feature_id) and again.feature_id.min() > first.feature_id.max()


def test_tracking_then_upkeep_gives_what_a_step_gives(short_recording: Recorder) -> None:
    """The live loop sends its commands between `track` and `upkeep`; split so, the tracker estimates
    exactly what `step` does, and an upkeep left out is done by the next `track`."""
    rec = short_recording("occlude")
    footage = open_footage(rec)
    camera = read_camera(rec / "camera.json")
    stepped, split, skipped = (Tracker(TrackerConfig(model="mesh"), camera, None) for _ in range(3))
    for k, (t_s, image) in enumerate(footage.frames()):
        a = stepped.step(image, t_s, None)
        b = split.track(image, t_s, None)
        split.upkeep()
        c = skipped.track(image, t_s, None)  # never upkept but by the next track
        for est in (b, c):
            assert est.nodes_m is not None and a.nodes_m is not None
            np.testing.assert_array_equal(est.nodes_m, a.nodes_m)
            np.testing.assert_array_equal(est.feature_id, a.feature_id)
        if k == 20:
            break
    assert split.upkeep() is None  # nothing left to do
    assert len(set(a.feature_id.tolist())) > 0
