"""A live recording keeps the further cameras' views the tracker was given, each under the first camera's
frame it was paired with, whether the view was paired before its frame was recorded (a frame tracked
ahead of its tick, or before the recording started) or after (between ticks); replay reads them back by
that index, a frame without one getting none."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from small_scenarios import SMALL_TOP, two_cameras

from clothd.config import RecordingFormat, load_config
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout
from clothd.core.messages import ModuleCommands, PairedView
from clothd.drivers.footage import open_footage, recorded_skews_s
from clothd.outputs.frame_outputs import FrameOutputs, RecordingSpec
from clothd.tools.offline import FurtherFrames
from hwsim import scenario as scenarios
from hwsim.recording import record

pytestmark = pytest.mark.clock_free

W, H = 64, 48
LAYOUT = ConveyorLayout.of_cell(load_config(None).cell)
STOP = ModuleCommands.all_stop(LAYOUT.n_modules)


def _image(value: int) -> np.ndarray:
    return np.full((H, W, 3), value, np.uint8)


def _outputs(max_bytes: int = 10_000_000) -> FrameOutputs:
    camera = CameraModel.ideal(W, H, 80.0, 1.0)
    spec = RecordingSpec(camera, [("side", camera)], LAYOUT, max_bytes, RecordingFormat.DIRECTORY)
    return FrameOutputs(spec, None)


def _rows(path: Path) -> list[tuple[int, float]]:
    with path.open(newline="") as f:
        return [(int(r["index"]), float(r["t_s"])) for r in csv.DictReader(f)]


def test_views_are_recorded_under_their_frames_index_however_they_come(tmp_path: Path) -> None:
    out = _outputs()
    t0 = 100.0
    out.add_views(t0, [PairedView(_image(11), t0 - 0.004)])  # paired before the recording started
    out.requests(tmp_path / "rec", record_stop=False)
    out.add(_image(10), t0, STOP, None)
    assert out.write_views()  # after the reply
    out.add_views(t0 + 0.066, [PairedView(_image(21), t0 + 0.060)])  # tracked ahead: before its frame
    assert not out.write_views()
    out.add(_image(20), t0 + 0.066, STOP, None)
    out.add(_image(30), t0 + 0.133, STOP, None)
    assert out.write_views()
    out.add_views(t0 + 0.133, [None])  # paired between ticks, with nothing near enough
    out.add(_image(40), t0 + 0.2, STOP, None)
    out.add_views(t0 + 0.2, [PairedView(_image(41), t0 + 0.21)])  # paired after its reply: kept ...
    out.requests(None, record_stop=True)  # ... and written as the recording stops
    side = tmp_path / "rec" / "cameras" / "side"
    rows = _rows(side / "frames.csv")
    assert [i for i, _ in rows] == [0, 1, 3]
    np.testing.assert_allclose([t for _, t in rows], [-0.004, 0.06, 0.21], atol=1e-6)  # the first's clock
    assert sorted(p.name for p in (side / "frames").iterdir()) == ["000000.png", "000001.png", "000003.png"]
    assert (side / "camera.json").exists()
    with np.load(tmp_path / "rec" / "estimates.npz") as z:  # a frame without an estimate reads lost
        assert len(z["t_s"]) == 4 and np.isnan(z["pose"]).all()

    # Replay pairs them back by index: frame 2 has no view.
    first = open_footage(tmp_path / "rec")
    further = FurtherFrames(side, read_ahead=False, first=first)
    views = [further.view_of(first.frame_index(k)) for k in range(4)]
    assert views[2] is None
    values = [int(v.image[0, 0, 0]) for v in views if v is not None]
    assert values == [11, 21, 41]
    assert [v.t_s for v in views if v is not None] == pytest.approx([-0.004, 0.06, 0.21], abs=1e-6)


def test_a_further_camera_that_never_paired_replays_as_none(tmp_path: Path) -> None:
    out = _outputs()
    out.requests(tmp_path / "rec", record_stop=False)
    for k in range(3):
        out.add(_image(k), 10.0 + k / 15, STOP, None)
    out.requests(None, record_stop=True)
    first = open_footage(tmp_path / "rec")
    further = FurtherFrames(tmp_path / "rec" / "cameras" / "side", read_ahead=True, first=first)
    assert [further.view_of(k) for k in range(3)] == [None, None, None]


def test_views_count_towards_the_size_limit(tmp_path: Path) -> None:
    noisy = np.random.default_rng(0).integers(0, 256, (H, W, 3), np.uint8)  # a PNG of ~9 kB
    out = _outputs(max_bytes=25_000)
    out.requests(tmp_path / "rec", record_stop=False)
    out.add(noisy, 1.0, STOP, None)
    out.add_views(1.0, [PairedView(noisy, 1.001)])
    out.write_views()
    rec = out.recorder
    assert rec is not None and rec.active and rec.frames == 1
    out.add(noisy, 1.066, STOP, None)
    assert not rec.active and rec.stopped_reason is not None and "size limit" in rec.stopped_reason
    assert rec.frames == 1 and rec.bytes <= 25_000


def test_an_hwsim_further_camera_takes_the_first_cameras_times_and_its_skew(
    tmp_path: Path,
) -> None:
    """hwsim writes no frames.csv: a further camera's frame k is the first camera's frame k, captured
    `capture_skew_s` later (scenario.yaml), at the scenario's frame rate."""
    late = {**SMALL_TOP, "name": "late", "capture_skew_s": 0.05}
    scenario = two_cameras(name="skewed", duration_s=0.4, fps=15, cameras=[SMALL_TOP, late])
    record(scenarios.parse(scenario), tmp_path)
    first = open_footage(tmp_path)
    assert recorded_skews_s(tmp_path) == {"cam0": 0.0, "late": 0.05}
    further = FurtherFrames(tmp_path / "cameras" / "late", read_ahead=False, first=first, skew_s=0.05)
    views = [further.view_of(k) for k in range(first.frame_count or 0)]
    assert len(views) == 7 and all(v is not None for v in views)  # 0.4 s at 15 frames/s, both ends
    assert [v.t_s for v in views if v is not None] == pytest.approx([k / 15 + 0.05 for k in range(7)])
