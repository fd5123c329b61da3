"""The stepper link against hwsim's firmware on a real pty: handshake, commands, acknowledgements,
e-stop, the controller watchdog, faults, unplugging, and controllers that answer nonsense."""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import struct
import threading
import time
import tty
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path

import numpy as np
import pytest

from clothd.config import StepperConfig
from clothd.core.messages import ModuleCommands
from clothd.drivers import wire
from clothd.drivers.stepper_link import ESTOP_REPEAT_S, StepperLink
from clothd.tools.pty_relay import PtyRelay
from hwsim.firmware import FAULT_WATCHDOG, WATCHDOG_S, Firmware, TableDrives
from hwsim.scenario import TableSpec
from hwsim.table import Table

N = 48


def _forward(speed_m_s: float) -> ModuleCommands:
    """Every module at speed_m_s along world +x."""
    return ModuleCommands(np.full(N, speed_m_s), np.zeros(N))


def test_frames_round_trip_and_corruption_is_caught() -> None:
    payload = wire.command_payload(np.array([0.1, -0.05]), np.array([0.5, -3.0]))
    packet = wire.encode(wire.MsgType.COMMAND, 513, payload)
    assert packet.count(0) == 1 and packet.endswith(b"\x00")  # COBS: the delimiter is the only zero
    frame = wire.decode(packet[:-1])
    assert (frame.type, frame.seq, frame.payload) == (wire.MsgType.COMMAND, 513, payload)
    bad = bytearray(packet[:-1])
    bad[3] ^= 0x10
    with pytest.raises(wire.WireError):
        wire.decode(bytes(bad))
    splitter = wire.FrameSplitter()
    assert splitter.feed(b"junk\x00" + packet[:5]) == [b"junk"]
    assert splitter.feed(packet[5:]) == [packet[:-1]]


Body = Callable[[Firmware, Table], Awaitable[None]]


def _with_firmware(tmp_path: Path, body: Body) -> None:
    """Run body against hwsim's firmware on a fresh pty, driving a table of N modules."""
    table = Table(TableSpec())
    fw = Firmware(TableDrives(table), tmp_path / "ttyCELL")
    fw.start()
    try:
        asyncio.run(asyncio.wait_for(body(fw, table), 20))
    finally:
        fw.stop()


async def _until(check: Callable[[], bool], timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, "condition not reached in time"
        await asyncio.sleep(0.01)


def _link(port: Path, n: int = N, **kw: object) -> StepperLink:
    cfg = StepperConfig(port=str(port), reconnect_initial_s=0.05, reconnect_max_s=0.2, **kw)
    return StepperLink(cfg, n)


@contextlib.asynccontextmanager
async def _running(link: StepperLink) -> AsyncIterator[StepperLink]:
    task = asyncio.create_task(link.run())
    try:
        yield link
    finally:
        task.cancel()


def test_commands_reach_the_modules_and_are_acknowledged(tmp_path: Path) -> None:
    async def body(fw: Firmware, table: Table) -> None:
        async with _running(_link(fw.link_path)) as link:
            await _until(lambda: link.connected)
            assert link.firmware and link.firmware.startswith("hwsim-fw")
            heading = np.linspace(-3, 3, N)
            for _ in range(5):
                assert link.send_commands(ModuleCommands(np.full(N, 0.05), heading)).sent
                await asyncio.sleep(0.02)
            await _until(lambda: link.counters.acked >= 5)
            np.testing.assert_allclose(table.cmd_speed_m_s, 0.05, atol=1e-4)
            np.testing.assert_allclose(table.cmd_heading_rad, heading, atol=2e-4)
            assert link.counters.snapshot()["rtt_p50_ms"] is not None
            # A negative speed is the same motion with the belt turned half round.
            link.send_commands(_forward(-0.02))
            await _until(lambda: abs(table.cmd_speed_m_s[0] - 0.02) < 1e-4)
            assert abs(abs(table.cmd_heading_rad[0]) - np.pi) < 1e-3
            await link.stop()

    _with_firmware(tmp_path, body)


def test_estop_cuts_the_drives_and_refuses_commands_until_cleared(tmp_path: Path) -> None:
    async def body(fw: Firmware, table: Table) -> None:
        async with _running(_link(fw.link_path)) as link:
            await _until(lambda: link.connected)
            link.send_commands(_forward(0.1))
            await _until(lambda: table.cmd_speed_m_s[0] > 0)
            table.speed_m_s[:] = 0.1  # the modules are running
            link.estop()
            await _until(lambda: link.controller_estopped)
            assert fw.estopped and not table.speed_m_s.any() and not table.cmd_speed_m_s.any()
            assert link.send_commands(_forward(0.1)).stopped  # the host holds back too
            link.estop_clear()
            await _until(lambda: not fw.estopped)
            await _until(
                lambda: (
                    link.send_commands(ModuleCommands(np.full(N, 0.03), np.zeros(N))).sent
                    and table.cmd_speed_m_s[0] > 0
                )
            )
            await link.stop()

    _with_firmware(tmp_path, body)


def test_an_estop_cleared_while_the_link_is_down_is_cleared_on_the_controller_when_it_is_back(
    tmp_path: Path,
) -> None:
    async def body(fw: Firmware, table: Table) -> None:
        async with _running(_link(fw.link_path)) as link:
            await _until(lambda: link.connected)
            link.estop()
            await _until(lambda: link.controller_estopped)
            fw.unplug(0.5)
            await _until(lambda: not link.connected)
            link.estop_clear()  # the operator clears it while the cable is out
            await _until(lambda: link.connected, timeout_s=5.0)
            await _until(lambda: not fw.estopped)
            await _until(lambda: link.send_commands(_forward(0.03)).sent and table.cmd_speed_m_s[0] > 0)
            await link.stop()

    _with_firmware(tmp_path, body)


def test_watchdog_stops_the_modules_when_the_host_goes_silent(tmp_path: Path) -> None:
    async def body(fw: Firmware, table: Table) -> None:
        link = _link(fw.link_path)
        async with _running(link):
            await _until(lambda: link.connected)
            # A host that has only said HELLO has driven nothing: its silence is no fault (start-up).
            await asyncio.sleep(3 * WATCHDOG_S)
            assert not fw.watchdog_tripped and not link.faults
            link.send_commands(_forward(0.1))
            await _until(lambda: table.cmd_speed_m_s[0] > 0)
            # The host stops talking (a hung or killed daemon): within the watchdog the modules stop.
            await _until(lambda: fw.watchdog_tripped, timeout_s=1.0)
            assert not table.cmd_speed_m_s.any()
            await _until(lambda: bool(link.faults))
            assert link.faults[0].code == FAULT_WATCHDOG

    _with_firmware(tmp_path, body)


def test_link_comes_back_after_an_unplug(tmp_path: Path) -> None:
    async def body(fw: Firmware, table: Table) -> None:
        async with _running(_link(fw.link_path)) as link:
            await _until(lambda: link.connected)
            fw.unplug(0.3)
            await _until(lambda: not link.connected)
            assert link.last_error and link.state in ("disconnected", "connecting")
            await _until(lambda: link.connected, timeout_s=5.0)
            assert link.counters.reconnects >= 1

    _with_firmware(tmp_path, body)


def test_a_port_that_appears_late_is_the_start_not_a_reconnect(tmp_path: Path) -> None:
    async def body(fw: Firmware, table: Table) -> None:
        port = tmp_path / "by-id"
        async with _running(_link(port)) as link:
            await asyncio.sleep(0.4)  # several tries (0.05 s doubling to 0.2 s) at a port not there yet
            assert link.state == "starting" and link.last_error
            port.symlink_to(fw.link_path)
            await _until(lambda: link.connected)
            assert link.counters.reconnects == 0 and not link.faults

    _with_firmware(tmp_path, body)


def test_wrong_module_count_is_a_clear_error(tmp_path: Path) -> None:
    async def body(fw: Firmware, table: Table) -> None:
        async with _running(_link(fw.link_path, n=12)) as link:
            await _until(lambda: link.last_error is not None)
            assert "drives 48 modules" in (link.last_error or "") and not link.connected

    _with_firmware(tmp_path, body)


def _against_a_device(
    tmp_path: Path, name: str, serve: Callable[[int], None], body: Callable[[Path], Awaitable[None]]
) -> None:
    """body(port) against a device on a fresh pty, its other end answered by serve(master) on a thread
    (until the pty closes)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    port = tmp_path / name
    port.symlink_to(os.ttyname(slave))
    threading.Thread(target=serve, args=(master,), daemon=True).start()
    try:
        asyncio.run(asyncio.wait_for(body(port), 20))
    finally:
        os.close(master)
        os.close(slave)


def _answering_hellos(answer: Callable[[int, int], None]) -> Callable[[int], None]:
    """A device that calls answer(master, seq) for each HELLO it reads, and ignores everything else."""

    def serve(master: int) -> None:
        splitter = wire.FrameSplitter()
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:
                return
            for packet in splitter.feed(data):
                msg = wire.decode(packet)
                if msg.type == wire.MsgType.HELLO:
                    answer(master, msg.seq)

    return serve


def test_a_controller_that_answers_garbage_gets_a_clear_error(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)

    def babble(master: int) -> None:  # answers every read with noise, zeros included (frame delimiters)
        while True:
            try:
                os.read(master, 4096)
                os.write(master, rng.integers(0, 256, 64, dtype=np.uint8).tobytes())
            except OSError:
                return

    async def body(port: Path) -> None:
        async with _running(_link(port, handshake_timeout_s=0.1)) as link:
            await _until(lambda: "not in the clothd stepper protocol" in (link.last_error or ""))
            assert not link.connected

    _against_a_device(tmp_path, "ttyGARBAGE", babble, body)


@pytest.mark.parametrize("answer", ["ack", "short"], ids=["an-ack", "a-short-hello-ack"])
def test_a_controller_that_answers_hello_wrongly_gets_a_clear_error_and_is_tried_again(
    tmp_path: Path, answer: str
) -> None:
    """A HELLO answered by a plain ACK or a HELLO_ACK too short to read: said so, and tried again (the link
    task ended on it, unseen, leaving the link `starting` for good)."""
    hellos: list[int] = []

    def answer_wrongly(master: int, seq: int) -> None:
        hellos.append(seq)
        kind, payload = (wire.MsgType.ACK, b"\x00") if answer == "ack" else (wire.MsgType.HELLO_ACK, b"\x01")
        os.write(master, wire.encode(kind, seq, payload))

    async def body(port: Path) -> None:
        async with _running(_link(port)) as link:
            await _until(lambda: "answered HELLO wrongly" in (link.last_error or ""))
            first_tries = len(hellos)
            await _until(lambda: len(hellos) > first_tries)  # the link task lives on, and tries again
            assert not link.connected

    _against_a_device(tmp_path, "ttyWRONG", _answering_hellos(answer_wrongly), body)


# -- faults injected between the link and the controller (a pty relay) ---------------------------------


async def _tick(
    link: StepperLink, commands: ModuleCommands, until: Callable[[], bool], timeout_s: float = 5.0
) -> None:
    """Send commands every 33 ms, as the daemon's loop does, until `until()` holds."""
    deadline = time.monotonic() + timeout_s
    while not until():
        assert time.monotonic() < deadline, "condition not reached in time"
        link.send_commands(commands)
        await asyncio.sleep(1 / 30)


def _with_relay(
    tmp_path: Path,
    body: Callable[[Firmware, Table, PtyRelay, StepperLink], Awaitable[None]],
    **link_cfg: object,
) -> None:
    """Run body with a link to the firmware through a relay that can drop or delay either way."""

    async def outer(fw: Firmware, table: Table) -> None:
        relay = PtyRelay(fw.link_path, tmp_path / "ttyRELAY")
        try:
            async with _running(_link(relay.link_path, **link_cfg)) as link:
                await _until(lambda: link.connected)
                await body(fw, table, relay, link)
        finally:
            relay.close()

    _with_firmware(tmp_path, outer)


def test_a_controller_that_stops_answering_is_declared_lost_and_stopped(tmp_path: Path) -> None:
    """Replies dropped: every tick's fresh command used to hide the silence, so nothing was ever
    retransmitted and the link stayed 'connected'. The age of the last answer now decides."""

    async def body(fw: Firmware, table: Table, relay: PtyRelay, link: StepperLink) -> None:
        await _tick(link, _forward(0.05), lambda: table.cmd_speed_m_s[0] > 0.04)
        relay.drop_replies = True
        await _tick(link, _forward(0.05), lambda: not link.connected)
        assert relay.dropped_bytes["replies"] > 0
        # Retransmits were really sent and counted (a loaded machine may wake past one of them).
        assert link.counters.losses == 1 and 1 <= link.counters.retransmitted <= link.cfg.max_retransmits
        assert "no answer" in (link.last_error or "")
        # The controller still hears: the all-stop written on the way out reached it.
        await _until(lambda: not table.cmd_speed_m_s.any(), timeout_s=1.0)
        relay.drop_replies = False
        await _until(lambda: link.connected, timeout_s=5.0)

    _with_relay(tmp_path, body)


def test_commands_that_never_arrive_lose_the_link_and_the_watchdog_stops_the_modules(tmp_path: Path) -> None:
    async def body(fw: Firmware, table: Table, relay: PtyRelay, link: StepperLink) -> None:
        await _tick(link, _forward(0.05), lambda: table.cmd_speed_m_s[0] > 0.04)
        relay.drop_commands = True
        await _tick(link, _forward(0.05), lambda: not link.connected)
        assert link.counters.losses == 1
        await _until(lambda: fw.watchdog_tripped and not table.cmd_speed_m_s.any(), timeout_s=1.0)

    _with_relay(tmp_path, body)


def test_late_answers_are_retransmitted_for_not_lost(tmp_path: Path) -> None:
    """80 ms each way: past the 50 ms acknowledgement timeout, so the newest command goes again, but well
    inside the 300 ms this link allows (ack_timeout_s x (max_retransmits + 1))."""

    async def body(fw: Firmware, table: Table, relay: PtyRelay, link: StepperLink) -> None:
        relay.delay_s = 0.08
        await _tick(link, _forward(0.03), lambda: link.counters.retransmitted >= 3)
        await _tick(link, _forward(0.03), lambda: link.counters.acked >= 30)
        assert link.connected and link.counters.losses == 0

    _with_relay(tmp_path, body, ack_timeout_s=0.05, max_retransmits=5)


def test_a_held_estop_keeps_the_link_alive_without_false_faults(tmp_path: Path) -> None:
    """While e-stopped the host sends no command; it used to go silent, and the controller's watchdog
    reported a fault that did not happen. PINGs now keep it fed and the link's liveness measured."""

    async def body(fw: Firmware, table: Table, relay: PtyRelay, link: StepperLink) -> None:
        await _tick(link, _forward(0.05), lambda: table.cmd_speed_m_s[0] > 0.04)
        link.estop()
        held_until = time.monotonic() + 0.8  # three watchdog periods
        await _tick(link, _forward(0.05), lambda: time.monotonic() > held_until)
        assert fw.estopped and not fw.watchdog_tripped
        assert link.connected and not link.faults and link.counters.losses == 0

    _with_relay(tmp_path, body)


def test_an_estop_waiting_on_a_late_controller_is_repeated_at_its_pace_not_flooded(tmp_path: Path) -> None:
    """Answers late (past the ack timeout, inside the deadline) when the e-stop comes: with no command
    left to retransmit, the link used to wake on every pass of its loop for the overdue retransmit and
    repeat the ESTOP each time, thousands a second, burying the controller's answers under them."""

    async def body(fw: Firmware, table: Table, relay: PtyRelay, link: StepperLink) -> None:
        await _tick(link, _forward(0.05), lambda: table.cmd_speed_m_s[0] > 0.04)
        relay.drop_replies = True  # the controller hears; its answers are late
        sent_before = link.counters.sent
        link.estop()
        held_s = 0.15  # the ack timeout (50 ms) passes, the deadline (300 ms here) does not
        await asyncio.sleep(held_s)
        repeats = link.counters.sent - sent_before - 1
        relay.drop_replies = False
        # One each ESTOP_REPEAT_S; a loaded machine wakes the link less often, never more.
        assert 0 < repeats <= held_s / ESTOP_REPEAT_S + 2, repeats
        await _until(lambda: link.controller_estopped)
        assert fw.estopped and not table.cmd_speed_m_s.any()

    _with_relay(tmp_path, body, max_retransmits=5)


def test_answers_from_before_a_clear_made_while_the_link_was_down_do_not_latch_it_again(
    tmp_path: Path,
) -> None:
    """The operator clears while the controller cannot be heard; the answers that were on their way (a
    backlog on a slow line, showing the old latch) arrive as the link comes back, before the clear goes.
    They used to latch the host again, and the clear was never sent."""

    async def body(fw: Firmware, table: Table, relay: PtyRelay, link: StepperLink) -> None:
        link.estop()
        await _until(lambda: fw.estopped and link.controller_estopped)
        relay.drop_replies = True
        await _tick(link, _forward(0.03), lambda: not link.connected)
        link.estop_clear()
        acked_before = link.counters.acked
        stale = wire.DELIMITER + wire.encode(wire.MsgType.ACK, 999, bytes([wire.FLAG_ESTOP]))
        # Read while the link is not up: a port being opened drops what waited in it, so sent until read.
        deadline = time.monotonic() + 3.0
        while link.counters.acked == acked_before:
            assert time.monotonic() < deadline, "the stale answer was never read"
            relay.inject(stale)
            await asyncio.sleep(0.1)
        assert not link.connected
        relay.drop_replies = False
        await _tick(
            link, _forward(0.03), lambda: not fw.estopped and table.cmd_speed_m_s[0] > 0.02, timeout_s=5.0
        )
        assert not link.estopped and not link.faults, (link.state, link.faults, link.counters)

    _with_relay(tmp_path, body)


def test_a_clear_lost_with_the_link_is_sent_again_when_it_is_back(tmp_path: Path) -> None:
    """A clear written as the link went down may never have reached the controller, which then refuses
    every command; the refusals answer messages sent after the clear, so they used to count for nothing,
    and the host and the controller stayed apart for good."""

    async def body(fw: Firmware, table: Table, relay: PtyRelay, link: StepperLink) -> None:
        link.estop()
        await _until(lambda: fw.estopped and link.controller_estopped)
        relay.drop_commands = True
        link.estop_clear()  # written, never heard
        await _tick(link, _forward(0.03), lambda: not link.connected)
        assert fw.estopped
        relay.drop_commands = False
        await _tick(
            link, _forward(0.03), lambda: not fw.estopped and table.cmd_speed_m_s[0] > 0.02, timeout_s=5.0
        )
        assert not link.estopped

    _with_relay(tmp_path, body)


def test_a_clear_lost_on_a_live_line_is_settled_by_the_next_answer(tmp_path: Path) -> None:
    """The ESTOP_CLEAR never reaches the controller, the link stays up: the answers to what went after it
    show the latch. Waiting for the clear's own answer, which never comes, the host used to count them for
    nothing, and sent commands the controller refused, for good, with no fault reported."""

    async def body(fw: Firmware, table: Table, relay: PtyRelay, link: StepperLink) -> None:
        reported: list[int] = []
        link.on_fault = lambda fault: reported.append(fault.code)
        link.estop()
        await _until(lambda: fw.estopped and link.controller_estopped)
        relay.drop_commands = True
        link.estop_clear()
        await _until(lambda: relay.dropped_bytes["commands"] > 0)
        relay.drop_commands = False
        await _tick(link, _forward(0.03), lambda: link.estopped)
        assert fw.estopped and not table.cmd_speed_m_s.any()
        assert reported == [wire.FAULT_ESTOP_INPUT] and link.connected

    _with_relay(tmp_path, body)


def test_overlong_frames_count_as_invalid(tmp_path: Path) -> None:
    async def body(fw: Firmware, table: Table, relay: PtyRelay, link: StepperLink) -> None:
        before = link.counters.invalid
        relay.inject(b"\x55" * (wire.MAX_FRAME_BYTES + 500))  # no delimiter: dropped whole
        await _tick(link, _forward(0.0), lambda: link.counters.invalid > before)
        assert link.connected

    _with_relay(tmp_path, body)


def test_a_hello_starts_a_new_session_whose_first_command_is_applied(tmp_path: Path) -> None:
    """A host that starts again numbers from 1: the controller must not take that COMMAND for a retransmit
    of the last one it applied (docs/serial-protocol.md)."""
    table = Table(TableSpec())
    fw = Firmware(TableDrives(table), tmp_path / "ttyCELL")
    fw.start()
    port = os.open(fw.link_path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(port)

    def send(msg_type: wire.MsgType, seq: int, payload: bytes = b"") -> None:
        os.write(port, wire.encode(msg_type, seq, payload))
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and not select.select([port], [], [], 0.05)[0]:
            pass
        os.read(port, 4096)  # its answer

    try:
        hello = bytes([wire.PROTOCOL_VERSION])
        send(wire.MsgType.HELLO, 1, hello)
        send(wire.MsgType.COMMAND, 2, wire.command_payload(np.full(N, 0.05), np.zeros(N)))
        assert fw.commands_applied == 1
        send(wire.MsgType.HELLO, 1, hello)  # the host started again
        send(wire.MsgType.COMMAND, 2, wire.command_payload(np.full(N, 0.02), np.zeros(N)))
        assert fw.commands_applied == 2 and abs(table.cmd_speed_m_s[0] - 0.02) < 1e-4
    finally:
        os.close(port)
        fw.stop()


def test_a_fault_that_shares_the_hellos_seq_is_not_taken_for_its_answer(tmp_path: Path) -> None:
    """A controller's FAULT numbers from its own counter: one with the pending HELLO's seq, arriving
    first, must not stand in for the HELLO_ACK."""

    def fault_first(master: int, seq: int) -> None:
        fault = struct.pack("<BH", FAULT_WATCHDOG, 0xFFFF) + b"left over"
        hello = struct.pack("<BH", wire.PROTOCOL_VERSION, N) + b"faulty-fw"
        os.write(master, wire.encode(wire.MsgType.FAULT, seq, fault))
        os.write(master, wire.encode(wire.MsgType.HELLO_ACK, seq, hello))

    async def body(port: Path) -> None:
        async with _running(_link(port)) as link:
            await _until(lambda: link.connected)
            assert link.firmware == "faulty-fw"
            await link.stop()

    _against_a_device(tmp_path, "ttyFAULTY", _answering_hellos(fault_first), body)


def test_a_run_past_the_bound_is_noise_up_to_the_next_zero(tmp_path: Path) -> None:
    """Even a valid frame is dropped when it runs past 1024 bytes; the run counts as one invalid frame,
    and the next frame after the delimiter is answered."""
    fw = Firmware(TableDrives(Table(TableSpec())), tmp_path / "ttyCELL")
    fw.start()
    port = os.open(fw.link_path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(port)

    def answers(wait_s: float) -> bytes:
        got = b""
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            if select.select([port], [], [], 0.02)[0]:
                got += os.read(port, 4096)
        return got

    try:
        os.write(port, wire.encode(wire.MsgType.PING, 7, bytes(1100)))  # valid, but 1100+ bytes long
        assert answers(0.3) == b"" and fw.frames_bad == 1
        os.write(port, wire.encode(wire.MsgType.PING, 8))
        reply = answers(0.3)
        assert reply and wire.decode(reply[:-1]).seq == 8 and fw.frames_bad == 1
    finally:
        os.close(port)
        fw.stop()


def test_a_controller_latched_unknown_to_the_host_latches_the_host_too(tmp_path: Path) -> None:
    """The controller's e-stop latched while the host heard nothing of it (its FAULT lost, or latched
    before the link came up): its answers say so, and the host latches, reporting that input's fault, so
    that no command waits to run on a clear. Answers to what went before a clear do not latch it again."""

    async def body(fw: Firmware, table: Table) -> None:
        link = _link(fw.link_path)
        reported: list[int] = []
        link.on_fault = lambda fault: reported.append(fault.code)
        async with _running(link):
            await _until(lambda: link.connected)
            assert link.send_commands(_forward(0.05)).sent
            await _until(lambda: table.cmd_speed_m_s[0] > 0)
            fw.estopped = True  # latched by its own input; the FAULT never reached the host
            link.send_commands(_forward(0.05))
            await _until(lambda: link.estopped)
            assert reported == [wire.FAULT_ESTOP_INPUT] and "e-stop input" in link.faults[-1].text
            assert link.send_commands(_forward(0.05)).stopped  # held back until the operator clears it
            link.estop_clear()
            await _until(lambda: not fw.estopped)
            for _ in range(10):
                link.send_commands(_forward(0.03))
                await asyncio.sleep(0.02)
            assert not link.estopped and reported == [wire.FAULT_ESTOP_INPUT]
            await _until(lambda: abs(table.cmd_speed_m_s[0] - 0.03) < 1e-4)
            await link.stop()

    _with_firmware(tmp_path, body)
