"""`clothd bench loop`: the closed loop against hwsim, measured from outside.

It starts `clothd run --sim` (the daemon, which starts `hwsim serve`) as a separate process and talks to
both over HTTP, as supervisory software would; the true cloth pose comes from hwsim's /truth.

- settle: from the cloth at rest, `move` to an offset of 100 mm and 30°. settle_s is the time after
  which the true pose stays within 5 mm and 1° of the setpoint through a hold window; the final errors
  are at the end of that window.
- missed ticks over a run of `run_s` seconds at the configured tick, and frame-to-command latency.
- load: 50 requests/s to GET /status and 4 WebSocket clients, one of them stalled (it never reads),
  for `load_s` seconds: /status p99 and the missed ticks meanwhile. With `opcua`, also an OPC UA client
  subscribed to every variable of the Cell at 10 Hz (tools/opcua_load.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import multiprocessing
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import websockets
from tqdm import tqdm

from clothd.tools.opcua_load import subscriber_process
from clothd.tools.procfs import stop_group

POS_TOL_M = 0.005
ANGLE_TOL_RAD = math.radians(1.0)
OFFSET = (0.10, 0.0, math.radians(30.0))
STATUS_RATE_HZ = 50.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class DaemonProcess:
    """`clothd run --sim` in its own process group; its first lines name the URLs. Its OPC UA server
    listens on a free port of its own (opcua_url), so that benches and tests never share 4840."""

    def __init__(self, config: Path | None, port: int, cameras: int | None = None) -> None:
        """cameras: `clothd run --cameras N`, the simulated cell's first N (None: all of them)."""
        self.opcua_url = f"opc.tcp://127.0.0.1:{free_port()}/clothd/"
        cmd = [sys.executable, "-m", "clothd.cli", "run", "--sim", "--port", str(port)]
        cmd += ["--opcua-endpoint", self.opcua_url]
        if cameras is not None:
            cmd += ["--cameras", str(cameras)]
        if config is not None:
            cmd += ["--config", str(config)]
        self.base = f"http://127.0.0.1:{port}"
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, start_new_session=True, text=True
        )
        self.truth_url = ""

    def wait_ready(self, timeout_s: float = 180.0) -> None:
        assert self.proc.stdout is not None
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self.truth_url:
            line = self.proc.stdout.readline()
            if not line and self.proc.poll() is not None:
                raise RuntimeError(f"clothd run exited with {self.proc.returncode}")
            if "truth" in line:
                self.truth_url = line.split()[-1]
        if not self.truth_url:
            raise RuntimeError("clothd run --sim did not report its URLs in time")

    def stop(self) -> None:
        stop_group(self.proc)


def pose_error(truth: list[float], target: tuple[float, float, float]) -> tuple[float, float]:
    """(position error m, |angle error| rad)."""
    d = math.hypot(truth[0] - target[0], truth[1] - target[1])
    return d, abs(math.remainder(truth[2] - target[2], 2 * math.pi))


async def _wait_tracking(client: httpx.AsyncClient, base: str, timeout_s: float = 60.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = (await client.get(f"{base}/api/v1/status")).json()
        if status["state"] == "tracking" and status["link"]["state"] == "connected":
            return dict(status)
        await asyncio.sleep(0.2)
    raise RuntimeError("the daemon did not start tracking")


async def measure_settle(
    client: httpx.AsyncClient, d: DaemonProcess, hold_s: float, timeout_s: float
) -> dict[str, float | None]:
    start = (await client.get(d.truth_url)).json()["pose"]
    target = (start[0] + OFFSET[0], start[1] + OFFSET[1], start[2] + OFFSET[2])
    body = {"mode": "move", "x_m": target[0], "y_m": target[1], "theta_rad": target[2]}
    (await client.put(f"{d.base}/api/v1/setpoint", json=body)).raise_for_status()
    t0 = time.monotonic()
    entered: float | None = None
    err = (math.inf, math.inf)
    while time.monotonic() - t0 < timeout_s:
        err = pose_error((await client.get(d.truth_url)).json()["pose"], target)
        now = time.monotonic() - t0
        inside = err[0] <= POS_TOL_M and err[1] <= ANGLE_TOL_RAD
        if inside and entered is None:
            entered = now
        elif not inside:
            entered = None
        if entered is not None and now - entered >= hold_s:
            break
        await asyncio.sleep(0.05)
    held = entered is not None and time.monotonic() - t0 - entered >= hold_s
    return {
        "settle_s": entered if held else None,
        "final_err_mm": err[0] * 1e3,
        "final_err_deg": math.degrees(err[1]),
    }


async def measure_estop(client: httpx.AsyncClient, d: DaemonProcess) -> dict[str, float]:
    """POST /estop while the modules run: the time until hwsim's firmware cut the drives (both on
    this host's monotonic clock), beside one tick plus the link's round trip."""
    body = {"mode": "move", "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}
    (await client.put(f"{d.base}/api/v1/setpoint", json=body)).raise_for_status()
    deadline = time.monotonic() + 5.0
    while max(map(abs, (await client.get(d.truth_url)).json()["module_speed_m_s"])) < 0.01:
        if time.monotonic() > deadline:
            raise RuntimeError("the modules did not start for the e-stop measurement")
        await asyncio.sleep(0.02)
    t0 = time.monotonic()
    (await client.post(f"{d.base}/api/v1/estop")).raise_for_status()
    truth = (await client.get(d.truth_url)).json()
    while not truth["estopped"]:
        await asyncio.sleep(0.005)
        truth = (await client.get(d.truth_url)).json()
    status = (await client.get(f"{d.base}/api/v1/status")).json()
    (await client.post(f"{d.base}/api/v1/estop/clear")).raise_for_status()
    return {
        "estop_ms": (truth["estop_t_mono_s"] - t0) * 1e3,
        "estop_modules_moving_after": float(sum(abs(v) > 0 for v in truth["module_speed_m_s"])),
        "link_rtt_p99_ms": status["link"]["counters"]["rtt_p99_ms"],
    }


async def _timing(client: httpx.AsyncClient, base: str) -> dict[str, Any]:
    return dict((await client.get(f"{base}/api/v1/status")).json()["timing"])


def _missed_pct(before: dict[str, Any], after: dict[str, Any]) -> float:
    ticks = after["ticks"] - before["ticks"]
    missed = after["missed_ticks"] - before["missed_ticks"]
    return 100.0 * missed / max(ticks + missed, 1)


def _overrun_pct(before: dict[str, Any], after: dict[str, Any]) -> float:
    """Ticks sent with the previous commands because the compute was not done."""
    ticks = after["ticks"] - before["ticks"]
    return 100.0 * (after["compute_overruns"] - before["compute_overruns"]) / max(ticks, 1)


async def measure_run(client: httpx.AsyncClient, base: str, run_s: float) -> dict[str, float | None]:
    before = await _timing(client, base)
    await asyncio.sleep(run_s)
    after = await _timing(client, base)
    latency, tail = after["frame_to_command"], after["frame_to_command_tail"]
    return {
        "missed_tick_pct": _missed_pct(before, after),
        "compute_overrun_pct": _overrun_pct(before, after),
        "latency_p50_ms": latency["p50_ms"],
        "latency_p99_ms": latency["p99_ms"],
        "latency_tail_wait_ms": tail["wait_ms"],
        "latency_tail_tick_ms": tail["tick_ms"],
        "latency_tail_compute_ms": tail["compute_ms"],
        "latency_tail_delivery_ms": tail["delivery_ms"],
    }


async def _reader(url: str, stop: asyncio.Event, counts: list[int]) -> None:
    async with websockets.connect(url, max_size=2**22) as ws:
        while not stop.is_set():
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(ws.recv(), 0.5)
                counts.append(1)


async def _stalled(url: str, stop: asyncio.Event) -> None:
    """Connects and never reads: the server's send buffer fills and stays full."""
    async with websockets.connect(url, max_size=2**22, max_queue=1) as ws:
        ws.transport.pause_reading()
        await stop.wait()


async def _websocket_clients(ws_url: str, seconds: float) -> int:
    stop = asyncio.Event()
    counts: list[int] = []
    clients = [asyncio.create_task(_reader(ws_url, stop, counts)) for _ in range(3)]
    clients.append(asyncio.create_task(_stalled(ws_url, stop)))
    await asyncio.sleep(seconds)
    stop.set()
    await asyncio.gather(*clients, return_exceptions=True)
    return len(counts)


def _websocket_process(ws_url: str, seconds: float, result: Any) -> None:
    result.value = asyncio.run(_websocket_clients(ws_url, seconds))


class StatusPoller:
    """GET /api/v1/status on one kept-alive connection, with the least client-side work: httpx spends
    about 3 ms of Python per request, which on a saturated 2-core machine is mostly what its p99 would
    measure, not the daemon."""

    def __init__(self, base: str) -> None:
        host, port = base.removeprefix("http://").split(":")
        self.host, self.port = host, int(port)
        self.request = f"GET /api/v1/status HTTP/1.1\r\nHost: {host}\r\n\r\n".encode()
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def get(self) -> bytes:
        if self.reader is None or self.writer is None:
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        self.writer.write(self.request)
        head = await self.reader.readuntil(b"\r\n\r\n")
        if not head.startswith(b"HTTP/1.1 200"):
            raise RuntimeError(f"GET /status answered {head[:40]!r}")
        length = next(
            int(line.split(b":")[1])
            for line in head.split(b"\r\n")
            if line.lower().startswith(b"content-length")
        )
        return await self.reader.readexactly(length)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


async def measure_load(
    client: httpx.AsyncClient, base: str, load_s: float, opcua_url: str | None = None
) -> dict[str, float]:
    """The WebSocket clients (and the OPC UA subscriber) run in processes of their own, so that their
    traffic does not delay the /status timer here and inflate the latencies measured."""
    ws_url = base.replace("http://", "ws://") + "/api/v1/stream"
    received = multiprocessing.Value("l", 0)
    clients = multiprocessing.Process(target=_websocket_process, args=(ws_url, load_s + 2.0, received))
    clients.start()
    notified = multiprocessing.Value("l", 0)
    subscriber = None
    if opcua_url is not None:
        subscriber = multiprocessing.Process(
            target=subscriber_process, args=(opcua_url, load_s + 2.0, notified)
        )
        subscriber.start()
    await asyncio.sleep(1.0)
    before = await _timing(client, base)
    latencies: list[float] = []
    period = 1.0 / STATUS_RATE_HZ
    poller = StatusPoller(base)
    t_next = time.monotonic()
    end = t_next + load_s
    try:
        while time.monotonic() < end:
            t0 = time.perf_counter()
            await poller.get()
            latencies.append(time.perf_counter() - t0)
            t_next += period
            await asyncio.sleep(max(0.0, t_next - time.monotonic()))
    finally:
        poller.close()
    after = await _timing(client, base)
    await asyncio.get_running_loop().run_in_executor(None, clients.join)
    if subscriber is not None:
        await asyncio.get_running_loop().run_in_executor(None, subscriber.join)
    lat = np.asarray(latencies) * 1e3
    opcua = {} if subscriber is None else {"loaded_opcua_notifications": float(notified.value)}
    return opcua | {
        "loaded_status_p50_ms": float(np.median(lat)),
        "loaded_status_p99_ms": float(np.percentile(lat, 99)),
        "loaded_missed_tick_pct": _missed_pct(before, after),
        "loaded_compute_overrun_pct": _overrun_pct(before, after),
        "loaded_requests": float(len(lat)),
        "loaded_ws_messages": float(received.value),
    }


async def _bench(
    config: Path | None, run_s: float, load_s: float, hold_s: float, opcua: bool, cameras: int | None
) -> dict[str, Any]:
    d = DaemonProcess(config, free_port(), cameras)
    try:
        await asyncio.get_running_loop().run_in_executor(None, d.wait_ready)
        async with httpx.AsyncClient(timeout=10.0) as client:
            await _wait_tracking(client, d.base)
            await asyncio.sleep(2.0)  # let the first ticks' start-up pass
            result: dict[str, Any] = {}
            with tqdm(total=4, desc="settle, e-stop, run, load", disable=None, leave=False) as bar:
                result.update(await measure_settle(client, d, hold_s, timeout_s=20.0))
                bar.update()
                result.update(await measure_estop(client, d))
                bar.update()
                result.update(await measure_run(client, d.base, run_s))
                bar.update()
                result.update(await measure_load(client, d.base, load_s, d.opcua_url if opcua else None))
                bar.update()
            return result
    finally:
        d.stop()


def run_bench(
    config: Path | None,
    run_s: float = 60.0,
    load_s: float = 30.0,
    hold_s: float = 3.0,
    opcua: bool = False,
    cameras: int | None = None,
) -> dict[str, Any]:
    """cameras: the simulated cell's first N (None: all of them)."""
    return asyncio.run(_bench(config, run_s, load_s, hold_s, opcua, cameras))


def format_result(r: dict[str, Any]) -> str:
    def f(key: str, unit: str, fmt: str = ".2f") -> str:
        v = r.get(key)
        return "n/a" if v is None else f"{v:{fmt}} {unit}"

    opcua = ""
    if "loaded_opcua_notifications" in r:
        notes = f("loaded_opcua_notifications", "notifications", ".0f")
        opcua = f", an OPC UA client subscribed at 10 Hz: {notes}"
    return "\n".join(
        [
            "clothd bench loop (closed loop against hwsim serve)",
            f"  move 100 mm + 30 deg: settled in {f('settle_s', 's')} "
            f"(final error {f('final_err_mm', 'mm')}, {f('final_err_deg', 'deg')}; bar 5 mm, 1 deg, 6 s)",
            f"  e-stop: drives cut {f('estop_ms', 'ms', '.1f')} after POST /estop "
            f"(one tick 33.3 ms + link RTT p99 {f('link_rtt_p99_ms', 'ms', '.1f')}); "
            f"modules still moving {f('estop_modules_moving_after', '', '.0f')}",
            f"  missed ticks {f('missed_tick_pct', '%', '.3f')} (bar 0.5 %); frame-to-command latency "
            f"p50 {f('latency_p50_ms', 'ms', '.1f')}, p99 {f('latency_p99_ms', 'ms', '.1f')}; "
            f"ticks resending the last commands {f('compute_overrun_pct', '%', '.2f')}",
            f"  the slowest 5 % of frames, on average: waiting {f('latency_tail_wait_ms', 'ms', '.1f')}, "
            f"compute {f('latency_tail_compute_ms', 'ms', '.1f')}, "
            f"reply to send {f('latency_tail_delivery_ms', 'ms', '.1f')}; "
            f"their tick asked {f('latency_tail_tick_ms', 'ms', '.1f')} after they arrived",
            f"  under load (50 req/s /status, 4 WebSocket clients, 1 stalled{opcua}): /status p50 "
            f"{f('loaded_status_p50_ms', 'ms')}, p99 {f('loaded_status_p99_ms', 'ms')} (bar 10 ms); "
            f"missed ticks {f('loaded_missed_tick_pct', '%', '.3f')}, "
            f"resending {f('loaded_compute_overrun_pct', '%', '.2f')}",
        ]
    )


def write_json(result: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(result, indent=2) + "\n")
