"""The ports the daemon's shell talks to hardware through. The real drivers (camera.py, stepper_link.py)
implement them; tests and tools may plug in anything that does the same.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from clothd.core.messages import ModuleCommands


@dataclass(frozen=True)
class CameraFrame:
    index: int  # counts frames since the source started, across reconnects
    t_mono_s: float  # host monotonic time of capture
    image: np.ndarray  # BGR


KEPT_FRAMES = 3  # frames a source keeps for `nearest` (200 ms at 15 frames/s)
RATE_WINDOW_S = 5.0  # a source's frame rate and longest gap are taken over this much of its recent frames


@dataclass(frozen=True)
class FrameSourceHealth:
    state: str  # connecting | streaming | lost
    healthy: bool  # a frame fresher than the source's stale limit is there
    last_error: str | None
    reconnects: int
    fps: float | None = None  # frames delivered per second over RATE_WINDOW_S; None before two
    longest_gap_ms: float | None = None  # the longest wait between two of those frames


class FrameSource(Protocol):
    """A camera: frames arrive on their own; `latest` hands out the newest and never blocks."""

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def latest(self) -> CameraFrame | None:
        """The newest frame, or None when there is none fresh enough."""

    def newer_than(self, index: int, timeout_s: float) -> CameraFrame | None:
        """The newest frame once one with an index past `index` is there, waiting up to timeout_s;
        otherwise what `latest` gives."""

    def nearest(self, t_mono_s: float) -> CameraFrame | None:
        """Of the last KEPT_FRAMES frames, the one that arrived nearest t_mono_s (None when `latest` is):
        a pair taken after the camera's next frame came still finds its own."""

    def health(self) -> FrameSourceHealth: ...


@dataclass(frozen=True)
class ControllerFault:
    """A fault the controller reported, stamped with the host's wall clock when it arrived."""

    t_unix_s: float
    code: int
    module: int
    text: str


@dataclass
class LinkCounters:
    sent: int = 0
    retransmitted: int = 0
    acked: int = 0
    invalid: int = 0
    nacked: int = 0
    faults: int = 0
    reconnects: int = 0
    losses: int = 0  # times the link was declared lost (no answer, a read or write error)
    rtt_ms: deque[float] = field(default_factory=lambda: deque(maxlen=256))

    def snapshot(self) -> dict[str, float | int | None]:
        rtt = np.asarray(self.rtt_ms) if self.rtt_ms else None
        return {
            "sent": self.sent,
            "retransmitted": self.retransmitted,
            "acked": self.acked,
            "invalid": self.invalid,
            "nacked": self.nacked,
            "faults": self.faults,
            "reconnects": self.reconnects,
            "losses": self.losses,
            "rtt_p50_ms": None if rtt is None else float(np.median(rtt)),
            "rtt_p99_ms": None if rtt is None else float(np.percentile(rtt, 99)),
        }


@dataclass(frozen=True)
class Handover:
    """What one tick's send left running on the modules, per module. Not `running`: its link is down or
    e-stopped, and it stops (the controller's watchdog or e-stop holds it). Running but not `fresh`: it
    keeps the last command it was sent (its controller's line was still busy with it: a fresh command is
    dropped rather than queued behind it)."""

    running: np.ndarray  # bool per module
    fresh: np.ndarray  # bool per module: took this tick's command

    @classmethod
    def of(cls, running: bool, fresh: bool, n_modules: int) -> Handover:
        return cls(np.full(n_modules, running), np.full(n_modules, running and fresh))

    @property
    def sent(self) -> bool:
        """Every module took this tick's command."""
        return bool(self.fresh.all())

    @property
    def stopped(self) -> bool:
        """No module runs."""
        return not self.running.any()

    def in_force(self, commands: ModuleCommands, before: ModuleCommands) -> ModuleCommands:
        """The commands the modules run after this send: `commands` where fresh, `before` where kept, and
        stopped where not running."""
        speed = np.where(self.fresh, commands.speed_m_s, before.speed_m_s)
        heading = np.where(self.fresh, commands.heading_rad, before.heading_rad)
        return ModuleCommands(np.where(self.running, speed, 0.0), np.where(self.running, heading, 0.0))


class ModuleLink(Protocol):
    """The stepper controllers (one, or several as one: drivers/link_group.py). `run` is the connection
    task; every other method returns at once.

    The emergency stop is latched here, in one place: `estopped` is true from `estop()` until
    `estop_clear()`, and no command goes out meanwhile. `on_fault`, when set, is called with each fault a
    controller reports, as it arrives."""

    on_fault: Callable[[ControllerFault], None] | None

    @property
    def state(self) -> str:
        """starting (never up since the start) | connecting | connected | disconnected"""

    @property
    def last_error(self) -> str | None: ...

    @property
    def firmware(self) -> str | None: ...

    @property
    def counters(self) -> LinkCounters: ...

    @property
    def faults(self) -> deque[ControllerFault]:
        """The newest few, oldest first."""

    @property
    def connected(self) -> bool: ...

    @property
    def estopped(self) -> bool: ...

    @property
    def controller_estopped(self) -> bool:
        """The controller says its own e-stop is set."""

    def send_commands(self, commands: ModuleCommands) -> Handover:
        """Send one tick's commands; what runs on the modules after it."""

    def estop(self) -> None: ...

    def estop_clear(self) -> None: ...

    async def run(self) -> None: ...

    async def stop(self) -> None:
        """Stop every module, then close."""
