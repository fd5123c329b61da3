"""The OPC UA server with asyncua's own client: in process over a daemon built but not started (the
address space, security, refusals), and against a live `clothd run --sim` (the pose, a move watched
through a subscription, the e-stop in hwsim, passwords)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
import stat
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from asyncua import Client, Node, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.ua.uaerrors import BadUserAccessDenied
from cryptography.x509.oid import ExtendedKeyUsageOID
from fastapi.testclient import TestClient
from live_cell import wait
from local_api import local_app
from local_cell import LocalCell

from clothd.api.commands import Commands
from clothd.api.opcua_nodes import NAMESPACE_URI, VARIABLES
from clothd.api.opcua_security import CERT_FILE, KEY_FILE
from clothd.api.opcua_server import OpcUaServer
from clothd.config import Config, OpcUaConfig
from clothd.run import build
from clothd.tools.bench_loop import ANGLE_TOL_RAD, POS_TOL_M, DaemonProcess, free_port, pose_error

TOKEN = "opcua-test-token-0123456789"
METHODS = ("Move", "Hold", "Idle", "Flatten", "EStop", "ClearEStop", "Reset")
N_MODULES = 48  # the default cell: 8 x 6
HOLD_S = 1.0  # a settled pose stays within clothd bench loop's bar (5 mm, 1 deg) this long
STATE = ua.NodeId(ua.ObjectIds.Server_ServerStatus_State)
VALUE = ua.AttributeIds.Value
BASE = "http://127.0.0.1:8080"  # the REST API's own name: its guard refuses any other Host


async def _cell(client: Client) -> tuple[Node, int]:
    idx = await client.get_namespace_index(NAMESPACE_URI)
    return await client.nodes.objects.get_child(f"{idx}:Cell"), idx


async def _call(client: Client, name: str, *args: float) -> ua.CallMethodResult:
    """The call's whole result: asyncua's call_method raises on a Bad code and drops the reason."""
    cell, idx = await _cell(client)
    method = await cell.get_child(f"{idx}:{name}")
    inputs = [ua.Variant(a, ua.VariantType.Double) for a in args]
    req = ua.CallMethodRequest(ObjectId=cell.nodeid, MethodId=method.nodeid, InputArguments=inputs)
    return (await client.uaclient.call([req]))[0]


def _user(url: str, password: str = TOKEN, name: str = "clothd") -> Client:
    client = Client(url)
    client.set_user(name)
    client.set_password(password)
    return client


# -- in process: a daemon built as `clothd run` builds it, never started (state "starting") -----------


@contextlib.asynccontextmanager
async def _server(
    cfg: OpcUaConfig, token: str | None, rest: list[TestClient] | None = None
) -> AsyncIterator[str]:
    """The server's URL; `rest` receives the REST API over the same daemon."""
    parts = build(Config())
    server = OpcUaServer(cfg, token, parts.hub, Commands(LocalCell(parts.daemon)))
    if rest is not None:
        rest.append(TestClient(local_app(parts), base_url=BASE))
    await server.start()
    try:
        yield cfg.endpoint
    finally:
        await server.stop()


def _loopback(**kw: Any) -> OpcUaConfig:
    return OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{free_port()}/clothd/", **kw)


def test_the_address_space_browses_as_documented() -> None:
    async def main() -> None:
        async with _server(_loopback(), None) as url, Client(url) as client:
            cell, idx = await _cell(client)
            names = {(await n.read_browse_name()).Name for n in await cell.get_children()}
            assert {"Identification", "MachineryItemState", "OperationMode", *METHODS} <= names
            assert {"State", "Mode", "Setpoint", "Pose", "Flatness", "Timing", "Modules", "Faults"} <= names
            for var in VARIABLES:  # every variable where docs/opcua.md puts it
                path = [f"{idx}:{part}" for part in var.path.split("/")]
                await (await cell.get_child(path)).read_value()
            ident = await cell.get_child(f"{idx}:Identification")
            assert (await (await ident.get_child(f"{idx}:SoftwareRevision")).read_value()) == "0.1.0"
            state = await cell.get_child([f"{idx}:MachineryItemState", "0:CurrentState"])
            assert (await state.read_value()).Text == "NotAvailable"  # the loop has not started
            speeds = await cell.get_child([f"{idx}:Modules", f"{idx}:Speed_m_s"])
            assert await speeds.read_value() == [0.0] * N_MODULES
            move = await cell.get_child(f"{idx}:Move")
            args = await (await move.get_child("0:InputArguments")).read_value()
            assert [a.Name for a in args] == ["x_m", "y_m", "theta_rad"]
            assert math.isnan(await (await cell.get_child([f"{idx}:Pose", f"{idx}:X_m"])).read_value())

    asyncio.run(main())


def test_one_camera_reads_as_one_entry_and_no_flatness_as_an_empty_basis() -> None:
    async def main() -> None:
        async with _server(_loopback(), None) as url, Client(url) as client:
            cell, idx = await _cell(client)
            names = await cell.get_child([f"{idx}:Cameras", f"{idx}:Name"])
            skews = await cell.get_child([f"{idx}:Cameras", f"{idx}:Skew_ms"])
            fps = await cell.get_child([f"{idx}:Cameras", f"{idx}:Fps"])
            basis = await cell.get_child([f"{idx}:Flatness", f"{idx}:Basis"])
            assert await names.read_value() == ["cam0"]
            (rate,) = await fps.read_value()
            assert math.isnan(rate)  # no camera has delivered a frame here
            (skew,) = await skews.read_value()
            assert math.isnan(skew)  # the first camera has no skew to itself
            assert await basis.read_value() == ""  # not tracking: no flatness

    asyncio.run(main())


def test_the_start_names_its_security_policy_in_words(caplog: pytest.LogCaptureFixture) -> None:
    """The log line once read "OPC UA on opc.tcp://.../clothd/ (None)", like a bug."""
    cfg = _loopback()

    async def main() -> None:
        async with _server(cfg, None):
            pass

    with caplog.at_level(logging.INFO, logger="clothd.api.opcua_server"):
        asyncio.run(main())
    assert f"OPC UA on {cfg.endpoint}, security policy None" in caplog.messages


def test_a_refusal_is_a_bad_code_with_the_rest_apis_reason() -> None:
    rest: list[TestClient] = []

    async def main() -> None:
        async with _server(_loopback(), None, rest) as url, Client(url) as client:
            out_of_bounds = await _call(client, "Move", 9.0, 0.0, 0.0)
            assert out_of_bounds.StatusCode.value == ua.StatusCodes.BadInvalidArgument
            body = {"mode": "move", "x_m": 9.0, "y_m": 0.0, "theta_rad": 0.0}
            r = rest[0].put("/api/v1/setpoint", json=body)
            reason = out_of_bounds.OutputArguments[
                0
            ].Value  # the argument's name, where REST names the body's
            assert reason == "x_m: Input should be less than or equal to 5 (less_than_equal)"
            assert r.status_code == 422 and r.json()["detail"] == f"body.move.{reason}"
            not_now = await _call(client, "Hold")  # the link is not up: the daemon never started
            assert not_now.StatusCode.value == ua.StatusCodes.BadInvalidState
            r = rest[0].put("/api/v1/setpoint", json={"mode": "hold"})
            assert r.status_code == 409 and not_now.OutputArguments[0].Value == r.json()["detail"]
            missing = await _call(client, "Move", 0.1)
            assert missing.StatusCode.value == ua.StatusCodes.BadArgumentsMissing
            done = await _call(client, "EStop")
            assert done.StatusCode.is_good() and done.OutputArguments[0].Value == "emergency stop latched"

    asyncio.run(main())


def test_with_a_token_anonymous_clients_read_and_only_clothd_calls() -> None:
    async def main() -> None:
        async with _server(_loopback(), TOKEN) as url:
            async with Client(url) as anonymous:
                cell, idx = await _cell(anonymous)
                assert await (await cell.get_child(f"{idx}:State")).read_value() == "starting"
                with pytest.raises(BadUserAccessDenied):
                    await _call(anonymous, "EStop")
            async with _user(url) as user:
                assert (await _call(user, "Reset")).StatusCode.is_good()
            for client in (_user(url, password="not-the-token-at-all"), _user(url, name="admin")):
                with pytest.raises(BadUserAccessDenied):
                    await client.connect()
                await client.disconnect()

    asyncio.run(main())


@contextlib.asynccontextmanager
async def _plain_session(url: str) -> AsyncIterator[Client]:
    """An anonymous session over the None policy, whatever the server offers (asyncua's Client checks
    the endpoints first, so its steps are taken one by one here)."""
    client = Client(url)
    await client.connect_socket()
    await client.send_hello()
    await client.open_secure_channel()
    session = ua.CreateSessionParameters(
        ClientDescription=ua.ApplicationDescription(),
        EndpointUrl=url,
        SessionName="plain",
        ClientNonce=bytes(32),
        RequestedSessionTimeout=60_000,
    )
    await client.uaclient.create_session(session)
    activate = ua.ActivateSessionParameters(UserIdentityToken=ua.AnonymousIdentityToken(PolicyId="anonymous"))
    await client.uaclient.activate_session(activate)
    try:
        yield client
    finally:
        client.disconnect_socket()


def test_sign_and_encrypt_with_a_certificate_made_on_first_start(tmp_path: Path) -> None:
    cfg = _loopback(security_policies=("Basic256Sha256_SignAndEncrypt",), cert_dir=tmp_path / "pki")

    async def main() -> None:
        client_key, client_cert = tmp_path / "client-key.pem", tmp_path / "client-cert.der"
        await setup_self_signed_certificate(
            client_key, client_cert, "urn:test:client", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {}
        )
        async with _server(cfg, TOKEN) as url:
            endpoints = await Client(url).connect_and_get_server_endpoints()
            assert [(e.SecurityPolicyUri.rpartition("#")[2], e.SecurityMode) for e in endpoints] == [
                ("Basic256Sha256", ua.MessageSecurityMode.SignAndEncrypt)
            ]
            async with _plain_session(url) as plain:  # asks for the None policy all the same: not served
                read = ua.ReadParameters(NodesToRead=[ua.ReadValueId(NodeId=STATE, AttributeId=VALUE)])
                with pytest.raises(BadUserAccessDenied):
                    await plain.uaclient.read(read)
            secure = _user(url)
            await secure.set_security_string(f"Basic256Sha256,SignAndEncrypt,{client_cert},{client_key}")
            async with secure:
                cell, idx = await _cell(secure)
                assert await (await cell.get_child(f"{idx}:Mode")).read_value() == "idle"
        return None

    asyncio.run(main())
    key = cfg.cert_dir / KEY_FILE
    assert (cfg.cert_dir / CERT_FILE).is_file() and stat.S_IMODE(key.stat().st_mode) == 0o600
    first = key.read_bytes()
    asyncio.run(main())  # the second start keeps the certificate and key
    assert key.read_bytes() == first


# -- against `clothd run --sim` ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[DaemonProcess]:
    path = tmp_path_factory.mktemp("opcua") / "clothd.yaml"
    path.write_text(yaml.safe_dump({"api": {"token": TOKEN}}))
    d = DaemonProcess(path, free_port())
    try:
        d.wait_ready()

        def tracking() -> bool:
            s = httpx.get(f"{d.base}/api/v1/status", timeout=5).json()
            return bool(s["state"] == "tracking" and s["link"]["state"] == "connected")

        wait(tracking, 120, "daemon tracking the cloth with the link up", every_s=0.3)
        yield d
    finally:
        d.stop()


def _truth(d: DaemonProcess) -> dict[str, Any]:
    return dict(httpx.get(d.truth_url, timeout=5).json())


def test_read_the_pose(live: DaemonProcess) -> None:
    async def main() -> None:
        async with Client(live.opcua_url) as client:
            cell, idx = await _cell(client)
            pose = await cell.get_child(f"{idx}:Pose")
            names = ("X_m", "Y_m", "Theta_rad", "XStd_m", "YStd_m", "ThetaStd_rad")
            nodes = [await pose.get_child(f"{idx}:{n}") for n in names]
            # The address space follows the status at 10 Hz: right after the daemon starts tracking it may
            # still hold the NaN it started with (this read failed so once in a full run).
            deadline = time.monotonic() + 5.0
            values = [await n.read_value() for n in nodes]
            while not all(math.isfinite(v) for v in values) and time.monotonic() < deadline:
                await asyncio.sleep(0.1)
                values = [await n.read_value() for n in nodes]
            x, y, theta, *std = values
        truth = _truth(live)["pose"]
        pos_err_m, angle_err_rad = pose_error(truth, (x, y, theta))
        assert pos_err_m < 0.005 and angle_err_rad < math.radians(1.0), (x, y, theta, truth)
        assert all(0 < s < 0.01 for s in std), std

    asyncio.run(main())


class _Latest:
    """A subscription handler keeping each node's newest value."""

    def __init__(self) -> None:
        self.values: dict[Any, Any] = {}

    def datachange_notification(self, node: Node, val: Any, data: Any) -> None:
        self.values[node.nodeid] = val


def test_move_settles_as_a_subscription_sees_it(live: DaemonProcess) -> None:
    async def main() -> None:
        async with _user(live.opcua_url) as client:
            cell, idx = await _cell(client)
            nodes = [await cell.get_child([f"{idx}:Pose", f"{idx}:{n}"]) for n in ("X_m", "Y_m", "Theta_rad")]
            latest = _Latest()
            sub = await client.create_subscription(100, latest)  # 10 Hz, as the server publishes
            await sub.subscribe_data_change(nodes)
            start = _truth(live)["pose"]
            target = (start[0] + 0.04, start[1] - 0.02, start[2] + math.radians(10.0))
            answer = await _call(client, "Move", *target)
            assert answer.StatusCode.is_good(), answer.OutputArguments
            assert answer.OutputArguments[0].Value == "mode move"

            def seen() -> list[float]:
                return [latest.values.get(n.nodeid, math.nan) for n in nodes]

            loop = asyncio.get_running_loop()
            deadline, inside_since = loop.time() + 30.0, math.inf
            while loop.time() - inside_since < HOLD_S:  # settled: inside the bar for a whole hold window
                err = pose_error(seen(), target)
                inside = err[0] <= POS_TOL_M and err[1] <= ANGLE_TOL_RAD
                inside_since = min(inside_since, loop.time()) if inside else math.inf
                if loop.time() > deadline:
                    status = httpx.get(f"{live.base}/api/v1/status", timeout=5).json()
                    pytest.fail(f"seen {seen()} for {target}: mode {status['mode']}, {status['halt_reason']}")
                await asyncio.sleep(0.1)
            await sub.delete()
            assert (await _call(client, "Idle")).StatusCode.is_good()
        err = pose_error(_truth(live)["pose"], target)  # the estimate settled where the cloth truly is
        assert err[0] <= POS_TOL_M and err[1] <= ANGLE_TOL_RAD, err

    asyncio.run(main())


def test_estop_stops_every_module_in_hwsim(live: DaemonProcess) -> None:
    async def main() -> None:
        async with _user(live.opcua_url) as client:
            cell, idx = await _cell(client)
            start = _truth(live)["pose"]
            assert (await _call(client, "Move", start[0] - 0.05, start[1], start[2])).StatusCode.is_good()
            await asyncio.to_thread(
                wait, lambda: max(map(abs, _truth(live)["module_speed_m_s"])) > 0.005, 10, "modules running"
            )
            assert (await _call(client, "EStop")).StatusCode.is_good()
            await asyncio.to_thread(
                wait,
                lambda: _truth(live)["estopped"] and not any(_truth(live)["module_speed_m_s"]),
                5,
                "every module stopped in hwsim",
            )
            latched = await cell.get_child(f"{idx}:EStopLatched")
            item_state = await cell.get_child([f"{idx}:MachineryItemState", "0:CurrentState"])
            speeds = await cell.get_child([f"{idx}:Modules", f"{idx}:Speed_m_s"])

            async def published() -> bool:
                state = (await item_state.read_value()).Text
                stopped = await speeds.read_value() == [0.0] * N_MODULES
                return bool(await latched.read_value()) and state == "OutOfService" and stopped

            for _ in range(50):  # the variables follow at 10 Hz, each from the tick it was published in
                if await published():
                    break
                await asyncio.sleep(0.1)
            assert await published(), (
                await latched.read_value(),
                (await item_state.read_value()).Text,
                await speeds.read_value(),
            )
            refused = await _call(client, "Hold")
            assert refused.StatusCode.value == ua.StatusCodes.BadInvalidState
            assert "emergency stop is latched" in refused.OutputArguments[0].Value
            assert (await _call(client, "ClearEStop")).StatusCode.is_good()

    asyncio.run(main())


def test_the_flatness_basis_and_both_cameras_skew_read_live(live: DaemonProcess) -> None:
    """`clothd run --sim` runs the default cell's two cameras: the second's skew is measured, and the
    flatness says what it rests on."""

    async def main() -> tuple[str, list[str], list[float]]:
        async with Client(live.opcua_url) as client:
            cell, idx = await _cell(client)
            basis = await cell.get_child([f"{idx}:Flatness", f"{idx}:Basis"])
            names = await cell.get_child([f"{idx}:Cameras", f"{idx}:Name"])
            skews = await cell.get_child([f"{idx}:Cameras", f"{idx}:Skew_ms"])
            for _ in range(100):  # the variables follow the status at 10 Hz
                values = (await basis.read_value(), await names.read_value(), await skews.read_value())
                if values[0] and len(values[2]) == 2 and math.isfinite(values[2][1]):
                    break
                await asyncio.sleep(0.1)
            return values

    basis, names, skews = asyncio.run(main())
    assert basis in ("measured", "since_start")
    assert names == ["cam0", "cam1"]
    assert math.isnan(skews[0]) and math.isfinite(skews[1]), skews


def test_a_wrong_password_is_refused_by_the_live_daemon(live: DaemonProcess) -> None:
    async def main() -> None:
        client = _user(live.opcua_url, password="wrong-password-0123456789")
        with pytest.raises(BadUserAccessDenied):
            await client.connect()
        await client.disconnect()
        async with Client(live.opcua_url) as anonymous:  # reads stay anonymous; calls do not
            with pytest.raises(BadUserAccessDenied):
                await _call(anonymous, "Reset")

    asyncio.run(main())


def test_a_taken_opcua_port_ends_the_start_at_once_and_clearly() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        endpoint = f"opc.tcp://127.0.0.1:{taken.getsockname()[1]}/clothd/"
        cmd = ["run", "--sim", "--port", str(free_port()), "--opcua-endpoint", endpoint]
        done = subprocess.run(
            [sys.executable, "-m", "clothd.cli", *cmd], capture_output=True, text=True, timeout=60
        )
    assert done.returncode == 2
    assert f"cannot listen on {endpoint}" in done.stderr and "opcua.endpoint" in done.stderr
    assert "hwsim" not in done.stdout  # nothing was started
