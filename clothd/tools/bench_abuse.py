"""`clothd bench abuse`: connection floods against `clothd run --sim`, measured from outside.

For each flood, `connections` sockets are held open to the API for `flood_s` seconds, re-opened as the
daemon drops them (at most REOPEN_PER_S a second), all on loopback and all closed at the end:
- slow-header: a request line and a header, then nothing (never the blank line);
- slow-body: whole headers announcing a 1,000-byte JSON body, then one byte a second.
Meanwhile POST /api/v1/estop is sent every 100 ms, twice, from a process of its own: on a fresh
connection each time (the first click after a pause), and on one kept alive (a dashboard or HMI that
stays connected): the round trips. Before and after: the daemon's missed ticks, and its open file
descriptors and resident memory (from /proc), the latter again a few seconds after the flood.
"""

from __future__ import annotations

import contextlib
import http.client
import multiprocessing
import resource
import socket
import threading
import time
from multiprocessing.queues import Queue as QueueType
from multiprocessing.synchronize import Event as EventType
from typing import Any

import httpx
import numpy as np
from tqdm import tqdm

from clothd.tools.bench_loop import DaemonProcess, free_port
from clothd.tools.procfs import open_fds, rss_mb

REOPEN_PER_S = 500.0
ESTOP_EVERY_S = 0.1
SETTLE_S = 7.0  # after a flood: longer than api.request_timeout_s, so dropped connections are gone
FLOODS = {
    "slow-header": b"GET /api/v1/status HTTP/1.1\r\nHost: 127.0.0.1\r\n",
    "slow-body": (
        b"PUT /api/v1/setpoint HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        b"Content-Length: 1000\r\n\r\n{"
    ),
}


class Flood:
    """Holds `n` sockets open to the port with `opening` sent, re-opening dropped ones, until stopped."""

    def __init__(self, port: int, opening: bytes, n: int) -> None:
        self.port, self.opening, self.n = port, opening, n
        self.opened = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Flood:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=30)

    def _open(self) -> socket.socket | None:
        try:
            s = socket.create_connection(("127.0.0.1", self.port), timeout=1)
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


def _post_estop(conn: http.client.HTTPConnection) -> int:
    conn.request("POST", "/api/v1/estop")
    reply = conn.getresponse()
    reply.read()
    return reply.status


def _probe_estops(port: int, stop: EventType, out: QueueType[Any]) -> None:
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
                status = _post_estop(conn)  # a fresh connection's connect is in the round trip
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


def _measure(d: DaemonProcess, port: int, kind: str, n: int, flood_s: float) -> dict[str, Any]:
    pid = d.proc.pid
    fds0, rss0 = open_fds(pid), rss_mb(pid)
    before = httpx.get(f"{d.base}/api/v1/status", timeout=5).json()["timing"]
    spawn = multiprocessing.get_context("spawn")
    stop, out = spawn.Event(), spawn.Queue()
    prober = spawn.Process(target=_probe_estops, args=(port, stop, out), daemon=True)
    with Flood(port, FLOODS[kind], n) as flood:
        prober.start()
        time.sleep(flood_s)
        fds_during = open_fds(pid)
        stop.set()
        rtts, failures = out.get(timeout=30)
        prober.join(timeout=10)
    after = httpx.get(f"{d.base}/api/v1/status", timeout=10).json()["timing"]
    time.sleep(SETTLE_S)
    ticks = after["ticks"] - before["ticks"]
    missed = after["missed_ticks"] - before["missed_ticks"]
    row: dict[str, Any] = {
        "flood": kind,
        "connections_held": n,
        "connections_opened": flood.opened,
        "estop_failed": len(failures),
    }
    for how, seconds in rtts.items():
        lat = np.asarray(seconds) * 1e3
        row[f"estop_{how}_answered"] = len(lat)
        row[f"estop_{how}_p50_ms"] = float(np.median(lat)) if len(lat) else None
        row[f"estop_{how}_p99_ms"] = float(np.percentile(lat, 99)) if len(lat) else None
    return {
        **row,
        "missed_tick_pct": 100.0 * missed / max(ticks + missed, 1),
        "gc_full_max_ms": after.get("gc_pause", {}).get("max_ms"),  # the longest full collection so far
        "fds_before": fds0,
        "fds_during": fds_during,
        "fds_after": open_fds(pid),
        "rss_before_mb": rss0,
        "rss_after_mb": rss_mb(pid),
    }


def run_bench(connections: int = 1100, flood_s: float = 20.0) -> list[dict[str, Any]]:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)  # this process holds the flood's sockets
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, max(soft, connections + 256)), hard))
    port = free_port()
    d = DaemonProcess(None, port)
    try:
        d.wait_ready()
        deadline = time.monotonic() + 120
        while httpx.get(f"{d.base}/api/v1/status", timeout=5).json()["state"] != "tracking":
            if time.monotonic() > deadline:
                raise RuntimeError("the daemon did not start tracking")
            time.sleep(0.2)
        time.sleep(2.0)
        floods = tqdm(FLOODS, desc="floods", disable=None, leave=False)
        rows = [_measure(d, port, kind, connections, flood_s) for kind in floods]
        httpx.post(f"{d.base}/api/v1/estop/clear", timeout=5)
        return rows
    finally:
        d.stop()


def _ms(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f} ms"


def format_rows(rows: list[dict[str, Any]]) -> str:
    out = ["clothd bench abuse (clothd run --sim; floods on loopback, bounded in count and time)"]
    for r in rows:
        held = f"{r['connections_held']} held ({r['connections_opened']} opened)"
        out.append(f"  {r['flood']:<11} {held}: missed ticks {r['missed_tick_pct']:.3f} % (bar 0.5 %)")
        for how in ("fresh", "kept"):
            p50, p99 = _ms(r[f"estop_{how}_p50_ms"]), _ms(r[f"estop_{how}_p99_ms"])
            n = r[f"estop_{how}_answered"]
            out.append(
                f"  {'':<11} e-stop, {how} connection: p50 {p50}, p99 {p99} (bar 100 ms), {n} answered"
            )
        fds = f"fds {r['fds_before']} -> {r['fds_during']} -> {r['fds_after']}"
        rss = f"RSS {r['rss_before_mb']:.1f} -> {r['rss_after_mb']:.1f} MB"
        out.append(f"  {'':<11} {r['estop_failed']} e-stops failed; {fds}; {rss}")
        out.append(
            f"  {'':<11} longest full garbage collection in the daemon so far {_ms(r['gc_full_max_ms'])}"
        )
    return "\n".join(out)
