"""Fan-out of the per-tick status to GET /status and the WebSocket clients.

The status is serialised once per tick, on the daemon's thread; every reader gets the same bytes. In the
API process they arrive serialised (`receive`). The subscribers live on the API's event loop: bytes
published from another thread are handed to it, never waited on.

Each client has a latest-value slot: publishing overwrites it (counting a drop if the client had not
taken the previous value) and never waits. Each client's sender takes the slot when it is ready, so a
slow or stalled client loses messages and never delays the loop or another client.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

from clothd.loop.status import Status

log = logging.getLogger(__name__)


class Subscriber:
    def __init__(self, min_interval_s: float) -> None:
        self.min_interval_s = min_interval_s
        self.dropped = 0
        self._slot: bytes | None = None
        self._event = asyncio.Event()

    def offer(self, data: bytes) -> None:
        if self._slot is not None:
            self.dropped += 1
        self._slot = data
        self._event.set()

    async def take(self) -> bytes:
        """The newest value not yet taken, waiting for one if need be."""
        while self._slot is None:
            self._event.clear()
            await self._event.wait()
        data, self._slot = self._slot, None
        return data


class StreamHub:
    def __init__(self) -> None:
        self.subscribers: set[Subscriber] = set()  # touched on the API's loop only
        self.status: Status | None = None
        self.status_json = b"{}"
        self._api_loop: asyncio.AbstractEventLoop | None = None
        # Told every status as it is taken, on the thread that takes it (what counts each one: metrics).
        self.listeners: list[Callable[[Status], None]] = []

    def subscribe(self, min_interval_s: float) -> Subscriber:
        self._api_loop = asyncio.get_running_loop()
        sub = Subscriber(min_interval_s)
        self.subscribers.add(sub)
        return sub

    def unsubscribe(self, sub: Subscriber) -> None:
        self.subscribers.discard(sub)

    def publish(self, status: Status) -> None:
        """Serialise the status (non-finite numbers as null) and offer it to every subscriber."""
        self._take(status, status.model_dump_json().encode())

    def receive(self, data: bytes) -> None:
        """A status as the daemon serialised it (in the API process): parsed for the readers that need
        the object (/healthz, /metrics, OPC UA), the same bytes to every subscriber."""
        self._take(Status.model_validate_json(data), data)

    def _take(self, status: Status, data: bytes) -> None:
        self.status, self.status_json = status, data  # readers on other threads see one or the other
        self._offer_all(data)
        for listen in self.listeners:
            try:
                listen(status)
            except Exception:  # a listener's bug must not break what takes the statuses
                log.exception("a status listener failed")

    def _offer_all(self, data: bytes) -> None:
        loop = self._api_loop
        if loop is None or loop.is_closed():
            return
        try:
            same = asyncio.get_running_loop() is loop
        except RuntimeError:
            same = False
        if same:
            self._offer(data)
        else:
            loop.call_soon_threadsafe(self._offer, data)

    def _offer(self, data: bytes) -> None:
        for sub in self.subscribers:
            sub.offer(data)
