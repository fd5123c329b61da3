"""The compute replies as soon as a tick's commands are ready; the tracker's upkeep, the recording and the
annotated view follow the reply, and what they make travels with the next one. Work done between ticks
(that, or tracking a frame ahead) that fails stops the modules at the next tick."""

from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from recorded_frames import compute_on, tick

from clothd.core.control import Setpoint
from clothd.core.messages import ModuleCommands
from clothd.loop.compute import Compute
from clothd.loop.compute_messages import TickRequest

pytestmark = pytest.mark.clock_free

IDLE = Setpoint("idle", None)


def _request(n_modules: int, want_view: bool) -> TickRequest:
    return TickRequest(IDLE, ModuleCommands.all_stop(n_modules), reset=False, want_view=want_view)


def test_the_view_asked_for_comes_with_the_next_reply(short_recording: Callable[[str], Path]) -> None:
    compute = compute_on(short_recording("translate"))
    n = compute.spec.layout.n_modules
    tick(compute, _request(n, want_view=False))  # initialises
    asked = compute.tick(_request(n, want_view=True))
    assert asked.view_jpeg is None and "view" not in asked.timing_s  # not drawn before the reply
    assert "tracker_resample" not in asked.timing_s
    compute.after_reply()
    following = tick(compute, _request(n, want_view=False))
    assert following.view_jpeg is not None
    view = cv2.imdecode(np.frombuffer(following.view_jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert view.shape[:2] == (480, 640)
    assert following.timing_s["view"] > 0 and "tracker_resample" in following.timing_s
    assert tick(compute, _request(n, want_view=False)).view_jpeg is None  # drawn once


@pytest.mark.parametrize(
    ("breaks", "between_ticks"),
    [("upkeep", Compute.after_reply), ("track", Compute.track_ahead)],
    ids=["after-the-reply", "tracking-ahead"],
)
def test_work_that_fails_between_ticks_stops_the_modules_at_the_next_tick(
    short_recording: Callable[[str], Path],
    monkeypatch: pytest.MonkeyPatch,
    breaks: str,
    between_ticks: Callable[[Compute], object],
) -> None:
    compute = compute_on(short_recording("translate"))
    n = compute.spec.layout.n_modules
    moving = TickRequest(
        Setpoint("move", np.array([0.02, 0.0, 0.0])), ModuleCommands.all_stop(n), reset=False, want_view=False
    )
    tick(compute, moving)  # initialises
    assert compute.tick(moving).commands.speed_m_s.any()  # its work after the reply is still to do

    def broken(*_: Any) -> Any:
        raise RuntimeError(f"{breaks} bug")

    monkeypatch.setattr(compute.tracker, breaks, broken)
    between_ticks(compute)
    monkeypatch.undo()
    stopped = tick(compute, moving)
    assert stopped.state == "fault" and stopped.halt_reason is not None
    assert not stopped.commands.speed_m_s.any()
    again = tick(compute, moving)  # the fault is answered once; the tracker starts afresh
    assert again.state == "tracking" and again.estimate is not None and again.estimate.tracking


def test_a_flows_frames_are_recorded_after_the_reply(
    short_recording: Callable[[str], Path], tmp_path: Path
) -> None:
    """In mode flow the pieces are tracked apart (no one estimate), and the frames and commands are still
    recorded, after each tick's reply."""
    compute = compute_on(short_recording("translate"), max_record_bytes=50_000_000)
    n = compute.spec.layout.n_modules
    flow = Setpoint("flow", None, started_mono_s=1.0)
    rec = tmp_path / "rec"
    first = TickRequest(flow, ModuleCommands.all_stop(n), reset=False, want_view=False, record_start=rec)
    reply = compute.tick(first)
    assert reply.pieces is not None and reply.recording is not None and reply.recording.frames == 0
    compute.after_reply()
    for _ in range(2):
        tick(compute, TickRequest(flow, ModuleCommands.all_stop(n), reset=False, want_view=False))
    stopped = TickRequest(IDLE, ModuleCommands.all_stop(n), reset=False, want_view=False, record_stop=True)
    assert tick(compute, stopped).recording.frames == 3
    assert len(list((rec / "frames").glob("*.png"))) == 3
    assert (rec / "commands.csv").read_text().count("\n") > n  # a row per module, then what changed
