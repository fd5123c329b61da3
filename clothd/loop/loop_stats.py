"""Rolling timing statistics of the loop: per-stage compute time, tick jitter, frame-to-command latency,
and the daemon process's full garbage collections (each holds the GIL, so the tick waits it out)."""

from __future__ import annotations

import gc
import math
import time
from collections import deque

import numpy as np

WINDOW = 900  # 30 s at 30 Hz


class Window:
    """The last WINDOW samples of one quantity, in milliseconds."""

    def __init__(self) -> None:
        self._ms: deque[float] = deque(maxlen=WINDOW)

    def add_s(self, seconds: float) -> None:
        self._ms.append(seconds * 1e3)

    def __len__(self) -> int:
        return len(self._ms)

    def summary(self) -> dict[str, float | None]:
        if not self._ms:
            return {"mean_ms": None, "p50_ms": None, "p99_ms": None, "max_ms": None}
        a = np.fromiter(self._ms, float, len(self._ms))
        p50, p99 = np.percentile(a, [50, 99])
        return {
            "mean_ms": float(a.mean()),
            "p50_ms": float(p50),
            "p99_ms": float(p99),
            "max_ms": float(a.max()),
        }


class FrameToCommand:
    """Each frame's way from its arrival to its commands on the wire (milliseconds), in three parts that
    add up: `wait`, until the compute began on it; `compute`; and `delivery`, the reply's way back to the
    event loop and the send. Besides, `tick`: how long the frame waited for its tick to ask the compute
    (0 for a frame that arrived after the ask; with the frame tracked ahead, it overlaps the compute).
    The percentiles say how long; the tail's parts say why (the status keeps no samples)."""

    TAIL_PCT = 95.0  # the tail: the frames at or above this percentile of the whole way
    PARTS = ("wait", "compute", "delivery", "tick")

    def __init__(self) -> None:
        self.total = Window()
        self._parts_ms: deque[np.ndarray] = deque(maxlen=WINDOW)

    def add(
        self, arrived_s: float, asked_s: float | None, compute_s: tuple[float, float] | None, sent_s: float
    ) -> None:
        """A frame that arrived at arrived_s, asked for at asked_s, computed from compute_s[0] to [1] and
        sent at sent_s (host monotonic)."""
        self.total.add_s(sent_s - arrived_s)
        if compute_s is None or asked_s is None:
            return
        start, end = compute_s
        parts_s = (
            sent_s - arrived_s,
            start - arrived_s,
            end - start,
            sent_s - end,
            max(asked_s - arrived_s, 0),
        )
        self._parts_ms.append(1e3 * np.array(parts_s))

    def tail(self) -> dict[str, float | int | None]:
        """The mean of each part over the frames in the tail (TAIL_PCT and above)."""
        if not self._parts_ms:
            return {"frames": 0} | {f"{part}_ms": None for part in self.PARTS}
        a = np.array(self._parts_ms)
        tail = a[a[:, 0] >= np.percentile(a[:, 0], self.TAIL_PCT)]
        means = tail[:, 1:].mean(axis=0)
        return {"frames": len(tail)} | {
            f"{part}_ms": float(m) for part, m in zip(self.PARTS, means, strict=True)
        }


class LoopStats:
    SUMMARY_EVERY_S = 0.5  # percentiles over the windows are recomputed at most this often

    def __init__(self) -> None:
        self._summary: dict[str, object] | None = None
        self._summary_t_s = -math.inf
        self.stages: dict[str, Window] = {}
        self.jitter = Window()
        self.latency = FrameToCommand()
        self.gc_pause = Window()  # full collections in the daemon's process, any thread
        self._gc_start_s: float | None = None
        self.ticks = 0
        self.missed_ticks = 0
        self.compute_overruns = 0  # ticks that went out with the previous commands: compute not done
        self.starved_restarts = 0  # the tracker started afresh after the daemon was silent too long
        self.frame_locked = False  # the tick's phase follows the camera's frames

    def add_stages(self, timing_s: dict[str, float]) -> None:
        for name, seconds in timing_s.items():
            self.stages.setdefault(name, Window()).add_s(seconds)

    @property
    def missed_pct(self) -> float:
        due = self.ticks + self.missed_ticks
        return 100.0 * self.missed_ticks / due if due else 0.0

    def cached_summary(self) -> dict[str, object]:
        """summary() with the percentiles refreshed every SUMMARY_EVERY_S and the counters always fresh:
        the status is built every tick, on the event loop."""
        now = time.monotonic()
        if self._summary is None or now - self._summary_t_s >= self.SUMMARY_EVERY_S:
            self._summary, self._summary_t_s = self.summary(), now
        return {
            **self._summary,
            "ticks": self.ticks,
            "missed_ticks": self.missed_ticks,
            "missed_pct": self.missed_pct,
            "compute_overruns": self.compute_overruns,
            "starved_restarts": self.starved_restarts,
            "frame_locked": self.frame_locked,
        }

    def summary(self) -> dict[str, object]:
        return {
            "ticks": self.ticks,
            "missed_ticks": self.missed_ticks,
            "missed_pct": self.missed_pct,
            "compute_overruns": self.compute_overruns,
            "starved_restarts": self.starved_restarts,
            "frame_locked": self.frame_locked,
            "stages": {name: w.summary() for name, w in self.stages.items()},
            "jitter": self.jitter.summary(),
            "frame_to_command": self.latency.total.summary(),
            "frame_to_command_tail": self.latency.tail(),
            "gc_pause": self.gc_pause.summary(),
        }

    def watch_full_collections(self) -> None:
        """Time every full (generation 2) collection from now on; the daemon calls it once."""
        gc.callbacks.append(self._on_gc)

    def _on_gc(self, phase: str, info: dict[str, int]) -> None:
        # Collections never overlap: the collector holds the GIL from start to stop.
        if info["generation"] != 2:
            return
        if phase == "start":
            self._gc_start_s = time.perf_counter()
        elif self._gc_start_s is not None:
            self.gc_pause.add_s(time.perf_counter() - self._gc_start_s)
            self._gc_start_s = None
