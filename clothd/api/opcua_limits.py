"""Bounds on what an OPC UA peer can make the server hold or copy, before and after it logs in.

asyncua 2.1 alone appends every received byte to a connection's buffer until the size its header
declares has arrived, with no cap: one peer declaring 4 GB and streaming 128 MiB into it held the GIL
long enough to miss a quarter of the ticks. And its one `max_connections` is shared by everyone, so
1,000 anonymous sessions locked the line controller's user out. Here:
- a chunk's declared size is read from its header as soon as its 8 bytes are in, and a peer declaring
  more than the negotiated receive buffer is closed at once, before anything more of it is buffered;
  a connection is handed to asyncua (its processor, its tasks: garbage for the collector, whose full
  runs hold the tick) only once its first header has passed, so a flood of such peers costs an accept;
  a message is at most `opcua.max_message_bytes`, and each connection queues at most
  MAX_QUEUED_MESSAGES whole chunks;
- connections are counted by class: activated anonymous sessions, activated user sessions, and pending
  ones (no activated session yet). Each class has its own cap, so anonymous sessions can never take a
  user's slot. An anonymous activation past its cap is refused (BadTooManySessions) and its connection
  closed; a new connection past the pending cap evicts the oldest pending one, and a pending one is
  closed after `opcua.activation_timeout_s`, so an idle flood cannot keep a user from logging in.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import math
import struct
from typing import Any

from asyncua import ua
from asyncua.common.connection import TransportLimits
from asyncua.common.utils import ServiceError
from asyncua.crypto.permission_rules import UserRole
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.internal_server import InternalServer
from asyncua.server.internal_session import SessionState

from clothd.config import OpcUaConfig

log = logging.getLogger(__name__)

HEADER_BYTES = 8  # message type (3), chunk type (1), size (UInt32, header included): Part 6, 7.1.2.2
CHUNK_BYTES = 65535  # the receive buffer offered in Acknowledge: no chunk may be larger
MAX_QUEUED_MESSAGES = 16  # whole chunks waiting for the server, per connection
REFUSED_CLOSE_S = 0.2  # a refused activation's fault goes out before its connection closes

# The connection whose message task runs: asyncua hands the user manager no connection.
_current: contextvars.ContextVar[GuardedProtocol | None] = contextvars.ContextVar("opcua_conn", default=None)


def transport_limits(cfg: OpcUaConfig) -> TransportLimits:
    chunk = min(CHUNK_BYTES, cfg.max_message_bytes)
    return TransportLimits(
        max_recv_buffer=chunk,
        max_send_buffer=CHUNK_BYTES,
        max_chunk_count=math.ceil(cfg.max_message_bytes / chunk),
        max_message_size=cfg.max_message_bytes,
    )


class SessionSlots:
    """The server's connections, and how many of them hold an activated session of each class."""

    def __init__(self, cfg: OpcUaConfig) -> None:
        self.cfg = cfg
        self.connections: list[OPCUAProtocol] = []  # asyncua's BinaryServer.clients: it adds and removes
        self.unopened: list[GuardedProtocol] = []  # accepted, their first header not yet in: not asyncua's
        self.caps = {UserRole.Anonymous: cfg.max_anonymous_sessions, UserRole.User: cfg.max_user_sessions}

    @property
    def max_connections(self) -> int:
        return sum(self.caps.values()) + self.cfg.max_pending_connections

    def admit(self, role: UserRole) -> None:
        """Called as a session activates with `role`: refuses it when that class is full, and closes the
        refused connection soon after its answer has gone out."""
        me = _current.get()
        held = sum(1 for c in self.connections if c is not me and _role(c) == role)
        if held < self.caps.get(role, 0):
            return
        if me is not None:
            me.close_soon()
        raise ServiceError(ua.StatusCodes.BadTooManySessions)

    def make_room_for_one_pending(self) -> None:
        """Before a new connection: past the pending cap, the oldest pending connection goes (one not yet
        handed to asyncua first: it has said least)."""
        opened = [c for c in self.connections if _role(c) is None and not _closing(c)]
        pending: list[OPCUAProtocol] = [*self.unopened, *opened]
        if len(pending) < self.cfg.max_pending_connections:
            return
        oldest = pending[0]
        if oldest.transport is not None:
            oldest.transport.abort()
        # Its slot is free now, not when asyncua hears of it.
        if isinstance(oldest, GuardedProtocol) and oldest in self.unopened:
            self.unopened.remove(oldest)
        else:
            self.connections.remove(oldest)


def _role(conn: OPCUAProtocol) -> UserRole | None:
    """The role of the connection's activated session; None while it has none."""
    session = conn.processor.session if conn.processor is not None else None
    if session is None or session.state != SessionState.Activated:
        return None
    role: UserRole = session.user.role
    return role


def _closing(conn: OPCUAProtocol) -> bool:
    return conn.transport is None or conn.transport.is_closing()


def declared_size(header: bytes) -> int:
    """The size a chunk's header says the chunk has (header included)."""
    return int(struct.unpack_from("<I", header, 4)[0])


class GuardedProtocol(OPCUAProtocol):
    """asyncua's connection, which closes a peer whose chunk claims more than the receive buffer before
    buffering it, and knows itself as the connection of the session work done on its behalf."""

    def __init__(self, *args: Any, slots: SessionSlots, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.slots = slots
        self._accepted: asyncio.Transport | None = None  # until the first header passes
        self._silent: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.slots.make_room_for_one_pending()
        self._accepted = self.transport = transport
        self.peer_name = transport.get_extra_info("peername")
        self.slots.unopened.append(self)
        timeout_s = self.slots.cfg.activation_timeout_s
        self._silent = asyncio.get_running_loop().call_later(timeout_s, transport.abort)

    def connection_lost(self, exc: BaseException | None) -> None:
        if self._accepted is None:
            super().connection_lost(exc)
            return
        self._leave_unopened()  # asyncua never knew it

    def data_received(self, data: bytes) -> None:
        if self._accepted is not None:
            if self._too_large(self._buffer + data[:HEADER_BYTES]):
                return
            if len(self._buffer) + len(data) < HEADER_BYTES:
                self._buffer += data
                return
            data, self._buffer = self._buffer + data, b""
            self._hand_over()
        elif self._too_large(self._buffer + data[:HEADER_BYTES]):
            return
        super().data_received(data)
        self._too_large(self._buffer)  # the next chunk's header, when it came with this data

    def _hand_over(self) -> None:
        """The first header passed: now asyncua's connection (its processor, its message task)."""
        transport = self._accepted
        self._leave_unopened()
        token = _current.set(self)  # copied into the connection's message task that asyncua starts
        try:
            super().connection_made(transport)  # type: ignore[arg-type]
        finally:
            _current.reset(token)

    def _leave_unopened(self) -> None:
        self._accepted = None
        if self._silent is not None:
            self._silent.cancel()
        if self in self.slots.unopened:
            self.slots.unopened.remove(self)

    def close_soon(self) -> None:
        if self.transport is not None:
            asyncio.get_running_loop().call_later(REFUSED_CLOSE_S, self.transport.close)

    def _too_large(self, pending: bytes) -> bool:
        """Close the connection when the chunk begun in `pending` claims more than a chunk may hold."""
        if len(pending) < HEADER_BYTES or declared_size(pending) <= self.limits.max_recv_buffer:
            return False
        log.warning(
            "OPC UA peer %s declared a %d-byte chunk (at most %d): closed",
            self.peer_name,
            declared_size(pending),
            self.limits.max_recv_buffer,
        )
        self._buffer = b""
        if self.transport is not None:
            self.transport.abort()
        return True


class GuardedBinaryServer(BinaryServer):
    def __init__(
        self,
        iserver: InternalServer,
        host: str | None,
        port: int | None,
        limits: TransportLimits,
        slots: SessionSlots,
    ) -> None:
        super().__init__(iserver, host, port, limits)  # type: ignore[arg-type]
        self.clients = slots.connections
        self.slots = slots
        iserver.max_connections = slots.max_connections
        iserver.max_pending_messages_per_connection = MAX_QUEUED_MESSAGES
        iserver.max_pending_activation_seconds = slots.cfg.activation_timeout_s

    def _make_protocol(self) -> OPCUAProtocol:
        return GuardedProtocol(
            iserver=self.iserver,
            policies=self._policies,
            clients=self.clients,
            closing_tasks=self.closing_tasks,
            limits=self.limits,
            slots=self.slots,
        )
