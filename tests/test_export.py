"""`clothd export` writes MCAP that the mcap reader reads back: the channels with Foxglove's schemas, a
message per frame on each, stamped with the frames' times."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path

import cv2
import foxglove
import numpy as np
import pytest
from mcap_files import EXPORT_SCHEMAS, read_mcap

from clothd.cli import main
from clothd.drivers.footage import open_footage
from clothd.errors import InputError
from clothd.formats import read_camera
from clothd.outputs.foxglove_channels import CellChannels, encode_jpeg
from clothd.outputs.view import draw_tracking
from clothd.tools.mcap_picture import read_cell_mcap

pytestmark = pytest.mark.clock_free

Recorder = Callable[[str], Path]


def test_a_recording_exports_to_mcap_with_foxglove_schemas(short_recording: Recorder, tmp_path: Path) -> None:
    rec = short_recording("translate")
    assert main(["replay", str(rec), "--out", str(tmp_path / "replay"), "--model", "mesh"]) == 0
    out = tmp_path / "rec.mcap"
    assert (
        main(
            [
                "export",
                str(rec),
                "--mcap",
                str(out),
                "--estimates",
                str(tmp_path / "replay" / "estimates.npz"),
            ]
        )
        == 0
    )
    frame_ns = [round(t * 1e9) for t, _ in open_footage(rec).frames()]
    got = read_mcap(out)
    assert got.schemas == EXPORT_SCHEMAS
    counts = Counter({topic: len(t) for topic, t in got.times.items()})
    assert all(counts[topic] == len(frame_ns) for topic in EXPORT_SCHEMAS)
    assert got.summary_messages == sum(counts.values())
    assert got.times["/camera"] == frame_ns and got.times["/pose"] == frame_ns
    last_command = got.json["/commands"][-1]
    assert len(last_command["speed_m_s"]) == 48
    assert np.isclose(last_command["t_s"], frame_ns[-1] / 1e9)


LABEL_BAND_PX = 32  # the label's rows, to whole 16 px JPEG blocks


def _jpeg_off(jpeg: bytes, image: np.ndarray, from_row: int = 0, where: np.ndarray | None = None) -> float:
    """Mean absolute difference between a JPEG and an image, from a row down, over a mask if given."""
    decoded = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert decoded is not None and decoded.shape == image.shape
    off = np.abs(decoded.astype(int) - image.astype(int)).mean(axis=2)
    keep = np.ones(off.shape, bool) if where is None else where.copy()
    keep[:from_row] = False
    return float(off[keep].mean())


def test_an_export_decodes_to_the_estimates_and_draws(short_recording: Recorder, tmp_path: Path) -> None:
    """Every protobuf message decodes from the schemas the file carries, and holds what the recording and
    its estimates hold: the frames as JPEG, with the estimate drawn on, the mesh's edges at the nodes'
    heights, the pose."""
    rec = short_recording("compress")
    replay = tmp_path / "replay"
    assert main(["replay", str(rec), "--out", str(replay), "--model", "mesh"]) == 0
    out = tmp_path / "exports" / "rec.mcap"  # a folder yet to be made, as --out's are
    assert main(["export", str(rec), "--mcap", str(out), "--estimates", str(replay / "estimates.npz")]) == 0
    est = np.load(replay / "estimates.npz")
    log = read_cell_mcap(out)
    frames = [image for _, image in open_footage(rec).frames()]
    assert _jpeg_off(log.camera[0][1], frames[0]) < 3.0  # JPEG, quality 85
    # The annotated view is that frame with that frame's estimate drawn on (below the label's band).
    assert [t for t, _ in log.annotated] == [t for t, _ in log.camera]
    k = len(frames) - 1
    drawing = draw_tracking(
        frames[k],
        est["nodes_m"][k],
        est["meas_px"][k],
        est["pred_px"][k],
        read_camera(rec / "camera.json"),
        "",
    )
    drawn_px = np.abs(drawing.astype(int) - frames[k].astype(int)).max(axis=2) > 60
    drawn_px[:LABEL_BAND_PX] = False
    assert drawn_px.sum() > 1000
    # Away from the label the file holds exactly that drawing's JPEG (the encoder is deterministic).
    jpeg = encode_jpeg(drawing)
    assert jpeg is not None
    as_written = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert _jpeg_off(log.annotated[k][1], as_written, LABEL_BAND_PX) < 0.1
    assert _jpeg_off(log.annotated[k][1], frames[k], LABEL_BAND_PX, drawn_px) > 30.0
    ny, nx = est["nodes_m"].shape[1:3]
    edges = (nx - 1) * ny + nx * (ny - 1)
    assert all(m.ends_m.shape == (2 * edges, 3) for m in log.mesh)
    frame_of = {t: k for k, (t, _) in enumerate(log.camera)}
    peaks_m = [(m.ends_m[:, 2].max(), est["nodes_m"][frame_of[m.t_ns]][..., 2].max()) for m in log.mesh]
    assert np.allclose(*np.transpose(peaks_m))
    assert max(drawn for drawn, _ in peaks_m) > 0.005  # compress lifts a fold into the mesh
    poses = np.array([p for _, p in log.pose])
    assert np.allclose(poses, est["pose"][: len(poses)], atol=1e-9)
    assert [s["features"] > 0 for _, s in log.status].count(True) == len(log.status)
    picture = tmp_path / "pictures" / "picture.png"
    assert main(["picture", str(out), "--out", str(picture)]) == 0
    drawn = cv2.imread(str(picture))
    assert drawn is not None and drawn.shape[1] >= 1000


def test_a_picture_of_a_file_without_camera_frames_is_refused(tmp_path: Path) -> None:
    empty = tmp_path / "empty.mcap"
    with foxglove.open_mcap(empty, context=foxglove.Context()):
        pass
    with pytest.raises(InputError, match="no /camera messages"):
        read_cell_mcap(empty)
    with pytest.raises(InputError, match="no such MCAP file"):
        read_cell_mcap(tmp_path / "missing.mcap")


def test_a_picture_past_the_files_end_is_refused_and_one_within_names_the_frame_it_drew(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--at-s 99` on a shorter file drew its last frame and said 99.00 s: a time outside the frames is
    refused, and a time within them is drawn at the nearest frame, whose time it prints."""
    mcap = tmp_path / "three.mcap"
    ctx = foxglove.Context()
    channels = CellChannels(ctx)
    jpeg = encode_jpeg(np.zeros((48, 64, 3), np.uint8))
    assert jpeg is not None
    with foxglove.open_mcap(mcap, context=ctx):
        for t_ns in (0, 100_000_000, 200_000_000):
            channels.log_camera(jpeg, t_ns)
    png = str(tmp_path / "p.png")
    assert main(["picture", str(mcap), "--out", png, "--at-s", "99"]) == 2
    assert "--at-s 99: the file's camera frames span 0 to 0.20 s" in capsys.readouterr().err
    assert main(["picture", str(mcap), "--out", png, "--at-s", "0.13"]) == 0
    assert f"drew {mcap} at 0.10 s" in capsys.readouterr().out
