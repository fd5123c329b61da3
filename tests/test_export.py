"""`clothd export` writes MCAP that the mcap reader reads back: the channels with Foxglove's schemas, a
message per frame on each, stamped with the frames' times."""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from clothd.cli import main
from clothd.drivers.footage import open_footage

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
    with out.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert schemas == {
            "/camera": "foxglove.CompressedImage",
            "/mesh": "foxglove.SceneUpdate",
            "/pose": "foxglove.PoseInFrame",
            "/commands": "clothd.ModuleCommands",
            "/status": "clothd.FrameStatus",
        }
        times: dict[str, list[int]] = {}
        last_command = None
        for _, channel, message in reader.iter_messages():
            times.setdefault(channel.topic, []).append(message.log_time)
            if channel.topic == "/commands":
                last_command = json.loads(message.data)
    counts = Counter({topic: len(t) for topic, t in times.items()})
    assert all(
        counts[topic] == len(frame_ns) for topic in ("/camera", "/mesh", "/pose", "/commands", "/status")
    )
    assert times["/camera"] == frame_ns and times["/pose"] == frame_ns
    assert last_command is not None and len(last_command["speed_m_s"]) == 48
    assert np.isclose(last_command["t_s"], frame_ns[-1] / 1e9)
