"""The stepper link on a line slower than its ticks (a controller that stops reading, as QEMU's emulated
USART does under load): COMMANDs do not queue up stale behind each other, and the e-stop discards what
has not left yet and goes next on the line, intact after a delimiter, ahead of every stale COMMAND.

A raw controller on a pty: it answers the HELLO by hand, then reads nothing until the test says so."""

from __future__ import annotations

import asyncio
import contextlib
import os
import struct
import tty
from collections.abc import AsyncIterator, Callable

import numpy as np

from clothd.config import StepperConfig
from clothd.core.messages import ModuleCommands
from clothd.drivers import wire
from clothd.drivers.stepper_link import StepperLink

N = 48
TICKS = 300  # 300 COMMANDs of 201 bytes: more than the pty holds (about 20 kB on Linux)
# What a pty's reader still gets after the writer's tcflush: the reader's line discipline keeps its
# 4 kB read buffer (N_TTY_BUF_SIZE), which no flush on the writer's side reaches.
PTY_READ_BUFFER = 4096
T = wire.MsgType


class RawController:
    """The master end of a pty, read frame by frame when the test asks."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.splitter = wire.FrameSplitter()
        self.bytes_read = 0
        self.frames: list[tuple[int, wire.Message | None]] = []  # bytes read before the frame ended

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)

    def _drain(self) -> None:
        with contextlib.suppress(BlockingIOError):
            while data := os.read(self.master, 4096):
                for k, byte in enumerate(data):
                    for packet in self.splitter.feed(bytes([byte])):
                        try:
                            msg: wire.Message | None = wire.decode(packet)
                        except wire.WireError:
                            msg = None  # a frame the link's discard cut midway
                        self.frames.append((self.bytes_read + k, msg))
                self.bytes_read += len(data)

    async def read_until(self, check: Callable[[], bool], timeout_s: float = 10.0) -> None:
        """Read what arrives until check() holds."""
        loop = asyncio.get_running_loop()
        arrived = asyncio.Event()
        loop.add_reader(self.master, arrived.set)
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    self._drain()
                    if check():
                        return
                    arrived.clear()
                    await arrived.wait()
        finally:
            loop.remove_reader(self.master)

    def of_type(self, msg_type: int) -> list[tuple[int, wire.Message]]:
        return [(at, m) for at, m in self.frames if m is not None and m.type == msg_type]


@contextlib.asynccontextmanager
async def _connected(ctrl: RawController) -> AsyncIterator[StepperLink]:
    # Never answered after the HELLO: lost only after 21 s of silence, well past the test.
    cfg = StepperConfig(port=ctrl.path, ack_timeout_s=1.0, max_retransmits=20)
    link = StepperLink(cfg, N)
    task = asyncio.create_task(link.run())
    try:
        await ctrl.read_until(lambda: bool(ctrl.of_type(T.HELLO)))
        _, hello = ctrl.of_type(T.HELLO)[0]
        os.write(ctrl.master, wire.encode(T.HELLO_ACK, hello.seq, struct.pack("<BH", 1, N) + b"raw"))
        async with asyncio.timeout(10):
            while not link.connected:
                await asyncio.sleep(0.01)
        yield link
    finally:
        await link.stop()
        task.cancel()


def _speed(mm_s: int) -> ModuleCommands:
    return ModuleCommands(np.full(N, mm_s * 1e-3), np.zeros(N))


def _speed_of(msg: wire.Message) -> int:
    return round(struct.unpack("<h", msg.payload[2:4])[0] * wire.SPEED_UNIT_M_S * 1e3)


def _commands(ctrl: RawController) -> int:
    """The COMMANDs read, a retransmit (the same seq) once."""
    return len({m.seq for _, m in ctrl.of_type(T.COMMAND)})


async def _ticks_on_a_blocked_line(link: StepperLink) -> int:
    """The ticks whose command was dropped, the one before staying in force."""
    kept = 0
    for k in range(TICKS):
        handover = link.send_commands(_speed(k + 1))
        kept += not handover.fresh.any() and handover.running.all()
        await asyncio.sleep(0)  # the transport's writer gets its turn, as between two ticks
    return kept


def test_commands_wait_for_the_line_instead_of_queuing_stale() -> None:
    async def body() -> None:
        ctrl = RawController()
        try:
            async with _connected(ctrl) as link:
                kept = await _ticks_on_a_blocked_line(link)
                # The line held what it could take; every later tick found it busy, wrote nothing, and
                # said that the command before stays in force.
                assert link.counters.sent < TICKS - 100
                assert kept == TICKS - (link.counters.sent - 1)  # less the HELLO
                await ctrl.read_until(lambda: _commands(ctrl) == link.counters.sent - 1)  # less the HELLO
                # Free again: the next tick's command goes out, right behind what the line held.
                assert link.send_commands(_speed(TICKS + 1)).sent
                await ctrl.read_until(lambda: _speed_of(ctrl.of_type(T.COMMAND)[-1][1]) == TICKS + 1)
                assert _commands(ctrl) == link.counters.sent - 1  # and nothing else was
        finally:
            ctrl.close()

    asyncio.run(body())


def test_the_estop_discards_the_commands_not_yet_gone_and_goes_next_intact() -> None:
    async def body() -> None:
        ctrl = RawController()
        try:
            async with _connected(ctrl) as link:
                await _ticks_on_a_blocked_line(link)
                written = len(wire.encode(T.COMMAND, 0, bytes(2 + 4 * N))) * link.counters.sent
                link.estop()
                await ctrl.read_until(lambda: bool(ctrl.of_type(T.ESTOP)))
                at, _ = ctrl.of_type(T.ESTOP)[0]
                # Only what the reader's side of the pty already held came before it: the rest of the
                # ~20 kB written was discarded, and the ESTOP decoded whole after its delimiter.
                assert at < 2 * PTY_READ_BUFFER < written
                assert not [m for a, m in ctrl.frames if a > at and (m is None or m.type == T.COMMAND)]
        finally:
            ctrl.close()

    asyncio.run(body())
