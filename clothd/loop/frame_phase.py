"""Locking the fixed tick's phase to the camera's frames, so that a frame is used as it arrives.

A frame that lands just after a tick started waits a whole period for the next one: with the tick's
phase left to chance the frame-to-command latency was 22-41 ms at p50, mostly waiting. The tick keeps
its fixed rate and its absolute deadlines; only its phase moves, by at most `max_shift_s` per tick,
until ticks start `lead_s` before the frames are due. The compute then waits for a due frame up to a
bound (`wait_until_s`), so a frame that arrives a little late is still used in its own tick.

The lock holds only while the camera's frame period is a whole number of ticks (15 frames/s with a 30 Hz
tick: every other tick gets a frame). Otherwise no phase suits every frame, and the tick runs free,
as it would without a lock.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

ARRIVALS_KEPT = 16  # the frames the period and phase are estimated over (about 1 s at 15 frames/s)
MIN_ARRIVALS = 6
WHOLE_TICKS_TOLERANCE = 0.05  # frame period / tick period within this of a whole number
# The gaps between arrivals at this percentile are taken as one frame period apart: a quarter of the frames
# on time finds the period with the rest dropped or late.
DROP_FREE_PCT = 25.0
GRID_PASSES = 2


class FramePhaseLock:
    def __init__(self, period_s: float, lead_s: float, max_shift_s: float, wait_s: float) -> None:
        self.period_s = period_s
        self.lead_s = lead_s
        self.max_shift_s = max_shift_s
        self.wait_s = wait_s
        self._arrivals: deque[float] = deque(maxlen=ARRIVALS_KEPT)
        # Set as frames arrive: the camera's period while locked, and when the last frame was due.
        self._frame_s: float | None = None
        self._last_due_s = 0.0

    def frame_arrived(self, t_mono_s: float) -> None:
        """A new frame the compute used, stamped when it arrived (the host's monotonic clock)."""
        if self._arrivals and t_mono_s <= self._arrivals[-1]:
            return
        self._arrivals.append(t_mono_s)
        self._frame_s = None
        if len(self._arrivals) < MIN_ARRIVALS:
            return
        t = np.asarray(self._arrivals)
        index = self._frame_index(np.diff(t))
        ticks = self._whole_ticks((t[-1] - t[0]) / index[-1])
        if ticks is not None:
            # The period is taken as exactly whole ticks: estimated from a few jittered gaps it was off by
            # tenths of a millisecond, which the frames back to the oldest kept multiplied into the phase.
            self._frame_s = ticks * self.period_s
            # The median phase: late frames are the usual jitter, and the compute waits for them.
            self._last_due_s = float(np.median(t + (index[-1] - index) * self._frame_s))

    @staticmethod
    def _frame_index(gaps_s: np.ndarray) -> np.ndarray:
        """Each kept arrival's frame number, counted from the oldest. A frame the camera dropped, or the
        compute skipped, leaves a gap of whole periods: counted as such, it neither lengthens the period
        nor shifts the phase."""
        frame_s = float(np.percentile(gaps_s, DROP_FREE_PCT))
        for _ in range(GRID_PASSES):  # the first guess runs short of early frames' gaps; the next, not
            periods_apart = np.maximum(1.0, np.round(gaps_s / frame_s))
            frame_s = float(np.median(gaps_s / periods_apart))
        return np.concatenate([[0.0], np.cumsum(periods_apart)])

    def _whole_ticks(self, frame_s: float) -> int | None:
        """How many ticks a frame period is, when it is a whole number of them; None otherwise."""
        ticks = frame_s / self.period_s
        whole = round(ticks)
        if whole < 1 or abs(ticks - whole) > WHOLE_TICKS_TOLERANCE * whole:
            return None
        return whole

    @property
    def locked(self) -> bool:
        return self._frame_s is not None

    def _next_due_s(self, after_s: float) -> float | None:
        """When the first frame not yet seen is due, on the arrivals' grid, at or after after_s - one
        period."""
        frame_s = self._frame_s
        if frame_s is None:
            return None
        due = self._last_due_s + frame_s
        if due < after_s - self.period_s:  # frames were missed (camera paused): the grid goes on
            due += math.ceil((after_s - self.period_s - due) / frame_s) * frame_s
        return due

    def shift_s(self, next_deadline_s: float) -> float:
        """How far to move the next deadline (positive: later) towards starting `lead_s` before a frame is
        due; bounded by max_shift_s, and 0 while not locked."""
        due = self._next_due_s(next_deadline_s)
        if due is None:
            return 0.0
        wanted = due - self.lead_s
        off = (next_deadline_s - wanted + self.period_s / 2) % self.period_s - self.period_s / 2
        return float(np.clip(-off, -self.max_shift_s, self.max_shift_s))

    def wait_until_s(self, tick_start_s: float) -> float | None:
        """Until when this tick's compute should wait for a frame it has not seen: set only when one is
        due within this tick's first `lead_s + wait_s`; None otherwise."""
        due = self._next_due_s(tick_start_s)
        if due is None or due > tick_start_s + self.lead_s + self.wait_s:
            return None
        return tick_start_s + self.lead_s + self.wait_s
