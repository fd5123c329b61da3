"""The tick's phase follows the camera's frames: ticks come to start just before a frame is due, the
rate stays fixed, late frames do not drag the phase, and a camera whose period is not a whole number of
ticks leaves the tick free."""

from __future__ import annotations

import numpy as np

from clothd.loop.frame_phase import FramePhaseLock

PERIOD_S = 1 / 30
LEAD_S = 0.001
STEP_S = 0.001
WAIT_S = 0.012


def _run(
    frame_s: float, first_frame_s: float, ticks: int, late_s: np.ndarray | None = None
) -> tuple[FramePhaseLock, list[float], list[float | None]]:
    """The daemon's loop in simulated time: each tick, the frames that arrived before it started are
    reported (as the compute's replies report them), then the next deadline is moved. Returns the lock,
    the tick starts and each tick's wait bound."""
    lock = FramePhaseLock(PERIOD_S, LEAD_S, STEP_S, WAIT_S)
    arrivals = first_frame_s + frame_s * np.arange(int(ticks * PERIOD_S / frame_s) + 2)
    if late_s is not None:
        arrivals = arrivals + late_s[: len(arrivals)]
    starts: list[float] = []
    waits: list[float | None] = []
    next_t = 0.0
    reported = 0
    for _ in range(ticks):
        start = next_t
        starts.append(start)
        waits.append(lock.wait_until_s(start))
        bound = waits[-1] if waits[-1] is not None else start
        while reported < len(arrivals) and arrivals[reported] <= bound:
            lock.frame_arrived(float(arrivals[reported]))
            reported += 1
        next_t += PERIOD_S
        next_t += lock.shift_s(next_t)
    return lock, starts, waits


def test_ticks_come_to_start_a_lead_before_each_frame_at_a_fixed_rate() -> None:
    frame_s = 2 * PERIOD_S  # 15 frames/s, a 30 Hz tick
    lock, starts, waits = _run(frame_s, first_frame_s=0.0207, ticks=300)
    assert lock.locked
    periods = np.diff(starts)
    assert np.all(np.abs(periods - PERIOD_S) <= STEP_S + 1e-9)  # the phase moves a step per tick at most
    assert abs(np.mean(periods[-200:]) - PERIOD_S) < 1e-6  # and the rate is the tick's
    frames = 0.0207 + frame_s * np.arange(400)
    for start in starts[-100:]:
        ahead_s = frames[np.searchsorted(frames, start)] - start
        assert np.isclose(ahead_s, LEAD_S, atol=1e-4) or np.isclose(ahead_s, LEAD_S + PERIOD_S, atol=1e-4)
    due = [w is not None for w in waits[-100:]]
    assert due.count(True) == 50  # every other tick waits for its frame, the others do not
    assert all(w is None or np.isclose(w - s, LEAD_S + WAIT_S) for w, s in zip(waits, starts, strict=True))


def test_late_frames_do_not_drag_the_phase() -> None:
    rng = np.random.default_rng(3)
    late_s = np.where(rng.random(400) < 0.3, rng.uniform(0.0, 0.010, 400), 0.0)  # 30 % up to 10 ms late
    frame_s = 2 * PERIOD_S
    _, starts, _ = _run(frame_s, first_frame_s=0.005, ticks=300, late_s=late_s)
    frames = 0.005 + frame_s * np.arange(400)
    ahead_s = [frames[np.searchsorted(frames, s)] - s for s in starts[-100:]]
    ahead_s = [a for a in ahead_s if a < PERIOD_S / 2]  # the ticks with a frame due
    assert abs(np.median(ahead_s) - LEAD_S) <= 5e-4


def test_a_camera_off_the_ticks_grid_leaves_the_tick_free() -> None:
    lock, starts, waits = _run(frame_s=1 / 25, first_frame_s=0.01, ticks=120)
    assert not lock.locked
    assert np.allclose(np.diff(starts), PERIOD_S)
    assert all(w is None for w in waits)


def test_no_frames_no_lock() -> None:
    lock = FramePhaseLock(PERIOD_S, LEAD_S, STEP_S, WAIT_S)
    assert lock.shift_s(1.0) == 0.0 and lock.wait_until_s(1.0) is None and not lock.locked


def test_after_a_long_pause_the_grid_goes_on_where_the_frames_would_be() -> None:
    """Hours without a frame: the next frame is expected on the grid the camera kept, found at once (it
    was stepped to one frame period at a time, a cost that grew with the pause)."""
    frame_s = 2 * PERIOD_S
    lock, starts, _ = _run(frame_s, first_frame_s=0.0207, ticks=120)
    assert lock.locked
    t_s = starts[-1] + 8 * 3600.0
    wait_until = lock.wait_until_s(t_s)
    shift = lock.shift_s(t_s)
    assert abs(shift) <= STEP_S + 1e-9
    # A frame is due within the next frame period of t_s - one tick, on the grid of 0.0207 + k frame_s.
    grid = 0.0207 + frame_s * np.ceil((t_s - PERIOD_S - 0.0207) / frame_s)
    expected_wait = t_s + LEAD_S + WAIT_S if grid <= t_s + LEAD_S + WAIT_S else None
    assert wait_until == expected_wait


def test_a_camera_that_drops_frames_keeps_the_lock_and_its_grid() -> None:
    """A third of the frames dropped and the rest up to 12 ms late: the lock holds, and the ticks with a
    frame due start a lead before its median arrival (the median of the gaps, about 1.5 periods, had
    left the tick free)."""
    rng = np.random.default_rng(5)
    frame_s = 2 * PERIOD_S
    n = 400
    late_s = rng.uniform(0.0, 0.012, n)
    kept = rng.random(n) >= 1 / 3
    lock = FramePhaseLock(PERIOD_S, LEAD_S, STEP_S, WAIT_S)
    frames = 0.005 + frame_s * np.arange(n)
    arrivals = (frames + late_s)[kept]
    starts: list[float] = []
    next_t, reported = 0.0, 0
    for _ in range(600):
        starts.append(next_t)
        while reported < len(arrivals) and arrivals[reported] <= next_t:
            lock.frame_arrived(float(arrivals[reported]))
            reported += 1
        next_t += PERIOD_S
        next_t += lock.shift_s(next_t)
    assert lock.locked
    due = frames + np.median(late_s)  # the grid's phase is the median arrival's
    ahead_s = [due[np.searchsorted(due, s)] - s for s in starts[-200:]]
    ahead_s = [a for a in ahead_s if a < PERIOD_S / 2]
    assert abs(np.median(ahead_s) - LEAD_S) <= 1e-3
