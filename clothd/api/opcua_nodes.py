"""The OPC UA address space of the cell: one `Cell` object under our namespace, its variables filled from
the status snapshots the daemon publishes (clothd/loop/status.py), and two state machines. docs/opcua.md
draws the tree.

Following OPC UA for Machinery (OPC 40001-1) where it fits: an `Identification` object with the
machine's identity properties, and a `MachineryItemState` state machine with the companion
specification's four states. The cell's own modes (idle, hold, move, flatten) are an `OperationMode`
state machine beside it: Machinery's operation modes (maintenance, setup, processing) do not describe
them. Node ids are strings ("Cell.Pose.X_m") so that a line controller can address them without
browsing.

An absent number (the pose while not tracked, the setpoint in idle) is NaN; `State` says why.
"""

from __future__ import annotations

import math
import socket
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC
from importlib.metadata import version
from typing import Any

from asyncua import Node, Server, ua
from pydantic import BaseModel

from clothd.core.modes import LoopState, Mode
from clothd.loop.status import Status

NAMESPACE_URI = "urn:clothd:cell"

D, S, B = ua.VariantType.Double, ua.VariantType.String, ua.VariantType.Boolean
N = ua.VariantType.Int64  # counts

# The cell's modes as OperationMode's states (MachineryItemState's are OPC 40001-1's: machinery_state).
MODE_STATES = {mode: mode.value.capitalize() for mode in Mode}


def _num(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _of(block: BaseModel | None, key: str) -> float:
    """A number of a status block that may be absent."""
    return math.nan if block is None else _num(getattr(block, key))


def _std(s: Status, i: int) -> float:
    """Standard deviation of pose component i, from the covariance's diagonal."""
    if s.pose is None:
        return math.nan
    var = s.pose.cov[i][i]
    return math.nan if var is None else math.sqrt(max(var, 0.0))


def _ridges(s: Status, key: str) -> list[float]:
    return [getattr(r, key) for r in s.flatness.ridges] if s.flatness else []


def _flaps(s: Status, key: str) -> list[float]:
    return [getattr(f, key) for f in s.flatness.flaps] if s.flatness else []


def node_id(name: str, idx: int) -> ua.NodeId:
    """Our string node ids: "Cell.Pose.X_m" in namespace idx."""
    return ua.NodeId(ua.String(name), ua.Int16(idx))


@dataclass(frozen=True)
class Var:
    path: str  # below Cell, "/"-separated: folders, then the variable's name
    vtype: ua.VariantType
    get: Callable[[Status], Any]


VARIABLES: tuple[Var, ...] = (
    Var("State", S, lambda s: s.state),
    Var("Mode", S, lambda s: s.mode),
    Var("EStopLatched", B, lambda s: s.estop),
    Var("HaltReason", S, lambda s: s.halt_reason or ""),
    Var("Setpoint/X_m", D, lambda s: _of(s.setpoint, "x_m")),
    Var("Setpoint/Y_m", D, lambda s: _of(s.setpoint, "y_m")),
    Var("Setpoint/Theta_rad", D, lambda s: _of(s.setpoint, "theta_rad")),
    Var("Pose/X_m", D, lambda s: _of(s.pose, "x_m")),
    Var("Pose/Y_m", D, lambda s: _of(s.pose, "y_m")),
    Var("Pose/Theta_rad", D, lambda s: _of(s.pose, "theta_rad")),
    Var("Pose/XStd_m", D, lambda s: _std(s, 0)),
    Var("Pose/YStd_m", D, lambda s: _std(s, 1)),
    Var("Pose/ThetaStd_rad", D, lambda s: _std(s, 2)),
    Var("Features/Count", N, lambda s: s.features),
    Var("Features/Rejected", N, lambda s: s.rejected_features),
    Var("Features/ResidualMean_px", D, lambda s: _num(s.residual.mean_px)),
    Var("Features/ResidualWorst_px", D, lambda s: _num(s.residual.worst_px)),
    Var("Flatness/Flat", B, lambda s: s.flatness is not None and s.flatness.flat),
    Var("Flatness/MaxHeight_mm", D, lambda s: _of(s.flatness, "max_height_mm")),
    Var("Flatness/CompressedArea_pct", D, lambda s: _of(s.flatness, "compressed_area_pct")),
    Var("Flatness/Basis", S, lambda s: s.flatness.basis.value if s.flatness else ""),
    Var("Flatness/Ridges/X_m", D, lambda s: _ridges(s, "x_m")),
    Var("Flatness/Ridges/Y_m", D, lambda s: _ridges(s, "y_m")),
    Var("Flatness/Ridges/Direction_rad", D, lambda s: _ridges(s, "direction_rad")),
    Var("Flatness/Ridges/Height_mm", D, lambda s: _ridges(s, "height_mm")),
    Var("Flatness/Ridges/Area_m2", D, lambda s: _ridges(s, "area_m2")),
    Var("Flatness/Flaps/X_m", D, lambda s: _flaps(s, "x_m")),
    Var("Flatness/Flaps/Y_m", D, lambda s: _flaps(s, "y_m")),
    Var("Flatness/Flaps/Area_m2", D, lambda s: _flaps(s, "area_m2")),
    Var("Timing/Ticks", N, lambda s: s.timing.ticks),
    Var("Timing/MissedTicks", N, lambda s: s.timing.missed_ticks),
    Var("Timing/Missed_pct", D, lambda s: s.timing.missed_pct),
    Var("Timing/ComputeOverruns", N, lambda s: s.timing.compute_overruns),
    Var("Timing/ComputeP50_ms", D, lambda s: _of(s.timing.stages.get("compute"), "p50_ms")),
    Var("Timing/ComputeP99_ms", D, lambda s: _of(s.timing.stages.get("compute"), "p99_ms")),
    Var("Timing/JitterP99_ms", D, lambda s: _of(s.timing.jitter, "p99_ms")),
    Var("Timing/FrameToCommandP50_ms", D, lambda s: _of(s.timing.frame_to_command, "p50_ms")),
    Var("Timing/FrameToCommandP99_ms", D, lambda s: _of(s.timing.frame_to_command, "p99_ms")),
    Var("Camera/State", S, lambda s: s.camera.state),
    Var("Camera/Healthy", B, lambda s: s.camera.healthy),
    Var("Camera/Reconnects", N, lambda s: s.camera.reconnects),
    Var("Camera/LastError", S, lambda s: s.camera.last_error or ""),
    Var("Cameras/Name", S, lambda s: [c.name for c in s.cameras]),
    Var("Cameras/State", S, lambda s: [c.state for c in s.cameras]),
    Var("Cameras/Healthy", B, lambda s: [c.healthy for c in s.cameras]),
    Var("Cameras/Fps", D, lambda s: [_num(c.fps) for c in s.cameras]),
    Var("Cameras/LongestGap_ms", D, lambda s: [_num(c.longest_gap_ms) for c in s.cameras]),
    Var("Cameras/Skew_ms", D, lambda s: [_num(c.skew_ms) for c in s.cameras]),
    Var("Cameras/Paired_pct", D, lambda s: [_num(c.paired_pct) for c in s.cameras]),
    Var("Link/State", S, lambda s: s.link.state),
    Var("Link/ControllerEStop", B, lambda s: s.link.controller_estop),
    Var("Link/Firmware", S, lambda s: s.link.firmware or ""),
    Var("Link/LastError", S, lambda s: s.link.last_error or ""),
    Var("Link/RttP99_ms", D, lambda s: _num(s.link.counters.rtt_p99_ms)),
    Var("Link/Retransmitted", N, lambda s: s.link.counters.retransmitted),
    Var("Link/Losses", N, lambda s: s.link.counters.losses),
    Var("Modules/Speed_m_s", D, lambda s: s.modules.speed_m_s),
    Var("Modules/Heading_rad", D, lambda s: s.modules.heading_rad),
    Var("Faults/T_unix_s", D, lambda s: [f.t_unix_s for f in s.faults]),
    Var("Faults/Code", N, lambda s: [f.code for f in s.faults]),
    Var("Faults/Module", N, lambda s: [f.module for f in s.faults]),
    Var("Faults/Text", S, lambda s: [f.text for f in s.faults]),
)


def machinery_state(s: Status) -> str:
    """MachineryItemState from the status: out of service while e-stopped or faulted, executing while it
    drives the cloth."""
    if s.estop or s.state == LoopState.FAULT:
        return "OutOfService"
    if s.state == LoopState.STARTING:
        return "NotAvailable"
    return "Executing" if s.mode != Mode.IDLE and s.state == LoopState.TRACKING else "NotExecuting"


def same(a: Any, b: Any) -> bool:
    """Equal, NaN equal to NaN: an unchanged NaN is not written again (nor notified to subscribers)."""
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return bool(a == b) or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


class StateVariable:
    """A StateMachineType object (Part 5, B.4) whose CurrentState, and its Id, name the present state;
    written only when it changes."""

    def __init__(self, current: Node, current_id: Node) -> None:
        self.current, self.current_id, self.name = current, current_id, ""

    @classmethod
    async def install(cls, cell: Node, idx: int, name: str) -> StateVariable:
        nid = node_id(f"Cell.{name}", idx)
        machine = await cell.add_object(nid, ua.QualifiedName(name, idx), ua.ObjectIds.StateMachineType)
        current = await machine.get_child("CurrentState")
        return cls(current, await current.get_child("Id"))

    async def set(self, name: str) -> None:
        if name != self.name:
            await self.current.write_value(ua.LocalizedText(name), ua.VariantType.LocalizedText)
            await self.current_id.write_value(name, ua.VariantType.String)
            self.name = name


class CellNodes:
    """The Cell object's variables and state machines, and what a new status changes in them."""

    def __init__(
        self, server: Server, cell: Node, nodes: list[Node], item_state: StateVariable, mode: StateVariable
    ) -> None:
        self.server, self.cell, self.nodes = server, cell, nodes
        self.item_state, self.mode = item_state, mode
        self.values: list[Any] = [None] * len(nodes)

    @classmethod
    async def build(cls, server: Server, idx: int, first: Status) -> CellNodes:
        cell = await server.nodes.objects.add_object(node_id("Cell", idx), ua.QualifiedName("Cell", idx))
        await _identification(cell, idx)
        folders: dict[str, Node] = {"": cell}
        nodes = []
        for var in VARIABLES:
            folder, _, name = var.path.rpartition("/")
            parent = await _folder(folders, folder, idx)
            value = var.get(first)
            nid = node_id("Cell." + var.path.replace("/", "."), idx)
            node = await parent.add_variable(nid, ua.QualifiedName(name, idx), ua.Variant(value, var.vtype))
            if isinstance(value, list):  # a one-dimensional array of any length
                await node.write_value_rank(ua.ValueRank.OneDimension)
            nodes.append(node)
        item_state = await StateVariable.install(cell, idx, "MachineryItemState")
        mode = await StateVariable.install(cell, idx, "OperationMode")
        out = cls(server, cell, nodes, item_state, mode)
        await out.update(first)
        return out

    async def update(self, s: Status) -> None:
        """Write what changed since the last status, stamped with the status's time."""
        stamp = ua.DateTime.fromtimestamp(s.t_unix_s, UTC)
        for i, var in enumerate(VARIABLES):
            value = var.get(s)
            if same(value, self.values[i]):
                continue
            self.values[i] = value
            data = ua.DataValue(ua.Variant(value, var.vtype), SourceTimestamp=stamp)
            await self.server.write_attribute_value(self.nodes[i].nodeid, data)
        await self.item_state.set(machinery_state(s))
        await self.mode.set(MODE_STATES[s.mode])


async def _folder(folders: dict[str, Node], path: str, idx: int) -> Node:
    """The object at `path` below Cell, made (with its parents) on first use."""
    if path not in folders:
        parent_path, _, name = path.rpartition("/")
        parent = await _folder(folders, parent_path, idx)
        nid = node_id("Cell." + path.replace("/", "."), idx)
        folders[path] = await parent.add_object(nid, ua.QualifiedName(name, idx))
    return folders[path]


async def _identification(cell: Node, idx: int) -> None:
    """Machinery's identification properties. One clothd runs one cell, so the cell PC's host name
    identifies the instance."""
    host = socket.gethostname()
    bname = ua.QualifiedName("Identification", idx)
    ident = await cell.add_object(node_id("Cell.Identification", idx), bname)
    for name, value in (
        ("Manufacturer", ua.LocalizedText("clothd")),
        ("Model", ua.LocalizedText("steerable-conveyor cloth cell")),
        ("ProductInstanceUri", f"urn:clothd:{host}"),
        ("SerialNumber", host),
        ("SoftwareRevision", version("clothd")),
    ):
        nid = node_id(f"Cell.Identification.{name}", idx)
        await ident.add_property(nid, ua.QualifiedName(name, idx), value)
