"""Live Foxglove output (clothd/outputs/foxglove_live.py): sessions recorded straight to MCAP by the compute
process's parts, read back with the mcap reader; their size limit and write errors; and the Foxglove
WebSocket server, with a real WebSocket client, and one that never reads."""

from __future__ import annotations

import json
import os
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from foxglove_client import SUBPROTOCOL, FoxgloveClient
from mcap_files import FOXGLOVE_SCHEMAS, read_mcap, read_mcap_front_to_back
from recorded_frames import compute_on, tick
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from clothd.config import FoxgloveConfig
from clothd.core.control import Setpoint
from clothd.core.messages import ModuleCommands
from clothd.errors import ConfigError
from clothd.loop.compute import Compute
from clothd.loop.compute_messages import TickReply, TickRequest
from clothd.outputs.foxglove_live import LiveFoxglove
from clothd.tools.bench_loop import free_port

Recorder = Callable[[str], Path]
N_MODULES = 48
IDLE = Setpoint("idle", None)


def _commands(k: int) -> ModuleCommands:
    """Commands that tell frames apart: module 0 runs at k mm/s."""
    speed = np.zeros(N_MODULES)
    speed[0] = k * 1e-3
    return ModuleCommands(speed, np.full(N_MODULES, 0.5))


def _tick(compute: Compute, k: int, **request: Any) -> TickReply:
    return tick(compute, TickRequest(IDLE, _commands(k), reset=False, want_view=False, **request))


def test_a_session_recorded_as_mcap_reads_back_with_the_exports_channels(
    short_recording: Recorder, tmp_path: Path
) -> None:
    compute = compute_on(short_recording("translate"), frames=8, recording_format="mcap")
    path = tmp_path / "session.mcap"
    started_unix_s = time.time()
    compute.start()
    try:
        replies = [_tick(compute, k, record_start=path if k == 0 else None) for k in range(12)]
        _tick(compute, 12, record_stop=True)  # the recording stops before this tick's frame
        for k in range(13, 100):  # it is active until the writer has finished the file
            rec = _tick(compute, k).recording
            if rec is not None and not rec.active:
                break
            time.sleep(0.01)
    finally:
        compute.close()  # the writer finishes the file
    ended_unix_s = time.time()
    assert compute.outputs.foxglove is not None
    status = compute.outputs.foxglove.recording_status()
    assert status is not None and status.format == "mcap" and status.dir == str(path)
    assert rec == status and not status.active
    assert (status.frames, status.dropped_frames, status.stopped_reason) == (12, 0, "stopped")
    assert status.bytes == path.stat().st_size

    got = read_mcap(path)
    assert got.schemas == FOXGLOVE_SCHEMAS
    tracking = [r.estimate is not None and r.estimate.tracking for r in replies]
    n_tracked = sum(tracking)
    assert n_tracked >= 10  # the cloth is found on the first frame or the next
    counts = {topic: len(t) for topic, t in got.times.items()}
    assert counts == {"/camera": 12, "/commands": 12, "/status": 12, "/pose": n_tracked, "/mesh": n_tracked}
    assert got.summary_messages == sum(counts.values())
    # One log time per frame, on every topic: the frame's capture time, as Unix time.
    times = np.array(got.times["/camera"])
    assert got.times["/commands"] == got.times["/status"] == list(times)
    assert np.all(np.diff(times) > 0)
    captured = np.array([r.frame_t_mono_s for r in replies], dtype=float)
    np.testing.assert_allclose(np.diff(times) / 1e9, np.diff(captured), atol=1e-6)
    assert started_unix_s <= times[0] / 1e9 and times[-1] / 1e9 <= ended_unix_s  # stamped in this run
    assert got.times["/pose"] == [t for t, tracked in zip(times, tracking, strict=True) if tracked]
    # The commands in force with each frame, and each frame's estimate, in order.
    assert [round(m["speed_m_s"][0] * 1e3) for m in got.json["/commands"]] == list(range(12))
    statuses = got.json["/status"]
    assert [s["tracking"] for s in statuses] == tracking
    for s, r, t in zip(statuses, replies, times, strict=True):
        assert r.estimate is not None
        assert s["features"] == int((~np.isnan(r.estimate.meas_px[:, 0])).sum())
        assert s["t_s"] == pytest.approx(t / 1e9, abs=1e-6)


def test_an_mcap_recording_stops_at_its_size_limit_and_its_file_stays_whole(
    short_recording: Recorder, tmp_path: Path
) -> None:
    max_bytes = 400_000  # a few of this footage's frames
    compute = compute_on(
        short_recording("translate"), frames=8, recording_format="mcap", max_record_bytes=max_bytes
    )
    path = tmp_path / "limited.mcap"
    compute.start()
    try:
        rec = _tick(compute, 0, record_start=path).recording
        for k in range(1, 60):
            rec = _tick(compute, k).recording
            if rec is not None and not rec.active:
                break
    finally:
        compute.close()
    assert rec is not None and not rec.active, "the recording never reached its limit"
    assert compute.outputs.foxglove is not None
    status = compute.outputs.foxglove.recording_status()
    assert status is not None and status.stopped_reason == f"size limit reached ({max_bytes} bytes)"
    print(f"stopped after {status.frames} frames, {status.bytes} bytes of {max_bytes}")
    assert 2 <= status.frames < 20
    assert status.bytes == path.stat().st_size <= max_bytes
    got = read_mcap(path)  # finished: the summary is there
    assert len(got.times["/camera"]) == len(got.times["/status"]) == status.frames


# Records noise frames in a process of its own whose files may not grow past FSIZE bytes: the write that
# would is refused (EFBIG), as a full disk refuses one.
WRITE_FAILS = """
import json, resource, signal, sys, time
from dataclasses import asdict
from pathlib import Path
import numpy as np
from clothd.core.messages import ModuleCommands
from clothd.outputs.foxglove_live import LiveFoxglove

signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[2]), int(sys.argv[2])))
rng = np.random.default_rng(0)
live = LiveFoxglove(None)
live.start()
live.start_recording(Path(sys.argv[1]), 10**9)
for k in range(200):
    image = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    live.add(image, time.monotonic(), ModuleCommands(np.full(4, k * 1e-3), np.zeros(4)), None)
    time.sleep(0.01)
    if not live.recording_status().active:
        break
live.close()
print(json.dumps(asdict(live.recording_status())))
"""


def test_a_write_error_stops_the_recording_and_the_file_reads_up_to_its_last_frame(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    limit = 1_000_000
    done = subprocess.run(
        [sys.executable, "-c", WRITE_FAILS, str(path), str(limit)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )
    assert done.returncode == 0, done.stderr
    status = json.loads(done.stdout.splitlines()[-1])
    print(status)
    assert not status["active"]
    assert status["stopped_reason"].startswith("write failed: File too large")
    assert "summary not written" in status["stopped_reason"]
    assert status["frames"] >= 3 and path.stat().st_size <= limit
    got = read_mcap_front_to_back(path)
    assert got.cut_short
    assert set(got.schemas) == {"/camera", "/commands"}
    # Every frame counted as written is in the file, whole, and in order.
    commands = got.json["/commands"]
    assert len(got.times["/camera"]) >= status["frames"] and len(commands) >= status["frames"]
    assert [round(m["speed_m_s"][0] * 1e3) for m in commands] == list(range(len(commands)))
    assert np.all(np.diff(got.times["/camera"]) > 0)


def test_a_recording_that_cannot_be_opened_says_why(tmp_path: Path) -> None:
    live = LiveFoxglove(None)
    live.start()
    live.start_recording(tmp_path / "no-such-dir" / "x.mcap", 10**6)
    live.close()
    status = live.recording_status()
    assert status is not None and not status.active
    assert status.stopped_reason is not None and "No such file or directory" in status.stopped_reason


# -- the WebSocket server ---------------------------------------------------------------------------


def test_a_foxglove_client_sees_the_channels_and_gets_the_pose(short_recording: Recorder) -> None:
    port = free_port()
    compute = compute_on(
        short_recording("translate"), frames=8, foxglove=FoxgloveConfig(enabled=True, port=port)
    )
    compute.start()
    client = FoxgloveClient(port, ("/pose", "/status"))
    replies = []
    try:
        assert client.subscribed.wait(20) and client.error is None, client.error
        for k in range(30):
            replies.append(_tick(compute, k))
            if len(client.received.get("/pose", [])) >= 2:
                break
            time.sleep(0.02)
        time.sleep(0.3)
    finally:
        client.close()
        compute.close()
    assert client.error is None, client.error
    advertised = {t: (c["schemaName"], c["encoding"]) for t, c in client.channels.items()}
    assert advertised == {
        "/camera": ("foxglove.CompressedImage", "protobuf"),
        "/mesh": ("foxglove.SceneUpdate", "protobuf"),
        "/pose": ("foxglove.PoseInFrame", "protobuf"),
        "/commands": ("clothd.ModuleCommands", "json"),
        "/status": ("clothd.FrameStatus", "json"),
    }
    poses = client.received.get("/pose", [])
    assert poses, f"no pose in {len(replies)} ticks"
    # Each pose came with its frame's status, tracking; and it is one of the estimates' (protobuf keeps a
    # double's 8 bytes as they are).
    statuses = {t: json.loads(p) for t, p in client.received["/status"]}
    estimates = [r.estimate.pose for r in replies if r.estimate is not None and r.estimate.tracking]
    for log_time, payload in poses:
        assert statuses[log_time]["tracking"] is True
        assert statuses[log_time]["t_s"] == pytest.approx(log_time / 1e9, abs=1e-6)
        assert any(
            struct.pack("<d", p[0]) in payload and struct.pack("<d", p[1]) in payload for p in estimates
        )
    assert not client.received.get("/camera")  # not subscribed, not sent


def test_a_client_that_never_reads_delays_neither_the_writer_nor_other_clients() -> None:
    port = free_port()
    live = LiveFoxglove(FoxgloveConfig(enabled=True, port=port))
    live.start()
    reader = FoxgloveClient(port, ("/commands",))
    rng = np.random.default_rng(1)
    frames = 150
    url = f"ws://127.0.0.1:{port}"
    try:
        with connect(url, subprotocols=[Subprotocol(SUBPROTOCOL)], close_timeout=0.1) as stalled:
            channels: dict[str, int] = {}
            while "/camera" not in channels:
                msg = json.loads(stalled.recv(timeout=10))
                if msg["op"] == "advertise":
                    channels.update({c["topic"]: c["id"] for c in msg["channels"]})
            sub = {"op": "subscribe", "subscriptions": [{"id": 0, "channelId": channels["/camera"]}]}
            stalled.send(json.dumps(sub))
            assert reader.subscribed.wait(20) and reader.error is None, reader.error
            time.sleep(0.2)
            # Noise JPEGs of ~100 kB: 15 MB for a client that reads nothing, far past any socket buffer.
            for k in range(frames):
                image = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
                live.add(image, time.monotonic(), _commands(k), None)
                time.sleep(0.005)

            def last_arrived() -> bool:
                got = reader.received.get("/commands", [])
                return bool(got) and round(json.loads(got[-1][1])["speed_m_s"][0] * 1e3) == frames - 1

            deadline = time.monotonic() + 20
            while not last_arrived() and time.monotonic() < deadline:
                time.sleep(0.05)
            assert last_arrived(), "the reading client never got the last frame's commands"
            assert live.channels.counts["/camera"] + live.dropped_frames == frames
            reader.close()
            assert reader.error is None, reader.error
            # Stopping does not wait for it either (only a second, for it to take its last messages).
            t0 = time.monotonic()
            live.close()
            assert time.monotonic() - t0 < 5
    finally:
        reader.close()
        live.close()
    assert reader.error is None, reader.error


def test_a_taken_port_is_a_clear_error(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        live = LiveFoxglove(FoxgloveConfig(enabled=True, port=port))
        with pytest.raises(ConfigError, match=f"cannot serve Foxglove on 127.0.0.1:{port}.*foxglove.port"):
            live.start()
        # clothd run finds it before anything starts: no simulated cell, no compute process.
        config = tmp_path / "c.yaml"
        config.write_text(yaml.safe_dump({"foxglove": {"enabled": True, "port": port}}))
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "clothd.cli",
                "run",
                "--sim",
                "--config",
                str(config),
                "--port",
                str(free_port()),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert done.returncode == 2
    assert f"cannot serve Foxglove on 127.0.0.1:{port}" in done.stderr and "foxglove.port" in done.stderr
    assert "hwsim" not in done.stdout
