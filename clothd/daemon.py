"""The fixed-rate loop: camera -> tracker -> control -> stepper link, and the state the API publishes.

Every tick has an absolute deadline (next += period). A tick that starts a whole period late counts the
ticks it missed and skips ahead; there are no catch-up ticks. The compute stages (tracker and control)
run on one dedicated worker thread, which is also the only thread that calls Taichi; the event loop only
schedules, talks to the serial port and serves the API.

Safety: whatever goes wrong in a tick (camera lost, cloth lost, an exception in the compute), the
modules are commanded to stop before anything else is done about it. If the host itself goes silent,
the controller's watchdog stops them.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from clothd.api.stream import StreamHub
from clothd.config import Config
from clothd.core.camera_model import CameraModel
from clothd.core.control import Mode, PoseController, Setpoint
from clothd.core.conveyor import ConveyorLayout
from clothd.core.messages import Estimate, ModuleCommands
from clothd.core.tracker import Tracker
from clothd.drivers.camera import CameraSource, Frame
from clothd.drivers.stepper_link import StepperLink
from clothd.drivers.wire import Fault
from clothd.errors import RequestError
from clothd.loop_stats import LoopStats
from clothd.notify import SystemdNotifier
from clothd.status import build_status
from clothd.taichi_runtime import start_taichi

log = logging.getLogger(__name__)

WATCHDOG_NOTIFY_S = 1.0
OVERRUN_LOG_S = 1.0


@dataclass
class TickResult:
    state: str  # tracking | tracking_lost | camera_lost | fault
    estimate: Estimate | None
    commands: ModuleCommands
    new_frame: bool
    timing_s: dict[str, float] = field(default_factory=dict)


class Daemon:
    def __init__(
        self, cfg: Config, camera_model: CameraModel, notifier: SystemdNotifier | None = None
    ) -> None:
        self.cfg = cfg
        cell = cfg.cell
        self.layout = ConveyorLayout(cell.modules_x, cell.modules_y, cell.pitch_m, cell.module_size_m)
        self.camera_model = camera_model
        self.camera = CameraSource(cfg.camera)
        self.link = StepperLink(cfg.stepper, self.layout.n_modules, on_fault=self._on_fault)
        self.tracker = Tracker(cfg.tracker, camera_model, self.layout, clock=time.perf_counter)
        self.controller = PoseController(cfg.control, cell, self.layout.centres_m)
        self.notifier = notifier or SystemdNotifier()
        self.stats = LoopStats()
        self.hub = StreamHub()
        self.setpoint = Setpoint("idle", None)
        self.estopped = False
        self.state = "starting"
        self.faults: deque[dict[str, object]] = deque(maxlen=20)
        self.latest_frame: Frame | None = None
        self.latest: TickResult | None = None
        self.status: dict[str, object] = {}
        self.status_json = b"{}"
        self._period_s = 1.0 / cfg.loop.tick_hz
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="compute")
        self._last_frame_index = -1
        self._commands_in_force = self.controller.stop()
        self._reset_requested = False
        self._stopping = False
        self._ready_sent = False
        self._last_watchdog_s = 0.0
        self._last_overrun_log_s = 0.0
        self.publish()

    # -- requests from the API (event loop thread) --------------------------------------------------

    def set_setpoint(self, mode: Mode, pose: np.ndarray | None) -> None:
        if self.estopped and mode != "idle":
            raise RequestError("the emergency stop is latched: clear it before moving the cloth")
        if mode == "move" and pose is None:
            raise RequestError("move needs x_m, y_m and theta_rad")
        if mode == "hold":
            est = self.latest.estimate if self.latest else None
            if est is None or est.status != "tracking":
                raise RequestError("hold needs a tracked cloth, and the cloth is not tracked now")
            pose = est.pose.copy()
        self.setpoint = Setpoint(mode, None if mode == "idle" else pose)
        self.publish()

    def estop(self) -> None:
        """Stop every module now, bypassing the loop; latched until estop_clear."""
        self.link.estop()
        self.estopped = True
        self.setpoint = Setpoint("idle", None)
        log.warning("emergency stop")
        self.publish()

    def estop_clear(self) -> None:
        self.link.estop_clear()
        self.estopped = False
        self.publish()

    def reset(self) -> None:
        """Re-initialise tracking on the next frame; the modules stop meanwhile (setpoint idle)."""
        self._reset_requested = True
        self.setpoint = Setpoint("idle", None)

    # -- lifecycle ------------------------------------------------------------------------------------

    async def run(self) -> None:
        """Run the loop until stop() is called."""
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self._worker, start_taichi, self.cfg.taichi.arch)
        self.camera.start()
        link_task = asyncio.create_task(self.link.run())
        try:
            await self._loop()
        finally:
            await self.shutdown("loop ended")
            link_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await link_task

    def stop(self) -> None:
        self._stopping = True

    async def shutdown(self, reason: str) -> None:
        """Stop the modules first, then everything else."""
        self._stopping = True
        log.info("shutting down: %s", reason)
        self.notifier.stopping()
        await self.link.stop()
        await asyncio.get_running_loop().run_in_executor(None, self.camera.stop)
        self._worker.shutdown(wait=True, cancel_futures=True)

    # -- the loop ------------------------------------------------------------------------------------

    async def _loop(self) -> None:
        period = self._period_s
        next_t = time.monotonic() + period
        while not self._stopping:
            delay = next_t - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            start = time.monotonic()
            self.stats.jitter.add_s(start - next_t)
            late = start - next_t
            if late >= period:
                missed = int(late // period)
                self.stats.missed_ticks += missed
                next_t += missed * period
                self._log_overrun(missed, late)
            await self._tick()
            next_t += period

    async def _tick(self) -> None:
        frame = self.camera.latest()
        setpoint, estopped = self.setpoint, self.estopped
        reset, self._reset_requested = self._reset_requested, False
        loop = asyncio.get_running_loop()
        try:
            result = await loop.run_in_executor(self._worker, self._compute, frame, setpoint, estopped, reset)
        except Exception:  # a bug in a compute stage must not take the loop, or the modules, with it
            log.exception("tick failed; stopping the modules")
            result = TickResult("fault", None, self.controller.stop(), False)
        if not self.estopped:
            self.link.send_commands(result.commands.speed_m_s, result.commands.heading_rad)
        sent = time.monotonic()
        if result.new_frame and frame is not None:
            self.stats.latency.add_s(sent - frame.t_mono_s)
        self.stats.ticks += 1
        self.stats.add_stages(result.timing_s)
        if result.state != self.state:
            log.info("state: %s -> %s", self.state, result.state)
        self.state = result.state
        self.latest, self.latest_frame = result, frame
        self.publish()
        self._notify_systemd(sent, result)

    def _compute(self, frame: Frame | None, setpoint: Setpoint, estopped: bool, reset: bool) -> TickResult:
        """One tick's tracking and control, on the worker thread."""
        t0 = time.perf_counter()
        if reset:
            self.tracker.reset()
            self.controller.reset()
        timing: dict[str, float] = {}
        new_frame = frame is not None and frame.index != self._last_frame_index
        est = self.latest.estimate if self.latest else None
        if frame is not None and new_frame:
            est = self.tracker.step(frame.image, frame.t_mono_s, self._commands_in_force)
            self._last_frame_index = frame.index
            timing.update({f"tracker_{k}": v for k, v in est.timing_s.items()})
        t1 = time.perf_counter()
        tracking = est is not None and est.status == "tracking"
        if frame is None:
            state, commands = "camera_lost", self.controller.stop()
        elif not tracking or est is None:
            state, commands = "tracking_lost", self.controller.stop()
        elif estopped or setpoint.mode == "idle" or setpoint.pose is None:
            state, commands = "tracking", self.controller.stop()
        else:
            state = "tracking"
            twist = self.controller.plan_twist(est.pose, setpoint.pose, self._period_s)
            outline = self.tracker.outline_m()
            commands = (
                self.controller.stop()
                if outline is None
                else self.controller.module_commands(est.pose, twist, outline)
            )
        if estopped:
            commands = ModuleCommands(np.zeros_like(commands.speed_m_s), commands.heading_rad)
        self._commands_in_force = commands
        timing["control"] = time.perf_counter() - t1
        timing["compute"] = time.perf_counter() - t0
        return TickResult(state, est, commands, new_frame, timing)

    # -- publishing ------------------------------------------------------------------------------------

    def publish(self) -> None:
        """Build the status once, serialise it once, and hand it to every stream subscriber."""
        self.status = build_status(self)
        self.status_json = _dumps(self.status)
        self.hub.publish(self.status_json)

    def _on_fault(self, fault: Fault) -> None:
        self.faults.append(
            {"t_unix_s": time.time(), "code": fault.code, "module": fault.module, "text": fault.text}
        )

    def _notify_systemd(self, now_s: float, result: TickResult) -> None:
        healthy = result.state == "tracking" and self.link.connected
        if healthy and not self._ready_sent:
            self.notifier.ready()
            self._ready_sent = True
        # The watchdog is fed only by a loop that is ticking, with the camera and the link alive.
        if self.camera.healthy and self.link.connected and now_s - self._last_watchdog_s >= WATCHDOG_NOTIFY_S:
            self.notifier.watchdog()
            self._last_watchdog_s = now_s

    def _log_overrun(self, missed: int, late_s: float) -> None:
        now = time.monotonic()
        if now - self._last_overrun_log_s >= OVERRUN_LOG_S:
            log.warning("tick overran by %.1f ms: skipped %d tick(s)", late_s * 1e3, missed)
            self._last_overrun_log_s = now


def _dumps(obj: object) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_json_default).encode()


def _json_default(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
