"""`hwsim serve`: the simulated cell as hardware, in real time.

- The stepper controller's firmware in a process of its own (hwsim.firmware_process), on a pty behind
  the symlink STATE_DIR/ttyCELL; with --controllers N, N controllers, each its own firmware process on
  its own pty (STATE_DIR/ttyCELL-K) driving an equal share of the modules, by id (the ready line's
  `controllers` lists each one's pty and module ids).
- Every camera as MJPEG over HTTP on 127.0.0.1 (GET /video/NAME.mjpg; GET /video.mjpg is the first),
  which OpenCV's FFmpeg backend reads.
- Ground truth and module states at GET /truth (JSON), for tests and the truth overlay: the lead piece's
  pose and sheet measures (null while a flow has emptied the table) and `pieces`, every piece on the
  table; GET /outfeed, the pieces a flow's outfeed judged (hwsim/outfeed.py).
- Test hooks: POST /unplug?seconds=S[&controller=K] (serial cable: every controller's, or K's),
  POST /camera/drop?seconds=S (video stream), POST /fault?code=C&module=M[&controller=K] (a controller
  fault report, M in K's own numbering; K 0 by default), POST /cloth with a JSON pose as in a
  scenario's `initial_pose` (lay the cloth down again there, ridges and all; 409 while a belt runs),
  POST /cloth/push with a JSON push (two hands push a ridge into the cloth where it lies).

The world steps at the scenario's rate with absolute deadlines; each camera shoots every `every` steps
of its own, rendered in a process of its own and delivered at its exposure plus a camera's latency
(hwsim/camera_process.py). It moves only by what the firmware receives: the loop is closed through the real
protocol and the real video. On start it prints one JSON line with the pty, the URLs and the paths of
camera.json (camera-NAME.json for each further camera) and table.json (and writes it to
STATE_DIR/ready.json).
"""

from __future__ import annotations

import functools
import json
import threading
import time
import traceback
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlparse

import numpy as np

from hwsim.camera import Camera
from hwsim.camera_process import CAMERA_LATENCY_S, CameraProcess, FrameClock, Shot, VideoFrame
from hwsim.cloth_grid import ClothGrid
from hwsim.firmware import Counters
from hwsim.firmware_process import FirmwareProcess, start_firmwares
from hwsim.pieces import piece_truth
from hwsim.recording import frame_states, write_table
from hwsim.scenario import Pose, Push, Scenario
from hwsim.streams import Stream, frame_intervals
from hwsim.taichi_runtime import ensure_taichi
from hwsim.world import World

MAX_CATCH_UP_S = 1.0  # further behind, the world gives up the time rather than run ever faster
# Between its step and each camera's frame the world gives up its core this long: the cloth and the camera
# take no core of a real cell's PC, and a kernel worker waiting behind a long run of them (a serial port's
# bytes) held the daemon's link answers up (docs/benchmarks.md, "A loaded PC").
CORE_BREAK_S = 0.0005


class Cell:
    """The world, its cameras and its firmware, advanced in real time on a thread."""

    def __init__(
        self,
        scenario: Scenario,
        state_dir: Path,
        camera_fps: float,
        arch: str = "cpu",
        other_cameras_fps: float | None = None,
        controllers: int = 1,
    ) -> None:
        self.scenario = scenario
        self.state_dir = state_dir
        state_dir.mkdir(parents=True, exist_ok=True)
        # The cameras' processes first: their start (Taichi, the renderers) overlaps the world's.
        self.frame_clock = FrameClock(self._deliver)
        self.cameras = [
            CameraProcess(
                scenario,
                ClothGrid.from_spec(scenario.cloth),  # the world's first piece's
                arch,
                i,
                functools.partial(self.frame_clock.put, i),  # each frame handed on when due
                lambda err: self.world_died(err),
            )
            for i in range(len(scenario.camera_specs))
        ]
        # One thread for the world's kernels: beside the daemon on a small machine, a real-time world must
        # not take every core for itself.
        ensure_taichi(arch, cpu_threads=1)
        self.world = World(scenario, arch, log_commands=False)
        self.streams = [
            self._make_stream(i, every)
            for i, every in enumerate(
                frame_intervals(scenario.fps, len(scenario.camera_specs), camera_fps, other_cameras_fps)
            )
        ]
        self.camera_every = self.streams[0].every
        self.lock = threading.Lock()  # the world and Taichi, between its thread and the HTTP handlers
        self.firmwares = start_firmwares(self.world.table.n_modules, controllers, state_dir)
        self.firmware = self.firmwares[0]
        for stream in self.streams:
            stream.camera.save(state_dir / stream.json_name)
        write_table(self.world, state_dir / "table.json")
        self.frame_cond = threading.Condition()  # a new frame from any camera
        self.video_dropped_until = 0.0
        self.video_generation = 0  # bumped by a drop: streaming clients hang up
        self.camera_frames_dropped = 0  # frames not rendered while the world caught up with real time
        self.behind_real_time_s = 0.0  # time the world fell behind real time for good
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="world", daemon=True)
        self.world_died: Callable[[BaseException], None] = lambda err: None  # serve() ends the process
        self._truth_cache: dict[str, Any] = {}
        self._outfeed_cache: tuple[dict[str, object], ...] = ()  # replaced whole, as the truth's cache

    def _make_stream(self, index: int, every: int) -> Stream:
        spec = self.scenario.camera_specs[index]
        name = str(spec.name)
        camera = Camera.from_spec(spec)
        return Stream(
            name, camera, spec.capture_skew_s, every, "camera.json" if index == 0 else f"camera-{name}.json"
        )

    def stream(self, name: str | None) -> Stream | None:
        """The camera called `name`; None: the first."""
        if name is None:
            return self.streams[0]
        return next((s for s in self.streams if s.name == name), None)

    def start(self) -> None:
        self._update_truth()  # /truth answers in full from the first request on
        # Every camera's first frame, its kernels compiled: a client that comes later finds it ready.
        now = time.monotonic() - CAMERA_LATENCY_S
        for camera, stream in zip(self.cameras, self.streams, strict=True):
            camera.shoot(self._shot(stream, now))  # all at once: each compiles its kernels meanwhile
        for camera, stream in zip(self.cameras, self.streams, strict=True):
            stream.frame = camera.first()
        self.frame_clock.start()
        for camera in self.cameras:
            camera.start()
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for camera in self.cameras:
            camera.ask_to_stop()
        for camera in self.cameras:
            camera.stop()
        self.frame_clock.stop()
        for firmware in self.firmwares:
            firmware.stop()

    def drop_video(self, seconds: float) -> None:
        with self.frame_cond:
            self.video_dropped_until = time.monotonic() + seconds
            self.video_generation += 1
            self.frame_cond.notify_all()

    @property
    def video_up(self) -> bool:
        return time.monotonic() >= self.video_dropped_until

    def lay_cloth(self, pose: Pose) -> bool:
        """Lay the cloth down again at `pose`; refused (False) while any belt runs."""
        with self.lock:
            if np.any(self.world.table.speed_m_s != 0.0):
                return False
            self.world.lay(pose)
            self._update_truth()
        return True

    def truth(self, with_nodes: bool) -> dict[str, Any]:
        # The cache is replaced whole after every step, never changed in place: it is read without the
        # lock, which a world behind real time takes back at once (a reader waited seconds for it).
        if not with_nodes:
            return dict(self._truth_cache)
        with self.lock:
            out = dict(self._truth_cache)
            if self.world.pieces:
                out["nodes_m"] = self.world.cloth.positions_m().round(5).tolist()
        return out

    def outfeed(self) -> list[dict[str, object]]:
        return list(self._outfeed_cache)

    def _run(self) -> None:
        try:
            self._step_in_real_time()
        except BaseException as err:  # the cell is dead: whoever runs it must hear so, not see it stall
            traceback.print_exc()
            self.world_died(err)

    def _step_in_real_time(self) -> None:
        """Step at absolute deadlines. A world held up (a loaded PC) catches up by stepping without
        shooting, as a real cloth keeps moving while a camera drops frames, though never two frames in a
        row: a camera does not fall silent. Only a world more than MAX_CATCH_UP_S behind gives up that
        time for good, counted in `behind_real_time_s`."""
        dt = self.world.dt_s
        next_t = time.monotonic()
        dropped_last = False
        while not self._stop.is_set():
            next_t += dt
            with self.lock:
                # Read before the drives are applied: an e-stop the truth reports has reached the belts.
                counters = [firmware.counters() for firmware in self.firmwares]
                for firmware in self.firmwares:
                    firmware.bus.apply_to(self.world.table, firmware.modules)
                self.world.step()
                self._update_truth(counters)
            time.sleep(CORE_BREAK_S)
            behind_s = time.monotonic() - next_t
            if any(self.world.frame_index % s.every == 0 for s in self.streams):
                dropped_last = behind_s >= dt and not dropped_last
                if dropped_last:
                    self.camera_frames_dropped += 1
                else:
                    # Under the lock too: a push or a lay between step and exposure would be half seen.
                    with self.lock:
                        shots = self._shots(next_t)
                    self.frame_clock.expect(self.world.frame_index, [i for i, _ in shots])
                    for i, shot in shots:
                        self.cameras[i].shoot(shot)
            if behind_s < 0:
                self._stop.wait(-behind_s)
            elif behind_s > MAX_CATCH_UP_S:
                self.behind_real_time_s += behind_s
                next_t = time.monotonic()

    def _update_truth(self, counters: list[Counters] | None = None) -> None:
        """counters: each firmware's, as of the drives the table runs now (None: read them now)."""
        counters = counters or [firmware.counters() for firmware in self.firmwares]
        t = self.world.table
        lead: dict[str, Any] = {"pose": None, **dict.fromkeys(("max_height_m", "area_ratio", "folded_ratio"))}
        if self.world.pieces:
            lead = {"pose": self.world.cloth_pose().tolist(), **self.world.sheet_measures()}
        if len(self.world.outfeed) != len(self._outfeed_cache):  # the outfeed only grows
            self._outfeed_cache = tuple(self.world.outfeed)
        self._truth_cache = {
            "t_s": self.world.t_s,
            "pose": lead["pose"],
            "module_speed_m_s": t.speed_m_s.tolist(),
            "module_heading_rad": t.heading_rad.tolist(),
            "module_cmd_speed_m_s": t.cmd_speed_m_s.tolist(),
            **counters[0],
            "controllers": [
                {"serial": str(f.link_path), **c} for f, c in zip(self.firmwares, counters, strict=True)
            ],
            "camera_frames_dropped": self.camera_frames_dropped + sum(c.dropped for c in self.cameras),
            "behind_real_time_s": self.behind_real_time_s,
            **{k: v for k, v in lead.items() if k != "pose"},
            "pieces": [piece_truth(p) for p in self.world.pieces],
        }

    def _shots(self, instant_mono_s: float) -> list[tuple[int, Shot]]:
        """What each camera due at this step sees, the world's instant being real time instant_mono_s. A
        camera other than the first is shot only while a client streams it."""
        shots = []
        for i, stream in enumerate(self.streams):
            if self.world.frame_index % stream.every != 0:
                continue
            if i > 0 and not stream.readers:  # nobody watches it: a render would only cost CPU
                stream.frame = None  # a client that comes waits for a fresh frame, not an old one
                continue
            shots.append((i, self._shot(stream, instant_mono_s)))
        return shots

    def _shot(self, stream: Stream, instant_mono_s: float) -> Shot:
        """The camera's frame of the world's current instant, due at the host a camera's latency after its
        exposure."""
        k = self.world.frame_index // stream.every
        deliver_mono_s = instant_mono_s + stream.skew_s + CAMERA_LATENCY_S
        states = frame_states(self.world, stream.skew_s)
        return Shot(self.world.frame_index, k, self.world.t_s + stream.skew_s, states, deliver_mono_s)

    def _deliver(self, frames: list[tuple[int, VideoFrame]]) -> None:
        """Frames reach the host: each stream's clients get its new frame, all at once."""
        with self.frame_cond:
            for stream, frame in frames:
                self.streams[stream].frame = frame
            self.frame_cond.notify_all()


class _Handler(BaseHTTPRequestHandler):
    cell: Cell  # set on the subclass made by serve()
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:
        pass  # the daemon under test logs; hwsim stays quiet

    def do_GET(self) -> None:
        url = urlparse(self.path)
        json_names = {"table.json", *(s.json_name for s in self.cell.streams)}
        if url.path == "/video.mjpg":
            self._stream(self.cell.streams[0])
        elif url.path.startswith("/video/") and url.path.endswith(".mjpg"):
            stream = self.cell.stream(url.path[len("/video/") : -len(".mjpg")])
            if stream is None:
                self.send_error(HTTPStatus.NOT_FOUND, "no such camera")
                return
            self._stream(stream)
        elif url.path == "/truth":
            self._json(self.cell.truth(with_nodes="nodes" in parse_qs(url.query)))
        elif url.path == "/outfeed":
            self._json(self.cell.outfeed())
        elif url.path[1:] in json_names:
            self._bytes((self.cell.state_dir / url.path[1:]).read_bytes(), "application/json")
        elif url.path == "/healthz":
            self._json({"ok": True})
        else:
            self.send_error(HTTPStatus.NOT_FOUND)

    def do_POST(self) -> None:
        url = urlparse(self.path)
        q = {k: v[0] for k, v in parse_qs(url.query).items()}
        try:
            if url.path == "/unplug":
                chosen = [self._controller(q)] if "controller" in q else self.cell.firmwares
                for firmware in chosen:
                    firmware.unplug(float(q.get("seconds", "1")))
            elif url.path == "/camera/drop":
                self.cell.drop_video(float(q.get("seconds", "1")))
            elif url.path == "/fault":
                module = int(q.get("module", "65535"))
                self._controller(q).report_fault(int(q["code"]), module, q.get("text", ""))
            elif url.path == "/cloth/push":
                length = int(self.headers.get("Content-Length", "0"))
                push = Push.model_validate_json(self.rfile.read(length))
                with self.cell.lock:
                    self.cell.world.push(push)
            elif url.path == "/cloth":
                length = int(self.headers.get("Content-Length", "0"))
                pose = Pose.model_validate_json(self.rfile.read(length))
                if not self.cell.lay_cloth(pose):
                    self.send_error(HTTPStatus.CONFLICT, "stop the belts before laying the cloth")
                    return
            else:
                self.send_error(HTTPStatus.NOT_FOUND)
                return
        except (KeyError, ValueError) as err:  # pydantic's ValidationError is a ValueError
            reason = " ".join(str(err).split())  # one line: it goes into the status line
            self.send_error(HTTPStatus.BAD_REQUEST, f"bad request: {reason}"[:300])
            return
        self._json({"ok": True})

    def _controller(self, q: dict[str, str]) -> FirmwareProcess:
        k = int(q.get("controller", "0"))
        if not 0 <= k < len(self.cell.firmwares):
            raise ValueError(f"controller {k}: the cell has {len(self.cell.firmwares)}")
        return self.cell.firmwares[k]

    def _json(self, obj: object) -> None:
        self._bytes(json.dumps(obj).encode(), "application/json")

    def _bytes(self, body: bytes, content_type: str) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def _stream(self, stream: Stream) -> None:
        cell = self.cell
        if not cell.video_up:
            self.send_error(HTTPStatus.SERVICE_UNAVAILABLE, "camera unplugged")
            return
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
        self.send_header("Cache-Control", "no-cache")
        self.send_header("Connection", "close")
        self.end_headers()
        generation, last = cell.video_generation, -1
        with cell.frame_cond:
            stream.readers += 1
        try:
            while True:
                with cell.frame_cond:
                    cell.frame_cond.wait(timeout=2.0)
                    if cell.video_generation != generation:
                        return
                    frame = stream.frame
                if frame is None or frame.index == last:
                    continue
                last = frame.index
                head = f"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: {len(frame.jpeg)}\r\n\r\n"
                self.wfile.write(head.encode() + frame.jpeg + b"\r\n")
                self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError):
            return
        finally:
            with cell.frame_cond:
                stream.readers -= 1
            self.close_connection = True


def serve(
    scenario: Scenario,
    state_dir: Path,
    port: int,
    camera_fps: float,
    arch: str = "cpu",
    other_cameras_fps: float | None = None,
    controllers: int = 1,
) -> None:
    """Run the cell until interrupted."""
    cell = Cell(scenario, state_dir, camera_fps, arch, other_cameras_fps, controllers)
    handler = type("Handler", (_Handler,), {"cell": cell})
    server = ThreadingHTTPServer(("127.0.0.1", port), handler)
    server.daemon_threads = True
    base = f"http://127.0.0.1:{server.server_address[1]}"
    ready = {
        "serial": str(cell.firmware.link_path),
        "controllers": [{"serial": str(f.link_path), "modules": f.modules.tolist()} for f in cell.firmwares],
        "video_url": f"{base}/video.mjpg",
        "truth_url": f"{base}/truth",
        "http": base,
        "camera_json": str(state_dir / "camera.json"),
        "table_json": str(state_dir / "table.json"),
        "camera_fps": scenario.fps / cell.camera_every,
        "cameras": [
            {
                "name": s.name,
                "video_url": f"{base}/video/{s.name}.mjpg",
                "camera_json": str(state_dir / s.json_name),
                "capture_skew_s": s.skew_s,
                "camera_fps": scenario.fps / s.every,
            }
            for s in cell.streams
        ],
    }
    if scenario.flow is not None:  # what the outfeed judges each piece against
        ready["placement"] = scenario.flow.placement.model_dump()
    died: list[BaseException] = []

    def world_died(err: BaseException) -> None:
        died.append(err)
        server.shutdown()  # serve_forever returns: the cell stops, and the process ends with the error

    cell.world_died = world_died
    cell.start()
    (state_dir / "ready.json").write_text(json.dumps(ready, indent=2) + "\n")
    print(json.dumps(ready), flush=True)
    try:
        server.serve_forever(poll_interval=0.2)
    finally:
        server.server_close()
        cell.stop()
    if died:
        raise SystemExit(f"hwsim serve: the world stopped: {died[0]!r}")
