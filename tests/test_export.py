"""`clothd export` writes MCAP that the mcap reader reads back: the channels with Foxglove's schemas, a
message per frame on each, stamped with the frames' times."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap_files import FOXGLOVE_SCHEMAS, read_mcap

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
    got = read_mcap(out)
    assert got.schemas == FOXGLOVE_SCHEMAS
    counts = Counter({topic: len(t) for topic, t in got.times.items()})
    assert all(counts[topic] == len(frame_ns) for topic in FOXGLOVE_SCHEMAS)
    assert got.summary_messages == sum(counts.values())
    assert got.times["/camera"] == frame_ns and got.times["/pose"] == frame_ns
    last_command = got.json["/commands"][-1]
    assert len(last_command["speed_m_s"]) == 48
    assert np.isclose(last_command["t_s"], frame_ns[-1] / 1e9)
