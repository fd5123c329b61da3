"""The daemon and `hwsim serve` as separate processes, over the real pty and the real MJPEG stream.

One simulated cell serves the whole module; the daemon under test is configured to use its pty and
video URL exactly as on a real cell. Figures that depend on this machine's speed are printed, and the
assertions keep a margin for a loaded CI machine.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import websockets
from live_cell import Cell, Daemon, start_daemon, wait
from websockets.exceptions import InvalidStatus
from websockets.typing import Origin

pytestmark = pytest.mark.slow
TICK_S = 1 / 30


def _pose_error(truth: list[float], pose: list[float]) -> tuple[float, float]:
    return math.hypot(truth[0] - pose[0], truth[1] - pose[1]), abs(
        math.remainder(truth[2] - pose[2], math.tau)
    )


def test_tracking_converges_on_the_true_pose(cell: Cell, daemon: Daemon) -> None:
    time.sleep(1.0)
    s, truth = daemon.status(), cell.truth()
    p = s["pose"]
    dist, ang = _pose_error(truth["pose"], [p["x_m"], p["y_m"], p["theta_rad"]])
    print(f"tracked pose error {dist * 1e3:.2f} mm, {math.degrees(ang):.2f} deg; {s['features']} features")
    assert dist < 0.002 and ang < math.radians(0.5)
    assert s["features"] > 100 and s["residual"]["mean_px"] < 1.0
    # The cloth lies flat, and the mesh estimate says so, in the status and in /metrics. Its measured
    # height is held to the second view's precision (issue 35: within 1.5 mm of the truth): over the
    # quads of a flat cloth the highest reads 0.7-1.3 mm of noise, run to run.
    f = s["flatness"]
    print(f"flatness at rest: {f}")
    assert f["flat"] and f["max_height_mm"] < 1.5 and f["ridges"] == [] and f["compressed_area_pct"] < 1.0
    metrics = httpx.get(f"{daemon.base}/metrics", timeout=5).text
    assert "clothd_flat 1.0" in metrics and "clothd_ridges 0.0" in metrics


def test_move_reaches_its_setpoint(cell: Cell, daemon: Daemon) -> None:
    target = [0.05, 0.03, 0.25]
    daemon.put_setpoint({"mode": "move", "x_m": target[0], "y_m": target[1], "theta_rad": target[2]})

    seen: list[tuple[float, float]] = []

    def there() -> bool:
        dist, ang = _pose_error(cell.truth()["pose"], target)
        seen.append((dist, ang))
        return dist < 0.005 and ang < math.radians(1.0)

    try:
        took = wait(there, 15, "true pose within 5 mm and 1 deg of the setpoint", every_s=0.1)
    except AssertionError:
        s = daemon.status()
        dist, ang = seen[-1]
        print(f"last true error {dist * 1e3:.1f} mm {math.degrees(ang):.2f} deg; estimate {s['pose']}")
        print(f"state {s['state']}, features {s['features']}, rejected {s['rejected_features']}")
        raise
    print(f"move settled in {took:.2f} s")
    time.sleep(1.0)
    assert there(), "the pose did not hold at the setpoint"


def test_estop_stops_every_module_at_once(cell: Cell, daemon: Daemon) -> None:
    daemon.put_setpoint({"mode": "move", "x_m": -0.05, "y_m": 0.0, "theta_rad": 0.0})
    wait(lambda: max(map(abs, cell.truth()["module_speed_m_s"])) > 0.02, 5, "modules running")
    commands_before = cell.truth()["commands_applied"]
    t0 = time.monotonic()
    daemon.post("/estop")
    seen: list[dict[str, Any]] = []

    def latched() -> bool:
        seen.append(cell.truth())
        return bool(seen[-1]["estopped"])

    wait(latched, 2, "controller e-stop latched", every_s=0.005)
    truth = seen[-1]  # the first truth that reports it: the belts stopped by then, not a step later
    assert not any(truth["module_speed_m_s"]), "every module stopped"
    # How fast is a benchmark figure (clothd bench loop: estop_ms); here, for the record:
    late = truth["commands_at_estop"] - commands_before
    took_ms = (truth["estop_t_mono_s"] - t0) * 1e3  # the firmware's clock is this host's monotonic clock
    print(f"e-stop: drives cut {took_ms:.1f} ms and {late} command(s) after the request")
    daemon.put_setpoint({"mode": "idle"})
    with pytest.raises(httpx.HTTPStatusError):  # moves are refused while the e-stop is latched
        daemon.put_setpoint({"mode": "move", "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0})
    time.sleep(0.3)
    assert not any(cell.truth()["module_cmd_speed_m_s"]), "nothing restarted the modules"
    s = daemon.status()
    assert s["estop"] and s["mode"] == "idle" and s["link"]["controller_estop"]
    daemon.post("/estop/clear")
    wait(lambda: not cell.truth()["estopped"], 2, "e-stop cleared")


def test_a_cloth_halted_past_the_edge_is_moved_back_to_the_centre(cell: Cell, daemon: Daemon) -> None:
    # The cloth's top edge 3 mm past the workspace (y 0.200 m): every tick sees it past the edge.
    daemon.put_setpoint({"mode": "idle"})
    wait(lambda: not any(cell.truth()["module_speed_m_s"]), 5, "belts still")
    httpx.post(f"{cell.http}/cloth", json={"x_m": 0.0, "y_m": 0.103, "theta_rad": 0.0}, timeout=5)
    daemon.post("/reset")
    wait(lambda: daemon.tracking_near((0.0, 0.103)), 30, "tracking the re-laid cloth", every_s=0.2)
    daemon.put_setpoint({"mode": "move", "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0})
    took = wait(lambda: _pose_error(cell.truth()["pose"], [0, 0, 0])[0] < 0.005, 15, "back at the centre")
    halt = daemon.status()["halt_reason"]
    print(f"back within 5 mm of the centre {took:.2f} s after the move; halt since: {halt}")
    assert halt is None or "edge" not in halt


def test_a_stalled_websocket_client_does_not_slow_the_loop(daemon: Daemon) -> None:
    url = daemon.base.replace("http://", "ws://") + "/api/v1/stream"

    async def body() -> tuple[int, int, int]:
        before = daemon.status()["timing"]
        async with (
            websockets.connect(url, close_timeout=0.1) as stalled,
            websockets.connect(url, close_timeout=0.1) as reader,
        ):
            stalled.transport.pause_reading()  # never reads: its socket fills up
            received = 0
            end = time.monotonic() + 4.0
            while time.monotonic() < end:
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(reader.recv(), 0.5)
                    received += 1
            after = daemon.status()["timing"]
        return after["ticks"] - before["ticks"], after["missed_ticks"] - before["missed_ticks"], received

    ticks, missed, received = asyncio.run(body())
    print(f"4 s with a stalled client: {ticks} ticks, {missed} missed, {received} messages to the reader")
    assert ticks >= 0.8 * 4.0 / TICK_S  # the loop kept its rate
    assert received >= 0.5 * ticks  # and the reader kept getting the status


def test_the_running_daemon_refuses_foreign_pages_and_huge_bodies(daemon: Daemon) -> None:
    """The guard in front of the real daemon: a cross-site "simple" request, a rebound host name, a
    100 MB body (refused from its Content-Length, never read) and a foreign WebSocket; the loop goes on."""
    api = f"{daemon.base}/api/v1"
    ticks = daemon.status()["timing"]["ticks"]
    evil = {"Origin": "http://evil.example", "Content-Type": "text/plain"}
    assert httpx.post(f"{api}/estop/clear", headers=evil, content="x", timeout=5).status_code == 403
    port = daemon.base.rsplit(":", 1)[1]
    assert httpx.get(f"{api}/status", headers={"Host": f"evil.example:{port}"}, timeout=5).status_code == 421
    huge = b"{" + b" " * 100_000_000 + b"}"
    r = httpx.put(f"{api}/setpoint", content=huge, headers={"Content-Type": "application/json"}, timeout=30)
    assert r.status_code == 413 and len(r.content) < 200

    async def foreign_websocket() -> None:
        url = daemon.base.replace("http", "ws") + "/api/v1/stream"
        with pytest.raises(InvalidStatus):
            async with websockets.connect(url, origin=Origin("http://evil.example")) as ws:
                await ws.recv()

    asyncio.run(foreign_websocket())
    wait(lambda: daemon.status()["timing"]["ticks"] > ticks + 10, 5, "the loop going on")


def test_unplugged_serial_and_video_are_survived(cell: Cell, daemon: Daemon) -> None:
    cell.post("/unplug?seconds=1.5")
    cell.post("/camera/drop?seconds=1.5")
    wait(lambda: daemon.status()["link"]["state"] != "connected", 5, "link loss noticed")
    wait(lambda: daemon.status()["state"] == "camera_lost", 5, "camera loss noticed")

    def recovered() -> bool:
        s = daemon.status()
        return s["state"] == "tracking" and s["link"]["state"] == "connected"

    took = wait(recovered, 30, "tracking again with the link up", every_s=0.2)
    s = daemon.status()
    reconnects = s["link"]["counters"]["reconnects"]
    print(f"recovered {took:.1f} s after the losses were seen; link reconnects {reconnects}")
    assert s["camera"]["reconnects"] >= 1 and s["link"]["counters"]["reconnects"] >= 1
    assert daemon.proc.poll() is None


def test_a_recording_cut_short_by_its_size_limit_replays(daemon: Daemon, tmp_path: Path) -> None:
    rec = daemon.recording_dir / "session"
    daemon.post_json("/record/start", {"dir": "session"})

    def cut_short() -> bool:
        r = daemon.status()["recording"] or {}
        return r.get("active") is False and Path(r["dir"]).name == "session"

    wait(cut_short, 20, "recording cut short")
    r = daemon.status()["recording"]
    print(f"recording stopped after {r['frames']} frames, {r['bytes']} bytes: {r['stopped_reason']}")
    assert "size limit" in r["stopped_reason"] and 0 < r["bytes"] <= 3_000_000
    ticks = daemon.status()["timing"]["ticks"]
    wait(lambda: daemon.status()["timing"]["ticks"] > ticks + 10, 5, "the loop going on")
    live = np.load(rec / "estimates.npz")
    assert len(live["t_s"]) == r["frames"]
    out = tmp_path / "replayed"
    done = subprocess.run(
        [sys.executable, "-m", "clothd.cli", "replay", str(rec), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    replayed = np.load(out / "estimates.npz")
    assert len(replayed["t_s"]) == r["frames"]
    np.testing.assert_allclose(replayed["t_s"] - replayed["t_s"][0], live["t_s"] - live["t_s"][0], atol=1e-5)
    # Offline, the same frames and commands give the same cloth: the pose agrees with what ran live.
    assert np.nanmax(np.abs(replayed["pose"][:, :2] - live["pose"][:, :2])) < 0.002


def test_both_cameras_stream_their_frames_pair_and_the_flatness_says_its_basis(daemon: Daemon) -> None:
    """The default cell's two cameras, each a stream of its own: the second's frames are paired with the
    first's and the skew measured; the flatness says what it rests on."""

    seen: list[dict[str, Any]] = []

    def paired() -> bool:
        seen.append(daemon.status())
        cams, flatness = seen[-1]["cameras"], seen[-1]["flatness"]
        streaming = all(c["state"] == "streaming" and c["healthy"] for c in cams)
        return streaming and cams[-1]["skew_ms"] is not None and flatness is not None

    wait(paired, 30, "both cameras streaming, the second paired", every_s=0.2)
    s = seen[-1]
    first, second = s["cameras"]
    print(
        f"second camera: skew {second['skew_ms']:.1f} ms (p95 {second['skew_p95_ms']:.1f}), "
        f"{second['paired_pct']:.0f} % paired; flatness basis {s['flatness']['basis']}; frames/s "
        f"{first['fps']:.1f} and {second['fps']:.1f}, longest gaps {first['longest_gap_ms']:.0f} and "
        f"{second['longest_gap_ms']:.0f} ms"
    )
    assert (first["name"], second["name"]) == ("cam0", "cam1")
    assert first["skew_ms"] is None and first["paired_pct"] is None  # the first is the reference
    assert math.isfinite(second["skew_ms"]) and math.isfinite(second["skew_p95_ms"])
    assert 0 <= second["paired_pct"] <= 100
    assert s["camera"]["source"] == first["source"]  # `camera` stays the first camera
    assert s["flatness"]["basis"] in ("measured", "since_start")
    for cam in (first, second):  # both streams deliver frames at a rate: a gap is at least a frame's time
        assert cam["fps"] > 0 and cam["longest_gap_ms"] >= 1e3 / cam["fps"]
    metrics = httpx.get(f"{daemon.base}/metrics", timeout=5).text
    assert 'clothd_camera_fps{camera="cam0"}' in metrics and 'clothd_camera_fps{camera="cam1"}' in metrics
    assert 'clothd_camera_skew_ms{camera="cam1"}' in metrics
    assert 'clothd_camera_healthy{camera="cam1"} 1.0' in metrics


def test_the_controller_watchdog_stops_the_modules_after_kill_9(
    cell: Cell, daemon: Daemon, tmp_path: Path
) -> None:
    daemon.stop()  # one host at a time on the controller's port
    victim = start_daemon(cell, tmp_path)
    try:
        victim.put_setpoint({"mode": "move", "x_m": 0.05, "y_m": -0.03, "theta_rad": -0.2})
        wait(lambda: max(map(abs, cell.truth()["module_speed_m_s"])) > 0.02, 5, "modules running")
        os.kill(victim.proc.pid, signal.SIGKILL)
        victim.proc.wait()
        took = wait(lambda: not any(cell.truth()["module_speed_m_s"]), 2, "every module stopped")
        assert cell.truth()["watchdog_tripped"]
        print(f"modules stopped {took * 1e3:.0f} ms after kill -9 (watchdog 250 ms, then the ramp)")
    finally:
        victim.stop()


def test_systemd_hears_ready_after_the_first_answered_tick_and_then_the_watchdog(
    cell: Cell, tmp_path: Path
) -> None:
    sock_path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(sock_path))
        sock.settimeout(30)
        d = start_daemon(cell, tmp_path, env={"NOTIFY_SOCKET": str(sock_path)})
        try:
            messages = [sock.recv(256).decode() for _ in range(3)]
        finally:
            d.stop()
    assert "READY=1" in messages and "WATCHDOG=1" in messages
