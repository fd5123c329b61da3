"""The cell as the API process sees it (api/cell.py's port, over the channel to the daemon,
api/channel.py): commands go out as calls and wait for their replies; the statuses that come in go to the
StreamHub, the views to a ViewBoard of this process, and the number of views open goes back so that the
daemon draws the view only while someone watches.

A refusal comes back as its class's name and message and is raised here as the same clothd error, so
each API maps it as it would the daemon's own (409, 422, ...).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import pickle
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

import clothd.errors as errors
from clothd.api.cell import CellSettings
from clothd.api.channel import Channel, clothd_error
from clothd.api.stream import StreamHub
from clothd.core.drive_script import DriveScript
from clothd.core.modes import Mode
from clothd.outputs.recorder import make_recording_place, remove_recording_place
from clothd.outputs.view import ViewBoard

log = logging.getLogger(__name__)

CALL_TIMEOUT_S = 10.0  # a daemon that does not answer a call in this time is not ticking either


def error_from(name: str, message: str) -> Exception:
    """The daemon's error by its class's name: a clothd error as itself, anything else as a bug (500)."""
    err = clothd_error(name, message)
    return err if err is not None else RuntimeError(f"the daemon failed: {name}: {message}")


class RemoteCell:
    def __init__(self, channel: Channel, hub: StreamHub, settings: CellSettings) -> None:
        self.channel = channel
        self.hub = hub
        self._settings = settings
        self.view = ViewBoard()
        self.daemon_gone = asyncio.Event()
        self._watchers = 0
        self._ids = itertools.count(1)
        self._calls: dict[int, asyncio.Future[Any]] = {}
        self._outbox: asyncio.Queue[bytes] = asyncio.Queue()
        self._writer: asyncio.Task[None] | None = None

    def start(self) -> None:
        """Take what the daemon sends, and send in order (on the running loop)."""
        loop = asyncio.get_running_loop()
        loop.add_reader(self.channel.sock, self._on_readable)
        self._writer = asyncio.create_task(self._write())

    def stop(self) -> None:
        asyncio.get_running_loop().remove_reader(self.channel.sock)
        if self._writer is not None:
            self._writer.cancel()

    def send(self, message: object) -> None:
        """Queued, in order; the writer waits for room (the daemon reads between its ticks)."""
        self._outbox.put_nowait(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))

    # -- the Cell ------------------------------------------------------------------------------------

    @property
    def settings(self) -> CellSettings:
        return self._settings

    async def set_setpoint(self, mode: Mode, pose: np.ndarray | None, script: DriveScript | None) -> None:
        await self._call("set_setpoint", mode, pose, script)

    async def estop(self) -> None:
        await self._call("estop")

    async def estop_clear(self) -> bool:
        return bool(await self._call("estop_clear"))

    async def reset(self) -> None:
        await self._call("reset")

    async def start_recording(self, out: Path) -> Path:
        """The place is made here, off the daemon's loop; one the daemon refuses is removed again."""
        out = await asyncio.to_thread(make_recording_place, out, self.settings.recording_format)
        try:
            await self._call("start_recording", out)
        except BaseException:
            await asyncio.to_thread(remove_recording_place, out)
            raise
        return out

    async def stop_recording(self) -> None:
        await self._call("stop_recording")

    @contextlib.contextmanager
    def watching(self) -> Iterator[None]:
        self._watch(+1)
        try:
            yield
        finally:
            self._watch(-1)

    def latest_view(self) -> tuple[bytes | None, int]:
        return self.view.latest()

    # -- the channel ---------------------------------------------------------------------------------

    async def _call(self, name: str, *args: object) -> Any:
        if self.daemon_gone.is_set():
            raise errors.HardwareError("the daemon is stopping")
        call_id = next(self._ids)
        answer = self._calls[call_id] = asyncio.get_running_loop().create_future()
        # Past this the caller has been told the daemon did not answer: the daemon must not act on it later.
        self.send(("call", call_id, name, args, time.monotonic() + CALL_TIMEOUT_S))
        try:
            return await asyncio.wait_for(answer, CALL_TIMEOUT_S)
        except TimeoutError:
            raise errors.HardwareError(f"the daemon did not answer within {CALL_TIMEOUT_S:.0f} s") from None
        finally:
            self._calls.pop(call_id, None)

    def _watch(self, step: int) -> None:
        self._watchers += step
        self.send(("watchers", self._watchers))

    async def _write(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            data = await self._outbox.get()
            with contextlib.suppress(OSError):  # the daemon gone: the reader sees the end
                await loop.sock_sendall(self.channel.sock, data)

    def _on_readable(self) -> None:
        for message in self.channel.receive():
            assert isinstance(message, tuple)
            self._take(message)
        if self.channel.closed:
            asyncio.get_running_loop().remove_reader(self.channel.sock)
            for answer in self._calls.values():
                if not answer.done():
                    answer.set_exception(errors.HardwareError("the daemon is stopping"))
            self.daemon_gone.set()

    def _take(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "status":
            try:
                self.hub.receive(message[1])
            except ValidationError:  # a bug: said, and the readers keep the last status
                log.exception("a status from the daemon does not parse")
        elif kind == "view":
            self.view.post(message[1])
        elif kind == "reply":
            _, call_id, ok, answer = message
            waiting = self._calls.get(call_id)
            if waiting is None or waiting.done():  # it timed out
                return
            if ok:
                waiting.set_result(answer)
            else:
                waiting.set_exception(error_from(*answer))
