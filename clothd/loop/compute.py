"""The compute process: camera capture, tracker, control and the annotated view, one request per tick.

It runs apart from the daemon's event loop so that the two never share a GIL: the tracker's Python,
its Taichi kernels and its LAPACK calls hold the GIL for milliseconds at a time, which in one process
delayed every API request and tick timer behind them (docs/benchmarks.md, "The closed loop"). The
daemon sends one TickRequest per tick over a pipe (compute_process.py) and gets one TickReply back;
this process is the only one that calls Taichi.

A tick replies as soon as its commands are ready; what they do not wait for (the tracker's upkeep, the
recording and the annotated view) follows in `after_reply`, and the view and its timing travel with the
next reply. Between requests the process tracks a frame as soon as it arrives (`track_ahead`), with the
commands the daemon says it has just sent (InForce): a frame that arrives before its tick asks is then
tracked while it waits, and its tick only controls (docs/architecture.md, "A frame's path").

Any exception in a tick is answered with all-stop commands and state "fault", and one in its
after-reply work answers the next tick so; the daemon treats the death of the process itself as a fault
too, and stops the modules.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection

import cv2

from clothd.core.cell_controller import CellController
from clothd.core.flatness import Flatness
from clothd.core.flow_cell import FlowCell
from clothd.core.messages import Estimate, ModuleCommands
from clothd.core.modes import LoopState, Mode
from clothd.core.tracker import Tracker
from clothd.drivers.ports import CameraFrame, FrameSource
from clothd.drivers.priority import bound_gil_wait, leave_realtime
from clothd.errors import ClothdError
from clothd.logs import configure_logging
from clothd.loop.compute_messages import ComputeSpec, InForce, TickReply, TickRequest
from clothd.loop.pairing import FramePairing
from clothd.outputs.frame_outputs import FrameOutputs, RecordingSpec
from clothd.outputs.view import ViewRenderer
from clothd.taichi_runtime import start_taichi

log = logging.getLogger(__name__)

AHEAD_POLL_S = 0.002  # between requests, how often the compute looks for a frame to track ahead


@dataclass(frozen=True)
class _Ahead:
    """A frame tracked as it arrived, before its tick asked: when and with which commands."""

    frame: CameraFrame
    estimate: Estimate
    flatness: Flatness | None
    commands_in_force: ModuleCommands
    began_mono_s: float


@dataclass(frozen=True)
class _AfterReply:
    """What a tick leaves for after its reply: its request, frame, whether the frame was new, the estimate
    it tracked (None when the frame was not new, or its pieces were tracked apart: mode flow) and the
    estimate and flatness its commands came from."""

    req: TickRequest
    frame: CameraFrame | None
    new_frame: bool
    commands_in_force: ModuleCommands  # those the frame was tracked with
    tracked: Estimate | None
    estimate: Estimate | None
    flatness: Flatness | None


class Compute:
    """One tick's tracking and control, and the view; lives in the compute process."""

    def __init__(
        self, spec: ComputeSpec, frames: FrameSource, others: Sequence[FrameSource] | None = None
    ) -> None:
        """frames: the first camera's; others: the further cameras', one per spec.other_cameras (None:
        opened from their factories)."""
        self.spec = spec
        self.frames = frames
        others = [c.frame_source() for c in spec.other_cameras] if others is None else others
        self.pairing = FramePairing(others, spec.tracker.stereo.max_skew_ms / 1e3)
        further = [(c.name, c.camera_model) for c in spec.other_cameras]
        recording = RecordingSpec(
            spec.camera_model, further, spec.layout, spec.max_record_bytes, spec.recording_format
        )
        self.outputs = FrameOutputs(recording, spec.foxglove)
        self.tracker = Tracker(
            spec.tracker,
            spec.camera_model,
            spec.layout,
            clock=time.perf_counter,
            other_cameras=[c.camera_model for c in spec.other_cameras],
        )
        self.cell = CellController(
            spec.control,
            spec.cell,
            spec.layout,
            spec.workspace,
            spec.period_s,
            spec.tracker.physics.strain_limit,
            spec.tracker.estimates_shape,
        )
        self.flow: FlowCell | None = None  # mode flow's pieces and their control, while in mode flow
        self._flow_set_s: float | None = None  # when the flow running was asked for (its setpoint's)
        self._flow_cell: FlowCell | None = None  # ... built at start (flow.warm_at_start) or when first asked
        self.view = ViewRenderer(spec.camera_model)
        self._estimate: Estimate | None = None
        self._flatness: Flatness | None = None  # of _estimate: read once per frame, kept between frames
        self._last_frame_index = -1
        self._after: _AfterReply | None = None  # the last tick's work left for after its reply
        self._late_timing: dict[str, float] = {}  # that work's stage times, for the next reply
        self._late_view: bytes | None = None  # the view it drew, for the next reply
        self._after_failed = False
        self._in_force: ModuleCommands | None = None  # what the modules were last told, as far as known
        self._heard_mono_s: float | None = None  # when the daemon last said what it sent
        self._ahead: _Ahead | None = None  # a frame tracked before its tick asked

    def start(self) -> None:
        if self.spec.flow.warm_at_start:
            self._flow_cell = self._new_flow_cell()
            self._flow_cell.tracking.warm(self.spec.camera_model.width, self.spec.camera_model.height)
        self.outputs.start()
        self.frames.start()
        self.pairing.start()

    def close(self) -> None:
        self.outputs.close("daemon stopped")
        self.frames.stop()
        self.pairing.stop()

    def stop_reply(self, state: LoopState) -> TickReply:
        return TickReply(
            state=state,
            estimate=None,
            commands=self.cell.stop(),
            new_frame=False,
            frame_t_mono_s=None,
            camera=self.frames.health(),
            cameras=self.pairing.reports(),
            halt_reason=f"the compute failed ({state})",
        )

    def in_force(self, commands: ModuleCommands, sent_mono_s: float) -> None:
        """The daemon told the modules this at sent_mono_s (InForce)."""
        self._in_force, self._heard_mono_s = commands, sent_mono_s

    def _silent_s(self, until_mono_s: float) -> float:
        """How long before `until_mono_s` the daemon last said what it sent (0 before it ever has). Its
        messages carry their send times: a compute busy with a slow tick is not a silent daemon."""
        return 0.0 if self._heard_mono_s is None else until_mono_s - self._heard_mono_s

    def track_ahead(self) -> None:
        """Between requests: track a frame that has arrived since the last tick, with the commands in
        force, so that its tick finds it tracked. One at a time: the next waits for a tick to take it."""
        if self._ahead is not None or self._in_force is None or self._after_failed or self.flow is not None:
            return
        frame = self.frames.latest()
        if frame is None or frame.index == self._last_frame_index:
            return
        if self._silent_s(frame.t_mono_s) > self.spec.starved_s:  # what the modules ran is unknown
            return
        began_mono_s = time.monotonic()
        try:
            est = self._track(frame, self._in_force, self._late_timing)  # timed with the next tick's
            flatness = self.cell.read_flatness(est)
        except Exception:  # as in a tick: a bug must not take the loop with it
            self._failed_between_ticks("tracking a frame ahead of its tick")
            return
        self._ahead = _Ahead(frame, est, flatness, self._in_force, began_mono_s)

    def tick(self, req: TickRequest) -> TickReply:
        # Silent past the bound, the daemon sent nothing, the controller's watchdog may have stopped the
        # modules, and the belts the model drove the cloth with are unknown: an estimate carried through
        # the gap invents ridges that the regulator then chases. The tracker starts afresh instead.
        silent_s = self._silent_s(req.sent_mono_s)
        starved = silent_s > self.spec.starved_s and self._estimate is not None
        reset = req.reset or starved
        self._in_force, self._heard_mono_s = req.commands_in_force, req.sent_mono_s
        ahead, self._ahead = self._ahead, None
        if self._after_failed:
            self._after_failed = False
            return self.stop_reply(LoopState.FAULT)
        ahead = None if reset else ahead  # tracked on the state a reset discards: tracked afresh below
        timing, self._late_timing = self._late_timing, {}
        if ahead is not None:
            frame: CameraFrame | None = ahead.frame
        else:
            frame = self._frame(req.frame_wait_until_mono_s, timing)  # its wait is not the compute's time
        t0, began_mono_s = time.perf_counter(), time.monotonic()
        flow_asked, set_s = req.setpoint.mode == Mode.FLOW, req.setpoint.started_mono_s
        # One cloth, or pieces; a flow asked for anew (after a setpoint no tick saw, too) starts afresh.
        if reset or (self.flow is not None) != flow_asked or (flow_asked and set_s != self._flow_set_s):
            self._start_afresh(set_s if flow_asked else None)
        self.outputs.requests(req.record_start, req.record_stop)
        if self.flow is not None:
            return self._flow_tick(self.flow, req, frame, timing, t0, began_mono_s)
        new_frame = frame is not None and frame.index != self._last_frame_index
        est = self._estimate
        tracked = None
        tracked_with = req.commands_in_force
        if ahead is not None:
            est = tracked = ahead.estimate
            self._flatness = ahead.flatness
            tracked_with, began_mono_s = ahead.commands_in_force, ahead.began_mono_s
        elif frame is not None and new_frame:
            est = tracked = self._track(frame, req.commands_in_force, timing)
            self._flatness = self.cell.read_flatness(est)
        if tracked is not None and frame is not None:
            self._estimate = tracked
            self._last_frame_index = frame.index
            timing.update({f"tracker_{k}": v for k, v in tracked.timing_s.items()})
        t1 = time.perf_counter()
        flatness = self._flatness
        step = self.cell.step(frame is not None, est, req.setpoint, flatness, time.monotonic())
        timing["control"] = time.perf_counter() - t1
        timing["compute"] = time.perf_counter() - t0
        self._after = _AfterReply(req, frame, tracked is not None, tracked_with, tracked, est, flatness)
        view, self._late_view = self._late_view, None
        return TickReply(
            state=step.state,
            estimate=est,
            commands=step.commands,
            new_frame=new_frame,
            frame_t_mono_s=frame.t_mono_s if frame is not None else None,
            camera=self.frames.health(),
            cameras=self.pairing.reports(),
            timing_s=timing,
            view_jpeg=view,
            recording=self.outputs.status(),
            halt_reason=step.halt_reason,
            flatness=flatness,
            compute_mono_s=(began_mono_s, time.monotonic()),
            starved_ms=silent_s * 1e3 if starved else None,
        )

    def _start_afresh(self, flow_set_s: float | None) -> None:
        """Tracking starts afresh: of one cloth, or of every piece (a flow asked for at flow_set_s)."""
        self.tracker.reset()
        self.cell.reset()
        self._estimate = self._flatness = None
        self.flow, self._flow_set_s = None, flow_set_s
        if flow_set_s is not None:
            if self._flow_cell is None:
                self._flow_cell = self._new_flow_cell()
            self.flow = self._flow_cell
            self.flow.reset()

    def _new_flow_cell(self) -> FlowCell:
        s = self.spec
        others = [c.camera_model for c in s.other_cameras]
        args = (s.flow, s.tracker, s.control, s.cell, s.camera_model, others, s.period_s)
        return FlowCell(*args, clock=time.perf_counter)

    def _flow_tick(
        self,
        flow: FlowCell,
        req: TickRequest,
        frame: CameraFrame | None,
        timing: dict[str, float],
        t0: float,
        began_mono_s: float,
    ) -> TickReply:
        """Mode flow: every piece tracked in the frame (each waits for its pair: heights now), then the
        flow's commands. Without a frame every module stops, as in every mode."""
        new_frame = frame is not None and frame.index != self._last_frame_index
        if frame is not None and new_frame:
            views = self.pairing.to_track(frame.t_mono_s, True) or []
            flow.track(frame.image, frame.t_mono_s, req.commands_in_force, views)
            self.outputs.add_views(frame.t_mono_s, views)
            self._last_frame_index = frame.index
            timing["track"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        commands = flow.step(time.monotonic()) if frame is not None else flow.stop()
        timing["control"] = time.perf_counter() - t1
        timing["compute"] = time.perf_counter() - t0
        self._after = _AfterReply(req, frame, new_frame, req.commands_in_force, None, None, None)
        view, self._late_view = self._late_view, None
        return TickReply(
            state=LoopState.TRACKING if frame is not None else LoopState.CAMERA_LOST,
            estimate=None,
            commands=commands,
            new_frame=new_frame,
            frame_t_mono_s=frame.t_mono_s if frame is not None else None,
            camera=self.frames.health(),
            cameras=self.pairing.reports(),
            timing_s=timing,
            view_jpeg=view,
            recording=self.outputs.status(),
            halt_reason=None if frame is not None else "the camera is lost",
            compute_mono_s=(began_mono_s, time.monotonic()),
            pieces=flow.reports(),
        )

    def after_reply(self) -> None:
        """The last tick's work that its commands do not wait for: the tracker's upkeep, the recording of
        the frame and the view. A failure here stops the modules at the next tick."""
        after, self._after = self._after, None
        if after is None:
            return
        try:
            self._do_after(after)
        except Exception:  # as in a tick: a bug must not take the loop with it
            self._failed_between_ticks("a tick's after-reply work")

    def _failed_between_ticks(self, what: str) -> None:
        """Work between requests failed: the next tick answers with all-stop, and tracking starts afresh
        from whatever the tracker was left half done with."""
        log.exception("%s failed; stopping the modules, tracking afresh", what)
        self._after_failed = True
        self.track_afresh()

    def track_afresh(self) -> None:
        """Forget the cloth, as a failed tick or work between ticks may have left it half tracked (a frame
        predicted and not corrected, heights whose measuring raised)."""
        self.tracker.reset()
        if self.flow is not None:
            self.flow.reset()
        self._estimate = self._flatness = None

    def _do_after(self, after: _AfterReply) -> None:
        timing = self._late_timing
        t_upkeep = time.perf_counter()
        if self.flow is not None:
            self.flow.upkeep()
        upkeep_s = self.tracker.upkeep() if self.flow is None else time.perf_counter() - t_upkeep
        if upkeep_s is not None:
            timing["tracker_resample"] = upkeep_s
        frame, req = after.frame, after.req
        if after.new_frame and frame is not None and self.outputs.sinks:
            t_rec = time.perf_counter()
            # The commands in force while this frame was captured: replay feeds them back the same way.
            self.outputs.add(frame.image, frame.t_mono_s, after.commands_in_force, after.tracked)
            timing["record"] = time.perf_counter() - t_rec
        t_views = time.perf_counter()
        if self.outputs.write_views():
            timing["record_views"] = time.perf_counter() - t_views
        if req.want_view and frame is not None:
            t_view = time.perf_counter()
            self._late_view = self.view.render(frame.image, after.estimate, req.setpoint, after.flatness)
            timing["view"] = time.perf_counter() - t_view

    def _frame(self, wait_until_mono_s: float | None, timing: dict[str, float]) -> CameraFrame | None:
        """The newest frame; when the tick started as a frame was due, waiting for it up to the bound."""
        frame = self.frames.latest()
        if wait_until_mono_s is None or (frame is not None and frame.index != self._last_frame_index):
            return frame
        t_wait = time.perf_counter()
        frame = self.frames.newer_than(self._last_frame_index, wait_until_mono_s - time.monotonic())
        timing["frame_wait"] = time.perf_counter() - t_wait
        return frame

    def _track(self, frame: CameraFrame, commands: ModuleCommands, timing: dict[str, float]) -> Estimate:
        """Track a first-camera frame: with its further views when tracking begins (their wait is the stage
        pair_wait), otherwise at once, its pair and heights left for `measure_heights`."""
        t0 = time.perf_counter()
        views = self.pairing.to_track(frame.t_mono_s, self.tracker.initialising)
        if views is not None and self.pairing.cameras:
            timing["pair_wait"] = time.perf_counter() - t0
        est = self.tracker.track(frame.image, frame.t_mono_s, commands, views)
        if views is not None:
            self.outputs.add_views(frame.t_mono_s, views)
        return est

    def measure_heights(self, wait: bool = False) -> None:
        """Between ticks: the last tracked frame's heights, once no further camera's frame nearer it is due
        (wait: waiting for it); the next estimate carries them, the next reply their time."""
        paired = self.pairing.later_views(wait)
        if paired is None or self._after_failed or self.flow is not None:
            return
        try:
            self.tracker.measure_heights(paired[1])  # on a thread of its own: the estimate times it
            self.outputs.add_views(*paired)
        except Exception:  # as in a tick: a bug must not take the loop with it
            self._failed_between_ticks("measuring a frame's heights")


def serve_compute(conn: Connection, spec: ComputeSpec) -> None:
    """The compute process's main: answer TickRequests until None arrives or the pipe closes."""
    # Signals are the daemon's to handle: it stops the modules, then tells this process to finish
    # (a terminal's Ctrl-C or systemd's stop reach the whole process group).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    leave_realtime()  # before its threads start: they inherit the class (clothd/drivers/priority.py)
    configure_logging()
    start_taichi(spec.taichi_arch)
    cv2.setNumThreads(spec.opencv_threads)
    bound_gil_wait()  # the tracking's thread beside the second view's heights
    compute = Compute(spec, spec.frame_source())
    try:
        compute.start()
    except ClothdError as err:  # the daemon says why it cannot start (a Foxglove port taken)
        conn.send(f"error: {err}")
        return
    conn.send("ready")
    try:
        while True:
            # Between requests, a frame is tracked as soon as it is there (polled: a request is taken the
            # moment it arrives, a frame within AHEAD_POLL_S).
            if spec.track_ahead and not conn.poll(AHEAD_POLL_S):
                compute.track_ahead()
                compute.measure_heights()
                continue
            try:
                req = conn.recv()
            except EOFError:
                return
            if req is None:
                return
            if isinstance(req, InForce):
                compute.in_force(req.commands, req.sent_mono_s)
                continue
            failed = False
            try:
                reply = compute.tick(req)
            except Exception:  # a bug in a stage must not take the loop, or the modules, with it
                log.exception("tick failed; stopping the modules, tracking afresh")
                reply, failed = compute.stop_reply(LoopState.FAULT), True
            conn.send(reply)
            if failed:  # once its all-stop is on its way
                compute.track_afresh()
            compute.after_reply()
            compute.measure_heights(wait=not spec.track_ahead)  # else between requests too, polled
    finally:
        compute.close()
