"""Between requests the compute tracks a frame as it arrives, with the commands the daemon said it had
sent; the tick that follows uses that estimate and only controls (clothd/loop/compute.py `track_ahead`)."""

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from recorded_frames import compute_on, tick

from clothd.core.control import Setpoint
from clothd.core.messages import ModuleCommands
from clothd.loop.compute import Compute
from clothd.loop.compute_messages import TickRequest

IDLE = Setpoint("idle", None)


def _counting(compute: Compute, monkeypatch: pytest.MonkeyPatch) -> list[ModuleCommands | None]:
    """The commands each tracker.track call was given, from now on."""
    calls: list[ModuleCommands | None] = []
    track = compute.tracker.track

    def counted(image: np.ndarray, frame_t_s: float, commands: ModuleCommands | None, views: Any = ()) -> Any:
        calls.append(commands)
        return track(image, frame_t_s, commands, views)

    monkeypatch.setattr(compute.tracker, "track", counted)
    return calls


def test_a_frame_tracked_ahead_is_what_the_next_tick_controls_on(
    short_recording: Callable[[str], Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    compute = compute_on(short_recording("translate"))
    n = compute.spec.layout.n_modules
    stopped = ModuleCommands.all_stop(n)
    tick(compute, TickRequest(IDLE, stopped, reset=False, want_view=False))  # initialises
    calls = _counting(compute, monkeypatch)
    sent = ModuleCommands(np.full(n, 0.03), np.full(n, np.pi / 2))
    compute.in_force(sent, time.monotonic())
    compute.track_ahead()
    compute.track_ahead()  # one at a time: the next waits for a tick to take this one
    assert len(calls) == 1 and calls[0] is sent
    asked_s = time.monotonic()
    reply = tick(compute, TickRequest(IDLE, sent, reset=False, want_view=False))
    assert len(calls) == 1  # the tick tracked nothing more
    assert reply.new_frame and reply.estimate is not None and reply.estimate.tracking
    assert reply.compute_mono_s is not None and reply.compute_mono_s[0] < asked_s  # began before the ask
    assert "tracker_klt" in reply.timing_s
    # The next tick, with no frame tracked ahead, tracks its own.
    reply = tick(compute, TickRequest(IDLE, sent, reset=False, want_view=False))
    assert len(calls) == 2 and reply.new_frame


def test_a_reset_tracks_the_frame_afresh_and_nothing_is_tracked_before_the_first_request(
    short_recording: Callable[[str], Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    compute = compute_on(short_recording("translate"))
    n = compute.spec.layout.n_modules
    calls = _counting(compute, monkeypatch)
    compute.track_ahead()
    assert calls == []  # what the modules do is not known yet
    stopped = ModuleCommands.all_stop(n)
    tick(compute, TickRequest(IDLE, stopped, reset=False, want_view=False))
    compute.track_ahead()
    assert len(calls) == 2
    reply = tick(compute, TickRequest(IDLE, stopped, reset=True, want_view=False))
    assert len(calls) == 3  # the reset threw the frame tracked ahead away with the tracker's state
    assert reply.new_frame and reply.estimate is not None


def test_after_the_daemon_fell_silent_past_the_bound_the_tracker_starts_afresh_and_says_so(
    short_recording: Callable[[str], Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    compute = compute_on(short_recording("translate"), starved_s=0.05)
    n = compute.spec.layout.n_modules
    sent = ModuleCommands(np.full(n, 0.03), np.full(n, np.pi / 2))
    reply = tick(compute, TickRequest(IDLE, sent, reset=False, want_view=False))
    assert reply.starved_ms is None  # the first request: nothing was heard before it
    resets: list[bool] = []
    monkeypatch.setattr(compute.tracker, "reset", lambda: resets.append(True))
    calls = _counting(compute, monkeypatch)
    compute.in_force(sent, time.monotonic())
    time.sleep(0.02)
    reply = tick(compute, TickRequest(IDLE, sent, reset=False, want_view=False))
    assert reply.starved_ms is None and resets == []  # within the bound: tracked on
    time.sleep(0.1)  # the daemon starved: the modules may have stopped on the controller's watchdog
    compute.track_ahead()
    assert calls == [sent], "a frame captured after the silence is not tracked with commands now unknown"
    reply = tick(compute, TickRequest(IDLE, sent, reset=False, want_view=False))
    assert reply.starved_ms is not None and reply.starved_ms >= 100
    assert resets == [True] and reply.new_frame
