"""Mode flow's pieces over OPC UA, with asyncua's own client against the server in process, over a daemon
built but not started: statuses with pieces are published into its hub as the loop would publish them.
The Pieces folder's counters and slots, the event for each piece gone, and the Flow method."""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator
from typing import Any

from asyncua import Client, Node, ua
from fastapi.testclient import TestClient
from flow_statuses import FLAP, piece, publish
from local_api import local_app
from local_cell import LocalCell

from clothd.api.commands import Commands
from clothd.api.opcua_nodes import NAMESPACE_URI
from clothd.api.opcua_pieces import EVENT_TYPE, SLOT_VARS, SLOTS
from clothd.api.opcua_server import OpcUaServer
from clothd.api.stream import StreamHub
from clothd.config import Config, OpcUaConfig
from clothd.core.modes import PieceState
from clothd.run import build
from clothd.tools.bench_loop import free_port

BASE = "http://127.0.0.1:8080"
WAIT_S = 20.0  # a bound on waiting for what must come, never a measured time


class Seen:
    """What one subscription delivers: the counters' values and the events, in order."""

    def __init__(self) -> None:
        self.values: dict[str, Any] = {}
        self.events: list[tuple[int, str, str, str]] = []
        self.names: dict[Any, str] = {}
        self.changed = asyncio.Event()

    def datachange_notification(self, node: Node, val: Any, data: Any) -> None:
        self.values[self.names[node.nodeid]] = val
        self.changed.set()

    def event_notification(self, event: Any) -> None:
        self.events.append((event.PieceId, event.PieceState, event.Reason, event.Message.Text))
        self.changed.set()

    async def until(self, what: str, ok: Any) -> None:
        async def loop() -> None:
            while not ok():
                self.changed.clear()
                await self.changed.wait()

        try:
            await asyncio.wait_for(loop(), WAIT_S)
        except TimeoutError:
            raise AssertionError(f"never saw {what}: {self.values}, {self.events}") from None


@contextlib.asynccontextmanager
async def _served() -> AsyncIterator[tuple[Client, Node, int, StreamHub, TestClient]]:
    parts = build(Config())
    cfg = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{free_port()}/clothd/")
    server = OpcUaServer(cfg, None, parts.hub, Commands(LocalCell(parts.daemon)))
    rest = TestClient(local_app(parts), base_url=BASE)
    await server.start()
    try:
        async with Client(cfg.endpoint) as client:
            idx = await client.get_namespace_index(NAMESPACE_URI)
            pieces = await client.nodes.objects.get_child([f"{idx}:Cell", f"{idx}:Pieces"])
            yield client, pieces, idx, parts.hub, rest
    finally:
        await server.stop()


async def _read(folder: Node, idx: int, *path: str) -> Any:
    return await (await folder.get_child([f"{idx}:{p}" for p in path])).read_value()


def test_the_pieces_folder_counts_each_piece_once_and_an_event_says_each_one_gone() -> None:
    async def main() -> None:
        async with _served() as (client, folder, idx, hub, _):
            seen = Seen()
            sub = await client.create_subscription(20, seen)
            counters = ("PiecesIn", "PiecesOut", "PiecesRejected", "OnTable")
            nodes = [await folder.get_child(f"{idx}:{name}") for name in counters]
            seen.names = {n.nodeid: name for n, name in zip(nodes, counters, strict=True)}
            await sub.subscribe_data_change(nodes)
            etype = client.get_node(ua.NodeId(EVENT_TYPE, idx))  # as docs/opcua.md names it
            await sub.subscribe_events(folder, etype)
            await seen.until("no pieces yet", lambda: seen.values.get("PiecesIn") == 0)
            assert await _read(folder, idx, "Slot0", "Id") == -1  # an empty slot

            publish(hub, [piece(0, PieceState.PLACING, 0.12), piece(1, PieceState.ENTERING)])
            await seen.until("two pieces in", lambda: seen.values["PiecesIn"] == 2)
            assert seen.values["OnTable"] == 2
            assert await _read(folder, idx, "Slot0", "State") == "placing"
            assert await _read(folder, idx, "Slot0", "X_m") == 0.12
            assert await _read(folder, idx, "Slot0", "Flat") is True
            assert await _read(folder, idx, "Slot1", "State") == "entering"
            assert math.isnan(await _read(folder, idx, "Slot1", "X_m"))  # not tracked yet: no pose
            assert await _read(folder, idx, "Slot2", "Id") == -1

            # Piece 0 has left; piece 1 is rejected and still on the table; piece 2 comes in.
            table = [piece(1, PieceState.REJECTED, 0.0, reason=FLAP), piece(2, PieceState.ENTERING)]
            publish(hub, [*table, piece(0, PieceState.LEFT, 0.5, gone=True)])
            await seen.until("piece 0 out", lambda: seen.values["PiecesOut"] == 1 and len(seen.events) == 1)
            assert (seen.values["PiecesIn"], seen.values["PiecesRejected"], seen.values["OnTable"]) == (
                3,
                1,
                2,
            )
            assert await _read(folder, idx, "Slot0", "Reason") == FLAP
            assert seen.events == [(0, "left", "", "piece 0 left")]

            # Piece 1 goes over the edge as a reject; piece 0 is still among the last gone, counted once.
            gone = [piece(0, PieceState.LEFT, 0.5, gone=True), piece(1, PieceState.REJECTED, 0.5, True, FLAP)]
            publish(hub, [piece(2, PieceState.TRACKED, -0.2), *gone])
            await seen.until("piece 1 gone", lambda: len(seen.events) == 2)
            publish(hub, [piece(2, PieceState.FLATTENING, -0.2), piece(3, PieceState.ENTERING), *gone])
            await seen.until("piece 3 in", lambda: seen.values["PiecesIn"] == 4)
            assert (seen.values["PiecesOut"], seen.values["PiecesRejected"], seen.values["OnTable"]) == (
                1,
                1,
                2,
            )
            assert seen.events[1] == (1, "rejected", FLAP, f"piece 1 rejected: {FLAP}")
            assert len(seen.events) == 2  # piece 3's count came after; no piece was announced twice

    asyncio.run(main())


def test_the_slots_are_documented_and_each_slot_has_every_variable() -> None:
    async def main() -> None:
        async with _served() as (_, folder, idx, _hub, _rest):
            names = {(await n.read_browse_name()).Name for n in await folder.get_children()}
            assert names == {"PiecesIn", "PiecesOut", "PiecesRejected", "PiecesAbandoned", "OnTable"} | {
                f"Slot{k}" for k in range(SLOTS)
            }
            for name, _, _ in SLOT_VARS:
                await _read(folder, idx, f"Slot{SLOTS - 1}", name)

    asyncio.run(main())


def test_the_flow_method_answers_as_put_setpoint_flow_does() -> None:
    async def main() -> None:
        async with _served() as (client, _, idx, _hub, rest):
            cell = await client.nodes.objects.get_child(f"{idx}:Cell")
            method = await cell.get_child(f"{idx}:Flow")
            assert (await method.read_browse_name()).Name == "Flow"
            for before in (None, "/api/v1/estop"):  # never started: "starting"; then the e-stop's refusal
                if before:
                    assert rest.post(before).status_code == 200
                req = ua.CallMethodRequest(ObjectId=cell.nodeid, MethodId=method.nodeid, InputArguments=[])
                (result,) = await client.uaclient.call([req])
                r = rest.put("/api/v1/setpoint", json={"mode": "flow"})
                assert result.StatusCode.value == ua.StatusCodes.BadInvalidState and r.status_code == 409
                assert result.OutputArguments[0].Value == r.json()["detail"]

    asyncio.run(main())
