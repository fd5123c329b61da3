"""Connections that never finish their request (a slow-header flood) are bounded in number and in time,
and the operator's e-stop is still served while they are open: uvicorn with clothd's bounded protocol,
in this process, on a free loopback port."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator

import httpx
import pytest
import uvicorn

from clothd.api.app import create_app
from clothd.api.connections import BoundedH11Protocol
from clothd.config import ApiConfig, Config
from clothd.run import bind_api, build

MAX_CONNECTIONS = 16
REQUEST_TIMEOUT_S = 1.0
FLOOD = 60  # bounded: a few dozen sockets on loopback, closed by the test


@pytest.fixture
def server() -> Iterator[tuple[uvicorn.Server, str]]:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    api = ApiConfig(port=port)
    parts = build(Config(api=api))
    listener = bind_api(api)
    app = create_app(parts.daemon, parts.hub, parts.camera_model, api)
    protocol = BoundedH11Protocol.bounded(MAX_CONNECTIONS, REQUEST_TIMEOUT_S)
    srv = uvicorn.Server(uvicorn.Config(app, log_level="warning", http=protocol))
    thread = threading.Thread(target=srv.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not srv.started:
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.02)
    try:
        yield srv, f"http://127.0.0.1:{port}"
    finally:
        srv.should_exit = True
        thread.join(timeout=10)
        listener.close()


def _slow_header(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    s.sendall(b"GET /api/v1/status HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # and never the blank line
    return s


def test_a_slow_header_flood_is_bounded_and_the_estop_still_answers(
    server: tuple[uvicorn.Server, str],
) -> None:
    srv, base = server
    port = int(base.rsplit(":", 1)[1])
    with contextlib.ExitStack() as stack:
        flood = [stack.enter_context(_slow_header(port)) for _ in range(FLOOD)]
        time.sleep(0.2)
        assert len(srv.server_state.connections) <= MAX_CONNECTIONS
        r = httpx.post(f"{base}/api/v1/estop", timeout=5)  # evicts the oldest idle connection
        assert r.status_code == 200 and r.json()["ok"]
        assert httpx.get(f"{base}/healthz", timeout=5).status_code == 503  # served (no camera: 503)
        # Past the request timeout, the server hangs up on every one of them (polled, not timed).
        for s in flood:
            s.settimeout(REQUEST_TIMEOUT_S + 10)
            with contextlib.suppress(ConnectionResetError):
                assert s.recv(1024) == b""
        deadline = time.monotonic() + 10
        while srv.server_state.connections and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(srv.server_state.connections) == 0


def test_whole_requests_are_not_cut_by_the_timeout(server: tuple[uvicorn.Server, str]) -> None:
    _, base = server
    with httpx.Client(base_url=base, timeout=5) as client:  # one kept-alive connection
        for _ in range(3):
            assert client.get("/api/v1/status").status_code == 200
            time.sleep(REQUEST_TIMEOUT_S / 2)


def test_answers_are_not_held_back_by_nagle(server: tuple[uvicorn.Server, str]) -> None:
    """The connections accepted on clothd's own listening socket get TCP_NODELAY, as uvicorn's would:
    without it every kept-alive response's body waited ~40 ms for the client's delayed ACK."""
    srv, base = server
    with httpx.Client(base_url=base, timeout=5) as client:
        assert client.get("/api/v1/status").status_code == 200
        sockets = [c.transport.get_extra_info("socket") for c in srv.server_state.connections]
        assert sockets and all(s.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) for s in sockets)
