"""The OPC UA `Cell/Pieces` folder (mode flow, docs/flow.md): counters of pieces in, out and rejected, the
pieces on the table in a fixed number of slots, and a `PieceGoneEventType` event, emitted by the folder,
for each piece that leaves over the outfeed edge, left or rejected. docs/opcua.md draws it.

Slots, because a line controller reads fixed node ids: slot k holds the k-th piece on the table, oldest
first (the one nearest the outfeed); an empty slot has Id -1, State "" and NaN numbers. hwsim's cell and
the daemon's pool hold at most four pieces at once (clothd/core/pieces.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from datetime import UTC
from typing import Any

from asyncua import Node, Server, ua

from clothd.api.opcua_nodes import B, D, N, S, node_id, same
from clothd.api.piece_counts import PieceCounts, on_table
from clothd.core.modes import PieceState
from clothd.loop.status import PieceStatus, Status

SLOTS = 4
EVENT_TYPE = "PieceGoneEventType"
SEVERITY = {PieceState.LEFT: 100, PieceState.REJECTED: 500}  # 1..1000: a reject wants a look


def _pose(p: PieceStatus | None, key: str) -> float:
    value = None if p is None or p.pose is None else getattr(p.pose, key)
    return math.nan if value is None else float(value)


SLOT_VARS: tuple[tuple[str, ua.VariantType, Callable[[PieceStatus | None], Any]], ...] = (
    ("Id", N, lambda p: -1 if p is None else p.id),
    ("State", S, lambda p: "" if p is None else p.state.value),
    ("X_m", D, lambda p: _pose(p, "x_m")),
    ("Y_m", D, lambda p: _pose(p, "y_m")),
    ("Theta_rad", D, lambda p: _pose(p, "theta_rad")),
    ("Flat", B, lambda p: p is not None and bool(p.flat)),
    ("MaxHeight_mm", D, lambda p: math.nan if p is None or p.max_height_mm is None else p.max_height_mm),
    ("Reason", S, lambda p: "" if p is None else p.reason or ""),
)
EVENT_FIELDS = (("PieceId", N), ("PieceState", S), ("Reason", S))
COUNTERS = ("PiecesIn", "PiecesOut", "PiecesRejected", "PiecesAbandoned", "OnTable")


def _values(counts: PieceCounts, s: Status) -> list[Any]:
    """Every variable's value, in the order PiecesNodes.build adds them."""
    pieces = on_table(s.pieces)
    values: list[Any] = [counts.pieces_in, counts.pieces_out, counts.rejected, counts.abandoned, len(pieces)]
    for k in range(SLOTS):
        piece = pieces[k] if k < len(pieces) else None
        values += [get(piece) for _, _, get in SLOT_VARS]
    return values


def _types() -> list[ua.VariantType]:
    return [N] * len(COUNTERS) + [vtype for _ in range(SLOTS) for _, vtype, _ in SLOT_VARS]


async def _event_type(server: Server, idx: int) -> Node:
    """PieceGoneEventType, a BaseEventType with the piece's id, state and reason; string node ids as the
    cell's ("PieceGoneEventType.PieceId"), so that a client can filter on it without browsing."""
    base = server.get_node(ua.ObjectIds.BaseEventType)
    etype = await base.add_object_type(node_id(EVENT_TYPE, idx), ua.QualifiedName(EVENT_TYPE, idx))
    for name, vtype in EVENT_FIELDS:
        nid, bname = node_id(f"{EVENT_TYPE}.{name}", idx), ua.QualifiedName(name, idx)
        await etype.add_property(nid, bname, ua.get_default_value(vtype), varianttype=vtype)
    return etype


class PiecesNodes:
    def __init__(self, server: Server, nodes: list[Node], event: Any, counts: PieceCounts) -> None:
        self.server, self.nodes, self.event, self.counts = server, nodes, event, counts
        self.values: list[Any] = [None] * len(nodes)

    @classmethod
    async def build(cls, server: Server, cell: Node, idx: int, first: Status) -> PiecesNodes:
        folder = await cell.add_object(node_id("Cell.Pieces", idx), ua.QualifiedName("Pieces", idx))
        nodes = []
        for name in COUNTERS:
            nid = node_id(f"Cell.Pieces.{name}", idx)
            nodes.append(await folder.add_variable(nid, ua.QualifiedName(name, idx), ua.Variant(0, N)))
        for k in range(SLOTS):
            slot_name = f"Slot{k}"
            slot = await folder.add_object(
                node_id(f"Cell.Pieces.{slot_name}", idx), ua.QualifiedName(slot_name, idx)
            )
            for name, vtype, get in SLOT_VARS:
                nid = node_id(f"Cell.Pieces.{slot_name}.{name}", idx)
                nodes.append(
                    await slot.add_variable(nid, ua.QualifiedName(name, idx), ua.Variant(get(None), vtype))
                )
        event = await server.get_event_generator(await _event_type(server, idx), emitting_node=folder.nodeid)
        out = cls(server, nodes, event, PieceCounts())
        await out.update(first)
        return out

    async def update(self, s: Status) -> None:
        """Count the new status's pieces, write what changed, and emit an event for each piece gone."""
        gone = self.counts.see(s.pieces)
        stamp = ua.DateTime.fromtimestamp(s.t_unix_s, UTC)
        for i, (value, vtype) in enumerate(zip(_values(self.counts, s), _types(), strict=True)):
            if same(value, self.values[i]):
                continue
            self.values[i] = value
            data = ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=stamp)
            await self.server.write_attribute_value(self.nodes[i].nodeid, data)
        for p in gone:
            await self._emit(p)

    async def _emit(self, p: PieceStatus) -> None:
        e = self.event.event
        e.PieceId, e.PieceState, e.Reason = p.id, p.state.value, p.reason or ""
        e.Severity = SEVERITY.get(p.state, 100)
        words = f"piece {p.id} left" if p.state == PieceState.LEFT else f"piece {p.id} {p.state.value}"
        await self.event.trigger(message=words + (f": {p.reason}" if p.reason else ""))
