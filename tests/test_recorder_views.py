"""A live recording keeps the further cameras' views the tracker was given, each under the first camera's
frame it was paired with, whether the view reaches the recorder before its frame (a frame tracked ahead
of its tick) or after (paired between ticks); replay reads them back by that index, a frame without one
getting none."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from clothd.config import load_config
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout
from clothd.core.messages import ModuleCommands, PairedView
from clothd.drivers.footage import open_footage
from clothd.outputs.recorder import Recorder
from clothd.tools.offline import FurtherFrames

pytestmark = pytest.mark.clock_free

W, H = 64, 48
LAYOUT = ConveyorLayout.of_cell(load_config(None).cell)
STOP = ModuleCommands.all_stop(LAYOUT.n_modules)


def _image(value: int) -> np.ndarray:
    return np.full((H, W, 3), value, np.uint8)


def _recorder(out: Path, max_bytes: int = 10_000_000) -> Recorder:
    camera = CameraModel.ideal(W, H, 80.0, 1.0)
    return Recorder(out, camera, LAYOUT, max_bytes, further=[("side", camera)])


def _rows(path: Path) -> list[tuple[int, float]]:
    with path.open(newline="") as f:
        return [(int(r["index"]), float(r["t_s"])) for r in csv.DictReader(f)]


def test_views_are_recorded_under_their_frames_index_before_or_after_it(tmp_path: Path) -> None:
    rec = _recorder(tmp_path / "rec")
    t0 = 100.0
    rec.add(_image(10), t0, STOP, None)
    rec.add_views(t0, [PairedView(_image(11), t0 - 0.004)])  # paired after its frame; seen just before it
    rec.add_views(t0 + 0.066, [PairedView(_image(21), t0 + 0.060)])  # tracked ahead: before its frame
    rec.add(_image(20), t0 + 0.066, STOP, None)
    rec.add(_image(30), t0 + 0.133, STOP, None)
    rec.add_views(t0 + 0.133, [None])  # no view near enough: nothing recorded
    rec.add(_image(40), t0 + 0.2, STOP, None)
    rec.add_views(t0 + 0.2, [PairedView(_image(41), t0 + 0.21)])
    rec.stop()
    side = tmp_path / "rec" / "cameras" / "side"
    rows = _rows(side / "frames.csv")
    assert [i for i, _ in rows] == [0, 1, 3]
    np.testing.assert_allclose([t for _, t in rows], [-0.004, 0.06, 0.21], atol=1e-6)  # on the first's clock
    assert sorted(p.name for p in (side / "frames").iterdir()) == ["000000.png", "000001.png", "000003.png"]
    assert (side / "camera.json").exists()

    # Replay pairs them back by index: frame 2 has no view.
    further = FurtherFrames(side, read_ahead=False)
    first = open_footage(tmp_path / "rec")
    views = [further.view_of(first.frame_index(k)) for k in range(4)]
    assert views[2] is None
    values = [int(v.image[0, 0, 0]) for v in views if v is not None]
    assert values == [11, 21, 41]
    assert [v.t_s for v in views if v is not None] == pytest.approx([-0.004, 0.06, 0.21], abs=1e-6)


def test_a_further_camera_that_never_paired_replays_as_none(tmp_path: Path) -> None:
    rec = _recorder(tmp_path / "rec")
    for k in range(3):
        rec.add(_image(k), 10.0 + k / 15, STOP, None)
    rec.stop()
    further = FurtherFrames(tmp_path / "rec" / "cameras" / "side", read_ahead=True)
    assert [further.view_of(k) for k in range(3)] == [None, None, None]


def test_views_count_towards_the_size_limit(tmp_path: Path) -> None:
    noisy = np.random.default_rng(0).integers(0, 256, (H, W, 3), np.uint8)  # a PNG of ~9 kB
    rec = _recorder(tmp_path / "rec", max_bytes=25_000)
    rec.add(noisy, 1.0, STOP, None)
    rec.add_views(1.0, [PairedView(noisy, 1.001)])
    assert rec.active and rec.frames == 1
    rec.add(noisy, 1.066, STOP, None)
    assert not rec.active and rec.stopped_reason is not None and "size limit" in rec.stopped_reason
    assert rec.frames == 1 and rec.bytes <= 25_000
