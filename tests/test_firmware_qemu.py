"""The STM32F405 port of the C reference firmware (deploy/firmware/stm32f4/), booted in QEMU's
netduinoplus2 machine, against the conformance kit and clothd's real stepper link: USART1 on a pty, the
SysTick clock in QEMU's emulated time (which follows the host's clock, never ahead of it).

What QEMU cannot show (step pulses, the drivers' pins, a real UART or USB CDC) is the bench's: see
deploy/firmware/README.md. The module builds with `make -C deploy/firmware stm32` and boots one QEMU for
all its tests; it fails, naming the Debian packages, where the cross compiler or QEMU is missing."""

from __future__ import annotations

import asyncio
import json
import math
import os
import statistics
import termios
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from firmware_links import QemuFirmware, boot_qemu, build_stm32, check_conformance, run, running, until

from clothd.cli import main
from clothd.core.messages import ModuleCommands
from clothd.drivers import wire
from clothd.drivers.stepper_link import StepperLink

N = 48  # BOARD_MODULES in stm32f4/board.h
WATCHDOG_S = 0.25  # docs/serial-protocol.md
FAULT_WATCHDOG = 1
FAULT_ESTOP_INPUT = 4
BOARD = 0xFFFF
ESTOP_INPUT_PIN = 1  # PA1: stm32f4/hal_stm32.c, docs/hardware.md
STEP_CHANNELS = (
    2 * 4
)  # BOARD_STEP_MODULES in stm32f4/board.h: channel 2m is module m's drive, 2m + 1 its steering
DRIVE_STEPS_PER_M = 200 * 16 / 0.040  # the core's example gearing (core/firmware.c, fw_default_config)
STEER_STEPS_PER_RAD = 200 * 16 * 4 / (2 * math.pi)
EMULATOR_MAX_STEPS_PER_S = 10_000 / 2  # stm32f4/board.h: STEP_TICK_HZ / 2 in the qemu clock profile


@pytest.fixture(scope="module")
def qemu_firmware(tmp_path_factory: pytest.TempPathFactory) -> Iterator[QemuFirmware]:
    """The firmware booted in QEMU, with a descriptor on its pty held open throughout.

    QEMU stops serving the pty when the last process closes it and notices a new one only up to a second
    later; holding it open keeps the link up between the tests (and the test that opens it next reads
    nothing this descriptor does not read, since it never reads)."""
    with boot_qemu(build_stm32(), tmp_path_factory.mktemp("qemu")) as firmware:
        yield firmware


@pytest.fixture
def firmware_port(qemu_firmware: QemuFirmware) -> str:
    """The pty with nothing stale queued: a watchdog trip the last test left coming happens, then what
    the firmware sent since is discarded."""
    time.sleep(2 * WATCHDOG_S)
    termios.tcflush(qemu_firmware.holder, termios.TCIOFLUSH)
    return qemu_firmware.pty


# -- the conformance kit ------------------------------------------------------------------------------


def test_the_qemu_build_passes_the_conformance_kit(firmware_port: str, tmp_path: Path) -> None:
    """Every rule that shows on the wire passes; those only the drives show are not observable here."""
    report = tmp_path / "conformance.json"
    code = main(["conformance", "--port", firmware_port, "--json", str(report)])
    rows = json.loads(report.read_text())["checks"]
    check_conformance(code, rows)
    assert sum(r["passed"] is not None for r in rows) >= 20
    hello = next(r for r in rows if r["name"] == "handshake.hello")
    assert f"{N} modules" in hello["figure"]


# -- through clothd's stepper link --------------------------------------------------------------------


def _forward(speed_m_s: float) -> ModuleCommands:
    return ModuleCommands(np.full(N, speed_m_s), np.zeros(N))


async def _commands_acked(link: StepperLink, count: int) -> float:
    """Send count COMMANDs a control period apart and wait for their ACKs; returns when the last left."""
    acked = link.counters.acked
    for i in range(count):
        if i:
            await asyncio.sleep(1 / 30)
        assert link.send_commands(_forward(0.05)).sent
        sent_s = time.monotonic()
    await until(lambda: link.counters.acked >= acked + count)
    return sent_s


def test_link_up_commands_acked_and_the_estop_latches_within_20_ms(firmware_port: str) -> None:
    async def body() -> None:
        async with running(firmware_port, N) as link:
            assert link.firmware and link.firmware.startswith("clothd-fw")
            latencies_s = []
            for _ in range(5):
                await _commands_acked(link, 5)
                link.estop()
                latencies_s.append(await until(lambda: link.controller_estopped, poll_s=0.0005))
                assert link.send_commands(_forward(0.05)).stopped  # held back: a PING goes instead
                link.estop_clear()
                await until(lambda: not link.controller_estopped)
            assert link.counters.nacked == 0 and link.counters.invalid == 0 and not link.faults
            ms = sorted(round(s * 1e3, 2) for s in latencies_s)
            print(f"\nQEMU e-stop latch (estop() to controller_estopped): {ms} ms")

    run(body(), 15.0)


def _more_faults_than(link: StepperLink, count: int) -> Callable[[], bool]:
    return lambda: len(link.faults) > count


def test_the_watchdog_fault_reaches_the_link_after_250_ms_of_silence(firmware_port: str) -> None:
    async def body() -> None:
        # A retransmit of the last COMMAND would feed the watchdog again: the link waits longer for an ACK
        # than it does by default, so the silence starts when the measurement says it does.
        async with running(firmware_port, N, ack_timeout_s=0.5) as link:
            latencies_s = []
            for _ in range(3):
                sent_s = await _commands_acked(link, 3)  # the last COMMAND: then silence
                await until(_more_faults_than(link, len(link.faults)), timeout_s=1.0, poll_s=0.0005)
                latencies_s.append(time.monotonic() - sent_s)
                fault = link.faults[-1]
                assert (fault.code, fault.module) == (FAULT_WATCHDOG, BOARD) and fault.text
                assert link.connected and link.counters.retransmitted == 0
            ms = sorted(round(s * 1e3, 1) for s in latencies_s)
            median = statistics.median(ms)
            print(f"\nQEMU watchdog (last COMMAND to FAULT at the link): {ms} ms, median {median} ms")
            # The firmware times from when the frame arrived, after the host wrote it: never sooner.
            assert min(latencies_s) >= WATCHDOG_S, f"FAULT after {ms} ms: sooner than the watchdog"

    run(body(), 15.0)


def test_the_estop_input_pin_latches_the_estop_and_reports_a_fault(
    qemu_firmware: QemuFirmware, firmware_port: str
) -> None:
    """PA1 rising (the chain opening), driven from outside through QEMU's SYSCFG and EXTI models: the
    interrupt cuts ENABLE and the core latches as for ESTOP. QEMU models no GPIO port, so the level the
    firmware reads back is always 0 (closed): this is the edge path; the level path is the host build's
    test (test_firmware_host.py) and the bench's."""
    fw = qemu_firmware

    async def body() -> None:
        async with running(firmware_port, N) as link:
            await _commands_acked(link, 3)
            assert fw.read_u8("drivers_enabled") == 1 and fw.read_i32("estop_edges") == 0
            faults, nacked = len(link.faults), link.counters.nacked
            raised_s = time.monotonic()
            fw.set_gpio_a(ESTOP_INPUT_PIN, 1)
            fw.set_gpio_a(ESTOP_INPUT_PIN, 0)
            await until(_more_faults_than(link, faults), timeout_s=1.0, poll_s=0.0005)
            took_ms = (time.monotonic() - raised_s) * 1e3
            fault = link.faults[faults]
            assert (fault.code, fault.module) == (FAULT_ESTOP_INPUT, BOARD) and fault.text
            assert fw.read_u8("drivers_enabled") == 0 and fw.read_i32("estop_edges") == 1
            assert link.send_commands(_forward(0.05)).sent  # the host did not e-stop: it sends, is refused
            await until(lambda: link.counters.nacked > nacked)
            link.estop()  # what the daemon does on hearing of it: latch its own too, then clear both
            await until(lambda: link.controller_estopped)
            link.estop_clear()
            await until(lambda: not link.controller_estopped)
            await _commands_acked(link, 2)
            assert fw.read_u8("drivers_enabled") == 1
            print(f"\nQEMU e-stop input: PA1 raised to FAULT(ESTOP_INPUT) at the link {took_ms:.1f} ms")

    run(body(), 15.0)


# -- step pulses: what the emulated step tick issued, read from the firmware's memory ------------------


class _Host:
    """COMMANDs by hand on the held pty, a control period apart, to feed the watchdog while the test reads
    the firmware's memory (its answers pile up unread and are flushed before the next test)."""

    def __init__(self, fw: QemuFirmware) -> None:
        self.fw, self.seq = fw, 0
        self.send(wire.MsgType.HELLO, wire.hello_payload())  # a new session: no seq taken for a retransmit

    def send(self, msg_type: int, payload: bytes = b"") -> None:
        self.seq += 1
        os.write(self.fw.holder, wire.encode(msg_type, self.seq, payload))

    def hold(self, speed_m_s: float, heading_rad: float, seconds: float) -> None:
        payload = wire.command_payload(np.full(N, speed_m_s), np.full(N, heading_rad))
        end_s = time.monotonic() + seconds
        while time.monotonic() < end_s:
            self.send(wire.MsgType.COMMAND, payload)
            time.sleep(1 / 30)

    def positions(self) -> tuple[list[int], float]:
        """Every channel's steps issued, and the firmware's clock (TIM2, emulated seconds) as read."""
        steps = [self.fw.read_i32("step_position", c) for c in range(STEP_CHANNELS)]
        return steps, self.fw.read_timer_us() / 1e6

    def drive_rate(self, speed_m_s: float, heading_rad: float, seconds: float) -> float:
        """Steps per second the drive channels issued over `seconds` at a steady speed, in emulated time;
        every drive channel the same, no steering."""
        before, t0 = self.positions()
        self.hold(speed_m_s, heading_rad, seconds)
        after, t1 = self.positions()
        moved = [b - a for a, b in zip(before, after, strict=True)]
        # one step apart at most: the channels are read one after another while they step
        assert max(moved[0::2]) - min(moved[0::2]) <= 1 and not any(moved[1::2]), moved
        return moved[0] / (t1 - t0)


def test_the_step_tick_issues_steps_at_the_commanded_rates(
    qemu_firmware: QemuFirmware, firmware_port: str
) -> None:
    """SysTick's step tick (stm32f4/steppers.c; 10 kHz in the emulator build, 40 kHz on a board) turns
    the core's rates into steps: at a steady
    speed the drive channels step at speed x steps/m in the firmware's own time, backwards for a negative
    speed, and a turn of the heading gives about heading x steps/rad of steering steps. What QEMU cannot
    show (the pins: it models no GPIO; pulse widths, jitter, DIR set-up) is the bench's."""
    host = _Host(qemu_firmware)
    # 400 steps/s: the emulated tick (10 kHz asked) must come at least twice as often, on a loaded host too
    # (at 1,600 steps/s a load average of 8 left QEMU short of ticks, and the steps owed piled up).
    speed = 0.005
    expected = speed * DRIVE_STEPS_PER_M
    host.hold(speed, 0.0, 0.2)  # ramped (10 ms at 2 m/s^2) and steady
    assert qemu_firmware.read_i32("drive_steps_per_s", 0) == round(expected)
    forward = host.drive_rate(speed, 0.0, 1.0)
    host.hold(-speed, 0.0, 0.2)  # the belt runs backwards: no steering, the shorter way
    backward = host.drive_rate(-speed, 0.0, 1.0)
    print(f"\nQEMU step rate: {forward:.1f} and {backward:.1f} steps/s for ±{expected:.0f} commanded")
    assert forward == pytest.approx(expected, rel=0.01) and backward == pytest.approx(-expected, rel=0.01)

    before, _ = host.positions()
    host.hold(speed, 0.5, 0.5)  # 0.5 rad at 3 rad/s: 0.17 s of steering, then still
    after, _ = host.positions()
    turned = [b - a for a, b in zip(before[1::2], after[1::2], strict=True)]
    # The turn runs at the steering limit, 3 rad/s (6,112 steps/s), above the emulator build's 5,000
    # steps/s ceiling (10 kHz tick): clipped, and counted. The core sets a rate each millisecond and the
    # tick steps at it until the next, and a loaded host delivers fewer ticks: the count is only held to
    # the right sign, the same on every module, and no more than the turn asks (measured 693-1017).
    clipped = min(3.0 * STEER_STEPS_PER_RAD, EMULATOR_MAX_STEPS_PER_S) * (0.5 / 3.0)
    print(f"QEMU steering steps for 0.5 rad: {turned} ({clipped:.0f} at the clipped rate)")
    assert max(turned) - min(turned) <= 1
    assert 0.5 * clipped < turned[0] <= 1.05 * 0.5 * STEER_STEPS_PER_RAD
    assert qemu_firmware.read_i32("step_rate_clips") > 0
    host.hold(0.0, 0.5, 0.1)


def _still(host: _Host) -> bool:
    """No channel steps over 100 ms."""
    before, _ = host.positions()
    time.sleep(0.1)
    return host.positions()[0] == before


def test_the_estop_and_the_watchdog_stop_the_steps(qemu_firmware: QemuFirmware, firmware_port: str) -> None:
    host = _Host(qemu_firmware)
    host.hold(0.05, 0.0, 0.2)
    assert not _still(host)
    host.send(wire.MsgType.ESTOP)  # the drivers cut: steps owed are dropped, none issued after
    time.sleep(0.05)
    assert qemu_firmware.read_u8("drivers_enabled") == 0 and _still(host)
    host.send(wire.MsgType.ESTOP_CLEAR)
    host.hold(0.05, 0.0, 0.2)
    assert qemu_firmware.read_u8("drivers_enabled") == 1 and not _still(host)
    time.sleep(2 * WATCHDOG_S)  # silence: the watchdog's controlled stop, to no steps at all
    assert _still(host) and qemu_firmware.read_i32("drive_steps_per_s", 0) == 0
    assert qemu_firmware.read_u8("drivers_enabled") == 1  # a stop, not a cut
