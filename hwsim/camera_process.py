"""`hwsim serve`'s cameras, each rendered in a process of its own.

The world thread steps the cloth and, at each frame's instant, takes what each camera sees (scene states:
nodes, belts, arms) and hands it over; the camera's process renders, adds the sensor's noise and
encodes. The frame comes back to a thread of the cell's, which publishes it when a real camera's would
reach the host: `CAMERA_LATENCY_S` after its exposure (the instant plus its camera's capture skew), or once
rendered if that is later. Two cameras' frames of one instant therefore arrive as far apart as their
exposures, as a real pair's do.

Why: rendered on the world thread, two views took it to 90 % of a core beside the daemon on two cores.
The world fell behind real time, dropped a seventh of its frames and delivered the rest 50-125 ms apart
(docs/benchmarks.md, "The closed loop"), a camera no cell has. A camera keeps its clock whatever the PC
does; rendered apart and ahead of real time, the frames keep it too. One process per camera: the two
views render side by side while the world steps on, and are done before the daemon needs the cores.

A render that falls behind renders the newest shot handed over and skips the older ones, as a camera
drops frames (`dropped`).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection

from hwsim.camera import Camera
from hwsim.cloth_grid import ClothGrid
from hwsim.scenario import Scenario
from hwsim.scene import SceneState
from hwsim.sensor import Sensor
from hwsim.taichi_runtime import ensure_taichi

# Readout and transfer: a USB camera's frame reaches the host 10-30 ms after its instant. Past a view's
# render beside the daemon (done about 3 ms after the instant, median, on two cores), and past the
# world's next step, whose Taichi kernels hold this process's GIL for its whole 14 ms (p90 21): a frame
# handed on during one reaches its clients only after it.
CAMERA_LATENCY_S = 0.025
START_TIMEOUT_S = 120.0  # the process's Taichi start and its kernels' first compile


@dataclass(frozen=True)
class VideoFrame:
    index: int
    jpeg: bytes
    t_s: float


@dataclass(frozen=True)
class Shot:
    """A frame to render: the world's instant it is shot at (its frame index), the frame's number and
    exposure time, what the camera sees, and when the frame reaches the host (monotonic clock)."""

    instant: int
    k: int
    t_s: float
    states: list[SceneState]
    deliver_mono_s: float


@dataclass(frozen=True)
class Rendered:
    instant: int
    frame: VideoFrame
    deliver_mono_s: float
    skipped: int  # shots handed over while this one rendered, never rendered


class CameraProcess:
    """Camera `index` of the scenario, rendered in a child process. `rendered` gets each frame as it comes
    back (with its instant and when it is due), on a thread of this process; `died` the error if the
    process ends unasked."""

    def __init__(
        self,
        scenario: Scenario,
        grid: ClothGrid,
        arch: str,
        index: int,
        rendered: Callable[[int, float, VideoFrame], None],
        died: Callable[[BaseException], None],
    ) -> None:
        self.rendered = rendered
        self.died = died
        self.dropped = 0
        ctx = multiprocessing.get_context("spawn")
        jobs_out, self._jobs = ctx.Pipe(duplex=False)
        self._frames, frames_in = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=serve_renders,
            args=(jobs_out, frames_in, scenario, grid, arch, index),
            name=f"hwsim-camera-{index}",
            daemon=True,
        )
        self._proc.start()
        jobs_out.close()
        frames_in.close()
        self._stopping = threading.Event()
        self._send_lock = threading.Lock()
        self._thread = threading.Thread(target=self._receive, name=f"camera-{index}", daemon=True)

    def first(self) -> VideoFrame:
        """The first shot's frame, once rendered (its kernels compiled on the way), before `start`."""
        if not self._frames.poll(START_TIMEOUT_S):
            raise RuntimeError(f"hwsim's camera rendered nothing within {START_TIMEOUT_S:.0f} s")
        frame: VideoFrame = self._frames.recv().frame
        return frame

    def start(self) -> None:
        """Hand the frames on as they come."""
        self._thread.start()

    def shoot(self, shot: Shot | None) -> None:
        """Hand a shot over to be rendered (None: the process ends)."""
        with self._send_lock:
            self._jobs.send(shot)

    def ask_to_stop(self) -> None:
        """Tell the process to end, without waiting: several cameras end side by side."""
        self._stopping.set()
        with contextlib.suppress(OSError):  # the process is gone already
            self.shoot(None)

    def stop(self) -> None:
        self.ask_to_stop()
        self._proc.join(timeout=5)
        if self._proc.is_alive():
            self._proc.kill()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def _receive(self) -> None:
        try:
            while True:
                rendered: Rendered = self._frames.recv()
                self.dropped += rendered.skipped
                self.rendered(rendered.instant, rendered.deliver_mono_s, rendered.frame)
        except (EOFError, OSError) as err:
            if not self._stopping.is_set():
                self.died(RuntimeError(f"hwsim's camera process ended ({err or type(err).__name__})"))


class FrameClock:
    """Hands the cameras' frames on to `deliver` when they are due, on a thread of its own: the frames of
    one world instant once every camera shot at it has rendered its frame (or skipped it for a newer
    one) and every earlier instant's frames have gone, each at its own due time, and the frames due
    together in one call. A synchronised pair's frames arrive together: handed on by a thread each, and
    each as soon as its own render was done, they came 1.5-28 ms apart (median over a live recording)
    where the old single render thread had 0.2-1."""

    def __init__(self, deliver: Callable[[list[tuple[int, VideoFrame]]], None]) -> None:
        self.deliver = deliver
        self._cond = threading.Condition()
        self._expected: dict[int, set[int]] = {}  # instant: the streams shot at it
        self._rendered: dict[int, list[tuple[float, int, VideoFrame]]] = {}  # instant: (due, stream, frame)
        self._newest: dict[int, int] = {}  # stream: the newest instant it rendered
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="frame-clock", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def expect(self, instant: int, streams: list[int]) -> None:
        """The streams shot at this world instant (before their frames are put)."""
        with self._cond:
            self._expected[instant] = set(streams)

    def put(self, stream: int, instant: int, due_mono_s: float, frame: VideoFrame) -> None:
        """Stream `stream`'s frame of world instant `instant`, rendered, due at due_mono_s."""
        with self._cond:
            self._rendered.setdefault(instant, []).append((due_mono_s, stream, frame))
            self._newest[stream] = max(instant, self._newest.get(stream, instant))
            self._cond.notify()

    def stop(self) -> None:
        with self._cond:
            self._stopping = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def _complete(self, instant: int) -> bool:
        got = {stream for _, stream, _ in self._rendered.get(instant, [])}
        return all(s in got or self._newest.get(s, -1) > instant for s in self._expected.get(instant, ()))

    def _take_due(self, now_s: float) -> tuple[list[tuple[int, VideoFrame]], float | None]:
        """The frames to hand on now, and when the next is due (None: none can be yet)."""
        due, next_s = [], None
        for instant in sorted(self._rendered):
            if not self._complete(instant):  # the later instants wait too: a stream never goes back
                break
            waiting = []
            for entry in sorted(self._rendered[instant], key=lambda e: e[0]):
                if entry[0] <= now_s:
                    due.append((entry[1], entry[2]))
                else:
                    waiting.append(entry)
                    next_s = entry[0] if next_s is None else min(next_s, entry[0])
            if waiting:
                self._rendered[instant] = waiting
            else:
                del self._rendered[instant]
                self._expected.pop(instant, None)
        return due, next_s

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._stopping:
                    due, next_s = self._take_due(time.monotonic())
                    if due:
                        break
                    self._cond.wait(None if next_s is None else next_s - time.monotonic())
                if self._stopping:
                    return
            self.deliver(due)


class _Latest:
    """The newest shot handed over and not yet rendered; older ones it replaces are counted skipped."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._shot: Shot | None = None
        self._closed = False
        self.skipped = 0

    def put(self, shot: Shot | None) -> None:
        with self._cond:
            if shot is None:
                self._closed = True
            else:
                self.skipped += self._shot is not None
                self._shot = shot
            self._cond.notify()

    def take(self) -> tuple[Shot, int] | None:
        with self._cond:
            self._cond.wait_for(lambda: self._shot is not None or self._closed)
            if self._closed:
                return None
            shot, self._shot = self._shot, None
            skipped, self.skipped = self.skipped, 0
            assert shot is not None
            return shot, skipped


def serve_renders(
    jobs: Connection, frames: Connection, scenario: Scenario, grid: ClothGrid, arch: str, index: int
) -> None:
    """The camera process's main: render each shot handed over on `jobs`, send it back on `frames`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the cell stops this process when it stops itself
    ensure_taichi(arch, cpu_threads=1)  # one render thread: beside the daemon on a small machine
    sensor = Sensor(scenario, Camera.from_spec(scenario.camera_specs[index]), grid, index)
    latest = _Latest()

    def receive() -> None:
        try:
            while True:
                shot = jobs.recv()
                latest.put(shot)
                if shot is None:
                    return
        except (EOFError, OSError):
            latest.put(None)

    threading.Thread(target=receive, name="shots", daemon=True).start()
    while (taken := latest.take()) is not None:
        shot, skipped = taken
        frame = VideoFrame(shot.k, sensor.encode(shot.states, shot.k), shot.t_s)
        frames.send(Rendered(shot.instant, frame, shot.deliver_mono_s, skipped))
