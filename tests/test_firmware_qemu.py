"""The STM32F405 port of the C reference firmware (deploy/firmware/stm32f4/), booted in QEMU's
netduinoplus2 machine, against the conformance kit and clothd's real stepper link: USART1 on a pty, the
SysTick clock in QEMU's emulated time (which follows the host's clock, never ahead of it).

What QEMU cannot show (step pulses, the drivers' pins, a real UART or USB CDC) is the bench's: see
deploy/firmware/README.md. The module builds with `make -C deploy/firmware stm32` and boots one QEMU for
all its tests; it fails, naming the Debian packages, where the cross compiler or QEMU is missing."""

from __future__ import annotations

import asyncio
import ctypes
import json
import os
import re
import select
import shutil
import signal
import statistics
import subprocess
import termios
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from firmware_links import check_conformance, run, running, until

from clothd.cli import main
from clothd.core.messages import ModuleCommands
from clothd.drivers import wire
from clothd.drivers.stepper_link import StepperLink

ROOT = Path(__file__).resolve().parents[1]
FIRMWARE_DIR = ROOT / "deploy" / "firmware"
ELF = FIRMWARE_DIR / "build" / "stm32" / "clothd-fw.elf"
N = 48  # BOARD_MODULES in stm32f4/board.h
WATCHDOG_S = 0.25  # docs/serial-protocol.md
FAULT_WATCHDOG = 1
BOARD = 0xFFFF
TOOLS = {
    "arm-none-eabi-gcc": "gcc-arm-none-eabi",
    "arm-none-eabi-objcopy": "gcc-arm-none-eabi",
    "qemu-system-arm": "qemu-system-arm",
    "make": "make",
}
PTY_LINE = re.compile(r"char device redirected to (/dev/pts/\d+) \(label serial0\)")


@pytest.fixture(scope="module")
def firmware_elf() -> Path:
    missing = sorted({package for tool, package in TOOLS.items() if shutil.which(tool) is None})
    if missing:
        pytest.fail(
            "the STM32 firmware's build and its QEMU run need the Debian packages "
            f"{', '.join(missing)} (apt-get install gcc-arm-none-eabi qemu-system-arm make)"
        )
    # Run from `make test`, a nested make would inherit the outer one's flags.
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    done = subprocess.run(
        ["make", "--no-print-directory", "-C", str(FIRMWARE_DIR), "stm32"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert done.returncode == 0, f"make -C deploy/firmware stm32 failed:\n{done.stdout}\n{done.stderr}"
    return ELF


def _wait_for(check: Callable[[], bool], what: str, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, f"{what}: not within {timeout_s} s"
        time.sleep(0.01)


def _qemu_pty(log: Path, qemu: subprocess.Popen[bytes]) -> str:
    """The pty QEMU gave USART1: it names it on stdout, "char device redirected to /dev/pts/N"."""
    found: list[str] = []

    def named() -> bool:
        assert qemu.poll() is None, f"QEMU exited: {log.read_text()}"
        found.extend(PTY_LINE.findall(log.read_text()))
        return bool(found)

    _wait_for(named, "QEMU naming its pty")
    return found[0]


def _die_with_parent() -> None:
    """Run in QEMU's child before exec: SIGTERM when pytest dies, so no emulator outlives a killed run."""
    pr_set_pdeathsig = 1
    ctypes.CDLL(None).prctl(pr_set_pdeathsig, signal.SIGTERM)


def _answers_ping(fd: int, timeout_s: float) -> bool:
    """Send PINGs until one is ACKed. QEMU looks for a reader on its pty only once a second and drops what
    the firmware sends before then, so the first PINGs may go unanswered."""
    splitter = wire.FrameSplitter()
    deadline = time.monotonic() + timeout_s
    seq = 0
    while time.monotonic() < deadline:
        seq += 1
        os.write(fd, wire.encode(wire.MsgType.PING, seq))
        retry_at = time.monotonic() + 0.1
        while (left_s := retry_at - time.monotonic()) > 0:
            if select.select([fd], [], [], left_s)[0]:
                for packet in splitter.feed(os.read(fd, 4096)):
                    reply = wire.decode(packet)
                    if reply.type == wire.MsgType.ACK and reply.seq == seq:
                        return True
    return False


@pytest.fixture(scope="module")
def qemu_firmware(firmware_elf: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, int]]:
    """The firmware booted in QEMU: its pty, and a descriptor on it this fixture holds open throughout.

    QEMU stops serving the pty when the last process closes it and notices a new one only up to a second
    later; holding it open keeps the link up between the tests (and the test that opens it next reads
    nothing this descriptor does not read, since it never reads)."""
    log = tmp_path_factory.mktemp("qemu") / "qemu.log"
    command = ["qemu-system-arm", "-machine", "netduinoplus2", "-display", "none", "-monitor", "none"]
    command += ["-serial", "pty", "-kernel", str(firmware_elf)]
    with log.open("wb") as out:
        qemu = subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            preexec_fn=_die_with_parent,
        )
    holder = -1
    try:
        pty = _qemu_pty(log, qemu)
        holder = os.open(pty, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(holder)  # QEMU sets raw mode too: an echo would hand the firmware its own replies
        answered = _answers_ping(holder, timeout_s=5.0)
        assert answered, f"the firmware in QEMU answers no PING: {log.read_text()}"
        yield pty, holder
    finally:
        if holder >= 0:
            os.close(holder)
        qemu.terminate()
        qemu.wait(timeout=5)


@pytest.fixture
def firmware_port(qemu_firmware: tuple[str, int]) -> str:
    """The pty with nothing stale queued: a watchdog trip the last test left coming happens, then what
    the firmware sent since is discarded."""
    pty, holder = qemu_firmware
    time.sleep(2 * WATCHDOG_S)
    termios.tcflush(holder, termios.TCIOFLUSH)
    return pty


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
        assert link.send_commands(_forward(0.05))
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
                assert not link.send_commands(_forward(0.05))  # held back: a PING goes instead
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
