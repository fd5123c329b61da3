"""A Foxglove WebSocket client for the tests, on a thread of its own."""

from __future__ import annotations

import asyncio
import json
import struct
import threading
from typing import Any

import websockets
from mcap_files import FOXGLOVE_SCHEMAS
from websockets.typing import Subprotocol

SUBPROTOCOL = "foxglove.sdk.v1"  # what foxglove-sdk 0.30's server speaks (the protocol's current name)


class FoxgloveClient:
    """A Foxglove WebSocket client on a thread of its own: reads the advertised channels, subscribes to
    `topics` and keeps what arrives (log time and payload per topic)."""

    def __init__(self, port: int, topics: tuple[str, ...]) -> None:
        self.port = port
        self.topics = topics
        self.channels: dict[str, dict[str, Any]] = {}
        self.received: dict[str, list[tuple[int, bytes]]] = {}
        self.subscribed = threading.Event()
        self.stop = threading.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run)
        self.thread.start()

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as err:
            self.error = err
            self.subscribed.set()

    async def _main(self) -> None:
        url = f"ws://127.0.0.1:{self.port}"
        async with websockets.connect(url, subprotocols=[Subprotocol(SUBPROTOCOL)]) as ws:
            while set(self.channels) != set(FOXGLOVE_SCHEMAS):
                msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
                if msg["op"] == "advertise":
                    self.channels.update({c["topic"]: c for c in msg["channels"]})
            subs = [{"id": k, "channelId": self.channels[t]["id"]} for k, t in enumerate(self.topics)]
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            self.subscribed.set()
            while not self.stop.is_set():
                try:
                    data = await asyncio.wait_for(ws.recv(), 0.1)
                except TimeoutError:
                    continue
                if isinstance(data, bytes) and data[0] == 1:  # a message: op, subscription, log time, payload
                    sub, log_time = struct.unpack_from("<IQ", data, 1)
                    self.received.setdefault(self.topics[sub], []).append((log_time, data[13:]))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(10)
