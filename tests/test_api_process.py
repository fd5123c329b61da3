"""The API in a process of its own (clothd/api/process.py, serve_api.py): what crosses the channel between
it and a daemon built as `clothd run` builds it (never started: no camera, no serial port), and how each
end stands when the other stops."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import httpx
import pytest
from websockets.asyncio.client import connect

from clothd.api.cell import CellSettings
from clothd.api.channel import Channel, channel_pair
from clothd.api.process import ApiProcess
from clothd.api.remote_cell import error_from
from clothd.api.serve_api import ApiSpec
from clothd.config import ApiConfig, Config, OpcUaConfig, RecordingConfig, TrackerConfig
from clothd.errors import (
    ClothdError,
    ConfigError,
    HardwareError,
    InvalidRequestError,
    RequestError,
    StorageError,
    UnreachableTargetError,
)
from clothd.loop.daemon import Daemon
from clothd.run import bind_api, build

pytestmark = pytest.mark.clock_free

WAIT_S = 30.0  # a bound on what must happen, never a measure


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _parts(cfg: Config) -> tuple[Daemon, ApiSpec]:
    parts = build(cfg)
    daemon = parts.daemon
    assert daemon.status is not None
    status_json = daemon.status.model_dump_json().encode()
    settings = CellSettings.of(daemon.settings)
    return daemon, ApiSpec(cfg.api, cfg.opcua, parts.camera_model, settings, status_json)


def _config(**sections: Any) -> Config:
    """On a free port, without OPC UA (its start, a few seconds, is tested on its own)."""
    return Config(api=ApiConfig(port=_free_port()), opcua=OpcUaConfig(enabled=False), **sections)


@asynccontextmanager
async def _served(cfg: Config) -> AsyncIterator[tuple[ApiProcess, Daemon, httpx.AsyncClient]]:
    """The API process over a daemon, its statuses going to it as `clothd run` sends them."""
    daemon, spec = _parts(cfg)
    api = ApiProcess(spec, daemon)
    daemon.on_status = api.publish
    listener = bind_api(cfg.api)
    try:
        await api.start(listener)
        base = f"http://{cfg.api.host}:{cfg.api.port}"
        async with httpx.AsyncClient(base_url=base, timeout=WAIT_S) as client:
            yield api, daemon, client
    finally:
        await api.stop()
        listener.close()


async def _until(check: Callable[[], bool], what: str) -> None:
    try:
        async with asyncio.timeout(WAIT_S):
            while not check():
                await asyncio.sleep(0.01)
    except TimeoutError:
        raise AssertionError(f"{what}: not within {WAIT_S} s") from None


def test_every_clothd_error_crosses_as_its_own_class() -> None:
    for cls in (ClothdError, ConfigError, HardwareError, RequestError, InvalidRequestError, StorageError):
        err = error_from(cls.__name__, "why")
        assert type(err) is cls and str(err) == "why"
    assert type(error_from(UnreachableTargetError.__name__, "off")) is UnreachableTargetError
    assert type(error_from("KeyError", "'x'")) is RuntimeError  # a bug in the daemon: 500, not a 4xx


def test_the_daemons_refusals_keep_their_http_status_across_the_process(tmp_path: Path) -> None:
    """409 stays 409 and 422 stays 422: each error is raised in the API process as the daemon's class."""
    (tmp_path / "file").write_text("not a directory")
    recording = RecordingConfig(dir=tmp_path)
    cfg = _config(recording=recording, tracker=TrackerConfig(model="rigid"))

    async def body() -> None:
        async with _served(cfg) as (_, daemon, client):
            r = await client.put("/api/v1/setpoint", json={"mode": "hold"})
            assert r.status_code == 409 and r.json()["detail"] == "starting"
            r = await client.put("/api/v1/setpoint", json={"mode": "flatten"})
            assert r.status_code == 409 and "mesh tracker" in r.json()["detail"]
            r = await client.post("/api/v1/record/start", json={"dir": "file/inside"})  # InvalidRequestError
            assert r.status_code == 422 and "cannot create" in r.json()["detail"]
            r = await client.post("/api/v1/record/start", json={"dir": "file"})  # RequestError: it exists
            assert r.status_code == 409 and "exists" in r.json()["detail"]
            r = await client.post("/api/v1/record/stop")
            assert r.status_code == 409 and r.json()["detail"] == "not recording"
            r = await client.post("/api/v1/record/start", json={"dir": "new"})
            assert r.status_code == 200 and str(tmp_path / "new") in r.json()["detail"]
            assert daemon._record_start == tmp_path / "new"  # the daemon's own request, as in-process
            # The API process made the place; one the daemon refuses is removed again.
            r = await client.post("/api/v1/record/start", json={"dir": "again"})
            assert r.status_code == 409 and "is starting in" in r.json()["detail"]
            assert not (tmp_path / "again").exists()

    asyncio.run(body())


def test_the_estop_latches_on_the_daemons_loop() -> None:
    cfg = _config()

    async def body() -> None:
        async with _served(cfg) as (_, daemon, client):
            assert not daemon.link.estopped
            r = await client.post("/api/v1/estop")
            assert r.status_code == 200 and daemon.link.estopped
            await _until(lambda: daemon.status is not None and daemon.status.estop, "estop published")
            r = await client.get("/api/v1/status")
            assert r.json()["estop"] is True  # Daemon.estop published it: it reached the API's readers
            r = await client.post("/api/v1/estop/clear")
            assert r.status_code == 200 and not daemon.link.estopped
            assert r.json()["detail"] == "emergency stop cleared; mode is idle"  # the answer crossed over
            r = await client.post("/api/v1/estop/clear")
            assert r.json()["detail"] == "no emergency stop was latched"

    asyncio.run(body())


def test_a_request_its_caller_gave_up_on_is_not_carried_out_but_a_late_estop_is() -> None:
    """The API answers "the daemon did not answer" after its timeout; a call that reaches the daemon
    after that (a loop held up) must not move the cloth behind the caller's back. An e-stop still stops."""
    cfg = _config()

    async def body() -> None:
        async with _served(cfg) as (api, daemon, _):
            late = time.monotonic() - 1.0
            api._answer(1, "reset", (), late)  # as the daemon's end takes a call off the socket
            assert not daemon._reset_requested
            api._answer(2, "reset", (), time.monotonic() + 10.0)
            assert daemon._reset_requested
            api._answer(3, "estop", (), late)
            assert daemon.link.estopped

    asyncio.run(body())


def test_a_published_status_reaches_get_status_the_health_check_and_a_websocket() -> None:
    cfg = _config()

    async def body() -> None:
        async with _served(cfg) as (_, daemon, client):
            url = f"ws://{cfg.api.host}:{cfg.api.port}/api/v1/stream"
            async with connect(url) as ws:
                first = json.loads(await ws.recv())
                assert first["halt_reason"] is None
                daemon.halt_reason = "a reason published by the daemon"
                daemon.publish()
                async with asyncio.timeout(WAIT_S):
                    while json.loads(await ws.recv())["halt_reason"] is None:
                        pass
            status = (await client.get("/api/v1/status")).json()
            assert status["halt_reason"] == "a reason published by the daemon"
            health = await client.get("/healthz")  # read from the parsed Status object
            assert health.status_code == 503 and "stepper link" in health.json()["problems"]
            metrics = (await client.get("/metrics")).text
            assert "clothd_ticks" in metrics

    asyncio.run(body())


def test_the_view_crosses_only_while_someone_watches() -> None:
    cfg = _config()
    jpeg = b"\xff\xd8 a view \xff\xd9"

    async def body() -> None:
        async with _served(cfg) as (api, daemon, client):
            daemon.view.post(b"\xff\xd8 unwatched \xff\xd9")
            daemon.publish()
            assert not daemon.view.watched and api.dropped_views == 0
            async with client.stream("GET", "/api/v1/view.mjpg") as stream:
                await _until(lambda: daemon.view.watched, "the daemon told someone watches")
                daemon.view.post(jpeg)
                daemon.publish()
                async with asyncio.timeout(WAIT_S):
                    async for chunk in stream.aiter_bytes():
                        if jpeg in chunk:
                            break
            await _until(lambda: not daemon.view.watched, "the daemon told no one watches")

    asyncio.run(body())


def test_the_daemon_never_waits_for_an_api_process_that_stops_reading(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Nothing reads the API's end: the statuses that find no room are dropped and counted (said once),
    and each publish returns (the channel never blocks); a reply waits, in order, for room."""
    cfg = _config()
    daemon, spec = _parts(cfg)
    ours, theirs = channel_pair()
    api = ApiProcess(spec, daemon, ends=(ours, theirs))
    daemon.on_status = api.publish
    published = 0
    with caplog.at_level(logging.WARNING, logger="clothd.api.process"):
        while api.dropped_statuses < 3 and published < 100_000:  # the send buffer holds a few MB of them
            daemon.publish()
            published += 1
    assert api.dropped_statuses == 3 and caplog.text.count("the API process is not reading") == 1
    sent = published - api.dropped_statuses
    api._answer(1, "reset", (), time.monotonic() + 10.0)  # a call's reply with no room: kept, not dropped
    assert api._replies
    reader = Channel(theirs)
    received = reader.receive()
    assert len(received) == sent and all(m[0] == "status" for m in received)  # type: ignore[index]
    daemon.publish()  # room again: the reply goes first, then the status
    kinds = [m[0] for m in reader.receive()]  # type: ignore[index]
    assert kinds == ["reply", "status"] and not api._replies
    ours.close()
    theirs.close()


def test_the_api_process_ends_when_the_daemons_end_closes() -> None:
    cfg = _config()

    async def body() -> None:
        async with _served(cfg) as (api, _, client):
            assert (await client.get("/api/v1/status")).status_code == 200
            process = api._process
            assert Path(f"/proc/{process.pid}/comm").read_text().strip() == "clothd-api"  # not the compute
            asyncio.get_running_loop().remove_reader(api.channel.sock)
            api.channel.close()  # as the kernel closes it when the daemon dies, however
            await asyncio.get_running_loop().run_in_executor(None, process.join, WAIT_S)
            assert process.exitcode == 0

    asyncio.run(body())


def test_the_daemon_hears_when_the_api_process_dies() -> None:
    cfg = _config()

    async def body() -> None:
        async with _served(cfg) as (api, _, _):
            assert api.ended is not None and not api.ended.done()
            os.kill(api._process.pid, signal.SIGKILL)
            async with asyncio.timeout(WAIT_S):
                reason = await api.ended
            assert "closed" in reason

    asyncio.run(body())


def test_an_error_in_the_api_process_is_told_to_the_daemon(caplog: pytest.LogCaptureFixture) -> None:
    """A Python error before it serves: the start raises, and the daemon's log has the traceback."""
    cfg = _config()
    daemon, spec = _parts(cfg)
    api = ApiProcess(replace(spec, status_json=b"{}"), daemon)  # a status the API process cannot parse
    listener = bind_api(cfg.api)

    async def body() -> None:
        try:
            with pytest.raises(HardwareError, match="did not start"):
                await api.start(listener)
        finally:
            await api.stop()
            listener.close()

    with caplog.at_level(logging.ERROR, logger="clothd.api.process"):
        asyncio.run(body())
    assert "Traceback" in caplog.text and "ValidationError" in caplog.text


def test_an_opcua_port_taken_ends_the_start_with_its_one_line() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        opcua = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{port}/clothd/")
        cfg = Config(api=ApiConfig(port=_free_port()), opcua=opcua)
        daemon, spec = _parts(cfg)
        api = ApiProcess(spec, daemon)
        listener = bind_api(cfg.api)

        async def body() -> None:
            try:
                with pytest.raises(ConfigError, match="cannot listen on"):
                    await api.start(listener)
            finally:
                await api.stop()
                listener.close()

        asyncio.run(body())


def test_the_api_process_does_not_import_taichi() -> None:
    """It runs none of the tracking: importing its main leaves Taichi (and its memory, ~80 MB) out."""
    probe = "import sys, clothd.api.serve_api; print('taichi' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False"]
