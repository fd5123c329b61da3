"""Several stepper controllers as one ModuleLink: a table larger than one board (`stepper.controllers`).

Each controller has its own StepperLink: its own port, handshake, sequence numbers, retransmits and
reconnects. A tick's commands are split by module: controller k is sent the speeds and headings of the
module ids its `modules` lists, in that order, which is its own numbering 0..len-1
(docs/serial-protocol.md, "Several controllers"). One controller drives every module in id order.

Safety, whatever the number of controllers:
- a link lost stops every module on every other controller at once (an all-stop written as it is
  lost), and until every link is up again each tick sends the others all-stop, never the commands: a
  cloth held by half its modules is torn, not stopped;
- the e-stop goes to every controller, each repeating its ESTOP until acknowledged;
- a controller's FAULT is reported with the cell's module id, and the daemon (`on_fault`) stops every
  module and drops the move.
"""

from __future__ import annotations

import asyncio
import functools
import itertools
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from clothd.core.messages import ModuleCommands
from clothd.drivers.ports import ControllerFault, Handover, LinkCounters
from clothd.drivers.stepper_link import FAULTS_KEPT, StepperLink

WHOLE_BOARD = 0xFFFF  # a FAULT's module for the whole board


@dataclass(frozen=True)
class Controller:
    """One controller of the group: its link and the cell's module ids by its own index."""

    link: StepperLink
    modules: np.ndarray  # int, the cell's id of the controller's module i

    @property
    def port(self) -> str:
        return self.link.cfg.port

    def part(self, commands: ModuleCommands) -> ModuleCommands:
        return ModuleCommands(commands.speed_m_s[self.modules], commands.heading_rad[self.modules])

    def cell_module(self, local: int) -> int:
        return int(self.modules[local]) if 0 <= local < len(self.modules) else local


class LinkGroup:
    """The ModuleLink over every controller's StepperLink; methods return at once, as the links' do."""

    def __init__(self, controllers: Sequence[tuple[StepperLink, Sequence[int]]], n_modules: int) -> None:
        self.controllers = [Controller(link, np.asarray(m, dtype=int)) for link, m in controllers]
        self.n_modules = n_modules
        self.on_fault: Callable[[ControllerFault], None] | None = None
        self._faults: deque[ControllerFault] = deque(maxlen=FAULTS_KEPT)
        for c in self.controllers:
            c.link.on_fault = functools.partial(self._fault, c)
            c.link.on_lost = self._stop_the_others

    # -- the state, taken together ------------------------------------------------------------------

    @property
    def state(self) -> str:
        """connected when every link is; starting while any has never been up; else disconnected while
        any was lost, connecting while the others connect."""
        states = [c.link.state for c in self.controllers]
        for state in ("starting", "disconnected", "connecting"):
            if state in states:
                return state
        return "connected"

    @property
    def connected(self) -> bool:
        return all(c.link.connected for c in self.controllers)

    @property
    def last_error(self) -> str | None:
        """The first controller's error that has one; with several, the port says whose."""
        for c in self.controllers:
            if c.link.last_error is not None:
                several = len(self.controllers) > 1
                return f"{c.port}: {c.link.last_error}" if several else c.link.last_error
        return None

    @property
    def firmware(self) -> str | None:
        names = list(dict.fromkeys(c.link.firmware for c in self.controllers if c.link.firmware))
        return ", ".join(names) or None

    @property
    def counters(self) -> LinkCounters:
        """Every link's counters summed, their round trips pooled."""
        out = LinkCounters(rtt_ms=deque(maxlen=256 * len(self.controllers)))
        for c in self.controllers:
            k = c.link.counters
            out.sent += k.sent
            out.retransmitted += k.retransmitted
            out.acked += k.acked
            out.invalid += k.invalid
            out.nacked += k.nacked
            out.faults += k.faults
            out.reconnects += k.reconnects
            out.losses += k.losses
        out.rtt_ms.extend(itertools.chain.from_iterable(c.link.counters.rtt_ms for c in self.controllers))
        return out

    @property
    def faults(self) -> deque[ControllerFault]:
        """Every controller's newest faults, oldest first, with the cell's module ids."""
        return self._faults

    @property
    def estopped(self) -> bool:
        return any(c.link.estopped for c in self.controllers)

    @property
    def controller_estopped(self) -> bool:
        """Any controller says its e-stop is set."""
        return any(c.link.controller_estopped for c in self.controllers)

    # -- commands -------------------------------------------------------------------------------------

    def send_commands(self, commands: ModuleCommands) -> Handover:
        """Each controller its modules' commands; with any link down, every connected one all-stop and
        nothing running (the lost one's watchdog stops its own)."""
        if not self.connected:
            self._stop_the_others()
            return Handover.of(False, False, self.n_modules)
        running = np.zeros(self.n_modules, dtype=bool)
        fresh = np.zeros(self.n_modules, dtype=bool)
        for c in self.controllers:
            handover = c.link.send_commands(c.part(commands))
            running[c.modules] = handover.running
            fresh[c.modules] = handover.fresh
        return Handover(running, fresh)

    def estop(self) -> None:
        """Every controller's ESTOP written now, each repeated until acknowledged."""
        for c in self.controllers:
            c.link.estop()

    def estop_clear(self) -> None:
        for c in self.controllers:
            c.link.estop_clear()

    async def run(self) -> None:
        await asyncio.gather(*(c.link.run() for c in self.controllers))

    async def stop(self) -> None:
        """Every controller's modules stopped, then every port closed."""
        await asyncio.gather(*(c.link.stop() for c in self.controllers))

    # -- faults -------------------------------------------------------------------------------------

    def _fault(self, controller: Controller, fault: ControllerFault) -> None:
        module = fault.module if fault.module == WHOLE_BOARD else controller.cell_module(fault.module)
        text = fault.text if len(self.controllers) == 1 else f"{fault.text} ({controller.port})".lstrip()
        report = ControllerFault(fault.t_unix_s, fault.code, module, text)
        self._faults.append(report)
        if self.on_fault is not None:
            self.on_fault(report)

    def _stop_the_others(self) -> None:
        """All-stop to every controller still connected."""
        for c in self.controllers:
            if c.link.connected:
                c.link.send_commands(ModuleCommands.all_stop(len(c.modules)))
