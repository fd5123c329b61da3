"""`clothd run` with Foxglove on, against `hwsim serve` as on a cell: a session recorded straight to MCAP
over the API, and the Foxglove WebSocket server, in the daemon's own processes."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from foxglove_client import FoxgloveClient
from live_cell import Cell, start_daemon, wait
from mcap_files import FOXGLOVE_SCHEMAS, read_mcap

from clothd.tools.bench_loop import free_port

pytestmark = pytest.mark.slow


def test_clothd_run_records_a_session_to_mcap_and_serves_foxglove(cell: Cell, tmp_path: Path) -> None:
    port = free_port()
    config = {
        "recording": {"format": "mcap", "max_bytes": 100_000_000},
        "foxglove": {"enabled": True, "port": port},
    }
    daemon = start_daemon(cell, tmp_path, config=config)
    client = FoxgloveClient(port, ("/pose", "/status"))
    try:
        assert client.subscribed.wait(20) and client.error is None, client.error
        started_unix_s = time.time()
        daemon.post_json("/record/start", {"dir": "session"})
        wait(lambda: (daemon.status()["recording"] or {}).get("frames", 0) >= 15, 30, "15 frames recorded")
        daemon.post("/record/stop")
        # The writer finishes the file off the tick: the recording is active until it has.
        wait(lambda: daemon.status()["recording"]["active"] is False, 10, "the file finished")
        final = daemon.status()["recording"]
        ended_unix_s = time.time()
        path = tmp_path / "recordings" / "session.mcap"
        assert (
            final["format"] == "mcap" and final["dir"] == str(path) and final["stopped_reason"] == "stopped"
        )
        assert final["bytes"] == path.stat().st_size
        poses = len(client.received.get("/pose", []))
        assert daemon.proc.poll() is None
    finally:
        client.close()
        daemon.stop()
    got = read_mcap(path)
    assert got.schemas == FOXGLOVE_SCHEMAS
    frames = len(got.times["/camera"])
    assert frames == final["frames"] >= 15 and final["dropped_frames"] == 0
    assert len(got.times["/commands"]) == len(got.times["/status"]) == frames
    assert len(got.times["/pose"]) >= frames - 2  # the cloth is tracked throughout
    assert np.all(np.diff(got.times["/camera"]) > 0)
    # Unix time, of this run: the frames' capture times, from the start request (less the 1 s a frame may
    # be old, camera.stale_after_s) to the file finished.
    assert started_unix_s - 1.0 <= got.times["/camera"][0] / 1e9
    assert got.times["/camera"][-1] / 1e9 <= ended_unix_s
    assert poses > 0 and client.error is None
