"""The fixed-rate loop: camera -> tracker -> control -> stepper link, and the state the API publishes.

Every tick has an absolute deadline (next += period). A tick that starts a whole period late counts the
ticks it missed and skips ahead; there are no catch-up ticks. The compute stages (camera capture,
tracker, control, the annotated view) run in the compute process (clothd/loop/compute.py), one request and
one reply per tick; this process's event loop only schedules, talks to the serial port and answers the
API process's calls (clothd/api/process.py), and shares its GIL with nothing heavy.

Safety: whatever goes wrong in a tick (camera lost, cloth lost, an exception in the compute, a stepper
link lost, a controller's FAULT), the modules, on every controller, are commanded to stop before anything
else is done about it. A FAULT(ESTOP_INPUT), the cell's hardware e-stop chain opened, latches the
daemon's own e-stop too, released only by the operator's clear. If the compute process dies the
modules are stopped and the daemon exits (systemd restarts it). If the host itself goes silent, the
controller's watchdog stops them.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import numpy as np

from clothd.core.control import Setpoint
from clothd.core.drive_script import DrivePlan, DriveScript, cloth_reach_m, swept_box_m
from clothd.core.messages import ModuleCommands
from clothd.core.modes import LoopState, Mode
from clothd.core.workspace import cloth_corners_m
from clothd.drivers import wire
from clothd.drivers.ports import ControllerFault, FrameSourceHealth, ModuleLink
from clothd.errors import HardwareError, RequestError, UnreachableTargetError
from clothd.loop.compute_messages import InForce, TickReply, TickRequest
from clothd.loop.compute_process import ComputeProcess
from clothd.loop.daemon_settings import DaemonSettings
from clothd.loop.frame_phase import FramePhaseLock
from clothd.loop.loop_stats import LoopStats
from clothd.loop.pairing import CameraReport
from clothd.loop.status import Status, build_status
from clothd.notify import SystemdNotifier
from clothd.outputs.view import ViewBoard

log = logging.getLogger(__name__)

WATCHDOG_NOTIFY_S = 1.0
OVERRUN_LOG_S = 1.0
SEND_MARGIN_S = 0.003  # a tick's commands go out this long before the next deadline at the latest


class Daemon:
    """The loop, and the one owner of the shell's state: the setpoint, the commands sent, the status.

    `link` is the stepper controller (ModuleLink) and `compute` the compute process; both are given, not
    built here. API handlers call the request methods on the event loop; none of them waits on a tick.
    `on_status` receives each new status (the API's fan-out)."""

    def __init__(
        self,
        settings: DaemonSettings,
        link: ModuleLink,
        compute: ComputeProcess,
        notifier: SystemdNotifier | None = None,
        on_status: Callable[[Status], None] | None = None,
    ) -> None:
        self.settings = settings
        self.link = link
        self.compute = compute
        self.notifier = notifier or SystemdNotifier()
        self.on_status = on_status
        self.stats = LoopStats()
        self.phase = (
            FramePhaseLock(
                settings.period_s, settings.frame_lead_s, settings.phase_step_s, settings.frame_wait_s
            )
            if settings.frame_lock
            else None
        )
        self.setpoint = Setpoint(Mode.IDLE, None)
        self.halt_reason: str | None = None  # why a move last stopped by itself; cleared by a new setpoint
        self.halt_t_unix_s: float | None = None  # when it stopped, wall clock
        self.state = LoopState.STARTING
        self.camera = FrameSourceHealth("connecting", False, None, 0)
        self.further: tuple[CameraReport, ...] = ()  # the further cameras' health and pairing
        self.latest: TickReply | None = None
        self.status: Status | None = None
        self.view = ViewBoard()
        self._last_view_s = -np.inf
        self._pending: asyncio.Future[TickReply] | None = None  # the compute in flight
        self._stale_ticks = 0  # ticks in a row the compute has not answered in time
        self._asked_s: float | None = None  # when the compute in flight was asked
        # The frame behind commands not yet sent: when it arrived, its compute was asked, began and replied.
        self._unsent_frame: tuple[float, float | None, tuple[float, float] | None] | None = None
        self._commands = ModuleCommands.all_stop(settings.n_modules)  # the newest from the compute
        self._in_force = self._commands  # what the modules were last told: the model's input
        self._reset_requested = False
        self._record_start: Path | None = None
        self._recording_starting: Path | None = None  # asked for, and no reply has shown the outcome yet
        self._start_in_flight = False  # the request in flight carries a recording's start
        self._record_stop = False
        self._stop_in_flight = False  # the request in flight carries a recording's stop
        self._stopping = False
        self._ready_sent = False
        self._last_watchdog_s = 0.0
        self._last_overrun_log_s = 0.0
        link.on_fault = self._controller_fault
        self.publish()

    # -- requests from the API (event loop thread) --------------------------------------------------

    def set_setpoint(self, mode: Mode, pose: np.ndarray | None, script: DriveScript | None = None) -> None:
        """The one way the modules start moving: hold, move, flatten or drive needs the e-stop clear, the
        link up and the cloth tracked; a move's target, and wherever a drive script could carry the cloth,
        must keep the whole cloth inside the workspace; flatten needs a tracker that follows the cloth's
        shape."""
        if mode == Mode.FLATTEN and not self.settings.estimates_shape:
            raise RequestError(
                "flatten needs the cloth's shape: run the mesh tracker (tracker.model mesh), not a rigid one"
            )
        if mode != Mode.IDLE:
            self._check_can_move(cloth=mode != Mode.FLOW)  # flow takes the pieces as they come
        if mode == Mode.FLOW and not self.settings.flow_ready:
            raise RequestError("flow needs flow.warm_at_start: true (a tracker built in a tick stalls it)")
        est = self.latest.estimate if self.latest else None
        if mode == Mode.MOVE:
            if pose is None:
                raise RequestError("move needs x_m, y_m and theta_rad")
            assert est is not None and est.cloth_size_m is not None  # tracked: _check_can_move
            reason = self.settings.workspace.leaves(cloth_corners_m(pose, est.cloth_size_m))
            if reason is not None:
                raise UnreachableTargetError(f"target x_m {pose[0]:g}, y_m {pose[1]:g}: {reason}")
        if mode in (Mode.HOLD, Mode.FLATTEN):
            assert est is not None
            pose = est.pose.copy()
        if mode == Mode.DRIVE:
            if script is None:
                raise RequestError("drive needs a script")
            assert est is not None and est.outline_m is not None  # tracked: _check_can_move
            plan = self._drive_plan(script, est.outline_m)
            self.setpoint = Setpoint(Mode.DRIVE, None, plan, time.monotonic())
        else:
            target = None if mode == Mode.IDLE else pose
            # Flow asked for while flowing goes on with the same pieces; asked for anew, it starts afresh.
            going_on = mode == self.setpoint.mode == Mode.FLOW
            started = self.setpoint.started_mono_s if going_on else time.monotonic()
            self.setpoint = Setpoint(mode, target, started_mono_s=started)
        self.halt_reason = self.halt_t_unix_s = None
        self.publish()

    def _drive_plan(self, script: DriveScript, outline_m: np.ndarray) -> DrivePlan:
        """The script compiled for this cell, refused (422) when the cell cannot play it or when it could
        carry the cloth out of the workspace."""
        s = self.settings
        plan = DrivePlan.compile(script, s.layout, s.max_speed_m_s)
        reach_m = cloth_reach_m(plan, outline_m, s.layout)
        reason = s.workspace.leaves(swept_box_m(outline_m, reach_m))
        if reason is not None:
            raise UnreachableTargetError(f"the script could carry the cloth {reach_m * 1e3:.0f} mm: {reason}")
        return plan

    def _check_can_move(self, cloth: bool = True) -> None:
        if self.link.estopped:
            raise RequestError("the emergency stop is latched: clear it before moving the cloth")
        if self.link.state == "starting":  # not up yet since the start: not a fault, only too early
            raise RequestError("starting")
        if not self.link.connected:
            raise RequestError("the stepper link is not connected: the modules cannot be moved now")
        est = self.latest.estimate if self.latest else None
        if cloth and (self.state != LoopState.TRACKING or est is None or not est.tracking):
            raise RequestError(f"the cloth is not tracked now (state {self.state}): nothing to move")

    def estop(self) -> None:
        """Stop every module now, bypassing the loop; latched until estop_clear."""
        self.link.estop()
        self.setpoint = Setpoint(Mode.IDLE, None)
        log.warning("emergency stop")
        self.publish()

    def estop_clear(self) -> bool:
        """Release a latched e-stop; whether one was latched."""
        latched = self.link.estopped
        self.link.estop_clear()
        self.publish()
        return latched

    def _controller_fault(self, fault: ControllerFault) -> None:
        """A controller's FAULT, as it arrives: every module on every controller told to stop at once, and
        the move dropped. The hardware e-stop chain opened (ESTOP_INPUT) latches the e-stop as the API's
        does, on every controller, until the operator clears it."""
        name = wire.FAULT_NAMES.get(fault.code, f"code {fault.code}")
        reason = f"controller fault {name} on module {fault.module}" + (
            f": {fault.text}" if fault.text else ""
        )
        stop = ModuleCommands.all_stop(self.settings.n_modules)
        self._commands = stop
        if fault.code == wire.FAULT_ESTOP_INPUT:
            self.link.estop()  # cuts every drive at once, whatever the line held
            self._in_force = stop
            log.warning("emergency stop: the hardware e-stop chain opened (%s)", reason)
            self._halt(reason, idle_too=True)
        else:
            self._in_force = self.link.send_commands(stop).in_force(stop, self._in_force)
            self._halt(reason)
        self.publish()

    def start_recording(self, out: Path) -> None:
        """Record from the next frame into `out`, a place already made (`make_recording_place`, off this
        loop: a slow disk stalls no tick; a place that cannot be written is refused before it gets here
        rather than found out by the compute later)."""
        rec = self.latest.recording if self.latest else None
        # A stop asked for, that no reply has shown done yet, goes first: the compute stops the old
        # recording before it starts the new one.
        stopping = self._record_stop or self._stop_in_flight
        if rec is not None and rec.active and not stopping:
            raise RequestError(f"already recording into {rec.dir}: stop it first")
        if self._recording_starting is not None:  # two requests at once: the first one wins
            raise RequestError(f"a recording is starting in {self._recording_starting}: stop it first")
        self._record_start = self._recording_starting = out

    def stop_recording(self) -> None:
        rec = self.latest.recording if self.latest else None
        if rec is None or not rec.active:
            raise RequestError("not recording")
        self._record_stop = True

    def reset(self) -> None:
        """Re-initialise tracking on the next frame; the modules stop meanwhile (setpoint idle)."""
        self._reset_requested = True
        self.setpoint = Setpoint(Mode.IDLE, None)

    # -- lifecycle ------------------------------------------------------------------------------------

    async def run(self) -> None:
        """Run the loop until stop() is called; whatever ends it, shutdown() runs."""
        await self.compute.start()
        link_task = asyncio.create_task(self.link.run())
        try:
            await self._loop()
        finally:
            await self.shutdown("loop ended")
            link_task.cancel()
            await asyncio.gather(link_task, return_exceptions=True)

    def stop(self) -> None:
        self._stopping = True

    async def shutdown(self, reason: str) -> None:
        """The one way out: stop the modules first, then the compute process."""
        self._stopping = True
        log.info("shutting down: %s", reason)
        self.notifier.stopping()
        await self.link.stop()
        await self.compute.stop()

    # -- the loop ------------------------------------------------------------------------------------

    async def _loop(self) -> None:
        period = self.settings.period_s
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
            next_t += period
            if self.phase is not None:
                next_t += self.phase.shift_s(next_t)
                self.stats.frame_locked = self.phase.locked
            await self._tick(next_t)

    async def _tick(self, next_deadline_s: float) -> None:
        """Send this tick's commands. Their compute runs in the compute process and may take until just
        before the next deadline; if it takes longer, this tick repeats the last commands (counted as a
        compute overrun) and the first tick after the reply arrives uses it and asks again. The tick
        rate never depends on the compute."""
        now = time.monotonic()
        self._end_played_drive(now)
        if self._pending is not None and self._pending.done():  # last tick's compute came in late
            self._use(self._pending, now)
            self._pending = None
        if self._pending is None:
            self._pending, self._asked_s = self._request(now), now
        budget_s = next_deadline_s - time.monotonic() - SEND_MARGIN_S
        done, _ = await asyncio.wait({self._pending}, timeout=max(0.0, budget_s))
        if done:
            self._use(self._pending, now)
            self._pending = None
            self._stale_ticks = 0
        else:
            self.stats.compute_overruns += 1
            self._stale_ticks += 1
            if self._stale_ticks >= self.settings.max_stale_ticks:  # commands this old steer blind
                self._commands = ModuleCommands.all_stop(self.settings.n_modules)
                self._halt(f"the compute has not answered for {self._stale_ticks} ticks")
        if not self.link.connected:
            self._halt("the stepper link is down")
        if self.setpoint.mode == Mode.IDLE:  # a reply asked for before a halt never restarts the modules
            self._commands = ModuleCommands.all_stop(self.settings.n_modules)
        calibration = self.settings.module_calibration
        handover = self.link.send_commands(
            self._commands if calibration is None else calibration.to_send(self._commands)
        )
        self._in_force = handover.in_force(self._commands, self._in_force)
        # Only to a compute that has answered: a hung one would fill the pipe until this send blocked.
        if self._pending is None:
            try:
                self.compute.tell_in_force(InForce(self._in_force))
            except OSError as err:
                self._compute_died(err)
        self.stats.ticks += 1
        if self._unsent_frame is not None:
            self.stats.latency.add(*self._unsent_frame, time.monotonic())
            self._unsent_frame = None
        self.publish()

    def _end_played_drive(self, now: float) -> None:
        """A drive script played to its end leaves the daemon idle (its modules already stopped)."""
        plan = self.setpoint.drive
        if plan is not None and now - self.setpoint.started_mono_s >= plan.duration_s:
            log.info("drive script played to its end (%.1f s); idle", plan.duration_s)
            self.setpoint = Setpoint(Mode.IDLE, None)

    def _request(self, now: float) -> asyncio.Future[TickReply]:
        want_view = self.view.watched and now - self._last_view_s >= self.settings.view_period_s
        reset, self._reset_requested = self._reset_requested, False
        start, self._record_start = self._record_start, None
        self._start_in_flight = start is not None
        stop, self._record_stop = self._record_stop, False
        self._stop_in_flight = stop
        wait_until = self.phase.wait_until_s(now) if self.phase is not None else None
        req = TickRequest(self.setpoint, self._in_force, reset, want_view, start, stop, wait_until)
        try:
            return self.compute.request(req)
        except OSError as err:
            self._compute_died(err)

    def _compute_died(self, err: BaseException) -> NoReturn:
        """Stop the modules, say so, and end the loop (systemd restarts the service)."""
        self.link.send_commands(ModuleCommands.all_stop(self.settings.n_modules))
        self.state = LoopState.FAULT
        self.publish()
        raise HardwareError(
            f"the compute process died ({err or type(err).__name__}); modules stopped"
        ) from err

    def _use(self, pending: asyncio.Future[TickReply], asked_s: float) -> None:
        """Take a finished compute's reply: its commands go out with this tick."""
        try:
            reply = pending.result()
        except (EOFError, OSError) as err:
            self._compute_died(err)
        self._commands = reply.commands
        if self._start_in_flight:  # the reply's recording status now says how the start went
            self._start_in_flight, self._recording_starting = False, None
        self._stop_in_flight = False  # ... and that the recording stopped
        if reply.new_frame and reply.frame_t_mono_s is not None:
            self._unsent_frame = (reply.frame_t_mono_s, self._asked_s, reply.compute_mono_s)
            if self.phase is not None:
                self.phase.frame_arrived(reply.frame_t_mono_s)
        self.stats.add_stages(reply.timing_s)
        if reply.view_jpeg is not None:
            self.view.post(reply.view_jpeg)
            self._last_view_s = asked_s
        state = reply.state
        if (
            state == LoopState.CAMERA_LOST
            and self.state == LoopState.STARTING
            and reply.camera.state == "connecting"
        ):
            state = LoopState.STARTING  # the camera's first opening is under way: nothing is lost yet
        if state != self.state:
            log.info("state: %s -> %s", self.state, state)
        self.state = state
        if reply.starved_ms is not None:
            self._starved(reply.starved_ms)
        if reply.halt_reason is not None:
            self._halt(reply.halt_reason)
        self.camera, self.further = reply.camera, reply.cameras
        self.latest = reply
        self._notify_systemd(time.monotonic())

    def _starved(self, silent_ms: float) -> None:
        """Said, not halted: the fresh estimate comes from the same tick's frame, and a move goes on from
        it; what the silence did to the link (its loss, the controller's watchdog) halts by itself."""
        self.stats.starved_restarts += 1
        log.warning("the daemon was silent %.0f ms (loop.starved_ms): the tracker started afresh", silent_ms)

    def _halt(self, reason: str, idle_too: bool = False) -> None:
        """A fault stopped the modules: drop the move, so that nothing restarts until a supervisor sends a
        new setpoint (no unexpected start-up, IEC 60204-1). Said while idle too when `idle_too`."""
        if self.setpoint.mode == Mode.IDLE and not idle_too:
            return
        log.warning("%s stopped: %s; idle until a new setpoint", self.setpoint.mode, reason)
        self.setpoint = Setpoint(Mode.IDLE, None)
        self.halt_reason, self.halt_t_unix_s = reason, time.time()

    # -- publishing ------------------------------------------------------------------------------------

    def publish(self) -> None:
        """Build the status once and hand it on (serialised once for every reader of the API's)."""
        s = self.settings
        self.status = build_status(
            state=self.state,
            setpoint=self.setpoint,
            halt_reason=self.halt_reason,
            halt_t_unix_s=self.halt_t_unix_s,
            estimate=self.latest.estimate if self.latest else None,
            flatness=self.latest.flatness if self.latest else None,
            timing=self.stats.cached_summary(),
            camera=self.camera,
            camera_source=s.camera_source,
            cameras=s.cameras,
            further=self.further,
            link=self.link,
            link_port=s.link_port,
            commands=self._in_force,
            recording=self.latest.recording if self.latest else None,
            pieces=self.latest.pieces if self.latest else None,
        )
        if self.on_status is not None:
            self.on_status(self.status)

    def _notify_systemd(self, now_s: float) -> None:
        """Ready and alive while the loop ticks and the compute answers (what a restart cures); a lost
        camera or link, an empty table, the daemon reports and retries (docs/deploy.md)."""
        if not self._ready_sent:
            self.notifier.ready()
            self._ready_sent = True
        if now_s - self._last_watchdog_s >= WATCHDOG_NOTIFY_S:
            self.notifier.watchdog()
            self._last_watchdog_s = now_s

    def _log_overrun(self, missed: int, late_s: float) -> None:
        now = time.monotonic()
        if now - self._last_overrun_log_s >= OVERRUN_LOG_S:
            log.warning("tick overran by %.1f ms: skipped %d tick(s)", late_s * 1e3, missed)
            self._last_overrun_log_s = now
