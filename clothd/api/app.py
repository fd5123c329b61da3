"""The HTTP API (FastAPI), versioned under /api/v1; the reference is docs/api.md and /docs (OpenAPI).

Reads are open to the daemon's own host names; changes need its own origin (or none: not a browser),
a JSON body and, when a token is configured, `Authorization: Bearer <token>` (guard.py).
Handlers only read the state the loop published or flip a request flag: none of them waits on the loop.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import httpx
from fastapi import APIRouter, FastAPI, Request, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from starlette.websockets import WebSocketDisconnect

from clothd.api.cell import Cell
from clothd.api.commands import Commands, describe_invalid
from clothd.api.connections import StreamSlots
from clothd.api.guard import GuardPolicy, RequestGuard
from clothd.api.metrics import registry_for
from clothd.api.schemas import (
    AccessInfo,
    CameraInfo,
    ErrorResponse,
    Ok,
    OutfeedPiece,
    RecordStart,
    SetpointRequest,
)
from clothd.api.stream import StreamHub
from clothd.config import ApiConfig
from clothd.core.camera_model import CameraModel
from clothd.core.modes import LoopState
from clothd.errors import ClothdError, HardwareError, InvalidRequestError, RequestError, StorageError
from clothd.loop.status import PieceStatus, Status
from clothd.outputs.recorder import recording_path

ERROR_DOC: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorResponse, "description": "a body that is not JSON"},
    401: {"model": ErrorResponse, "description": "a token is configured: none came, or another"},
    403: {"model": ErrorResponse, "description": "from another web origin"},
    413: {"model": ErrorResponse, "description": "a body over api.max_body_bytes"},
    415: {"model": ErrorResponse, "description": "a body that is not application/json"},
    421: {"model": ErrorResponse, "description": "a Host that is not one of the daemon's names"},
    422: {"model": ErrorResponse, "description": "a request that can never be carried out as given"},
    507: {"model": ErrorResponse, "description": "no room on the disk for a recording"},
    409: {"model": ErrorResponse, "description": "not possible in the daemon's current state"},
}
STATIC_DIR = Path(__file__).resolve().parent / "static"
MAX_STREAM_HZ = 30.0  # the tick's rate at most: a faster stream would only repeat it
STATUS_DOC: dict[int | str, dict[str, Any]] = {
    200: {"model": Status, "description": "the state published by the last tick"}
}

SIM_DOC: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "not running against hwsim"},
    503: {"model": ErrorResponse, "description": "hwsim is not answering"},
}

# clothd's errors as HTTP statuses; the most specific class that matches wins.
ERROR_STATUS: dict[type[ClothdError], int] = {
    InvalidRequestError: 422,  # can never be carried out as given
    StorageError: 507,
    RequestError: 409,  # not in the daemon's present state
    ClothdError: 503,  # the hardware, or hwsim's truth, is not answering
}


def _detail_response(status_code: int) -> Callable[[Request, Exception], Awaitable[JSONResponse]]:
    async def respond(request: Request, err: Exception) -> JSONResponse:
        return JSONResponse({"detail": str(err)}, status_code=status_code)

    return respond


def create_app(
    cell: Cell,
    hub: StreamHub,
    camera_model: CameraModel,
    api_cfg: ApiConfig,
    sim_truth_url: str | None = None,
) -> FastAPI:
    """The app over a cell (cell.py) whose daemon's statuses `hub` receives, behind the request guard
    (guard.py). sim_truth_url: hwsim's ground truth, relayed for the dashboard when running against hwsim;
    its outfeed (GET /outfeed) is beside it."""
    commands = Commands(cell)
    registry = registry_for(hub)
    streams = StreamSlots(api_cfg.max_streams)
    # /docs and /redoc from the daemon's own files: a cell PC may have no internet for a CDN.
    app = FastAPIOffline(title="clothd", version="1", description="Real-time cloth tracking and control")
    c = api_cfg
    policy = GuardPolicy(c.port, c.allowed_hosts, c.allowed_origins, c.token, c.max_body_bytes)
    if c.allowed_origins:  # no CORS unless configured: then only for those origins, and only what we use
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(c.allowed_origins),
            allow_methods=["GET", "PUT", "POST"],
            allow_headers=["Authorization", "Content-Type"],
        )
    app.add_middleware(RequestGuard, policy=policy)  # added last, so it runs first

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, err: RequestValidationError) -> JSONResponse:
        """Where and what, never the input: a body is not echoed back."""
        return JSONResponse({"detail": describe_invalid(err.errors())}, status_code=422)

    for error, status_code in ERROR_STATUS.items():
        app.add_exception_handler(error, _detail_response(status_code))

    api = APIRouter(prefix="/api/v1")

    @api.get("/access", response_model=AccessInfo)
    async def access() -> AccessInfo:
        """Whether changes, the e-stop among them, need the token: the dashboard asks for it as it opens,
        not when the E-STOP is pressed."""
        return AccessInfo(token_required=c.token is not None)

    _add_control_routes(api, cell, hub, commands)
    _add_view_routes(api, cell, hub, streams, camera_model, sim_truth_url)
    app.include_router(api)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    _add_page_routes(app, hub, registry)
    return app


def _add_control_routes(api: APIRouter, cell: Cell, hub: StreamHub, commands: Commands) -> None:
    """The status, and what changes the cell: setpoints, the e-stop, a reset, recordings."""

    @api.get("/status", responses=STATUS_DOC, response_model=None)
    async def status() -> Response:
        """Mode and setpoint, pose with covariance and mesh, features and residuals, tick timing,
        camera and link state."""
        return Response(hub.status_json, media_type="application/json")

    @api.get("/pieces", response_model=list[PieceStatus])
    async def pieces() -> list[PieceStatus]:
        """Mode flow: every piece on the table (its state, pose and flatness), then the last that left or
        were rejected, with the reason; empty in any other mode."""
        status = hub.status
        return [] if status is None or status.pieces is None else status.pieces

    @api.put("/setpoint", responses=ERROR_DOC)
    async def setpoint(body: SetpointRequest) -> Ok:
        return Ok(detail=await commands.setpoint(body))

    @api.post("/estop", responses=ERROR_DOC)
    async def estop() -> Ok:
        """Stop every module now; latched until /estop/clear."""
        return Ok(detail=await commands.estop())

    @api.post("/estop/clear", responses=ERROR_DOC)
    async def estop_clear() -> Ok:
        return Ok(detail=await commands.estop_clear())

    @api.post("/reset", responses=ERROR_DOC)
    async def reset() -> Ok:
        """Re-initialise tracking from the next frame; the mode becomes idle."""
        return Ok(detail=await commands.reset())

    @api.post("/record/start", responses=ERROR_DOC)
    async def record_start(body: RecordStart | None = None) -> Ok:
        """Record the session (frames, commands, estimates) in the format `clothd replay` reads, or with
        recording.format mcap as one .mcap file (NAME.mcap) for Foxglove."""
        suffix = cell.settings.recording_format.suffix
        where = recording_path(cell.settings.recording_dir, body.dir if body else None, suffix)
        path = await cell.start_recording(where)
        return Ok(detail=f"recording into {path}")

    @api.post("/record/stop", responses=ERROR_DOC)
    async def record_stop() -> Ok:
        await cell.stop_recording()
        return Ok(detail=f"recording stops; {cell.settings.recording_format.finished_by} is written")


def _add_view_routes(
    api: APIRouter,
    cell: Cell,
    hub: StreamHub,
    streams: StreamSlots,
    camera_model: CameraModel,
    sim_truth_url: str | None,
) -> None:
    """What shows the cell: the camera's geometry, hwsim's truth, the annotated view and the stream."""

    @api.get("/camera", response_model=CameraInfo)
    async def camera() -> CameraInfo:
        """The image size and the table plane's homography to pixels, for picking poses on the view."""
        cam = camera_model
        return CameraInfo(width=cam.width, height=cam.height, table_to_pixel=cam.table_homography().tolist())

    @api.get("/sim/truth", responses={**SIM_DOC, 422: ERROR_DOC[422]})
    async def sim_truth(nodes: bool = True) -> JSONResponse:
        """hwsim's ground truth (pose, module states, whether it keeps real time, and the lead cloth's
        nodes unless `nodes=false`), relayed for the dashboard's truth overlay and the benches; 404 unless
        the daemon runs against the simulated cell."""
        return await _relay_sim(sim_truth_url, "truth", {"nodes": 1} if nodes else None)

    @api.get("/sim/outfeed", responses={200: {"model": list[OutfeedPiece]}, **SIM_DOC})
    async def sim_outfeed() -> JSONResponse:
        """The pieces hwsim's outfeed judged from its truth as each left the table (mode flow), oldest
        first; 404 unless the daemon runs against the simulated cell."""
        return await _relay_sim(sim_truth_url, "outfeed")

    @api.get("/view.mjpg", response_class=StreamingResponse, responses={503: {"model": ErrorResponse}})
    async def view_mjpg() -> Response:
        """The annotated camera view as MJPEG (multipart/x-mixed-replace); 503 while api.max_streams
        streams are open."""
        if not streams.take():
            return _streams_full(streams)
        frames = _mjpeg(cell, streams)
        return StreamingResponse(frames, media_type="multipart/x-mixed-replace; boundary=frame")

    @api.websocket("/stream")
    async def stream(ws: WebSocket, hz: str | None = None) -> None:
        """The status every tick, or at most `hz` (0 < hz <= 30) times a second. A slow client misses
        messages; one that reads nothing is dropped. Refused (close 1013, "try again later") while
        api.max_streams are open; a bad `hz` is accepted and closed (1008) with the reason, where a check
        before the handshake could only answer a bare 403."""
        rate_hz = _stream_hz(hz)
        if isinstance(rate_hz, str):
            await ws.accept()
            await ws.close(code=1008, reason=rate_hz)
            return
        if not streams.take():
            await ws.close(code=1013, reason=f"{streams.max_streams} streams are open (api.max_streams)")
            return
        try:
            await _serve_stream(ws, hub, rate_hz)
        finally:
            streams.give_back()


def _add_page_routes(app: FastAPI, hub: StreamHub, registry: CollectorRegistry) -> None:
    """The dashboard, the health check and the metrics."""

    @app.get("/", response_class=FileResponse, include_in_schema=False)
    async def dashboard() -> FileResponse:
        """The operator dashboard (static HTML and JavaScript, no build step)."""
        return FileResponse(STATIC_DIR / "index.html")

    @app.get("/healthz", responses={503: {"description": "unhealthy; `problems` names what"}})
    async def healthz() -> JSONResponse:
        """200 while the loop ticks with the first camera and the link up, else 503 with the reasons;
        `degraded` names further cameras without fresh frames (tracking goes on with one view)."""
        problems = []
        s = hub.status  # the last tick's snapshot: nothing here reads the daemon's live state
        assert s is not None  # the daemon publishes once when it is built
        if not s.camera.healthy:
            problems.append("camera")
        if s.link.state != "connected":
            problems.append("stepper link")
        if s.state == LoopState.FAULT:
            problems.append("loop fault")
        # A further camera's loss leaves tracking on one view: said, not unhealthy.
        degraded = [f"camera {c.name}" for c in s.cameras[1:] if not c.healthy]
        body = {"ok": not problems, "state": s.state, "problems": problems, "degraded": degraded}
        return JSONResponse(body, status_code=503 if problems else 200)

    @app.get("/metrics", response_class=PlainTextResponse)
    async def metrics() -> Response:
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)


async def _relay_sim(truth_url: str | None, what: str, params: dict[str, Any] | None = None) -> JSONResponse:
    """hwsim's GET /<what> (beside its /truth), relayed as it answers."""
    if truth_url is None:
        return JSONResponse({"detail": "not running against hwsim (clothd run --sim)"}, status_code=404)
    try:
        async with httpx.AsyncClient(timeout=1.0) as client:
            r = await client.get(httpx.URL(truth_url).join(what), params=params)
            r.raise_for_status()
        return JSONResponse(r.json())
    except (httpx.HTTPError, ValueError) as err:
        raise HardwareError(f"hwsim's {what} is not answering: {err}") from err


def _streams_full(streams: StreamSlots) -> JSONResponse:
    detail = f"{streams.max_streams} streams are open (api.max_streams); try again later"
    return JSONResponse({"detail": detail}, status_code=503, headers={"Retry-After": "5"})


def _stream_hz(hz: str | None) -> float | str | None:
    """The stream's rate from its query (None: every tick), or why it is no rate."""
    if hz is None:
        return None
    try:
        rate = float(hz)
    except ValueError:
        rate = math.nan
    return rate if 0.0 < rate <= MAX_STREAM_HZ else f"hz must be a number in (0, {MAX_STREAM_HZ:g}]"


async def _serve_stream(ws: WebSocket, hub: StreamHub, hz: float | None) -> None:
    await ws.accept()
    sub = hub.subscribe(1.0 / hz if hz else 0.0)
    try:
        await ws.send_text(hub.status_json.decode())
        next_s = time.monotonic()
        while True:
            if sub.min_interval_s:
                await asyncio.sleep(max(0.0, next_s - time.monotonic()))
                next_s = time.monotonic() + sub.min_interval_s
            data = await sub.take()
            await ws.send_text(data.decode())
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        hub.unsubscribe(sub)


async def _mjpeg(cell: Cell, streams: StreamSlots) -> AsyncIterator[bytes]:
    """Frames as the compute process draws them; it draws only while someone watches. The stream's slot
    was taken by the handler and is given back here, however the stream ends."""
    last = 0
    try:
        with cell.watching():
            while True:
                jpeg, index = cell.latest_view()
                if jpeg is None or index == last:
                    await asyncio.sleep(cell.settings.view_period_s / 2)
                    continue
                last = index
                head = f"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n"
                yield head.encode() + jpeg + b"\r\n"
    finally:
        streams.give_back()
