"""The daemon's loop against fakes at its ports (a ModuleLink and a compute process): a fault that stops
the modules drops the move, and nothing moves again until a new setpoint; moves are refused unless the
e-stop is clear, the link up and the cloth tracked inside the workspace."""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections import deque
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from recorded_frames import compute_on

from clothd.config import AreaConfig, CellConfig
from clothd.core.control import Setpoint
from clothd.core.drive_script import DriveScript
from clothd.core.ekf import UpdateStats
from clothd.core.messages import Estimate, ModuleCommands
from clothd.core.module_calibration import ModuleCalibration
from clothd.core.module_check import ModuleCalibrationEntry
from clothd.core.workspace import Workspace
from clothd.drivers.ports import ControllerFault, FrameSourceHealth, Handover, LinkCounters
from clothd.errors import InvalidRequestError, RequestError, UnreachableTargetError
from clothd.loop.compute_messages import InForce, TickReply, TickRequest
from clothd.loop.daemon import Daemon
from clothd.loop.daemon_settings import DaemonSettings
from clothd.outputs.recorder import RecordingStatus

N = 48
PERIOD_S = 0.01
MOVING = ModuleCommands(np.full(N, 0.05), np.zeros(N))


class FakeLink:
    """A ModuleLink that records what it was told."""

    def __init__(self) -> None:
        self.state = "connected"
        self.last_error: str | None = None
        self.firmware: str | None = "fake"
        self.counters = LinkCounters()
        self.faults: deque[ControllerFault] = deque()
        self.controller_estopped = False
        self.sent: list[ModuleCommands] = []
        self.busy = np.zeros(N, dtype=bool)  # modules whose controller's line still holds the last command
        self._estopped = False

    @property
    def connected(self) -> bool:
        return self.state == "connected"

    @property
    def estopped(self) -> bool:
        return self._estopped

    def send_commands(self, commands: ModuleCommands) -> Handover:
        if not self.connected or self._estopped:
            return Handover.of(False, False, N)
        self.sent.append(commands)
        return Handover(np.ones(N, dtype=bool), ~self.busy)

    def estop(self) -> None:
        self._estopped = True

    def estop_clear(self) -> None:
        self._estopped = False

    async def run(self) -> None:
        await asyncio.Event().wait()

    async def stop(self) -> None:
        self.sent.append(ModuleCommands.all_stop(N))


def _estimate(pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Estimate:
    p = np.array(pose)
    outline = np.array([[-0.125, -0.1], [0.125, -0.1], [0.125, 0.1], [-0.125, 0.1]]) + p[:2]
    empty = np.zeros((0, 2))
    return Estimate(
        frame_t_s=0.0,
        status="tracking",
        pose=p,
        pose_cov=np.eye(3) * 1e-8,
        nodes_m=None,
        outline_m=outline,
        cloth_size_m=(0.25, 0.2),
        feature_id=np.zeros(0, np.int64),
        meas_px=empty,
        pred_px=empty,
        stats=UpdateStats(0, 0, 0.0),
    )


class FakeCompute:
    """Answers each request at once with what `answer` makes of it; `silent` holds the answers back."""

    def __init__(self) -> None:
        self.requests: list[TickRequest] = []
        self.in_force: list[ModuleCommands] = []  # what the daemon said it had sent, after each tick
        self.silent = False
        self.state = "tracking"
        self.camera_state = "streaming"
        self.halt_reason: str | None = None
        self.recording: RecordingStatus | None = None  # as a recorder would say, from the requests

    async def start(self) -> None:
        pass

    async def stop(self) -> None:
        pass

    def tell_in_force(self, in_force: InForce) -> None:
        self.in_force.append(in_force.commands)

    def request(self, req: TickRequest) -> asyncio.Future[TickReply]:
        self.requests.append(req)
        fut: asyncio.Future[TickReply] = asyncio.get_running_loop().create_future()
        if not self.silent:
            fut.set_result(self._answer(req))
        return fut

    def _answer(self, req: TickRequest) -> TickReply:
        if req.record_stop and self.recording is not None:  # the stop first, as the compute does
            self.recording = dataclasses.replace(self.recording, active=False)
        if req.record_start is not None:
            self.recording = RecordingStatus(True, str(req.record_start), 0, 0, 10**9, None)
        moving = req.setpoint.mode != "idle" and self.state == "tracking" and self.halt_reason is None
        commands = MOVING if moving else ModuleCommands.all_stop(N)
        est = _estimate() if self.state == "tracking" else None
        camera = FrameSourceHealth(self.camera_state, self.state != "camera_lost", None, 0)
        return TickReply(
            state=self.state,
            estimate=est,
            commands=commands,
            new_frame=True,
            frame_t_mono_s=None,
            camera=camera,
            halt_reason=self.halt_reason,
            recording=self.recording,
        )


Scenario = Callable[[Daemon, FakeLink, FakeCompute], Awaitable[None]]


def _run(
    scenario: Scenario,
    max_stale_ticks: int = 3,
    estimates_shape: bool = True,
    module_calibration: ModuleCalibration | None = None,
    flow_ready: bool = False,
    camera_opening: bool = False,
    notifier: Any = None,
) -> None:
    link, compute = FakeLink(), FakeCompute()
    if camera_opening:  # from the start, no frame: the camera's first opening under way
        compute.state, compute.camera_state = "camera_lost", "connecting"
    settings = DaemonSettings(
        period_s=PERIOD_S,
        max_stale_ticks=max_stale_ticks,
        n_modules=N,
        workspace=Workspace.of_cell(CellConfig()),
        view_period_s=0.1,
        recording_dir=Path("/nonexistent"),
        camera_source="fake",
        link_port="fake",
        estimates_shape=estimates_shape,
        module_calibration=module_calibration,
        flow_ready=flow_ready,
    )
    daemon = Daemon(settings, link, compute, notifier)  # type: ignore[arg-type]

    async def main() -> None:
        loop_task = asyncio.create_task(daemon.run())
        try:
            await _ticks(daemon, 3)
            await scenario(daemon, link, compute)
        finally:
            daemon.stop()
            await asyncio.wait_for(loop_task, 2)

    asyncio.run(asyncio.wait_for(main(), 20))


async def _ticks(daemon: Daemon, n: int) -> None:
    """Wait for n more ticks of the loop (counted, not timed: a loaded machine only makes it slower)."""
    target = daemon.stats.ticks + n
    while daemon.stats.ticks < target:
        await asyncio.sleep(PERIOD_S / 2)


def _moving(link: FakeLink) -> bool:
    return bool(link.sent) and bool(link.sent[-1].speed_m_s.any())


def _move(daemon: Daemon) -> None:
    daemon.set_setpoint("move", np.array([0.05, 0.0, 0.0]))


@pytest.mark.parametrize(
    ("fault", "expected"),
    [
        ("camera_lost", "camera"),
        ("tracking_lost", "not tracked"),
        ("fault", "compute failed"),
        ("link", "stepper link"),
        ("workspace", "workspace"),
    ],
)
def test_no_restart_after_a_fault_until_a_new_setpoint(fault: str, expected: str) -> None:
    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        _move(daemon)
        await _ticks(daemon, 3)
        assert _moving(link)
        if fault == "link":
            link.state = "disconnected"
        elif fault == "workspace":
            compute.halt_reason = "at the workspace's edge: the cloth would reach ..."
        else:
            compute.state = fault
            compute.halt_reason = {
                "camera_lost": "the camera is lost",
                "tracking_lost": "the cloth is not tracked",
            }.get(fault, f"the compute failed ({fault})")
        before_unix_s = time.time()
        await _ticks(daemon, 3)
        after_unix_s = time.time()
        assert daemon.setpoint.mode == "idle"
        assert daemon.halt_reason is not None and expected in daemon.halt_reason
        assert daemon.status is not None and daemon.status.halt_reason == daemon.halt_reason
        halt_t = daemon.status.halt_t_unix_s  # stamped by one of these ticks
        assert halt_t is not None and before_unix_s <= halt_t <= after_unix_s
        # The fault goes away: the camera is back, the link reconnects. Nothing moves by itself.
        link.state, compute.state, compute.halt_reason = "connected", "tracking", None
        link.sent.clear()
        await _ticks(daemon, 5)
        assert link.sent and not any(c.speed_m_s.any() for c in link.sent)
        assert all(r.setpoint.mode == "idle" for r in compute.requests[-4:])
        # A new setpoint, and only that, moves the cloth again.
        _move(daemon)
        await _ticks(daemon, 3)
        assert _moving(link) and daemon.halt_reason is None and daemon.halt_t_unix_s is None

    _run(scenario)


def test_a_compute_that_stops_answering_stops_the_modules() -> None:
    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        _move(daemon)
        await _ticks(daemon, 3)
        assert _moving(link)
        compute.silent = True
        told = len(compute.in_force)
        await _ticks(daemon, 8)
        assert daemon.stats.compute_overruns >= 3
        assert not link.sent[-1].speed_m_s.any()  # stale commands are not resent past max_stale_ticks
        assert daemon.setpoint.mode == "idle" and "compute has not answered" in (daemon.halt_reason or "")
        # Nothing more is sent to a compute still at its request: a hung one would fill the pipe until
        # the send blocked the tick.
        assert len(compute.in_force) == told

    _run(scenario, max_stale_ticks=3)


def test_moves_are_refused_unless_tracked_linked_clear_and_on_the_table() -> None:
    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        with pytest.raises(UnreachableTargetError, match="workspace"):
            daemon.set_setpoint("move", np.array([5.0, -5.0, 0.0]))
        with pytest.raises(UnreachableTargetError, match="workspace"):  # the centre is on, a corner is not
            daemon.set_setpoint("move", np.array([0.2, 0.0, 0.0]))
        daemon.estop()
        with pytest.raises(RequestError, match="emergency stop"):
            _move(daemon)
        daemon.estop_clear()
        link.state = "starting"  # not up yet since the start
        with pytest.raises(RequestError, match=r"^starting$"):
            _move(daemon)
        link.state = "disconnected"
        with pytest.raises(RequestError, match="stepper link"):
            _move(daemon)
        link.state = "connected"
        compute.state = "tracking_lost"
        await _ticks(daemon, 3)
        with pytest.raises(RequestError, match="not tracked"):
            daemon.set_setpoint("hold", None)
        compute.state = "tracking"
        await _ticks(daemon, 3)
        _move(daemon)
        assert daemon.setpoint.mode == "move" and daemon.setpoint.pose is not None
        np.testing.assert_array_equal(daemon.setpoint.pose, [0.05, 0.0, 0.0])

    _run(scenario)


def test_a_camera_still_opening_at_start_is_starting_not_lost() -> None:
    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        assert daemon.state == "starting"
        compute.camera_state = "lost"  # its opening failed
        await _ticks(daemon, 1)
        assert daemon.state == "camera_lost"
        compute.state, compute.camera_state = "tracking", "streaming"
        await _ticks(daemon, 1)
        compute.state, compute.camera_state = "camera_lost", "connecting"  # reopening after a loss
        await _ticks(daemon, 1)
        assert daemon.state == "camera_lost"

    _run(scenario, camera_opening=True)


@pytest.mark.parametrize("flow_ready", [True, False])
def test_flow_needs_no_tracked_cloth_but_the_link_the_e_stop_and_its_trackers_built(flow_ready: bool) -> None:
    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        compute.state = "tracking_lost"  # an empty table: nothing tracked
        await _ticks(daemon, 3)
        daemon.estop()
        with pytest.raises(RequestError, match="emergency stop"):
            daemon.set_setpoint("flow", None)
        daemon.estop_clear()
        if not flow_ready:
            with pytest.raises(RequestError, match="warm_at_start"):
                daemon.set_setpoint("flow", None)
            assert daemon.setpoint.mode == "idle"
            return
        daemon.set_setpoint("flow", None)
        assert daemon.setpoint.mode == "flow" and daemon.setpoint.pose is None
        # Asked again while flowing, the flow goes on (the compute starts afresh on a new setpoint time);
        # asked anew after another setpoint, it is a new flow.
        asked = daemon.setpoint.started_mono_s
        daemon.set_setpoint("flow", None)
        assert daemon.setpoint.started_mono_s == asked
        daemon.set_setpoint("idle", None)
        daemon.set_setpoint("flow", None)
        assert daemon.setpoint.started_mono_s > asked

    _run(scenario, flow_ready=flow_ready)


@pytest.mark.parametrize("estimates_shape", [True, False])
def test_flatten_holds_the_pose_and_needs_a_tracker_that_sees_the_shape(estimates_shape: bool) -> None:
    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        await _ticks(daemon, 3)
        if not estimates_shape:
            with pytest.raises(RequestError, match="mesh tracker"):
                daemon.set_setpoint("flatten", None)
            assert daemon.setpoint.mode == "idle"
            return
        daemon.set_setpoint("flatten", None)
        assert daemon.setpoint.mode == "flatten" and daemon.setpoint.pose is not None
        est = daemon.latest.estimate if daemon.latest else None
        assert est is not None
        np.testing.assert_array_equal(daemon.setpoint.pose, est.pose)

    _run(scenario, estimates_shape=estimates_shape)


def test_the_model_input_is_what_went_out_on_the_wire() -> None:
    """While e-stopped nothing goes out, so the tracker is told the modules stand still."""

    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        _move(daemon)
        await _ticks(daemon, 3)
        assert compute.requests[-1].commands_in_force.speed_m_s.any()
        daemon.estop()
        await _ticks(daemon, 3)
        assert not compute.requests[-1].commands_in_force.speed_m_s.any()

    _run(scenario)


def test_a_cloth_at_the_workspace_edge_is_stopped_in_closed_loop(
    short_recording: Callable[[str], Path],
) -> None:
    """The compute's own check: a moving cloth whose estimated outline leaves the workspace is stopped,
    and the reply says why (the daemon then drops the move)."""
    tight = CellConfig(workspace=AreaConfig(x_min_m=-0.1, x_max_m=0.1, y_min_m=-0.08, y_max_m=0.08))
    compute = compute_on(short_recording("translate"), cell=tight)
    stopped = ModuleCommands.all_stop(N)
    move = Setpoint("move", np.array([0.05, 0.0, 0.0]))
    first = compute.tick(TickRequest(move, stopped, reset=False, want_view=False))
    assert first.estimate is not None and first.estimate.tracking
    reply = compute.tick(TickRequest(move, stopped, reset=False, want_view=False))
    assert reply.halt_reason is not None and "workspace" in reply.halt_reason
    assert not reply.commands.speed_m_s.any()
    # The same cloth on the default workspace (the belts less 2 cm) moves.
    roomy = compute_on(short_recording("translate"))
    roomy.tick(TickRequest(move, stopped, reset=False, want_view=False))
    reply = roomy.tick(TickRequest(move, stopped, reset=False, want_view=False))
    assert reply.halt_reason is None and reply.commands.speed_m_s.any()


class _Notes:
    """systemd's notifications, as the daemon sends them."""

    def __init__(self) -> None:
        self.sent: list[str] = []

    def ready(self) -> None:
        self.sent.append("READY")

    def watchdog(self) -> None:
        self.sent.append("WATCHDOG")

    def stopping(self) -> None:
        self.sent.append("STOPPING")


def test_systemd_hears_ready_and_the_watchdog_while_the_loop_and_compute_run_whatever_the_hardware() -> None:
    """No cloth on the table, the camera lost, the link down: reported and retried by the daemon, who is
    ready and alive all the same (a restart would cure none of it). A compute that stops answering feeds
    the watchdog no more: that, a restart cures."""
    notes = _Notes()

    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        assert notes.sent[0] == "READY"  # no frame yet, the camera still opening
        link.state = "disconnected"
        await _ticks(daemon, 2)
        fed = notes.sent.count("WATCHDOG")
        await _ticks(daemon, 150)  # over a second of ticks: the watchdog is fed once a second at most
        assert notes.sent.count("READY") == 1 and notes.sent.count("WATCHDOG") > fed
        compute.silent = True
        await _ticks(daemon, 2)
        fed = notes.sent.count("WATCHDOG")
        await _ticks(daemon, 150)
        assert notes.sent.count("WATCHDOG") == fed

    _run(scenario, camera_opening=True, notifier=notes)


def test_the_compute_is_told_what_went_out_after_every_tick() -> None:
    """It tracks frames that arrive before the next request with these commands (compute.track_ahead):
    what was sent; the command before where a controller's line was still busy with it (the new one was
    dropped); all-stop while the link moves nothing."""

    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        _move(daemon)
        await _ticks(daemon, 3)
        np.testing.assert_array_equal(compute.in_force[-1].speed_m_s, MOVING.speed_m_s)
        link.busy[: N // 2] = True
        daemon.set_setpoint("idle", None)
        await _ticks(daemon, 2)
        kept = compute.in_force[-1].speed_m_s
        np.testing.assert_array_equal(kept[: N // 2], MOVING.speed_m_s[: N // 2])
        assert not kept[N // 2 :].any()
        link.busy[:] = False
        await _ticks(daemon, 2)
        assert not compute.in_force[-1].speed_m_s.any()
        _move(daemon)
        await _ticks(daemon, 2)
        link.estop()
        await _ticks(daemon, 2)
        assert not compute.in_force[-1].speed_m_s.any()

    _run(scenario)


def _drive_script(speed_m_s: float, duration_s: float, modules: dict[str, object]) -> DriveScript:
    entry = {"t_s": 0.0, "modules": modules, "speed_m_s": speed_m_s, "heading_rad": 0.0}
    return DriveScript.model_validate({"duration_s": duration_s, "timeline": [entry]})


def test_a_drive_script_is_refused_off_limits_stops_on_a_fault_and_ends_idle() -> None:
    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        with pytest.raises(UnreachableTargetError, match=r"could carry the cloth 300 mm: .*workspace"):
            daemon.set_setpoint("drive", None, _drive_script(0.1, 3.0, {"all": True}))
        with pytest.raises(InvalidRequestError, match=r"exceeds the modules' 0\.2 m/s"):
            daemon.set_setpoint("drive", None, _drive_script(0.5, 0.1, {"ids": [27]}))
        daemon.set_setpoint("drive", None, _drive_script(0.02, 2.0, {"ids": [27]}))
        await _ticks(daemon, 3)
        assert daemon.setpoint.mode == "drive" and compute.requests[-1].setpoint.drive is not None
        assert _moving(link)
        compute.halt_reason = "the camera is lost"
        await _ticks(daemon, 3)
        assert daemon.setpoint.mode == "idle" and daemon.halt_reason == "the camera is lost"
        compute.halt_reason = None
        daemon.set_setpoint("drive", None, _drive_script(0.02, 0.05, {"ids": [27]}))
        assert daemon.halt_reason is None
        await _ticks(daemon, 10)  # 0.1 s: played to its end
        assert daemon.setpoint.mode == "idle" and daemon.halt_reason is None

    _run(scenario)


def test_a_module_calibration_corrects_what_goes_out_not_what_is_in_force() -> None:
    wrong = ModuleCalibrationEntry(module=3, reversed=True, heading_offset_deg=10.0, speed_scale=0.8)

    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        _move(daemon)
        await _ticks(daemon, 3)
        sent, in_force = link.sent[-1], compute.in_force[-1]
        np.testing.assert_array_equal(in_force.speed_m_s, MOVING.speed_m_s)  # the tracker's input: as asked
        assert sent.speed_m_s[3] == pytest.approx(0.05 / 0.8) and sent.speed_m_s[2] == pytest.approx(0.05)
        assert sent.heading_rad[3] == pytest.approx(np.pi - np.radians(10.0))

    _run(scenario, module_calibration=ModuleCalibration.of([wrong], N))


def test_a_recording_may_start_as_soon_as_the_last_one_was_told_to_stop(tmp_path: Path) -> None:
    """No tick between the stop and the start, so the status still shows the first recording: the start
    is taken all the same, and reaches the compute with or after the stop."""

    async def scenario(daemon: Daemon, link: FakeLink, compute: FakeCompute) -> None:
        daemon.start_recording(tmp_path / "first")
        await _ticks(daemon, 2)
        assert compute.recording is not None and compute.recording.active
        daemon.stop_recording()
        daemon.start_recording(tmp_path / "second")  # RequestError while the first was shown active
        await _ticks(daemon, 2)
        assert compute.recording.active and Path(str(compute.recording.dir)).name == "second"
        stop_at = next(k for k, r in enumerate(compute.requests) if r.record_stop)
        start_at = next(k for k, r in enumerate(compute.requests) if r.record_start == tmp_path / "second")
        assert stop_at <= start_at

    _run(scenario)
