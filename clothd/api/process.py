"""The daemon's end of the API process (serve_api.py): start it, answer its calls on the daemon's loop,
send it each status and, while someone watches, each new view, and end it.

Nothing here waits on the API process: the channel (channel.py) is read when the loop finds it readable,
and a status or a view it has no room for is dropped and counted (the next tick sends a newer one). A
reply it has no room for waits in order for the next tick's status, which sends it first. A call runs at
once on the loop's thread, the e-stop included: it is the loop's, in the real-time class, and shares its
GIL with no request.

The API process ending before the daemon does is a fault: `ended` says why, and the daemon's runner
stops the modules and exits with an error (systemd restarts the whole daemon).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import socket
import time
from collections import deque
from contextlib import AbstractContextManager
from typing import Any

from clothd.api.channel import Channel, channel_pair, clothd_error
from clothd.api.serve_api import ApiSpec, serve_api
from clothd.errors import ClothdError, HardwareError
from clothd.loop.daemon import Daemon
from clothd.loop.status import Status

log = logging.getLogger(__name__)

START_TIMEOUT_S = 120.0  # the OPC UA address space is built at start
JOIN_TIMEOUT_S = 10.0
# What the API process may call: the daemon's request methods, nothing else.
CALLS = frozenset({"set_setpoint", "estop", "estop_clear", "reset", "start_recording", "stop_recording"})


class ApiProcess:
    def __init__(
        self, spec: ApiSpec, daemon: Daemon, ends: tuple[socket.socket, socket.socket] | None = None
    ) -> None:
        """ends: the channel's, the daemon's first (channel_pair(), made here unless given)."""
        self.spec = spec
        self.daemon = daemon
        ours, theirs = ends or channel_pair()
        self.channel = Channel(ours)
        self._their_end: socket.socket | None = theirs
        self.dropped_statuses = 0
        self.dropped_views = 0
        self.ended: asyncio.Future[str] | None = None  # resolved with the reason when it ends unasked
        self._ready: asyncio.Future[None] | None = None
        self._process: Any = None
        self._replies: deque[tuple[Any, ...]] = deque()
        self._watching: AbstractContextManager[None] | None = None
        self._view_sent = 0
        self._reading = True  # the last status went: the API process reads
        self._stopping = False

    async def start(self, listener: socket.socket) -> None:
        """Start it on `listener` and return once it serves; its start's error raised here."""
        loop = asyncio.get_running_loop()
        self.ended, self._ready = loop.create_future(), loop.create_future()
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter, as the compute's
        self._process = ctx.Process(
            target=serve_api, args=(self._their_end, listener, self.spec), name="clothd-api", daemon=True
        )
        self._process.start()
        assert self._their_end is not None
        self._their_end.close()  # its only copy is the process's: its end closes when it does
        self._their_end = None
        loop.add_reader(self.channel.sock, self._on_readable)
        try:
            await asyncio.wait_for(asyncio.shield(self._ready), START_TIMEOUT_S)
        except TimeoutError:
            raise HardwareError(f"the API process did not serve within {START_TIMEOUT_S:.0f} s") from None

    def publish(self, status: Status) -> None:
        """The daemon's on_status: the status to the API process, and the newest view while watched."""
        self._send_replies()
        if self.channel.send(("status", status.model_dump_json().encode())):
            self._reading = True
        else:
            self.dropped_statuses += 1
            if self._reading:  # said once each time it stops reading
                dropped = self.dropped_statuses
                log.warning("the API process is not reading: statuses dropped (%d so far)", dropped)
            self._reading = False
        if self._watching is not None:
            jpeg, index = self.daemon.view.latest()
            if jpeg is not None and index != self._view_sent:
                self._view_sent = index  # dropped or not: the next view supersedes it
                if not self.channel.send(("view", jpeg)):
                    self.dropped_views += 1

    async def stop(self) -> None:
        """End it (its channel closes), then make sure it has ended."""
        self._stopping = True
        with contextlib.suppress(ValueError, OSError):  # not started, or closed already
            asyncio.get_running_loop().remove_reader(self.channel.sock)
        self._unwatch()
        self.channel.close()
        if self._their_end is not None:  # never started
            self._their_end.close()
        if self._process is None:
            return
        await asyncio.get_running_loop().run_in_executor(None, self._process.join, JOIN_TIMEOUT_S)
        if self._process.is_alive():
            log.warning("the API process did not end within %.0f s: killed", JOIN_TIMEOUT_S)
            self._process.kill()
        elif self._process.exitcode:
            log.error("the API process exited with code %d", self._process.exitcode)

    # -- from the API process --------------------------------------------------------------------------

    def _on_readable(self) -> None:
        for message in self.channel.receive():
            assert isinstance(message, tuple)
            self._take(message)
        if self.channel.closed:
            asyncio.get_running_loop().remove_reader(self.channel.sock)
            self._end("its channel closed")

    def _take(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "call":
            self._answer(*message[1:])
        elif kind == "watchers":
            if message[1] > 0 and self._watching is None:
                self._watching = self.daemon.view.watching()
                self._watching.__enter__()
            elif message[1] == 0:
                self._unwatch()
        elif kind == "ready" and self._ready is not None and not self._ready.done():
            self._ready.set_result(None)
        elif kind == "error":
            self._failed(*message[1:])

    def _answer(self, call_id: int, name: str, args: tuple[Any, ...], deadline_mono_s: float) -> None:
        try:
            if name not in CALLS:
                raise HardwareError(f"the API process called {name!r}, which is not a request")
            # A request its caller has given up on is not carried out after all (a late move would surprise
            # whoever was told it failed); a late e-stop still stops.
            if name != "estop" and time.monotonic() > deadline_mono_s:
                raise HardwareError(f"{name} came after its caller had given up on it: not carried out")
            reply: tuple[Any, ...] = ("reply", call_id, True, getattr(self.daemon, name)(*args))
        except ClothdError as err:
            reply = ("reply", call_id, False, (type(err).__name__, str(err)))
        except Exception as err:  # a bug: said here, and the request answered 500
            log.exception("the API's call %s failed", name)
            reply = ("reply", call_id, False, (type(err).__name__, str(err)))
        self._replies.append(reply)
        self._send_replies()

    def _send_replies(self) -> None:
        while self._replies and self.channel.send(self._replies[0]):
            self._replies.popleft()

    def _unwatch(self) -> None:
        if self._watching is not None:
            self._watching.__exit__(None, None, None)
            self._watching = None

    def _failed(self, name: str, message: str, trace: str | None) -> None:
        """Its last words: before it served, the start's error (a clothd error as itself); after, a
        fault, logged with its traceback."""
        if self._ready is not None and not self._ready.done():
            error = clothd_error(name, message) if trace is None else None  # its message says it all
            self._ready.set_exception(error or HardwareError(f"the API process did not start: {message}"))
        if trace is not None:
            log.error("the API process failed:\n%s", trace.rstrip())
        elif self._ready is not None and self._ready.exception() is None:
            log.error("the API process failed: %s", message)

    def _end(self, reason: str) -> None:
        self._unwatch()
        if self._ready is not None and not self._ready.done():
            self._ready.set_exception(HardwareError(f"the API process ended before it served ({reason})"))
        if not self._stopping and self.ended is not None and not self.ended.done():
            self.ended.set_result(reason)
