"""Connections bounded in number and in time, below the API (uvicorn's h11 protocol, subclassed).

A client that opens a connection and never finishes its request (a slow-header or slow-body flood)
used to hold its file descriptor forever: 1,100 of them exhausted the service's 1,024, the accept loop
logged an error storm, the API stopped answering and the tick stalled behind the logging. Now:
- a request must arrive whole within `api.request_timeout_s` of the connection opening (or of the
  previous response on a kept-alive one), else the connection is dropped;
- at most `api.max_connections` are open; one more evicts the oldest connection that has not yet sent a
  whole request (one that never has first, then an idle kept-alive one), so a flood of idle connections
  cannot lock out the operator's e-stop, nor push out the dashboard's kept-alive connection. Only when
  every open connection is busy with a real request is the newcomer turned away.
- a connection whose bytes still wait unread in the kernel has not been judged: the server is behind,
  not the client. The event loop accepts a burst of connections before it reads any of them, so under a
  flood the oldest waiting connection was often one accepted a moment before, its whole e-stop request
  unread (1 fresh e-stop in 30 reset). Such connections are never evicted; while some are waiting,
  newcomers are let in past the cap, up to twice it, rather than evict a kept-alive one, and the first
  read past the cap trims the count back to it.
Streams are bounded apart (`StreamSlots`): WebSockets and MJPEG views, at most `api.max_streams`
together. An upgraded WebSocket leaves the HTTP count, so open WebSockets can never fill the slots an
e-stop request needs. And any client that stops reading is dropped (`DropsStalledReaders`): once its
unsent bytes pass asyncio's high-water mark, it has `api.stall_timeout_s` to read before the connection
is aborted, so a stream's slot and descriptor are never held by a client that is gone.
The caps sit far below the unit's LimitNOFILE (deploy/clothd.service), so the daemon never runs out of
descriptors, and nothing here logs per connection.
"""

from __future__ import annotations

import asyncio
import fcntl
import struct
import termios
from typing import Any

from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol


class StreamSlots:
    """How many long-lived streams (WebSockets, MJPEG views) are open, against their own cap."""

    def __init__(self, max_streams: int) -> None:
        self.max_streams = max_streams
        self.open = 0

    def take(self) -> bool:
        if self.open >= self.max_streams:
            return False
        self.open += 1
        return True

    def give_back(self) -> None:
        self.open -= 1


class DropsStalledReaders(asyncio.Protocol):
    """Aborts the connection when its peer has not read for `stall_timeout_s` while writes wait."""

    stall_timeout_s = 5.0
    transport: Any
    _stall: asyncio.TimerHandle | None = None

    def pause_writing(self) -> None:
        super().pause_writing()
        if self._stall is None:
            self._stall = asyncio.get_running_loop().call_later(self.stall_timeout_s, self.transport.abort)

    def resume_writing(self) -> None:
        self._cancel_stall()
        super().resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_stall()
        super().connection_lost(exc)

    def _cancel_stall(self) -> None:
        if self._stall is not None:
            self._stall.cancel()
            self._stall = None


class BoundedWebSocketProtocol(DropsStalledReaders, WebSocketsSansIOProtocol):
    """uvicorn's WebSocket protocol, dropping a client that does not read."""

    @classmethod
    def bounded(cls, stall_timeout_s: float) -> type[BoundedWebSocketProtocol]:
        return type("BoundedWebSocketProtocol", (cls,), {"stall_timeout_s": stall_timeout_s})


class BoundedH11Protocol(DropsStalledReaders, H11Protocol):
    max_connections = 128
    request_timeout_s = 5.0

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._deadline: asyncio.TimerHandle | None = None
        self._opened_s = 0.0
        self._answered = 0  # whole requests answered on this connection

    @classmethod
    def bounded(
        cls, max_connections: int, request_timeout_s: float, stall_timeout_s: float
    ) -> type[BoundedH11Protocol]:
        """This protocol with its own bounds (uvicorn takes a class)."""
        bounds = {
            "max_connections": max_connections,
            "request_timeout_s": request_timeout_s,
            "stall_timeout_s": stall_timeout_s,
        }
        return type("BoundedH11Protocol", (cls,), bounds)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if not self._make_room():
            self.transport.abort()
            return
        self._arm_deadline()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if len(self.connections) > self.max_connections:  # a burst let in past the cap, read now: trim it
            self._make_room()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm_deadline()
        super().connection_lost(exc)

    def handle_websocket_upgrade(self, event: Any) -> None:
        self._disarm_deadline()  # the WebSocket's own protocol takes the connection over
        super().handle_websocket_upgrade(event)

    def on_response_complete(self) -> None:
        self._answered += 1
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_deadline()  # the next request on a kept-alive connection gets the same time

    def waiting(self) -> bool:
        """No whole request yet: no request line and headers, or a body still coming."""
        cycle = self.cycle
        return cycle is None or cycle.response_complete or cycle.more_body

    def _make_room(self) -> bool:
        """Whether this one may stay open. Past the cap, waiting connections the server has read are evicted
        back down to it: those that never sent a whole request first, and only then idle kept-alive ones,
        and not even those while some waiting connection is still unread (it may be the e-stop): then the
        cap may be passed, up to twice it, until they are read."""
        http = sum(1 for c in self.connections if isinstance(c, H11Protocol))  # upgraded ones have left
        excess = http - self.max_connections
        if excess <= 0:
            return True
        waiting = sorted((c for c in self._others() if c.waiting()), key=lambda c: c._opened_s)
        read = [c for c in waiting if not c.unread()]
        never_answered = [c for c in read if c._answered == 0]
        unread = len(read) < len(waiting)
        victims = never_answered if unread else never_answered + [c for c in read if c._answered > 0]
        for c in victims[:excess]:
            c.transport.abort()
        return bool(victims) or (unread and http <= 2 * self.max_connections)

    def _others(self) -> list[BoundedH11Protocol]:
        return [
            c
            for c in self.connections
            if c is not self and isinstance(c, BoundedH11Protocol) and not c.transport.is_closing()
        ]

    def unread(self) -> bool:
        """Bytes wait in the kernel for this connection (FIONREAD): the server has not read them yet."""
        sock = self.transport.get_extra_info("socket")
        if sock is None:
            return False
        try:
            pending = fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0\0\0\0")
        except OSError:
            return False
        return bool(struct.unpack("i", pending)[0])

    def _arm_deadline(self) -> None:
        self._disarm_deadline()
        self._opened_s = self.loop.time()
        self._deadline = self.loop.call_later(self.request_timeout_s, self._drop_if_waiting)

    def _disarm_deadline(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _drop_if_waiting(self) -> None:
        self._deadline = None
        if self.waiting():
            self.transport.abort()
