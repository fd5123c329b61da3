"""The API process's main: the HTTP API (uvicorn, on the listening socket the daemon bound) and the OPC UA
server, over the cell the daemon serves through the channel (remote_cell.py). A process of its own, so
that no request, however many, holds the GIL the daemon's tick needs (docs/api.md).

It never outlives the daemon: it ends when the channel does (the daemon stopped, or was killed). Signals
are the daemon's to handle: a terminal's Ctrl-C or systemd's stop reach this process too, and the
daemon stops the modules first, then closes the channel.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import signal
import socket
import traceback
from collections.abc import Generator
from dataclasses import dataclass
from pathlib import Path

import uvicorn
from fastapi import FastAPI

from clothd.api.app import create_app
from clothd.api.cell import CellSettings
from clothd.api.channel import Channel
from clothd.api.commands import Commands
from clothd.api.connections import BoundedH11Protocol, BoundedWebSocketProtocol
from clothd.api.opcua_server import OpcUaServer
from clothd.api.remote_cell import RemoteCell
from clothd.api.stream import StreamHub
from clothd.config import ApiConfig, OpcUaConfig
from clothd.core.camera_model import CameraModel
from clothd.drivers.priority import leave_realtime
from clothd.errors import ClothdError
from clothd.logs import configure_logging
from clothd.loop.process_names import API_PROCESS_NAME

EXIT_TIMEOUT_S = 5.0  # open streams get this long to close once the daemon has gone
LAST_WORDS_TIMEOUT_S = 1.0


@dataclass(frozen=True)
class ApiSpec:
    """What the API process is started with."""

    api: ApiConfig
    opcua: OpcUaConfig
    camera_model: CameraModel
    settings: CellSettings
    status_json: bytes  # the daemon's newest status: the OPC UA address space is built from it
    sim_truth_url: str | None = None


def api_server_config(app: FastAPI, api: ApiConfig) -> uvicorn.Config:
    """uvicorn's configuration for the API, with connections bounded in number, time and reading
    (api/connections.py)."""
    http = BoundedH11Protocol.bounded(api.max_connections, api.request_timeout_s, api.stall_timeout_s)
    ws = BoundedWebSocketProtocol.bounded(api.stall_timeout_s)
    return uvicorn.Config(app, host=api.host, port=api.port, log_level="warning", http=http, ws=ws)


class QuietServer(uvicorn.Server):
    """uvicorn without its own signal handling: the daemon stops the modules first, then this process."""

    @contextlib.contextmanager
    def capture_signals(self) -> Generator[None, None, None]:
        yield


def serve_api(sock: socket.socket, listener: socket.socket, spec: ApiSpec) -> None:
    """The process's main, until the daemon's end of `sock` closes. An error that ends it is told to the
    daemon, which logs it (or, before it served, raises it)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    with contextlib.suppress(OSError):  # its name in ps and top, apart from the compute process's
        Path("/proc/self/comm").write_text(API_PROCESS_NAME)
    leave_realtime()  # at the loop's nice value, in the normal class (clothd/drivers/priority.py)
    configure_logging()
    channel = Channel(sock)
    try:
        asyncio.run(_serve(channel, listener, spec))
    except ClothdError as err:  # a reason in words (an OPC UA port taken)
        channel.send_waiting(("error", type(err).__name__, str(err), None), LAST_WORDS_TIMEOUT_S)
        raise SystemExit(1) from None
    except BaseException as err:
        last = ("error", type(err).__name__, str(err), traceback.format_exc())
        channel.send_waiting(last, LAST_WORDS_TIMEOUT_S)
        raise


async def _serve(channel: Channel, listener: socket.socket, spec: ApiSpec) -> None:
    hub = StreamHub()
    hub.receive(spec.status_json)
    cell = RemoteCell(channel, hub, spec.settings)
    cell.start()
    app = create_app(cell, hub, spec.camera_model, spec.api, spec.sim_truth_url)
    server = QuietServer(api_server_config(app, spec.api))
    opcua = OpcUaServer(spec.opcua, spec.api.token, hub, Commands(cell)) if spec.opcua.enabled else None
    if opcua is not None:
        await opcua.start()
    try:
        serving = asyncio.create_task(server.serve(sockets=[listener]))
        gone = asyncio.create_task(cell.daemon_gone.wait())
        while not server.started and not serving.done() and not gone.done():
            await asyncio.wait({serving, gone}, timeout=0.05)
        if server.started:
            # As the daemon does: what start-up built lives as long as the process, out of the
            # collector's sight (the OPC UA address space, ~10^5 objects).
            gc.collect()
            gc.freeze()
            cell.send(("ready",))
            await asyncio.wait({serving, gone}, return_when=asyncio.FIRST_COMPLETED)
        server.should_exit = True
        gone.cancel()
        await asyncio.wait({serving}, timeout=EXIT_TIMEOUT_S)
        if serving.done():
            serving.result()  # its error, if it ended with one
    finally:
        if opcua is not None:
            await opcua.stop()
        cell.stop()
