"""`clothd run` driving the STM32 firmware in QEMU: hwsim's rendered camera for the cloth, and
`stepper.port` on a pty that taps the line between the daemon and QEMU's USART (every frame timestamped
both ways). A move's COMMANDs reach the firmware (its ACKs on the wire, its step rates and step counts
read from its memory through qtest), `POST /api/v1/estop` latches it (the ESTOP frame and the ACK with
the e-stop flag on the wire, the drivers cut in its memory), and killing the daemon stops it through its
watchdog. The cloth does not move: the firmware drives no table; what is checked is the link.

Figures are printed (the e-stop on the wire, the watchdog's FAULT after the last frame); the test holds
them to their order and to "not early", never to a wall-clock upper bound: the machine is shared, and a
loaded one starves QEMU's emulated USART, the daemon and the link for seconds at a time (the link may
even be lost and reconnect), so every wait on a condition is generous."""

from __future__ import annotations

import bisect
import contextlib
import os
import select
import signal
import threading
import time
import tty
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from firmware_links import QemuFirmware, boot_qemu, build_stm32
from live_cell import Cell, Daemon, serve_cell, start_daemon, wait

from clothd.drivers import wire

pytestmark = pytest.mark.slow
N = 48  # BOARD_MODULES, and hwsim's cell
WATCHDOG_S = 0.25  # docs/serial-protocol.md
FAULT_WATCHDOG = 1
QUIET_S = 10.0  # no frame from a killed daemon this long after its last: that one was the last
KILL_ATTEMPTS = 3
MOVE_OVER_S = 5.0  # no COMMAND with a speed this long: the move is over
T = wire.MsgType


@dataclass(frozen=True)
class Seen:
    t_s: float  # time.monotonic() when the tap read it
    to_firmware: bool
    msg: wire.Message


class WireTap:
    """A pty for the daemon, copied byte for byte to and from QEMU's pty by a thread that decodes and
    timestamps every frame on the way."""

    def __init__(self, firmware_fd: int) -> None:
        self.firmware_fd = firmware_fd
        self.master, self.slave = os.openpty()  # the slave held open: the daemon may close and reopen it
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.frames: list[Seen] = []  # in the order read, so by t_s
        self.arrived = threading.Condition()
        self.stop_r, self.stop_w = os.pipe()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _copy(self, src: int, dst: int, splitter: wire.FrameSplitter, to_firmware: bool) -> bool:
        """Copies what src has to dst; False when the tap is told to stop while dst is full."""
        data = os.read(src, 4096)
        t_s = time.monotonic()
        view = memoryview(data)
        while view:
            # QEMU's side is non-blocking and takes bytes only as the emulated USART frees up: wait
            # until it has room (a write to a full one would raise), however long a loaded machine takes.
            ready = select.select([self.stop_r], [dst], [], 1.0)[0:2]
            if self.stop_r in ready[0]:
                return False
            if ready[1]:
                with contextlib.suppress(BlockingIOError):
                    view = view[os.write(dst, view) :]
        for packet in splitter.feed(data):
            try:
                seen = Seen(t_s, to_firmware, wire.decode(packet))
            except ValueError:
                continue  # counted by the link's own 'invalid'; nothing to time
            with self.arrived:
                self.frames.append(seen)
                self.arrived.notify_all()
        return True

    def _run(self) -> None:
        out, back = wire.FrameSplitter(), wire.FrameSplitter()
        while True:
            ready = select.select([self.master, self.firmware_fd, self.stop_r], [], [])[0]
            if self.stop_r in ready:
                return
            if self.master in ready and not self._copy(self.master, self.firmware_fd, out, True):
                return
            if self.firmware_fd in ready and not self._copy(self.firmware_fd, self.master, back, False):
                return

    def since(self, t_s: float) -> list[Seen]:
        with self.arrived:
            return self.frames[bisect.bisect_left(self.frames, t_s, key=lambda f: f.t_s) :]

    def first(self, t_s: float, match: Callable[[Seen], bool], what: str, timeout_s: float = 90.0) -> Seen:
        """The first frame read at t_s or later that matches. The test's thread sleeps until the tap's
        thread has read a frame and looks only at the new ones, rather than copying the whole list every
        millisecond with the GIL that the tap's thread needs to timestamp a frame."""
        deadline = time.monotonic() + timeout_s
        with self.arrived:
            k = bisect.bisect_left(self.frames, t_s, key=lambda f: f.t_s)
            while True:
                # A frame read before t_s may be appended after it: the tap writes on before it appends.
                found = next((f for f in self.frames[k:] if f.t_s >= t_s and match(f)), None)
                if found is not None:
                    return found
                k = len(self.frames)
                left_s = deadline - time.monotonic()
                if left_s <= 0:
                    raise AssertionError(f"{what}: not within {timeout_s} s")
                self.arrived.wait(left_s)

    def close(self) -> None:
        os.write(self.stop_w, b"x")
        self.thread.join(timeout=5)
        for fd in (self.master, self.slave, self.stop_r, self.stop_w):
            os.close(fd)


@pytest.fixture(scope="module")
def firmware(tmp_path_factory: pytest.TempPathFactory) -> Iterator[QemuFirmware]:
    with boot_qemu(build_stm32(), tmp_path_factory.mktemp("qemu")) as booted:
        yield booted


@pytest.fixture(scope="module")
def tap(firmware: QemuFirmware) -> Iterator[WireTap]:
    wire_tap = WireTap(firmware.holder)
    yield wire_tap
    wire_tap.close()


@pytest.fixture(scope="module")
def hwsim_cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cell]:
    """hwsim serve for its camera only: the daemon's stepper link goes to the tap, not to hwsim's pty."""
    yield from serve_cell(tmp_path_factory)


def _rates(firmware: QemuFirmware) -> list[int]:
    """The drive step rates the core last set, for every module (steps/s)."""
    return [firmware.read_i32("drive_steps_per_s", m) for m in range(N)]


def _positions(firmware: QemuFirmware) -> list[int]:
    """Steps issued on the 8 stepper channels that have pins (modules 0-3)."""
    return [firmware.read_i32("step_position", c) for c in range(8)]


def _is(msg_type: int, to_firmware: bool) -> Callable[[Seen], bool]:
    return lambda f: f.msg.type == msg_type and f.to_firmware == to_firmware


def _moving_command(f: Seen) -> bool:
    if not (f.to_firmware and f.msg.type == T.COMMAND):
        return False
    speeds = [int.from_bytes(f.msg.payload[2 + 4 * i : 4 + 4 * i], "little", signed=True) for i in range(N)]
    return any(speeds)


def _acked(tap: WireTap, command: Seen) -> Seen:
    return tap.first(
        command.t_s,
        lambda f: f.msg.type == T.ACK and not f.to_firmware and f.msg.seq == command.msg.seq,
        f"the ACK of COMMAND seq {command.msg.seq}",
    )


def _move(daemon: Daemon, tap: WireTap, firmware: QemuFirmware) -> Seen:
    """A move: its COMMANDs with speeds on the wire, ACKed, and the firmware's rates set from them."""
    refusals: list[str] = []
    command = None

    def started() -> bool:
        # On a loaded machine the link may be reconnecting, or tracking starting again, for a moment; or
        # a FAULT that was on its way (the watchdog's, after a stall at the start) drops the move.
        nonlocal command
        t0 = time.monotonic()
        try:
            daemon.put_setpoint({"mode": "move", "x_m": 0.05, "y_m": 0.03, "theta_rad": 0.25})
        except httpx.HTTPStatusError as err:
            refusals.append(err.response.text)
            return False
        command = _next_moving_command(tap, t0)
        if command is None:
            refusals.append(f"accepted, then dropped: {daemon.status()['halt_reason']}")
        return command is not None

    wait(started, 90, "a move under way", every_s=0.5)
    if refusals:
        print(f"\nmove refused {len(refusals)} time(s) first: {refusals[-1]}")
    assert command is not None
    ack = _acked(tap, command)
    assert wire.parse_ack(ack.msg.payload) == 0
    wait(lambda: any(_rates(firmware)), 60, "the firmware stepping from the host's COMMANDs")
    return command


def _next_moving_command(tap: WireTap, t_s: float | None = None) -> Seen | None:
    """The first COMMAND with a speed to the firmware from t_s (None: now); None when none comes within
    MOVE_OVER_S."""
    start_s = time.monotonic() if t_s is None else t_s
    try:
        return tap.first(start_s, _moving_command, "a COMMAND with a speed", MOVE_OVER_S)
    except AssertionError:
        return None


def _sent(tap: WireTap) -> list[Seen]:
    return [f for f in tap.since(0.0) if f.to_firmware]  # in the order read


def _followed(tap: WireTap, count: int) -> bool:
    """Whether more than `count` frames have gone to the firmware within QUIET_S."""
    deadline = time.monotonic() + QUIET_S
    while len(_sent(tap)) <= count:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


def _last_frame_and_its_watchdog_fault(tap: WireTap) -> tuple[Seen, Seen] | None:
    """The daemon's last frame and the watchdog's FAULT after it; None when that frame is no COMMAND with
    a speed (killed as its link reconnected, or after the move: no move for the watchdog to stop). What
    the killed daemon wrote may still be on its way through the tap: the last frame is the last one once
    the FAULT after its ACK is there, or QUIET_S has passed, and no later frame has come (a later one would
    have re-armed the watchdog)."""
    while True:
        sent = _sent(tap)
        last = sent[-1]
        if not _moving_command(last):
            if _followed(tap, len(sent)):
                continue
            return None
        # The last COMMAND's ACK: a FAULT after it on the line was sent after the COMMAND re-armed the
        # watchdog (a stalled daemon on a loaded machine may have tripped it just before).
        ack = _acked(tap, last)
        fault = tap.first(
            ack.t_s,
            lambda f: f.msg.type == T.FAULT and not f.to_firmware and f.msg.payload[0] == FAULT_WATCHDOG,
            "the watchdog's FAULT",
        )
        if _sent(tap)[-1] is last:
            return last, fault


def _start(hwsim_cell: Cell, tap: WireTap, tmp_path: Path) -> Daemon:
    # QEMU's emulated USART on a loaded machine pauses for longer than a controller answers (150 ms by
    # default): the link waits up to a second before it takes the emulator for lost and says HELLO again.
    link = {"port": tap.path, "ack_timeout_s": 0.2, "max_retransmits": 4}
    return start_daemon(hwsim_cell, tmp_path, config={"stepper": link})


def test_clothd_run_drives_the_qemu_firmware_and_its_estop_latches(
    hwsim_cell: Cell, tap: WireTap, firmware: QemuFirmware, tmp_path: Path
) -> None:
    daemon = _start(hwsim_cell, tap, tmp_path)
    try:
        hello = tap.first(0.0, _is(T.HELLO_ACK, to_firmware=False), "the firmware's HELLO_ACK")
        assert wire.parse_hello_ack(hello.msg.payload).n_modules == N
        _move(daemon, tap, firmware)
        acked_before = daemon.status()["link"]["counters"]["acked"]

        # From a client already built and connected, as the dashboard's kept-alive connection is: a
        # fresh httpx client builds its TLS context first (25-100 ms), before it sends a byte.
        with httpx.Client(base_url=daemon.base, timeout=5) as client:
            client.get("/api/v1/status").raise_for_status()
            t_post = time.monotonic()
            client.post("/api/v1/estop").raise_for_status()
        estop = tap.first(t_post, _is(T.ESTOP, to_firmware=True), "the ESTOP frame")
        latched = tap.first(
            estop.t_s,
            lambda f: f.msg.type == T.ACK and not f.to_firmware and f.msg.seq == estop.msg.seq,
            "the ESTOP's ACK",
        )
        assert wire.parse_ack(latched.msg.payload) & wire.FLAG_ESTOP
        assert t_post <= estop.t_s <= latched.t_s
        print(
            "\nclothd run -> QEMU e-stop on the wire: POST to ESTOP frame "
            f"{(estop.t_s - t_post) * 1e3:.1f} ms, "
            f"to its ACK with the e-stop flag {(latched.t_s - t_post) * 1e3:.1f} ms "
            f"(ESTOP frame to ACK {(latched.t_s - estop.t_s) * 1e3:.1f} ms)"
        )
        assert firmware.read_u8("drivers_enabled") == 0 and not any(_rates(firmware))
        held = _positions(firmware)
        time.sleep(0.3)  # held: the daemon PINGs, sends no COMMAND, and no step is issued
        # The daemon's loop writes the ESTOP as the API process's call arrives and repeats it until the
        # firmware latches: a COMMAND between them (already on its way) is refused by the latched firmware;
        # no speed after the last (an all-stop may: a loaded machine can lose the link, which writes one on
        # its way out).
        sent = [f for f in tap.since(t_post) if f.to_firmware]
        last_estop = max(k for k, f in enumerate(sent) if f.msg.type == T.ESTOP)
        assert not [f for f in sent[last_estop:] if _moving_command(f)]
        assert firmware.read_u8("drivers_enabled") == 0 and _positions(firmware) == held

        def reported() -> bool:
            s = daemon.status()
            return bool(
                s["estop"] and s["link"]["controller_estop"] and s["link"]["counters"]["acked"] > acked_before
            )

        wait(reported, 60, "the daemon's status reporting the controller's e-stop")

        t_clear = time.monotonic()
        daemon.post("/estop/clear")
        clear = tap.first(t_clear, _is(T.ESTOP_CLEAR, to_firmware=True), "the ESTOP_CLEAR frame")
        cleared = _acked(tap, clear)
        # Released: no e-stop flag. (Its watchdog flag may be set: on a loaded machine QEMU or the tap
        # can starve past the 250 ms watchdog while the e-stop is held, and only a COMMAND clears it.)
        assert not wire.parse_ack(cleared.msg.payload) & wire.FLAG_ESTOP
        assert firmware.read_u8("drivers_enabled") == 1
    finally:
        daemon.stop()


def test_killing_clothd_run_stops_the_qemu_firmware_through_its_watchdog(
    hwsim_cell: Cell, tap: WireTap, firmware: QemuFirmware, tmp_path: Path
) -> None:
    for attempt in range(KILL_ATTEMPTS):
        (workdir := tmp_path / f"attempt{attempt}").mkdir()
        daemon = _start(hwsim_cell, tap, workdir)
        try:
            _move(daemon, tap, firmware)
            # Killed mid-move: right after a fresh COMMAND's ACK, not after the qtest reads above (on a
            # loaded machine the move may be over by then: a move is asked for again).
            judged = None
            moving = _next_moving_command(tap)
            if moving is not None:
                _acked(tap, moving)
                os.kill(daemon.proc.pid, signal.SIGKILL)
                daemon.proc.wait()
                judged = _last_frame_and_its_watchdog_fault(tap)
        finally:
            daemon.stop()
        if judged is not None:
            break
        # A loaded machine starves the emulator past the link's deadline now and then, or the move ends.
        print(f"\nattempt {attempt + 1}: killed as its link reconnected or after the move; again")
    else:
        pytest.fail(f"in {KILL_ATTEMPTS} attempts, no kill came mid-move")
    last, fault = judged
    took_s = fault.t_s - last.t_s
    print(f"\nclothd run killed -> QEMU watchdog FAULT {took_s * 1e3:.1f} ms after its last frame")
    # The firmware times from when the last frame arrived, after the tap passed it on: never sooner.
    assert took_s >= WATCHDOG_S
    wait(lambda: not any(_rates(firmware)), 60, "every module ramped to a stop")
    assert firmware.read_u8("drivers_enabled") == 1  # a controlled stop, not a cut
    still = _positions(firmware)
    time.sleep(0.1)
    assert _positions(firmware) == still
