"""What the firmware tests share: clothd's stepper link run against a controller on a port, the
conformance kit's verdict judged without a wall-clock upper bound, and the STM32 build booted in QEMU's
netduinoplus2 with its USART on a pty and QEMU's qtest interface on a socket (to read the guest's memory
and raise a GPIO line the board would see from outside)."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import os
import re
import select
import shutil
import signal
import socket
import subprocess
import time
import tty
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from clothd.config import StepperConfig
from clothd.drivers import wire
from clothd.drivers.stepper_link import StepperLink
from clothd.tools.conformance_checks import WATCHDOG_MS

TIMED_CHECKS = {"watchdog.fault"}  # its upper bound is wall-clock: the kit's table reports it


async def until(check: Callable[[], bool], timeout_s: float = 3.0, poll_s: float = 0.01) -> float:
    """Wait for check(); returns the seconds it took."""
    start = time.monotonic()
    while not check():
        assert time.monotonic() - start < timeout_s, "condition not reached in time"
        await asyncio.sleep(poll_s)
    return time.monotonic() - start


@contextlib.asynccontextmanager
async def running(
    port: Path | str, n_modules: int, ack_timeout_s: float = 0.05
) -> AsyncIterator[StepperLink]:
    """clothd's stepper link on `port`, connected; stopped on leaving."""
    cfg = StepperConfig(
        port=str(port), reconnect_initial_s=0.05, reconnect_max_s=0.2, ack_timeout_s=ack_timeout_s
    )
    link = StepperLink(cfg, n_modules)
    task = asyncio.create_task(link.run())
    try:
        await until(lambda: link.connected)
        yield link
    finally:
        await link.stop()
        task.cancel()


def run(body: Awaitable[None], timeout_s: float = 10.0) -> None:
    asyncio.run(asyncio.wait_for(body, timeout_s))


def check_conformance(code: int, rows: list[dict[str, Any]]) -> None:
    """Every rule the kit checked holds. The watchdog's FAULT may come late on a loaded machine (a figure
    for the kit's table), never early: the test holds it to no sooner than the watchdog."""
    failed = {r["name"] for r in rows if r["passed"] is False}
    watchdog = next(r for r in rows if r["name"] == "watchdog.fault")
    assert float(str(watchdog["figure"]).removesuffix(" ms")) >= WATCHDOG_MS, watchdog
    assert failed <= TIMED_CHECKS, failed
    assert code == (1 if failed else 0)


# -- the STM32 build in QEMU --------------------------------------------------------------------------

FIRMWARE_DIR = Path(__file__).resolve().parents[1] / "deploy" / "firmware"
STM32_ELF = FIRMWARE_DIR / "build" / "stm32" / "clothd-fw.elf"
STM32_TOOLS = {
    "arm-none-eabi-gcc": "gcc-arm-none-eabi",
    "arm-none-eabi-objcopy": "gcc-arm-none-eabi",
    "arm-none-eabi-nm": "binutils-arm-none-eabi",
    "qemu-system-arm": "qemu-system-arm",
    "make": "make",
}
PTY_LINE = re.compile(r"char device redirected to (/dev/pts/\d+) \(label serial0\)")
SYMBOL_LINE = re.compile(r"^([0-9a-f]{8}) [bBdD] (\w+)$", re.MULTILINE)


def build_stm32() -> Path:
    """`make -C deploy/firmware stm32`; fails naming the Debian packages where a tool is missing."""
    missing = sorted({package for tool, package in STM32_TOOLS.items() if shutil.which(tool) is None})
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
    return STM32_ELF


def _wait_for(check: Callable[[], bool], what: str, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, f"{what}: not within {timeout_s} s"
        time.sleep(0.01)


class Qtest:
    """QEMU's qtest protocol (one text line out, one back): it runs beside the emulated CPU (-accel tcg),
    so the firmware runs as usual while the test reads its memory and drives a device's input lines."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(str(path))
        self.buffer = b""

    def command(self, line: str) -> str:
        self.sock.sendall(line.encode() + b"\n")
        while b"\n" not in self.buffer:
            chunk = self.sock.recv(4096)
            assert chunk, f"QEMU closed its qtest socket after {line!r}"
            self.buffer += chunk
        reply, self.buffer = self.buffer.split(b"\n", 1)
        text = reply.decode()
        assert text.startswith("OK"), f"qtest {line!r}: {text}"
        return text

    def readl(self, address: int) -> int:
        return int(self.command(f"readl {address:#x}").split()[1], 16)

    def set_irq_in(self, qom_path: str, line: int, level: int) -> None:
        self.command(f"set_irq_in {qom_path} unnamed-gpio-in {line} {level}")

    def close(self) -> None:
        self.sock.close()


@dataclass
class QemuFirmware:
    pty: str  # USART1
    holder: int  # a descriptor on the pty held open throughout (QEMU serves it only while one is)
    qtest: Qtest
    symbols: dict[str, int]  # the ELF's data symbols, statics included: name -> address

    def read_i32(self, symbol: str, index: int = 0) -> int:
        value = self.qtest.readl(self.symbols[symbol] + 4 * index)
        return value - (1 << 32) if value >= 1 << 31 else value

    def read_u8(self, symbol: str) -> int:
        address = self.symbols[symbol]
        word = self.qtest.readl(address & ~3)  # little-endian: the byte's place in its aligned word
        return (word >> (8 * (address & 3))) & 0xFF

    def read_timer_us(self) -> int:
        """TIM2's count: the firmware's microseconds, in QEMU's emulated time."""
        return self.qtest.readl(0x40000024)

    def set_gpio_a(self, pin: int, level: int) -> None:
        """Drive input pin PA<pin> from outside. QEMU 7.2 models no GPIO port, but does model SYSCFG and
        EXTI: its SYSCFG takes line 16 * port + pin and passes it to EXTI if EXTICR selects that port,
        so this is the edge the board's EXTI sees (only port A: 7.2's SYSCFG mis-indexes the others)."""
        self.qtest.set_irq_in("syscfg", pin, level)


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


def _symbols(elf: Path) -> dict[str, int]:
    nm = subprocess.run(["arm-none-eabi-nm", str(elf)], capture_output=True, text=True, check=True)
    return {name: int(address, 16) for address, name in SYMBOL_LINE.findall(nm.stdout)}


@contextlib.contextmanager
def boot_qemu(elf: Path, workdir: Path) -> Iterator[QemuFirmware]:
    """The firmware booted in QEMU and answering PINGs on its pty."""
    log, qtest_path = workdir / "qemu.log", workdir / "qtest.sock"
    command = ["qemu-system-arm", "-machine", "netduinoplus2", "-display", "none", "-monitor", "none"]
    command += ["-serial", "pty", "-accel", "tcg", "-qtest", f"unix:{qtest_path},server=on,wait=off"]
    command += ["-qtest-log", "/dev/null", "-kernel", str(elf)]
    with log.open("wb") as out:
        qemu = subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            preexec_fn=_die_with_parent,
        )
    holder, qtest = -1, None
    try:
        found: list[str] = []

        def named() -> bool:
            assert qemu.poll() is None, f"QEMU exited: {log.read_text()}"
            found.extend(PTY_LINE.findall(log.read_text()))
            return bool(found) and qtest_path.exists()

        _wait_for(named, "QEMU naming its pty and opening its qtest socket")
        holder = os.open(found[0], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(holder)  # QEMU sets raw mode too: an echo would hand the firmware its own replies
        assert _answers_ping(holder, timeout_s=5.0), (
            f"the firmware in QEMU answers no PING: {log.read_text()}"
        )
        qtest = Qtest(qtest_path)
        yield QemuFirmware(found[0], holder, qtest, _symbols(elf))
    finally:
        if qtest is not None:
            qtest.close()
        if holder >= 0:
            os.close(holder)
        qemu.terminate()
        qemu.wait(timeout=5)
