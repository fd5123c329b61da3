"""`clothd run`, the composition root: the configuration is loaded, overridden and validated once, the
camera model, module layout and tick period are derived once, and each part is built here and handed
only what it needs: the daemon its settings, the stepper link (a ModuleLink) and the compute process;
the compute process its spec, with the camera (a FrameSource) as a factory it opens itself.

Order on the way out, whatever the cause (signal, error, end): the modules stop first (the daemon's
shutdown), then the API process (HTTP and OPC UA, api/process.py), then the hwsim child.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gc
import json
import logging
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from clothd.api.cell import CellSettings
from clothd.api.process import ApiProcess
from clothd.api.serve_api import ApiSpec
from clothd.api.stream import StreamHub
from clothd.config import (
    ApiConfig,
    CameraSourceConfig,
    Config,
    FoxgloveConfig,
    OpcUaConfig,
    first_cameras,
    opcua_host_port,
    parse_config,
    with_cameras,
)
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout
from clothd.core.module_calibration import ModuleCalibration
from clothd.core.workspace import Workspace
from clothd.drivers.camera import VideoCaptureSource, redact_source
from clothd.drivers.link_group import LinkGroup
from clothd.drivers.priority import bound_gil_wait, claim_realtime, set_session_nice, set_thread_nice
from clothd.drivers.stepper_link import StepperLink
from clothd.errors import ConfigError, HardwareError
from clothd.formats import read_camera, read_module_calibration
from clothd.loop.compute_messages import ComputeSpec
from clothd.loop.compute_process import ComputeProcess
from clothd.loop.daemon import Daemon
from clothd.loop.daemon_settings import DaemonSettings
from clothd.loop.pairing import FurtherCamera
from clothd.outputs.recorder import make_recording_place

log = logging.getLogger(__name__)

SIM_START_TIMEOUT_S = 120.0
SIM_READ_POLL_S = 0.5


@dataclass
class SimCell:
    process: subprocess.Popen[bytes]
    state_dir: Path  # hwsim's files (camera.json, the pty's link): made for this cell, removed with it
    ready: dict[str, object]

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        shutil.rmtree(self.state_dir, ignore_errors=True)


def start_sim(scenario: str, controllers: int = 1) -> SimCell:
    """Start `hwsim serve` (its modules split among `controllers` firmwares) and wait for the line that
    says where its hardware is."""
    state_dir = Path(tempfile.mkdtemp(prefix="clothd-sim-"))
    cmd = [sys.executable, "-m", "hwsim.cli", "serve", "--scenario", scenario, "--state-dir", str(state_dir)]
    cmd += ["--controllers", str(controllers)]
    cmd.append("--exit-with-parent")  # a daemon killed with -9 takes its simulated cell with it
    # Its own session: a Ctrl-C in the terminal must not take the cell away before the daemon has
    # stopped the modules; the daemon stops it last.
    cell = SimCell(subprocess.Popen(cmd, stdout=subprocess.PIPE, start_new_session=True), state_dir, {})
    try:
        cell.ready = _ready_line(cell.process)
    except BaseException:  # not ready, or a Ctrl-C while waiting: nothing of it is left behind
        cell.stop()
        raise
    return cell


def _ready_line(proc: subprocess.Popen[bytes]) -> dict[str, object]:
    """The line in which `hwsim serve` says where its hardware is."""
    assert proc.stdout is not None
    deadline = time.monotonic() + SIM_START_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise HardwareError(f"hwsim serve exited with code {proc.returncode} before it was ready")
        ready, _, _ = select.select([proc.stdout], [], [], SIM_READ_POLL_S)
        if ready:
            line = proc.stdout.readline()
            with contextlib.suppress(json.JSONDecodeError):
                info = json.loads(line)
                if isinstance(info, dict) and "serial" in info:
                    return info
    raise HardwareError(f"hwsim serve was not ready within {SIM_START_TIMEOUT_S:.0f} s")


def sim_config(cfg: Config, ready: dict[str, Any]) -> Config:
    """Point the cameras (every camera of the cell, first first) and the stepper link at the simulated
    cell: stepper.port at its one controller, or stepper.controllers at each of several. An hwsim that
    lists no cameras serves one, at video_url."""
    cameras = ready.get("cameras") or [{"video_url": ready["video_url"], "camera_json": ready["camera_json"]}]
    entries = [
        {"name": c.get("name"), "source": str(c["video_url"]), "calibration": str(c["camera_json"])}
        for c in cameras
    ]
    data = with_cameras(cfg, entries).model_dump(exclude_unset=True)
    # The simulated cell's table (and a flow's placement) are what it is: as a plant's cell: section is.
    table = json.loads(Path(ready["table_json"]).read_text())
    keys = ("modules_x", "modules_y", "pitch_m", "module_size_m")
    data["cell"] = {**data.get("cell", {}), **{k: table[k] for k in keys}}
    if "placement" in ready:  # a flow's cell: its trackers built at start, so that mode flow may run
        data["flow"] = {**data.get("flow", {}), "placement": ready["placement"], "warm_at_start": True}
    stepper = {k: v for k, v in data.get("stepper", {}).items() if k not in ("port", "controllers")}
    controllers = ready.get("controllers") or []
    if len(controllers) > 1:
        stepper["controllers"] = [{"port": str(c["serial"]), "modules": c["modules"]} for c in controllers]
    else:
        stepper["port"] = str(ready["serial"])
    return parse_config({**data, "stepper": stepper}, "<sim>")


def sim_replaced_cameras(cfg: Config) -> str | None:
    """A line for `clothd run --sim` when the configuration names cameras of its own (a `cameras:` list, a
    camera.source or a camera.calibration): the simulated cell's, true calibrations and all, replace them."""
    named = [
        key
        for key, given in (
            ("cameras", cfg.cameras is not None),
            ("camera.source", cfg.camera.source != CameraSourceConfig().source),
            ("camera.calibration", cfg.camera.calibration is not None),
        )
        if given
    ]
    if not named:
        return None
    replaced = " and ".join(named)
    return f"clothd: --sim: the simulated cell's cameras and their true calibrations replace {replaced}"


def camera_model_for(cfg: Config) -> CameraModel:
    """The first camera's model: its calibration, or else the ideal tracker.camera."""
    calibration = cfg.all_cameras[0].source.calibration
    if calibration is not None:
        return read_camera(calibration)
    c = cfg.tracker.camera
    return CameraModel.ideal(c.width_px, c.height_px, c.f_px, c.distance_m)


def capture_priority(cfg: Config) -> int:
    """The cameras' capture threads: in the real-time class just below the loop's thread (the tick never
    waits on a decode); in the normal class with the loop's thread (clothd/drivers/priority.py)."""
    return max(cfg.loop.realtime_priority - 1, 0)


def further_cameras(cfg: Config) -> tuple[FurtherCamera, ...]:
    """The cameras after the first, each with its calibrated model (the configuration requires one)."""
    out = []
    for cam in cfg.all_cameras[1:]:
        assert cam.source.calibration is not None  # config/camera.py check_cameras
        model = read_camera(cam.source.calibration)
        source = functools.partial(VideoCaptureSource, cam.source, capture_priority(cfg))
        out.append(FurtherCamera(cam.name, model, source))
    return tuple(out)


def module_calibration_for(cfg: Config, layout: ConveyorLayout) -> ModuleCalibration | None:
    path = cfg.cell.module_calibration
    return (
        None
        if path is None
        else ModuleCalibration.of(read_module_calibration(path, layout.n_modules), layout.n_modules)
    )


@dataclass
class Parts:
    daemon: Daemon
    hub: StreamHub
    camera_model: CameraModel


def build(cfg: Config) -> Parts:
    """Every part of the daemon, built once from the validated configuration; nothing is started."""
    camera_model = camera_model_for(cfg)
    layout = ConveyorLayout.of_cell(cfg.cell)
    workspace = Workspace.of_cell(cfg.cell)
    spec = ComputeSpec(
        tracker=cfg.tracker,
        control=cfg.control,
        cell=cfg.cell,
        layout=layout,
        camera_model=camera_model,
        period_s=cfg.loop.period_s,
        workspace=workspace,
        taichi_arch=cfg.taichi.arch,
        max_record_bytes=cfg.recording.max_bytes,
        frame_source=functools.partial(VideoCaptureSource, cfg.all_cameras[0].source, capture_priority(cfg)),
        other_cameras=further_cameras(cfg),
        recording_format=cfg.recording.format,
        foxglove=cfg.foxglove,
        track_ahead=cfg.loop.track_ahead,
        opencv_threads=cfg.loop.compute_threads,
        starved_s=cfg.loop.starved_ms / 1e3,
        flow=cfg.flow,
    )
    settings = DaemonSettings(
        period_s=cfg.loop.period_s,
        max_stale_ticks=cfg.loop.max_stale_ticks,
        n_modules=layout.n_modules,
        workspace=workspace,
        view_period_s=1.0 / cfg.api.view_fps,
        recording_dir=cfg.recording.dir,
        camera_source=redact_source(cfg.all_cameras[0].source.source),
        cameras=tuple((c.name, redact_source(c.source.source)) for c in cfg.all_cameras),
        flow_ready=cfg.flow.warm_at_start,
        link_port=cfg.stepper.links(layout.n_modules)[0].cfg.port,
        estimates_shape=cfg.tracker.estimates_shape,
        recording_format=cfg.recording.format,
        frame_lock=cfg.loop.frame_lock,
        frame_lead_s=cfg.loop.frame_lead_ms / 1e3,
        frame_wait_s=cfg.loop.frame_wait_ms / 1e3,
        phase_step_s=cfg.loop.phase_step_ms / 1e3,
        layout=layout,
        max_speed_m_s=cfg.cell.max_speed_m_s,
        module_calibration=module_calibration_for(cfg, layout),
    )
    hub = StreamHub()
    link = LinkGroup(
        [
            (StepperLink(c.cfg, len(c.modules), n_modules_from=c.n_from), c.modules)
            for c in cfg.stepper.links(layout.n_modules)
        ],
        layout.n_modules,
    )
    daemon = Daemon(settings, link, ComputeProcess(spec), on_status=hub.publish)
    return Parts(daemon, hub, camera_model)


def bind_api(api: ApiConfig) -> socket.socket:
    """The API's listening address, taken first: a port in use ends the start with one clear line,
    before hwsim, the compute process or any hardware is opened."""
    family = socket.AF_INET6 if ":" in api.host else socket.AF_INET
    # IPPROTO_TCP named, not left 0: asyncio sets TCP_NODELAY only on sockets that say they are TCP, and
    # without it a response's headers and body wait on the client's delayed ACK (~40 ms a request).
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((api.host, api.port))
    except OSError as err:
        sock.close()
        raise ConfigError(
            f"cannot listen on {api.host}:{api.port}: {err.strerror or err}; "
            "choose another address with --host/--port or api.host/api.port"
        ) from None
    return sock


def check_opcua_port(opcua: OpcUaConfig) -> None:
    """The OPC UA port is free (asyncua binds it itself, later): a taken one ends the start with one clear
    line, before hwsim, the compute process or any hardware is opened."""
    if not opcua.enabled:
        return
    host, port = opcua_host_port(opcua.endpoint)
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as err:
        raise ConfigError(f"opcua.endpoint: cannot resolve {host}: {err.strerror or err}") from None
    for family, kind, proto, _, address in infos:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server will
            try:
                probe.bind(address)
            except OSError as err:
                raise ConfigError(
                    f"cannot listen on {opcua.endpoint}: {err.strerror or err}; "
                    "choose another address with --opcua-endpoint or opcua.endpoint"
                ) from None


def check_foxglove_port(fox: FoxgloveConfig) -> None:
    """The Foxglove server's port must be free: taken, the start ends here with one clear line, before
    hwsim or the compute process (which serves it) start. Bound and let go at once, not listened on."""
    if not fox.enabled:
        return
    family = socket.AF_INET6 if ":" in fox.host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((fox.host, fox.port))
        except OSError as err:
            raise ConfigError(
                f"cannot serve Foxglove on {fox.host}:{fox.port}: {err.strerror or err}; "
                "choose another address with foxglove.host/foxglove.port"
            ) from None


async def serve(
    cfg: Config,
    listener: socket.socket,
    on_ready: str | None = None,
    sim_truth_url: str | None = None,
    record_dir: Path | None = None,
    sim_process: subprocess.Popen[bytes] | None = None,
) -> None:
    """The daemon on this event loop, once its API process (api/process.py) serves on `listener`; until
    a signal, an error, or the end of the API process or of the simulated cell (`sim_process`), which
    stops the modules and raises HardwareError."""
    parts = build(cfg)
    daemon = parts.daemon
    if record_dir is not None:  # the operator's own choice, anywhere
        daemon.start_recording(make_recording_place(record_dir, cfg.recording.format))
    assert daemon.status is not None  # published once as it was built
    settings = CellSettings.of(daemon.settings)
    status_json = daemon.status.model_dump_json().encode()
    spec = ApiSpec(cfg.api, cfg.opcua, parts.camera_model, settings, status_json, sim_truth_url)
    api = ApiProcess(spec, daemon)
    daemon.on_status = api.publish  # the statuses go to the API process, which fans them out
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, daemon.stop)
    try:
        await api.start(listener)
        # Everything built so far lives as long as the daemon: out of the collector's sight, a full
        # collection (which holds the GIL, so the tick too) walks only what the running daemon makes.
        gc.collect()
        gc.freeze()
        daemon.stats.watch_full_collections()
        loop_task = asyncio.create_task(daemon.run())
        if on_ready:
            print(on_ready, flush=True)
        assert api.ended is not None
        sim_ended = asyncio.create_task(_exit_code(sim_process))
        either: set[asyncio.Future[Any]] = {loop_task, api.ended, sim_ended}
        await asyncio.wait(either, return_when=asyncio.FIRST_COMPLETED)
        if api.ended.done():  # no API, no e-stop from it: the modules stop (fail safe)
            log.error("the API process ended (%s): stopping the modules", api.ended.result())
            daemon.stop()
        if sim_ended.done():  # a simulated cell does not come back: say so, rather than retry for ever
            log.error("the simulated cell (hwsim serve) ended with code %s: stopping", sim_ended.result())
            daemon.stop()
        sim_ended.cancel()
        await asyncio.gather(loop_task, return_exceptions=True)
    finally:
        await api.stop()  # after the modules stopped
    if loop_task.exception() is not None:
        raise loop_task.exception()  # type: ignore[misc]
    if api.ended.done():
        raise HardwareError(f"the API process ended ({api.ended.result()}); modules stopped")
    if sim_ended.done() and not sim_ended.cancelled():
        raise HardwareError(f"the simulated cell (hwsim serve) ended with code {sim_ended.result()}")


async def _exit_code(process: subprocess.Popen[bytes] | None) -> int:
    """The process's exit code once it has ended; never, for none."""
    while process is None or process.poll() is None:
        await asyncio.sleep(SIM_READ_POLL_S)
    return process.returncode


def run(
    cfg: Config,
    sim_scenario: str | None,
    record_dir: Path | None = None,
    cameras: int | None = None,
    sim_controllers: int = 1,
) -> int:
    """Run the daemon with `cfg` (loaded and validated by the caller), against hwsim when sim_scenario
    names a scenario (its modules split among `sim_controllers` controllers); with only the first
    `cameras` cameras when given (1: one view)."""
    bound_gil_wait()
    listener = bind_api(cfg.api)
    try:
        check_opcua_port(cfg.opcua)
        check_foxglove_port(cfg.foxglove)
    except ConfigError:
        listener.close()
        raise
    # This thread runs the tick and the stepper link; the threads and the compute process started from it
    # inherit its priority (clothd/drivers/priority.py). hwsim inherits the nice value, not the real-time
    # class: it runs its firmware, the stand-in for a microcontroller, in that class itself.
    set_thread_nice(cfg.loop.nice, "the loop")
    set_session_nice(cfg.loop.nice)
    sim = start_sim(sim_scenario, sim_controllers) if sim_scenario is not None else None
    try:
        claim_realtime(cfg.loop.realtime_priority, "the loop")
        replaced = None
        if sim is not None:
            replaced = sim_replaced_cameras(cfg)
            cfg = sim_config(cfg, sim.ready)
        if cameras is not None:
            cfg = first_cameras(cfg, cameras, "the configuration" if sim is None else "the simulated cell")
        base = f"http://{cfg.api.host}:{cfg.api.port}"
        urls = (
            f"clothd: dashboard {base}/\n"
            f"clothd: status {base}/api/v1/status\n"
            f"clothd: annotated view {base}/api/v1/view.mjpg\n"
            f"clothd: API docs {base}/docs"
        )
        if cfg.opcua.enabled:
            urls += f"\nclothd: OPC UA {cfg.opcua.endpoint}"
        if cfg.foxglove.enabled:
            urls += f"\nclothd: Foxglove ws://{cfg.foxglove.host}:{cfg.foxglove.port}"
        if sim is not None:
            urls += f"\nclothd: simulated cell truth {sim.ready['truth_url']}"
        if replaced is not None:
            urls += f"\n{replaced}"
        if record_dir is not None:
            urls += f"\nclothd: recording into {record_dir}"
        truth_url = None if sim is None else str(sim.ready["truth_url"])
        asyncio.run(serve(cfg, listener, urls, truth_url, record_dir, None if sim is None else sim.process))
    finally:
        listener.close()
        if sim is not None:
            sim.stop()
    return 0
