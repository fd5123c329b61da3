"""What the stepper controller tells the module drives, shared between the firmware's process and the world's.

On a cell the controller is a microcontroller: nothing the PC runs can delay its answers. hwsim runs its
firmware in a process of its own (hwsim.firmware_process) for the same reason, and this bus is the wire
between that process and the world's: the firmware writes the drives' targets and its own counters, the
world reads them before each step. One small file, mapped by both; a sequence counter (odd while the
firmware writes) lets the reader take a consistent copy without a lock that either side could hold up.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hwsim.firmware import COUNTERS, Counters
from hwsim.table import Table

_SEQ, _TARGETS, _CUTS, _HEAD = 0, 1, 2, 3  # the sequence, then how often targets were set and drives cut
_BOOLS = ("estopped", "watchdog_tripped")


class DriveBus:
    """The drives' targets and the firmware's counters in a file mapped by both processes. One writer
    (the firmware's process), any number of readers."""

    def __init__(self, path: Path, n_modules: int, create: bool = False) -> None:
        self.path = path
        self.n_modules = n_modules
        size = _HEAD + 2 * n_modules + len(COUNTERS)
        if create:
            np.zeros(size).tofile(path)
        self._a = np.memmap(path, dtype=np.float64, mode="r+", shape=(size,))
        self._speed = slice(_HEAD, _HEAD + n_modules)
        self._heading = slice(_HEAD + n_modules, _HEAD + 2 * n_modules)
        self._counters = slice(_HEAD + 2 * n_modules, size)
        self._seen_targets = 0.0
        self._seen_cuts = 0.0

    # -- the firmware's side (hwsim.firmware.Drives) ----------------------------------------------------

    def command(self, speed_m_s: np.ndarray, heading_rad: np.ndarray) -> None:
        with self._writing():
            self._a[self._speed] = speed_m_s
            self._a[self._heading] = heading_rad
            self._a[_TARGETS] += 1

    def stop_all(self) -> None:
        with self._writing():
            self._a[self._speed] = 0.0
            self._a[_TARGETS] += 1

    def cut(self) -> None:
        with self._writing():
            self._a[self._speed] = 0.0
            self._a[_TARGETS] += 1
            self._a[_CUTS] += 1

    def publish(self, counters: Counters) -> None:
        """The firmware's counters (None is stored as NaN)."""
        values = [counters[name] for name in COUNTERS]
        with self._writing():
            self._a[self._counters] = [math.nan if v is None else float(v) for v in values]

    # -- the world's side ------------------------------------------------------------------------------

    def apply_to(self, table: Table, modules: np.ndarray | None = None) -> None:
        """Give the table what the firmware set since the last call: a cut stops every module it drives at
        once (drivers disabled, no ramp), new targets are commanded. `modules`: the table's module ids of
        the firmware's modules 0..n-1 (a controller of several); default, the table's own."""
        ids = np.arange(self.n_modules) if modules is None else modules
        a = self._snapshot()
        if a[_CUTS] != self._seen_cuts:
            self._seen_cuts = a[_CUTS]
            table.speed_m_s[ids] = 0.0
        if a[_TARGETS] != self._seen_targets:
            self._seen_targets = a[_TARGETS]
            table.command(ids, a[self._speed], a[self._heading])

    def counters(self) -> Counters:
        values = self._snapshot()[self._counters]
        out: Counters = {}
        for name, v in zip(COUNTERS, values, strict=True):
            if math.isnan(v):
                out[name] = None
            elif name in _BOOLS:
                out[name] = bool(v)
            elif name == "estop_t_mono_s":
                out[name] = float(v)
            else:
                out[name] = int(v)
        return out

    def _snapshot(self) -> np.ndarray:
        while True:
            seq = self._a[_SEQ]
            if seq % 2 == 0:
                copy = np.array(self._a)
                if self._a[_SEQ] == seq:
                    return copy
            time.sleep(0)  # the writer is mid-write: let it finish

    @contextlib.contextmanager
    def _writing(self) -> Iterator[None]:
        self._a[_SEQ] += 1  # odd: a reader that sees it waits
        try:
            yield
        finally:
            self._a[_SEQ] += 1
