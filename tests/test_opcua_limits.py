"""The OPC UA server's bounds, with asyncua's own client and raw sockets, in process over a daemon built
but not started: a chunk declared too large closes its peer before it is buffered, anonymous sessions
have a cap of their own that never takes a user's slot, and idle connections cannot keep a user out."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from collections.abc import AsyncIterator
from typing import Any
from urllib.parse import urlsplit

import pytest
from asyncua import Client
from asyncua.ua.uaerrors import BadTooManySessions
from local_cell import LocalCell
from test_opcua import TOKEN, _call, _user

from clothd.api.commands import Commands
from clothd.api.opcua_limits import CHUNK_BYTES, declared_size, transport_limits
from clothd.api.opcua_server import OpcUaServer
from clothd.config import Config, OpcUaConfig
from clothd.run import build
from clothd.tools.bench_loop import free_port


@contextlib.asynccontextmanager
async def _server(**limits: Any) -> AsyncIterator[OpcUaServer]:
    cfg = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{free_port()}/clothd/", **limits)
    parts = build(Config())
    server = OpcUaServer(cfg, TOKEN, parts.hub, Commands(LocalCell(parts.daemon)))
    await server.start()
    try:
        yield server
    finally:
        await server.stop()


def _address(server: OpcUaServer) -> tuple[str, int]:
    url = urlsplit(server.cfg.endpoint)
    assert url.hostname is not None and url.port is not None
    return url.hostname, url.port


def test_the_transport_limits_follow_the_one_configured_message_size() -> None:
    limits = transport_limits(OpcUaConfig(max_message_bytes=262_144))
    assert limits.max_recv_buffer == CHUNK_BYTES and limits.max_message_size == 262_144
    assert limits.max_chunk_count * limits.max_recv_buffer >= 262_144
    small = transport_limits(OpcUaConfig(max_message_bytes=16_384))
    assert small.max_recv_buffer == 16_384 and small.max_chunk_count == 1
    assert declared_size(b"HELF" + struct.pack("<I", 4_000_000_000)) == 4_000_000_000


def test_a_peer_declaring_a_huge_chunk_is_closed_before_it_is_buffered() -> None:
    async def main() -> None:
        async with _server() as server:
            reader, writer = await asyncio.open_connection(*_address(server))
            writer.write(b"HELF" + struct.pack("<I", 4_000_000_000))  # 4 GB declared, before any Hello
            writer.write(bytes(65536))  # the stream begins
            assert await _closed_by_peer(reader), "the server closed it"
            assert server.server.bserver is not None and server.server.bserver.clients == []
            writer.close()
            async with _user(server.cfg.endpoint) as user:  # the server serves on
                assert (await _call(user, "Reset")).StatusCode.is_good()

    asyncio.run(main())


def test_anonymous_sessions_past_their_cap_are_refused_and_a_user_still_gets_in() -> None:
    async def main() -> None:
        async with _server(max_anonymous_sessions=3, max_user_sessions=1) as server:
            url = server.cfg.endpoint
            async with contextlib.AsyncExitStack() as held:
                for _ in range(3):
                    await held.enter_async_context(Client(url))
                extra = Client(url)
                with pytest.raises(BadTooManySessions):
                    await extra.connect()
                await extra.disconnect()
                async with _user(url) as user:
                    assert (await _call(user, "EStop")).StatusCode.is_good()
                    second = _user(url)
                    with pytest.raises(BadTooManySessions):  # users have their own cap too
                        await second.connect()
                    await second.disconnect()

    asyncio.run(main())


def test_idle_connections_past_the_pending_cap_make_room_for_a_login() -> None:
    async def main() -> None:
        async with _server(max_pending_connections=4) as server:
            idle = [socket.create_connection(_address(server)) for _ in range(20)]
            try:
                await asyncio.sleep(0.2)
                async with _user(server.cfg.endpoint) as user:
                    assert (await _call(user, "EStop")).StatusCode.is_good()
                closed = sum(_closed(s) for s in idle)
                print(f"{closed} of {len(idle)} idle connections closed")
                assert closed >= len(idle) - 4
            finally:
                for s in idle:
                    s.close()

    asyncio.run(main())


async def _closed_by_peer(reader: asyncio.StreamReader) -> bool:
    try:
        return await asyncio.wait_for(reader.read(), timeout=5) == b""
    except ConnectionResetError:  # aborted: a reset, not a FIN
        return True


def _closed(sock: socket.socket) -> bool:
    sock.setblocking(False)
    try:
        return sock.recv(1) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True


def test_a_pending_connection_is_closed_after_the_activation_timeout() -> None:
    async def main() -> None:
        async with _server(activation_timeout_s=0.3) as server:
            client = Client(server.cfg.endpoint)
            await client.connect_socket()
            await client.send_hello()
            await asyncio.sleep(1.0)
            assert server.server.bserver is not None and server.server.bserver.clients == []
            client.disconnect_socket()

    asyncio.run(main())


def test_a_peer_is_asyncuas_only_once_its_first_header_passed_and_a_silent_one_is_closed() -> None:
    async def main() -> None:
        async with _server(activation_timeout_s=0.5) as server:
            bserver = server.server.bserver
            assert bserver is not None
            reader, writer = await asyncio.open_connection(*_address(server))
            writer.write(b"HEL")  # less than a header
            await asyncio.sleep(0.2)
            assert bserver.clients == [], "no processor, no tasks for a peer that has said nothing yet"
            assert await _closed_by_peer(reader), "closed after the activation timeout"
            writer.close()
            async with _user(server.cfg.endpoint) as user:  # a real client is handed over whole
                assert len(bserver.clients) == 1
                assert (await _call(user, "Reset")).StatusCode.is_good()

    asyncio.run(main())
