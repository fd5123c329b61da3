"""`clothd bench abuse`: floods from a local process with no credentials against `clothd run --sim`
(with api.token set, or without it: `token`; the daemon and its API process each held to 1,024 file
descriptors as under systemd), measured from outside. Each flood lasts `flood_s` seconds, all on
loopback, everything closed at the end:
- slow-header: `connections` sockets send a request line and a header, then nothing;
- slow-body: `connections` sockets send whole headers announcing a 1,000-byte body, then a byte a second;
- websocket-idle: WEBSOCKETS WebSocket handshakes, and then nothing is ever read;
- opcua-declared: OPC UA connections whose first header declares ~4 GB, each then streaming up to
  128 MiB into it, one after another;
- opcua-sessions: OPC_SESSIONS anonymous OPC UA sessions opened (OPC_CONCURRENCY at a time) and held;
  then user `clothd` logs in and calls EStop: does it latch, and how long did it take?
The held sockets are re-opened as the daemon drops them (at most REOPEN_PER_S a second).
Meanwhile POST /api/v1/estop is sent every 100 ms, twice, from a process of its own: on a fresh
connection each time (the first click after a pause), and on one kept alive (a dashboard or HMI that
stays connected): the round trips. Before and after: the daemon's missed ticks and link losses, the
API process's open file descriptors and resident memory (from /proc: it holds the connections), and the
flatness the daemon reports on the flat cloth, sampled through the flood and after it.
"""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import logging
import multiprocessing
import resource
import socket
import struct
import tempfile
import threading
import time
from collections.abc import Callable
from multiprocessing.queues import Queue as QueueType
from multiprocessing.synchronize import Event as EventType
from pathlib import Path
from typing import Any, Self

import httpx
import numpy as np
import yaml
from asyncua import Client
from tqdm import tqdm

from clothd.loop.process_names import API_PROCESS_NAME
from clothd.tools.bench_loop import DaemonProcess, free_port
from clothd.tools.opcua_load import NAMESPACE_URI
from clothd.tools.procfs import open_fds, rss_mb, spawned_children

REOPEN_PER_S = 500.0
ESTOP_EVERY_S = 0.1
SETTLE_S = 7.0  # after a flood: longer than api.request_timeout_s, so dropped connections are gone
SAMPLE_EVERY_S = 0.5  # the flatness the daemon reports, sampled through a flood
DAEMON_FDS = 1024  # systemd's default LimitNOFILE
TOKEN = "bench-abuse-token-0123456789"
WEBSOCKETS = 130
DECLARED_BYTES = 4_000_000_000
STREAM_BYTES = 128 * 1024 * 1024
OPC_SESSIONS = 1000
OPC_CONCURRENCY = 50
SOCKET_FLOODS = {
    "slow-header": b"GET /api/v1/status HTTP/1.1\r\nHost: 127.0.0.1\r\n",
    "slow-body": (
        b"PUT /api/v1/setpoint HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        b"Content-Length: 1000\r\n\r\n{"
    ),
    "websocket-idle": (
        b"GET /api/v1/stream HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    ),
}
FLOODS = (*SOCKET_FLOODS, "opcua-declared", "opcua-sessions")


class Background:
    """Work on a thread of its own from `with` to its end, which stops and joins it."""

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=60)

    def _run(self) -> None:
        raise NotImplementedError


class Flood(Background):
    """Holds `n` sockets open to the port with `opening` sent, re-opening dropped ones, until stopped."""

    def __init__(self, port: int, opening: bytes, n: int) -> None:
        self.port, self.opening, self.n = port, opening, n
        self.opened = 0
        super().__init__()

    def _open(self) -> socket.socket | None:
        try:
            s = socket.socket()
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # never read: it fills soon
            s.settimeout(1)
            s.connect(("127.0.0.1", self.port))
            s.sendall(self.opening)
            s.setblocking(False)
            self.opened += 1
            return s
        except OSError:
            return None

    def _run(self) -> None:
        held: list[socket.socket] = []
        last_trickle = time.monotonic()
        try:
            while not self._stop.is_set():
                alive = []
                for s in held:  # keep those the daemon has not dropped
                    try:
                        dropped = s.recv(1, socket.MSG_PEEK) == b""
                    except BlockingIOError:
                        dropped = False
                    except OSError:
                        dropped = True
                    if dropped:
                        s.close()
                    else:
                        alive.append(s)
                held = alive
                if time.monotonic() - last_trickle >= 1.0:  # the slow body's one byte a second
                    for s in held:
                        with contextlib.suppress(OSError):
                            s.send(b" ")
                    last_trickle = time.monotonic()
                budget = int(REOPEN_PER_S * 0.05)
                while len(held) < self.n and budget > 0 and not self._stop.is_set():
                    opened = self._open()
                    if opened is not None:
                        held.append(opened)
                    budget -= 1
                self._stop.wait(0.05)
        finally:
            for s in held:
                s.close()


def _auth(token: bool) -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKEN}"} if token else {}


def _post_estop(conn: http.client.HTTPConnection, token: bool) -> int:
    conn.request("POST", "/api/v1/estop", headers=_auth(token))
    reply = conn.getresponse()
    reply.read()
    return reply.status


def _probe_estops(port: int, token: bool, stop: EventType, out: QueueType[Any]) -> None:
    """In a process of its own, so that neither the flood's thread nor the bench's own work delays a
    probe: POST /api/v1/estop every ESTOP_EVERY_S, on a fresh connection and on a kept-alive one, with
    the standard library's HTTP client (no TLS context to build, unlike a fresh httpx client, whose
    ~20 ms of Python the earlier figures included). Puts (round trips by kind, failures) when stopped."""
    rtts: dict[str, list[float]] = {"fresh": [], "kept": []}
    failures: list[str] = []
    kept = http.client.HTTPConnection("127.0.0.1", port, timeout=2.0)
    while not stop.is_set():
        t0 = time.monotonic()
        for how in ("fresh", "kept"):
            conn = kept if how == "kept" else http.client.HTTPConnection("127.0.0.1", port, timeout=2.0)
            t = time.monotonic()
            try:
                status = _post_estop(conn, token)  # a fresh connection's connect is in the round trip
                if status == 200:
                    rtts[how].append(time.monotonic() - t)
                else:
                    failures.append(f"{how} {status}")
            except (OSError, http.client.HTTPException) as err:
                failures.append(f"{how} {type(err).__name__}")
                conn.close()  # the kept one reconnects with its next request
            if how == "fresh":
                conn.close()
        stop.wait(max(0.0, ESTOP_EVERY_S - (time.monotonic() - t0)))
    kept.close()
    out.put((rtts, failures))


class OpcDeclaredFlood(Background):
    """One OPC UA connection after another: a header declaring DECLARED_BYTES, then up to STREAM_BYTES
    streamed into it until the daemon closes it (before any Hello: no login helps)."""

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.opened = 0
        self.streamed_bytes = 0
        super().__init__()

    def _run(self) -> None:
        block = bytes(65536)
        while not self._stop.is_set():
            try:
                with socket.create_connection((self.host, self.port), timeout=2) as s:
                    self.opened += 1
                    s.sendall(b"HELF" + struct.pack("<I", DECLARED_BYTES))
                    sent = 0
                    while sent < STREAM_BYTES and not self._stop.is_set():
                        s.sendall(block)
                        sent += len(block)
                        self.streamed_bytes += len(block)
            except OSError:
                self._stop.wait(1.0 / REOPEN_PER_S)


class OpcSessionFlood(Background):
    """OPC_SESSIONS anonymous sessions opened, OPC_CONCURRENCY at a time, and held; then user clothd logs
    in and calls EStop (its outcome in `user_estop`)."""

    def __init__(self, url: str, token: bool) -> None:
        self.url, self.token = url, token
        self.opened = 0
        self.refused = 0
        self.user_estop: dict[str, Any] = {}
        super().__init__()

    def _run(self) -> None:
        asyncio.run(self._flood())

    async def _flood(self) -> None:
        logging.getLogger("asyncua").setLevel(logging.CRITICAL)  # the refusals are the point, not news
        held: list[Client] = []
        gate = asyncio.Semaphore(OPC_CONCURRENCY)

        async def one() -> None:
            async with gate:
                client = Client(self.url, timeout=5)
                try:
                    await client.connect()
                    held.append(client)
                    self.opened += 1
                except Exception:  # refused (BadTooManySessions), closed, timed out: all count the same
                    self.refused += 1
                    with contextlib.suppress(Exception):
                        await client.disconnect()

        await asyncio.gather(*(one() for _ in range(OPC_SESSIONS)))
        if self.token:  # without one there is no user: the anonymous slots are all there is
            self.user_estop = await self._user_estop()
        while not self._stop.is_set():
            await asyncio.sleep(0.1)
        for client in held:
            with contextlib.suppress(Exception):
                await client.disconnect()

    async def _user_estop(self) -> dict[str, Any]:
        client = Client(self.url, timeout=5)
        client.set_user("clothd")
        client.set_password(TOKEN)
        t0 = time.monotonic()
        try:
            async with client:
                idx = await client.get_namespace_index(NAMESPACE_URI)
                cell = await client.nodes.objects.get_child(f"{idx}:Cell")
                await cell.call_method(f"{idx}:EStop")
            return {"latched": True, "ms": (time.monotonic() - t0) * 1e3}
        except Exception as err:
            return {"latched": False, "ms": None, "error": f"{type(err).__name__}: {err}"[:200]}


def _flood(d: DaemonProcess, port: int, kind: str, n: int, token: bool) -> Any:
    if kind in SOCKET_FLOODS:
        return Flood(port, SOCKET_FLOODS[kind], WEBSOCKETS if kind == "websocket-idle" else n)
    if kind == "opcua-declared":
        host, opc_port = d.opcua_url.split("//")[1].split("/")[0].split(":")
        return OpcDeclaredFlood(host, int(opc_port))
    return OpcSessionFlood(d.opcua_url, token)


class FlatnessSampler(Background):
    """The daemon's reported flatness, sampled every SAMPLE_EVERY_S on a thread of its own."""

    def __init__(self, base: str) -> None:
        self.base = base
        self.max_ridges = 0
        self.max_height_mm = 0.0
        self.links_lost = 0
        super().__init__()

    def sample(self) -> None:
        with contextlib.suppress(httpx.HTTPError, KeyError, TypeError):
            f = httpx.get(f"{self.base}/api/v1/status", timeout=2).json()["flatness"]
            if f is not None:
                self.max_ridges = max(self.max_ridges, len(f["ridges"]))
                self.max_height_mm = max(self.max_height_mm, f["max_height_mm"] or 0.0)

    def _run(self) -> None:
        while not self._stop.wait(SAMPLE_EVERY_S):
            self.sample()


def _link_losses(d: DaemonProcess) -> int:
    return int(httpx.get(f"{d.base}/api/v1/status", timeout=10).json()["link"]["counters"]["losses"])


def api_process_pid(d: DaemonProcess) -> int:
    """The process that holds the floods' connections: the daemon's API process."""
    for pid, name in spawned_children(d.proc.pid).items():
        if name == API_PROCESS_NAME:
            return pid
    raise RuntimeError("no API process found under the daemon")


def _measure(d: DaemonProcess, port: int, kind: str, n: int, flood_s: float, token: bool) -> dict[str, Any]:
    pid = api_process_pid(d)
    fds0, rss0 = open_fds(pid), rss_mb(pid)
    before = httpx.get(f"{d.base}/api/v1/status", timeout=5).json()["timing"]
    losses0 = _link_losses(d)
    spawn = multiprocessing.get_context("spawn")
    stop, out = spawn.Event(), spawn.Queue()
    prober = spawn.Process(target=_probe_estops, args=(port, token, stop, out), daemon=True)
    with FlatnessSampler(d.base) as flatness, _flood(d, port, kind, n, token) as flood:
        prober.start()
        time.sleep(flood_s)
        fds_during = open_fds(pid)
        stop.set()
        rtts, failures = out.get(timeout=30)
        prober.join(timeout=10)
    after = httpx.get(f"{d.base}/api/v1/status", timeout=10).json()["timing"]
    time.sleep(SETTLE_S)
    flatness.sample()  # after the flood
    ticks = after["ticks"] - before["ticks"]
    missed = after["missed_ticks"] - before["missed_ticks"]
    row: dict[str, Any] = {
        "flood": kind,
        "token": token,
        "connections_held": getattr(flood, "n", None),
        "connections_opened": flood.opened,
        "estop_failed": len(failures),
        "estop_failures": sorted(set(failures)),  # how they failed: which connection, what error
    }
    if isinstance(flood, OpcDeclaredFlood):
        row["streamed_mb"] = flood.streamed_bytes / 2**20
    if isinstance(flood, OpcSessionFlood):
        row.update(sessions_opened=flood.opened, sessions_refused=flood.refused)
        if token:
            row["user_estop"] = flood.user_estop
    for how, seconds in rtts.items():
        lat = np.asarray(seconds) * 1e3
        row[f"estop_{how}_answered"] = len(lat)
        row[f"estop_{how}_p50_ms"] = float(np.median(lat)) if len(lat) else None
        row[f"estop_{how}_p99_ms"] = float(np.percentile(lat, 99)) if len(lat) else None
    return {
        **row,
        "missed_tick_pct": 100.0 * missed / max(ticks + missed, 1),
        "links_lost": _link_losses(d) - losses0,
        "max_ridges": flatness.max_ridges,
        "max_height_mm": flatness.max_height_mm,
        "gc_full_max_ms": after.get("gc_pause", {}).get("max_ms"),  # the longest full collection so far
        "fds_before": fds0,
        "fds_during": fds_during,
        "fds_after": open_fds(pid),
        "rss_before_mb": rss0,
        "rss_after_mb": rss_mb(pid),
    }


def _config(directory: Path, token: bool) -> Path:
    path = directory / "abuse.yaml"
    path.write_text(yaml.safe_dump({"api": {"token": TOKEN}} if token else {}))
    return path


def run_bench(
    connections: int = 1100, flood_s: float = 20.0, floods: tuple[str, ...] = FLOODS, token: bool = True
) -> list[dict[str, Any]]:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)  # this process holds the flood's sockets
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, max(soft, connections + 256)), hard))
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="clothd-abuse-") as tmp:
        d = DaemonProcess(_config(Path(tmp), token), port)
        try:
            d.wait_ready()
            for pid in (d.proc.pid, api_process_pid(d)):
                resource.prlimit(pid, resource.RLIMIT_NOFILE, (DAEMON_FDS, DAEMON_FDS))
            _wait(lambda: httpx.get(f"{d.base}/api/v1/status", timeout=5).json()["state"] == "tracking", 120)
            time.sleep(2.0)
            shown = tqdm(floods, "floods", leave=False, disable=None)
            rows = [_measure(d, port, kind, connections, flood_s, token) for kind in shown]
            httpx.post(f"{d.base}/api/v1/estop/clear", headers=_auth(token), timeout=5)
            return rows
        finally:
            d.stop()


def _wait(check: Callable[[], bool], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise RuntimeError("the daemon did not start tracking")
        time.sleep(0.2)


def _ms(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f} ms"


def format_rows(rows: list[dict[str, Any]]) -> str:
    with_token = "with" if all(r["token"] for r in rows) else "without"
    out = [
        f"clothd bench abuse (clothd run --sim {with_token} api.token, at 1,024 fds; floods on loopback)",
        "  bars: e-stop p99 <= 100 ms, none failed; missed ticks <= 0.5 %; no link lost; RSS +<= 10 %;"
        " no ridge",
    ]
    w = 14
    for r in rows:
        what = f"{r['connections_opened']} connections opened"
        if r["connections_held"] is not None:
            what += f", {r['connections_held']} held at a time"
        if "streamed_mb" in r:
            what += f", {r['streamed_mb']:.0f} MiB written into them before each was closed"
        if "sessions_opened" in r:
            what = f"{r['sessions_opened']} anonymous sessions held, {r['sessions_refused']} refused"
        out.append(f"  {r['flood']:<{w}} {what}")
        out.append(
            f"  {'':<{w}} missed ticks {r['missed_tick_pct']:.3f} %, links lost {r['links_lost']}, "
            f"ridges seen {r['max_ridges']} (max height {r['max_height_mm']:.1f} mm)"
        )
        for how in ("fresh", "kept"):
            p50, p99 = _ms(r[f"estop_{how}_p50_ms"]), _ms(r[f"estop_{how}_p99_ms"])
            n = r[f"estop_{how}_answered"]
            out.append(f"  {'':<{w}} HTTP e-stop, {how} connection: p50 {p50}, p99 {p99}, {n} answered")
        if "user_estop" in r:
            u = r["user_estop"]
            said = f"latched in {_ms(u['ms'])}" if u["latched"] else f"FAILED: {u.get('error')}"
            out.append(f"  {'':<{w}} OPC UA user clothd's EStop while they are held: {said}")
        fds = f"API process fds {r['fds_before']} -> {r['fds_during']} -> {r['fds_after']}"
        grew = 100.0 * (r["rss_after_mb"] / r["rss_before_mb"] - 1.0)
        rss = f"RSS {r['rss_before_mb']:.1f} -> {r['rss_after_mb']:.1f} MB ({grew:+.1f} %)"
        failed = f" ({', '.join(r['estop_failures'])})" if r["estop_failed"] else ""
        out.append(f"  {'':<{w}} {r['estop_failed']} e-stops failed{failed}; {fds}; {rss}")
        out.append(
            f"  {'':<{w}} longest full garbage collection in the daemon so far {_ms(r['gc_full_max_ms'])}"
        )
    return "\n".join(out)
