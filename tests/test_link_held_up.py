"""The link's own thread held up is not the controller's silence.

On a loaded PC the loop's thread can wake from its wait for the port late: it waits for the GIL, which a
preempted thread of the API holds. The controller's answer that came meanwhile is then in the port, not
yet read, when the deadline is judged. A selector that sleeps once after a wait that returned nothing
stands in for that wait: the same place, the same order of what the event loop then does."""

from __future__ import annotations

import asyncio
import selectors
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from firmware_links import until

from clothd.config import StepperConfig
from clothd.core.messages import ModuleCommands
from clothd.drivers.stepper_link import StepperLink
from clothd.tools.pty_relay import PtyRelay
from hwsim.firmware import Firmware, TableDrives
from hwsim.scenario import TableSpec
from hwsim.table import Table

N = 48
ANSWER_DELAY_S = 0.02  # each way: the answer comes 40 ms after the command, inside the 50 ms ack timeout
HELD_UP_S = 0.2  # past the 150 ms the link allows an answer, inside the controller's 250 ms watchdog


class HeldUpSelector(selectors.DefaultSelector):
    """Once armed, the next wait that returns no event keeps the thread this long before it goes on;
    `on_hold()` is called as the hold begins."""

    def __init__(self, on_hold: Callable[[], None]) -> None:
        super().__init__()
        self.hold_s = 0.0
        self.on_hold = on_hold

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        events = super().select(timeout)
        if self.hold_s and not events:
            self.on_hold()
            time.sleep(self.hold_s)
            self.hold_s = 0.0
        return list(events)


def test_an_answer_that_came_while_the_link_was_held_up_is_read_before_the_link_is_judged(
    tmp_path: Path,
) -> None:
    table = Table(TableSpec())
    fw = Firmware(TableDrives(table), tmp_path / "ttyCELL")
    fw.start()
    relay = PtyRelay(fw.link_path, tmp_path / "ttyRELAY")
    acked_at_hold: list[int] = []
    link: StepperLink | None = None
    selector = HeldUpSelector(lambda: acked_at_hold.append(link.counters.acked if link else -1))
    forward = ModuleCommands(np.full(N, 0.03), np.zeros(N))

    async def body() -> None:
        nonlocal link
        cfg = StepperConfig(port=str(relay.link_path), reconnect_initial_s=0.05, reconnect_max_s=0.2)
        link = StepperLink(cfg, N)
        task = asyncio.create_task(link.run())
        try:
            await until(lambda: link.connected)
            relay.delay_s = ANSWER_DELAY_S
            for _ in range(5):
                assert link.send_commands(forward).sent
                await asyncio.sleep(1 / 30)
            selector.hold_s = HELD_UP_S
            assert link.send_commands(forward).sent
            await asyncio.sleep(HELD_UP_S + 0.2)
            assert link.counters.losses == 0 and link.connected, link.counters
            # The hold (past the link's 150 ms) came while the command's answer was still to be read.
            assert len(acked_at_hold) == 1 and link.counters.acked > acked_at_hold[0]
        finally:
            await link.stop()
            task.cancel()

    try:
        with asyncio.Runner(loop_factory=lambda: asyncio.SelectorEventLoop(selector)) as runner:
            runner.run(asyncio.wait_for(body(), 10))
    finally:
        relay.close()
        fw.stop()
