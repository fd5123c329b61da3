"""The C reference firmware (deploy/firmware/) against clothd's real stepper link, on a pseudo-terminal:
handshake, acknowledged commands, the e-stop latch and its clearing, the watchdog's FAULT; and, frame by
frame with clothd's wire encoder, the NACKs and flags docs/serial-protocol.md specifies, and the hardware
e-stop input (SIGUSR1 opens the chain, SIGUSR2 closes it).

The build runs `make -C deploy/firmware host check` once per module: the C unit tests run with it."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import select
import shutil
import signal
import struct
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from firmware_links import check_conformance, run, running, until
from test_loop_safety import FakeCompute

from clothd.cli import main
from clothd.config import CellConfig, StepperConfig
from clothd.core.messages import ModuleCommands
from clothd.core.modes import Mode
from clothd.core.workspace import Workspace
from clothd.drivers import wire
from clothd.drivers.link_group import LinkGroup
from clothd.drivers.stepper_link import StepperLink
from clothd.errors import RequestError
from clothd.loop.daemon import Daemon
from clothd.loop.daemon_settings import DaemonSettings

ROOT = Path(__file__).resolve().parents[1]
FIRMWARE_DIR = ROOT / "deploy" / "firmware"
BINARY = FIRMWARE_DIR / "build" / "host" / "clothd-fw-host"
N = 48
WATCHDOG_S = 0.25  # docs/serial-protocol.md
FAULT_WATCHDOG = 1
FAULT_ESTOP_INPUT = 4
BOARD = 0xFFFF
NACK_ESTOPPED, NACK_BAD_LENGTH, NACK_UNKNOWN_TYPE, NACK_BAD_VERSION = 1, 2, 3, 4


@pytest.fixture(scope="module")
def firmware_binary() -> Path:
    if shutil.which("gcc") is None or shutil.which("make") is None:
        pytest.fail("the C firmware's host build needs gcc and make (Debian: apt-get install gcc make)")
    # Run from `make test`, a nested make would inherit the outer one's flags.
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    done = subprocess.run(
        ["make", "--no-print-directory", "-C", str(FIRMWARE_DIR), "host", "check"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert done.returncode == 0, f"make -C deploy/firmware host check failed:\n{done.stdout}\n{done.stderr}"
    assert ", 0 failed" in done.stdout
    return BINARY


def _wait_for(check: Callable[[], bool], timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.01)


@contextlib.contextmanager
def _firmware(binary: Path, link: Path) -> Iterator[subprocess.Popen[bytes]]:
    """clothd-fw-host on a fresh pty behind `link`; stopped with SIGTERM, which must exit cleanly."""
    proc = subprocess.Popen(
        [str(binary), "--link", str(link), "--modules", str(N), "--exit-on-stdin-eof"],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        _wait_for(lambda: link.exists() or proc.poll() is not None)
        assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=5)
        err = proc.stderr.read().decode() if proc.stderr else ""
    assert proc.returncode == 0, err
    assert "clothd-fw-host: frames ok" in err  # the exit summary: it left its loop, not killed
    assert not link.exists()  # the firmware removed its own symlink


@pytest.fixture
def firmware_link(firmware_binary: Path, tmp_path: Path) -> Iterator[Path]:
    link = tmp_path / "ttyFW"
    with _firmware(firmware_binary, link):
        yield link


# -- through clothd's stepper link ------------------------------------------------------------------


def _forward(speed_m_s: float) -> ModuleCommands:
    return ModuleCommands(np.full(N, speed_m_s), np.zeros(N))


def test_link_comes_up_commands_are_acked_and_the_estop_latches_until_cleared(firmware_link: Path) -> None:
    async def body() -> None:
        async with running(firmware_link, N) as link:
            assert link.firmware and link.firmware.startswith("clothd-fw")
            for _ in range(5):
                assert link.send_commands(_forward(0.05)).sent
                await asyncio.sleep(1 / 30)
            await until(lambda: link.counters.acked >= 5)
            assert link.counters.nacked == 0 and link.counters.invalid == 0
            assert link.counters.snapshot()["rtt_p50_ms"] is not None

            link.estop()
            await until(lambda: link.controller_estopped)
            # The host holds back and PINGs each tick: the watchdog stays fed through a held e-stop.
            held_until = time.monotonic() + 1.5 * WATCHDOG_S
            while time.monotonic() < held_until:
                assert link.send_commands(_forward(0.05)).stopped
                await asyncio.sleep(1 / 30)
            assert link.controller_estopped and not link.faults and link.counters.nacked == 0

            link.estop_clear()
            await until(lambda: not link.controller_estopped)
            acked = link.counters.acked
            assert link.send_commands(_forward(0.03)).sent
            await until(lambda: link.counters.acked > acked)
            assert link.counters.nacked == 0 and link.counters.losses == 0

    run(body())


def test_the_watchdog_fault_reaches_the_link_when_the_host_falls_silent(firmware_link: Path) -> None:
    async def body() -> None:
        async with running(firmware_link, N) as link:
            # A host that has only said HELLO has driven nothing: its silence is no fault.
            await asyncio.sleep(1.5 * WATCHDOG_S)
            assert not link.faults
            link.send_commands(_forward(0.1))
            await until(lambda: bool(link.faults), timeout_s=1.0)
            fault = link.faults[0]
            assert (fault.code, fault.module) == (FAULT_WATCHDOG, BOARD) and fault.text
            assert link.counters.faults == 1 and link.connected

    run(body())


# -- frame by frame ----------------------------------------------------------------------------------


class _RawHost:
    """The host side of the pty by hand: clothd's wire encoder out, its splitter and decoder in."""

    def __init__(self, port: Path) -> None:
        self.fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
        self.splitter = wire.FrameSplitter()
        self.pending: list[wire.Message] = []

    def close(self) -> None:
        os.close(self.fd)

    def send(self, msg_type: int, seq: int, payload: bytes = b"") -> None:
        os.write(self.fd, wire.encode(msg_type, seq, payload))

    def receive(self, timeout_s: float = 1.0) -> wire.Message:
        deadline = time.monotonic() + timeout_s
        while not self.pending:
            left_s = deadline - time.monotonic()
            assert left_s > 0, "no frame from the firmware"
            ready, _, _ = select.select([self.fd], [], [], left_s)
            if ready:
                self.pending += [wire.decode(p) for p in self.splitter.feed(os.read(self.fd, 4096))]
        return self.pending.pop(0)

    def ask(self, msg_type: int, seq: int, payload: bytes = b"") -> tuple[int, int, bytes]:
        self.send(msg_type, seq, payload)
        reply = self.receive()
        return reply.type, reply.seq, reply.payload


def _command(speed_m_s: float, n: int = N) -> bytes:
    return wire.command_payload(np.full(n, speed_m_s), np.zeros(n))


def test_nacks_flags_and_the_watchdog_frame_by_frame(firmware_link: Path) -> None:
    host = _RawHost(firmware_link)
    try:
        ack, nack, T = wire.MsgType.ACK, wire.MsgType.NACK, wire.MsgType
        assert host.ask(T.HELLO, 1, bytes([2])) == (nack, 1, bytes([NACK_BAD_VERSION]))
        kind, seq, payload = host.ask(T.HELLO, 2, wire.hello_payload())
        hello = wire.parse_hello_ack(payload)
        assert (kind, seq, hello.version, hello.n_modules) == (T.HELLO_ACK, 2, 1, N)
        assert host.ask(T.COMMAND, 3, _command(0.1, n=N - 1)) == (nack, 3, bytes([NACK_BAD_LENGTH]))
        assert host.ask(0x42, 4) == (nack, 4, bytes([NACK_UNKNOWN_TYPE]))
        assert host.ask(T.ESTOP, 5) == (ack, 5, bytes([wire.FLAG_ESTOP]))
        assert host.ask(T.COMMAND, 6, _command(0.1)) == (nack, 6, bytes([NACK_ESTOPPED]))
        assert host.ask(T.ESTOP_CLEAR, 7) == (ack, 7, b"\x00")
        assert host.ask(T.COMMAND, 8, _command(0.1)) == (ack, 8, b"\x00")
        assert host.ask(T.COMMAND, 8, _command(0.1)) == (ack, 8, b"\x00")  # a retransmit: ACKed again
        # Silent for the watchdog's 250 ms: FAULT(WATCHDOG) for the whole board, the flag in later ACKs.
        sent_s = time.monotonic()
        fault = host.receive(timeout_s=1.0)
        assert fault.type == T.FAULT and time.monotonic() - sent_s >= WATCHDOG_S - 0.02
        code, module = struct.unpack("<BH", fault.payload[:3])
        assert (code, module) == (FAULT_WATCHDOG, BOARD)
        assert host.ask(T.PING, 9) == (ack, 9, bytes([wire.FLAG_WATCHDOG]))
        assert host.ask(T.COMMAND, 10, _command(0.0)) == (ack, 10, b"\x00")  # the next command clears it
    finally:
        host.close()


def _fault_code_and_module(fault: wire.Message) -> tuple[int, int]:
    assert fault.type == wire.MsgType.FAULT, fault
    assert fault.payload[3:].isascii() and fault.payload[3:], fault  # a text a person can read
    code, module = struct.unpack("<BH", fault.payload[:3])
    return code, module


def test_the_hardware_estop_input_latches_like_estop_until_closed_and_cleared(
    firmware_binary: Path, tmp_path: Path
) -> None:
    link = tmp_path / "ttyFW"
    with _firmware(firmware_binary, link) as proc:
        host = _RawHost(link)
        try:
            ack, nack, T = wire.MsgType.ACK, wire.MsgType.NACK, wire.MsgType
            estopped = bytes([wire.FLAG_ESTOP])
            assert host.ask(T.HELLO, 1, wire.hello_payload())[0] == T.HELLO_ACK
            assert host.ask(T.COMMAND, 2, _command(0.1)) == (ack, 2, b"\x00")
            proc.send_signal(signal.SIGUSR1)  # the chain opens: unasked, the controller says so
            assert _fault_code_and_module(host.receive()) == (FAULT_ESTOP_INPUT, BOARD)
            assert host.ask(T.COMMAND, 3, _command(0.1)) == (nack, 3, bytes([NACK_ESTOPPED]))
            assert host.ask(T.ESTOP_CLEAR, 4) == (ack, 4, estopped)  # refused while the chain is open
            proc.send_signal(signal.SIGUSR2)  # closed again: that alone restarts nothing
            assert host.ask(T.PING, 5) == (ack, 5, estopped)
            assert host.ask(T.COMMAND, 6, _command(0.1)) == (nack, 6, bytes([NACK_ESTOPPED]))
            assert host.ask(T.ESTOP_CLEAR, 7) == (ack, 7, b"\x00")
            assert host.ask(T.COMMAND, 8, _command(0.1)) == (ack, 8, b"\x00")
            # Opened and closed again before the firmware looks: the opening is not lost.
            proc.send_signal(signal.SIGUSR1)
            proc.send_signal(signal.SIGUSR2)
            assert _fault_code_and_module(host.receive()) == (FAULT_ESTOP_INPUT, BOARD)
            assert host.ask(T.PING, 9) == (ack, 9, estopped)
            assert host.ask(T.ESTOP_CLEAR, 10) == (ack, 10, b"\x00")
            assert host.ask(T.COMMAND, 11, _command(0.0)) == (ack, 11, b"\x00")
        finally:
            host.close()


def test_the_firmware_exits_when_its_stdin_closes(firmware_binary: Path, tmp_path: Path) -> None:
    link = tmp_path / "ttyFW"
    with _firmware(firmware_binary, link) as proc:
        assert proc.stdin is not None
        proc.stdin.close()
        proc.wait(timeout=2)


def test_the_host_build_passes_the_conformance_kit(firmware_link: Path, tmp_path: Path) -> None:
    """Every rule that shows on the wire passes; those only the drives show are not observable here."""
    report = tmp_path / "conformance.json"
    code = main(["conformance", "--port", str(firmware_link), "--json", str(report)])
    rows = json.loads(report.read_text())["checks"]
    check_conformance(code, rows)
    assert sum(r["passed"] is not None for r in rows) >= 20


def test_the_daemon_latches_its_own_estop_when_the_hardware_chain_opens(
    firmware_binary: Path, tmp_path: Path
) -> None:
    """The daemon (its compute a fake that tracks a cloth) on clothd's link to the C firmware: the chain
    opened (FAULT ESTOP_INPUT) stops a move and latches the daemon's e-stop, shown in its status; the
    chain closed again releases nothing until the operator's clear."""
    link_path = tmp_path / "ttyFW"
    with _firmware(firmware_binary, link_path) as proc:

        async def body() -> None:
            cfg = StepperConfig(port=str(link_path), reconnect_initial_s=0.05, reconnect_max_s=0.2)
            group = LinkGroup([(StepperLink(cfg, N), range(N))], N)
            settings = DaemonSettings(
                period_s=1 / 30,
                max_stale_ticks=10,
                n_modules=N,
                workspace=Workspace.of_cell(CellConfig()),
                view_period_s=0.1,
                recording_dir=tmp_path,
                camera_source="fake",
                link_port=str(link_path),
                estimates_shape=True,
            )
            daemon = Daemon(settings, group, FakeCompute())  # type: ignore[arg-type]
            task = asyncio.create_task(daemon.run())
            try:
                await until(lambda: group.connected and daemon.state == "tracking", 10)
                daemon.set_setpoint(Mode.MOVE, np.array([0.02, 0.0, 0.0]))
                await until(lambda: bool(np.any(daemon.status and daemon.status.modules.speed_m_s)), 5)
                proc.send_signal(signal.SIGUSR1)  # the chain opens
                await until(lambda: daemon.status is not None and daemon.status.estop, 5)
                status = daemon.status
                assert status.mode == Mode.IDLE and not any(status.modules.speed_m_s)
                assert status.halt_reason is not None and "ESTOP_INPUT" in status.halt_reason
                assert status.faults[-1].code == FAULT_ESTOP_INPUT
                await until(lambda: group.controller_estopped, 5)
                with pytest.raises(RequestError, match="emergency stop is latched"):
                    daemon.set_setpoint(Mode.MOVE, np.array([0.02, 0.0, 0.0]))
                proc.send_signal(signal.SIGUSR2)  # closed again: that alone releases nothing
                await asyncio.sleep(0.2)
                assert daemon.status.estop and group.controller_estopped
                daemon.estop_clear()  # the operator's clear
                await until(lambda: not group.controller_estopped and not daemon.status.estop, 5)
                daemon.set_setpoint(Mode.MOVE, np.array([0.02, 0.0, 0.0]))
            finally:
                daemon.stop()
                await asyncio.wait_for(task, 5)

        run(body(), timeout_s=30)
