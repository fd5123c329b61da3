"""Connections that never finish their request (a slow-header flood) are bounded in number and in time,
WebSockets that never read have a cap of their own and are dropped, and the operator's e-stop is still
served while they are open: uvicorn with clothd's bounded protocols, in this process, on a free loopback
port."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import httpx
import pytest
import uvicorn
from local_api import local_app

from clothd.api.connections import BoundedWebSocketProtocol
from clothd.api.serve_api import api_server_config
from clothd.api.stream import StreamHub
from clothd.config import ApiConfig, Config
from clothd.run import bind_api, build

MAX_CONNECTIONS = 16
REQUEST_TIMEOUT_S = 1.0
FLOOD = 60  # bounded: a few dozen sockets on loopback, closed by the test
MAX_STREAMS = 8
STALL_TIMEOUT_S = 1.0


@dataclass
class Served:
    srv: uvicorn.Server
    base: str
    hub: StreamHub

    @property
    def port(self) -> int:
        return int(self.base.rsplit(":", 1)[1])


@pytest.fixture
def server() -> Iterator[Served]:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    api = ApiConfig(
        port=port,
        max_connections=MAX_CONNECTIONS,
        request_timeout_s=REQUEST_TIMEOUT_S,
        max_streams=MAX_STREAMS,
        stall_timeout_s=STALL_TIMEOUT_S,
    )
    parts = build(Config(api=api))
    listener = bind_api(api)
    app = local_app(parts, api)
    srv = uvicorn.Server(api_server_config(app, api))
    thread = threading.Thread(target=srv.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not srv.started:
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.02)
    try:
        yield Served(srv, f"http://127.0.0.1:{port}", parts.hub)
    finally:
        srv.should_exit = True
        thread.join(timeout=10)
        listener.close()


def _slow_header(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    s.sendall(b"GET /api/v1/status HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # and never the blank line
    return s


def test_a_slow_header_flood_is_bounded_and_the_estop_still_answers(server: Served) -> None:
    srv, base, port = server.srv, server.base, server.port
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


def test_an_estop_accepted_in_a_burst_is_not_evicted_before_it_is_read(server: Served) -> None:
    """The event loop accepts a burst of connections before it reads any: the e-stop first in a burst of
    more than the cap is the oldest waiting connection, its request still unread. It must be answered."""
    srv, port = server.srv, server.port
    loop = srv.servers[0].get_loop()
    held = threading.Event()
    loop.call_soon_threadsafe(held.wait, 10.0)  # the server's loop busy: connections queue in the backlog
    with contextlib.ExitStack() as stack:
        estop = stack.enter_context(socket.create_connection(("127.0.0.1", port), timeout=10))
        estop.sendall(b"POST /api/v1/estop HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 0\r\n\r\n")
        for _ in range(MAX_CONNECTIONS + 8):
            stack.enter_context(_slow_header(port))
        held.set()
        reply = estop.recv(4096)
        assert reply.startswith(b"HTTP/1.1 200"), reply
        # Once read, the slow ones are judged: the next newcomer evicts one, and the cap holds again.
        with httpx.Client(base_url=server.base, timeout=5) as client:
            assert client.post("/api/v1/estop").status_code == 200
        assert len(srv.server_state.connections) <= MAX_CONNECTIONS


def test_whole_requests_are_not_cut_by_the_timeout(server: Served) -> None:
    base = server.base
    with httpx.Client(base_url=base, timeout=5) as client:  # one kept-alive connection
        for _ in range(3):
            assert client.get("/api/v1/status").status_code == 200
            time.sleep(REQUEST_TIMEOUT_S / 2)


def test_answers_are_not_held_back_by_nagle(server: Served) -> None:
    """The connections accepted on clothd's own listening socket get TCP_NODELAY, as uvicorn's would:
    without it every kept-alive response's body waited ~40 ms for the client's delayed ACK."""
    srv, base = server.srv, server.base
    with httpx.Client(base_url=base, timeout=5) as client:
        assert client.get("/api/v1/status").status_code == 200
        sockets = [c.transport.get_extra_info("socket") for c in srv.server_state.connections]
        assert sockets and all(s.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) for s in sockets)


def _websocket_that_never_reads(port: int) -> socket.socket:
    """A WebSocket handshake sent, and nothing read, ever; a small receive buffer fills soon."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect(("127.0.0.1", port))
    s.sendall(
        b"GET /api/v1/stream HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    return s


def test_websockets_that_never_read_neither_block_the_estop_nor_outlive_their_stall(server: Served) -> None:
    srv, base = server.srv, server.base
    with contextlib.ExitStack() as stack:
        readers = [
            stack.enter_context(_websocket_that_never_reads(server.port)) for _ in range(3 * MAX_STREAMS)
        ]
        time.sleep(0.5)
        streams = [c for c in srv.server_state.connections if isinstance(c, BoundedWebSocketProtocol)]
        assert len(streams) <= MAX_STREAMS, "streams past the cap are refused"
        for _ in range(5):
            r = httpx.post(f"{base}/api/v1/estop", timeout=5)
            assert r.status_code == 200 and r.json()["ok"]
        # Statuses flow; the readers' buffers fill; after the stall timeout they are dropped.
        status = server.hub.status
        assert status is not None
        deadline = time.monotonic() + STALL_TIMEOUT_S + 20
        while any(isinstance(c, BoundedWebSocketProtocol) for c in srv.server_state.connections):
            assert time.monotonic() < deadline, "a WebSocket that never reads was not dropped"
            server.hub.publish(status)
            time.sleep(0.001)
        for s in readers:
            _read_until_closed(s)


def _read_until_closed(sock: socket.socket) -> None:
    """Returns once the peer has closed the socket (what it had sent is skipped); a timeout raises."""
    sock.settimeout(5)
    with contextlib.suppress(ConnectionResetError):
        while sock.recv(65536):
            pass
