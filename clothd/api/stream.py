"""Fan-out of the per-tick status to WebSocket clients.

Each client has a latest-value slot: publishing overwrites it (counting a drop if the client had not
taken the previous value) and never waits. Each client's sender takes the slot when it is ready, so a
slow or stalled client loses messages and never delays the loop or another client.
"""

from __future__ import annotations

import asyncio


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
        self.subscribers: set[Subscriber] = set()

    def subscribe(self, min_interval_s: float) -> Subscriber:
        sub = Subscriber(min_interval_s)
        self.subscribers.add(sub)
        return sub

    def unsubscribe(self, sub: Subscriber) -> None:
        self.subscribers.discard(sub)

    def publish(self, data: bytes) -> None:
        for sub in self.subscribers:
            sub.offer(data)
