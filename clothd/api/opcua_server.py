"""The OPC UA server (asyncua): the cell for line controllers, MES and HMIs; docs/opcua.md.

It runs in the API process, on its event loop (serve_api.py), beside the REST API and for the same
reason: no client, however slow or busy, can delay the tick. Its variables follow the status snapshots
the daemon publishes for the WebSocket (StreamHub.status), at most opcua.publish_hz times a second,
only what changed. Its methods are the REST API's commands (commands.py): the same answers and refusals.

A method answers one output argument, `Detail`: the answer in words, or why it was refused. A refusal
is a Bad status code (ERROR_STATUS) with that reason beside it: asyncua's own high-level `call_method`
raises on the code alone; the reason is in the call's result (docs/opcua.md shows how to read it).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import Server, ua
from asyncua.crypto import uacrypto

from clothd.api.commands import Commands
from clothd.api.opcua_limits import GuardedBinaryServer, SessionSlots, transport_limits
from clothd.api.opcua_nodes import NAMESPACE_URI, CellNodes, node_id
from clothd.api.opcua_pieces import PiecesNodes
from clothd.api.opcua_security import CellRules, DiscoveryOnly, TokenUsers, server_certificate
from clothd.api.schemas import FlattenSetpoint, FlowSetpoint, HoldSetpoint, IdleSetpoint
from clothd.api.stream import StreamHub
from clothd.config import OPCUA_SIGN_AND_ENCRYPT, OpcUaConfig, is_loopback, opcua_host_port
from clothd.core.modes import Mode
from clothd.errors import (
    ClothdError,
    ConfigError,
    HardwareError,
    InvalidRequestError,
    RequestError,
    StorageError,
    UnreachableTargetError,
)

log = logging.getLogger(__name__)

# clothd's errors as OPC UA status codes, as app.py maps them to HTTP; the most specific class wins.
ERROR_STATUS: dict[type[ClothdError], int] = {
    UnreachableTargetError: ua.StatusCodes.BadOutOfRange,  # 422: the target leaves the workspace
    InvalidRequestError: ua.StatusCodes.BadInvalidArgument,  # 422: never possible as given
    StorageError: ua.StatusCodes.BadResourceUnavailable,  # 507
    RequestError: ua.StatusCodes.BadInvalidState,  # 409: not in the daemon's present state
    HardwareError: ua.StatusCodes.BadDeviceFailure,  # 503
    ClothdError: ua.StatusCodes.BadDeviceFailure,
}
POLICIES = {
    "None": ua.SecurityPolicyType.NoSecurity,
    OPCUA_SIGN_AND_ENCRYPT: ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
}
APPLICATION_URI = "urn:clothd:server"


def status_for(err: ClothdError) -> int:
    return next(ERROR_STATUS[c] for c in type(err).__mro__ if c in ERROR_STATUS)


def _argument(name: str, vtype: ua.VariantType, description: str) -> ua.Argument:
    return ua.Argument(
        Name=name,
        DataType=ua.NodeId(ua.Int32(vtype.value)),
        ValueRank=ua.ValueRank.Scalar,
        Description=ua.LocalizedText(description),
    )


DETAIL = _argument("Detail", ua.VariantType.String, "the answer in words, or why the call was refused")
MOVE_ARGS = [
    _argument("x_m", ua.VariantType.Double, "target x, world frame, metres (-5..5)"),
    _argument("y_m", ua.VariantType.Double, "target y, world frame, metres (-5..5)"),
    _argument("theta_rad", ua.VariantType.Double, "target heading, radians (-pi..pi)"),
]


class _Server(Server):
    def __init__(self, slots: SessionSlots, user_manager: TokenUsers) -> None:
        super().__init__(user_manager=user_manager)
        self.slots = slots
        self.limits = transport_limits(slots.cfg)

    async def _setup_server_nodes(self) -> None:
        """asyncua's policies for the offered endpoints, then None for discovery only (DiscoveryOnly)."""
        await super()._setup_server_nodes()
        self._policies.append(DiscoveryOnly())  # after ours: a None that we offer matches first

    async def start(self) -> None:
        """asyncua's Server.start with connections that keep to the limits (opcua_limits.py)."""
        if self.iserver.certificate is not None:  # asyncua's warnings about it, as its start gives them
            uacrypto.check_certificate(self.iserver.certificate, self._application_uri, socket.gethostname())
        await self._setup_server_nodes()
        await self.iserver.start()
        host, port = self._get_bind_socket_info()
        self.bserver = GuardedBinaryServer(self.iserver, host, port, self.limits, self.slots)
        self.bserver.set_policies(self._policies)
        try:
            await self.bserver.start()
        except Exception:
            await self.iserver.stop()
            raise


class OpcUaServer:
    def __init__(self, cfg: OpcUaConfig, token: str | None, hub: StreamHub, commands: Commands) -> None:
        self.cfg = cfg
        self.hub = hub
        self.commands = commands
        host, _ = opcua_host_port(cfg.endpoint)
        loopback = is_loopback(host)
        slots = SessionSlots(cfg)
        self.server = _Server(slots, TokenUsers(token, anonymous=loopback, slots=slots))
        self.token_set = token is not None
        self.loopback = loopback
        self.nodes: CellNodes | None = None
        self.pieces: PiecesNodes | None = None
        self._publisher: asyncio.Task[None] | None = None

    async def start(self) -> None:
        """Build the address space from the newest status and listen (on the running loop: the API's)."""
        s = self.server
        await s.init()
        s.set_endpoint(self.cfg.endpoint)
        s.set_server_name("clothd")
        await s.set_application_uri(APPLICATION_URI)
        tokens: list[type] = [ua.UserNameIdentityToken] if self.token_set else []
        if self.loopback:
            tokens.append(ua.AnonymousIdentityToken)
        s.set_identity_tokens(tokens)
        s.set_security_policy([POLICIES[p] for p in self.cfg.security_policies], CellRules(self.token_set))
        if OPCUA_SIGN_AND_ENCRYPT in self.cfg.security_policies:
            cert, key = await server_certificate(self.cfg.cert_dir, APPLICATION_URI)
            await s.load_certificate(str(cert))
            await s.load_private_key(str(key))
        idx = await s.register_namespace(NAMESPACE_URI)
        assert self.hub.status is not None  # the daemon publishes once when it is built
        self.nodes = await CellNodes.build(s, idx, self.hub.status)
        self.pieces = await PiecesNodes.build(s, self.nodes.cell, idx, self.hub.status)
        await self._add_methods(idx)
        try:
            await s.start()
        except OSError as err:
            raise ConfigError(
                f"cannot listen on {self.cfg.endpoint}: {err.strerror or err}; "
                "choose another address with --opcua-endpoint or opcua.endpoint"
            ) from None
        self._publisher = asyncio.create_task(self._publish())
        policies = self.cfg.security_policies
        named = "security policy" if len(policies) == 1 else "security policies"
        log.info("OPC UA on %s, %s %s", self.cfg.endpoint, named, " and ".join(policies))

    async def stop(self) -> None:
        if self._publisher is not None:
            self._publisher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._publisher
        await self.server.stop()

    async def _publish(self) -> None:
        """The newest status into the variables, at most publish_hz times a second."""
        assert self.nodes is not None and self.pieces is not None
        period_s = 1.0 / self.cfg.publish_hz
        last = None
        while True:
            status = self.hub.status
            if status is not None and status is not last:
                await self.nodes.update(status)
                await self.pieces.update(status)
                last = status
            await asyncio.sleep(period_s)

    async def _add_methods(self, idx: int) -> None:
        assert self.nodes is not None
        c = self.commands
        methods: dict[str, tuple[Callable[..., Awaitable[str]], list[ua.Argument]]] = {
            "Move": (c.move, MOVE_ARGS),
            "Hold": (lambda: c.setpoint(HoldSetpoint(mode=Mode.HOLD)), []),
            "Idle": (lambda: c.setpoint(IdleSetpoint(mode=Mode.IDLE)), []),
            "Flatten": (lambda: c.setpoint(FlattenSetpoint(mode=Mode.FLATTEN)), []),
            "Flow": (lambda: c.setpoint(FlowSetpoint(mode=Mode.FLOW)), []),
            "EStop": (c.estop, []),
            "ClearEStop": (c.estop_clear, []),
            "Reset": (c.reset, []),
        }
        for name, (command, inputs) in methods.items():
            callback = _method(command, len(inputs))
            nid, bname = node_id(f"Cell.{name}", idx), ua.QualifiedName(name, idx)
            await self.nodes.cell.add_method(nid, bname, callback, inputs, [DETAIL])


def _method(command: Callable[..., Awaitable[str]], n_inputs: int) -> Callable[..., Awaitable[Any]]:
    """An asyncua method callback around a command: its answer as Detail, a refusal as a Bad code."""

    async def call(parent: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
        if len(args) != n_inputs:
            few = len(args) < n_inputs
            code = ua.StatusCodes.BadArgumentsMissing if few else ua.StatusCodes.BadTooManyArguments
            return _result(code, f"takes {n_inputs} arguments, got {len(args)}")
        try:
            return _result(ua.StatusCodes.Good, await command(*(a.Value for a in args)))
        except ClothdError as err:
            return _result(status_for(err), str(err))

    return call


def _result(code: int, detail: str) -> ua.CallMethodResult:
    return ua.CallMethodResult(
        StatusCode=ua.StatusCode(ua.UInt32(code)), OutputArguments=[ua.Variant(detail, ua.VariantType.String)]
    )
