"""The stepper controller's firmware, on a pseudo-terminal: the far end of clothd's stepper link.

This is an independent implementation of docs/serial-protocol.md (a real controller would run it in C),
so the host's driver is tested against the specification rather than against itself. The host opens
the pty's slave end by a stable symlink, as it would a /dev/serial/by-id path; `unplug` closes the
pty and, after a pause, opens a new one behind the same symlink.

Safety behaviour:
- watchdog: armed by the first COMMAND; then no valid frame for WATCHDOG_S -> every module commanded
  to stop (a controlled stop at the acceleration limit), a WATCHDOG fault sent, and the flag held until
  the next command;
- e-stop: every module's speed is cut to zero at once (drivers disabled) and latched; commands are
  refused (NACK) until ESTOP_CLEAR.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import select
import struct
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import numpy as np

from hwsim.table import Table

WATCHDOG_S = 0.25
MAX_RUN = 1024  # encoded bytes without a delimiter: past it, line noise
FIRMWARE = "hwsim-fw 1.0"
_VERSION = 1
# Message types and codes, as specified in docs/serial-protocol.md.
HELLO, COMMAND, ESTOP, ESTOP_CLEAR, PING = 0x01, 0x02, 0x03, 0x04, 0x05
ACK, HELLO_ACK, NACK, FAULT = 0x80, 0x81, 0x82, 0x90
NACK_ESTOPPED, NACK_BAD_LENGTH, NACK_UNKNOWN_TYPE, NACK_BAD_VERSION = 1, 2, 3, 4
FAULT_WATCHDOG = 1
FLAG_ESTOP, FLAG_WATCHDOG = 0x01, 0x02
_UNIT = 1e-4  # speed (m/s) and heading (rad) per int16 step
# The firmware's counters, as hwsim's truth reports them.
COUNTERS = (
    "estopped",
    "estop_t_mono_s",
    "commands_applied",
    "commands_at_estop",
    "watchdog_tripped",
    "frames_ok",
    "frames_bad",
)
Counters = dict[str, float | int | bool | None]


def _crc_ccitt(data: bytes) -> int:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def _cobs_encode(data: bytes) -> bytes:
    out = bytearray()
    for block in data.split(b"\x00"):
        while len(block) >= 254:
            out += b"\xff" + block[:254]
            block = block[254:]
        out += bytes([len(block) + 1]) + block
    return bytes(out)


def _cobs_decode(data: bytes) -> bytes | None:
    out = bytearray()
    i = 0
    while i < len(data):
        code = data[i]
        if code == 0 or i + code > len(data) + 1:
            return None
        out += data[i + 1 : i + code]
        i += code
        if code < 0xFF and i < len(data):
            out.append(0)
    return bytes(out)


def drive_targets(speed_m_s: np.ndarray, heading_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A COMMAND's signed speeds and headings as the drives' targets: a negative speed is the same motion
    with the belt turned half round."""
    return np.abs(speed_m_s), np.where(speed_m_s < 0, heading_rad + math.pi, heading_rad)


class Drives(Protocol):
    """The module drives as the firmware commands them."""

    n_modules: int

    def command(self, speed_m_s: np.ndarray, heading_rad: np.ndarray) -> None:
        """Every module's target speed (>= 0) and heading."""

    def stop_all(self) -> None:
        """A controlled stop: every target speed zero, reached at the acceleration limit."""

    def cut(self) -> None:
        """Drivers disabled: every module stops at once."""


class TableDrives:
    """The drives of a table in this process; every access holds `lock`, shared with whoever steps it."""

    def __init__(self, table: Table, lock: threading.Lock | None = None) -> None:
        self.table = table
        self.n_modules = table.n_modules
        self.lock = lock or threading.Lock()

    def command(self, speed_m_s: np.ndarray, heading_rad: np.ndarray) -> None:
        with self.lock:
            self.table.command(np.arange(self.n_modules), speed_m_s, heading_rad)

    def stop_all(self) -> None:
        with self.lock:
            self.table.stop_all()

    def cut(self) -> None:
        with self.lock:
            self.table.stop_all()
            self.table.speed_m_s[:] = 0.0


def frame(msg_type: int, seq: int, payload: bytes = b"") -> bytes:
    body = struct.pack("<BH", msg_type, seq) + payload
    return _cobs_encode(body + struct.pack("<H", _crc_ccitt(body))) + b"\x00"


class Firmware:
    """Drives the modules from the frames the host sends."""

    def __init__(
        self, drives: Drives, link_path: Path, on_change: Callable[[Counters], None] | None = None
    ) -> None:
        self.drives = drives
        self.on_change = on_change  # told the counters whenever a frame or the watchdog changed them
        self.link_path = link_path
        self.estopped = False
        self.estop_t_mono_s: float | None = None  # when the drives were last cut, host monotonic clock
        self.commands_applied = 0
        self.commands_at_estop: int | None = None  # commands applied when the e-stop arrived
        self.watchdog_tripped = False
        self.frames_ok = 0
        self.frames_bad = 0
        self.last_host_s: float | None = None
        self._last_seq: int | None = None
        self._fault_seq = 0
        self._master = -1
        self._slave = -1
        self._plugged = threading.Event()
        self._stop = threading.Event()
        self._buf = bytearray()
        self._in_noise = False  # discarding a run past MAX_RUN until the next delimiter
        self._open_pty()
        self._thread = threading.Thread(target=self._run, name="firmware", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._close_pty()

    def unplug(self, seconds: float) -> None:
        """Pull the cable for `seconds`: the host sees the port vanish, the modules stop on the watchdog."""
        self._plugged.clear()
        self._close_pty()
        threading.Timer(seconds, self._open_pty).start()

    def report_fault(self, code: int, module: int, text: str) -> None:
        self._fault_seq = (self._fault_seq + 1) & 0xFFFF
        payload = struct.pack("<BH", code, module) + text.encode("ascii", errors="replace")
        self._send(frame(FAULT, self._fault_seq, payload))

    # -- the pty ----------------------------------------------------------------------------------

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline: a byte pipe like a USB CDC port
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        tmp = self.link_path.with_suffix(".new")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(self.link_path)
        self._buf.clear()
        self._in_noise = False
        self._plugged.set()

    def _close_pty(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    # -- the firmware loop ------------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self._plugged.wait(timeout=0.05):
                self._check_watchdog()
                continue
            master = self._master
            try:
                ready, _, _ = select.select([master], [], [], 0.01)
                data = os.read(master, 4096) if ready else b""
            except OSError as err:
                if err.errno not in (errno.EIO, errno.EBADF, errno.EAGAIN):
                    raise
                data = b""
                time.sleep(0.01)
            if data:
                self._receive(data)
            self._check_watchdog()

    def counters(self) -> Counters:
        return {name: getattr(self, name) for name in COUNTERS}

    def _changed(self) -> None:
        if self.on_change is not None:
            self.on_change(self.counters())

    def _receive(self, data: bytes) -> None:
        """A run of more than MAX_RUN bytes without a delimiter is line noise: dropped up to the next zero
        and counted invalid once (docs/serial-protocol.md)."""
        self._buf += data
        *packets, rest = self._buf.split(b"\x00")
        for packet in packets:
            if self._in_noise:  # the end of a run already counted
                self._in_noise = False
            elif len(packet) > MAX_RUN:
                self.frames_bad += 1
            elif packet:
                self._handle(bytes(packet))
        if len(rest) > MAX_RUN:
            self.frames_bad += 0 if self._in_noise else 1
            self._in_noise, rest = True, bytearray()
        self._buf = bytearray(rest)
        self._changed()

    def _handle(self, packet: bytes) -> None:
        raw = _cobs_decode(packet)
        if raw is None or len(raw) < 5 or _crc_ccitt(raw[:-2]) != struct.unpack("<H", raw[-2:])[0]:
            self.frames_bad += 1
            return
        self.frames_ok += 1
        self.last_host_s = time.monotonic()
        msg_type, seq = struct.unpack("<BH", raw[:3])
        payload = raw[3:-2]
        if msg_type == HELLO:
            if not payload or payload[0] != _VERSION:
                self._send(frame(NACK, seq, bytes([NACK_BAD_VERSION])))
                return
            hello = struct.pack("<BH", _VERSION, self.drives.n_modules) + FIRMWARE.encode()
            self._last_seq = None  # a new host session: its first COMMAND is never a retransmit
            self._send(frame(HELLO_ACK, seq, hello))
        elif msg_type == COMMAND:
            self._command(seq, payload)
        elif msg_type == ESTOP:
            self.drives.cut()
            self.estopped = True
            self.estop_t_mono_s = time.monotonic()
            self.commands_at_estop = self.commands_applied
            self._ack(seq)
        elif msg_type == ESTOP_CLEAR:
            self.estopped = False
            self._ack(seq)
        elif msg_type == PING:
            self._ack(seq)
        else:
            self._send(frame(NACK, seq, bytes([NACK_UNKNOWN_TYPE])))

    def _command(self, seq: int, payload: bytes) -> None:
        n = self.drives.n_modules
        if len(payload) != 2 + 4 * n or struct.unpack("<H", payload[:2])[0] != n:
            self._send(frame(NACK, seq, bytes([NACK_BAD_LENGTH])))
            return
        if self.estopped:
            self._send(frame(NACK, seq, bytes([NACK_ESTOPPED])))
            return
        if seq != self._last_seq:  # a retransmit of what was applied is only acknowledged again
            values = np.frombuffer(payload[2:], dtype="<i2").reshape(n, 2).astype(float) * _UNIT
            self.drives.command(*drive_targets(values[:, 0], values[:, 1]))
            self.watchdog_tripped = False
            self._last_seq = seq
            self.commands_applied += 1
        self._ack(seq)

    def _check_watchdog(self) -> None:
        # Before the first COMMAND no host has driven anything: a host that said HELLO and went quiet
        # (a handshake that timed out, a daemon still starting) left nothing running to stop.
        if self.last_host_s is None or not self.commands_applied or self.watchdog_tripped:
            return
        if time.monotonic() - self.last_host_s > WATCHDOG_S:
            self.drives.stop_all()
            self.watchdog_tripped = True
            self._changed()
            self.report_fault(FAULT_WATCHDOG, 0xFFFF, "host silent: all modules stopped")

    def _flags(self) -> int:
        return (FLAG_ESTOP if self.estopped else 0) | (FLAG_WATCHDOG if self.watchdog_tripped else 0)

    def _ack(self, seq: int) -> None:
        self._send(frame(ACK, seq, bytes([self._flags()])))

    def _send(self, data: bytes) -> None:
        master = self._master
        if master < 0:
            return
        with contextlib.suppress(OSError):  # nobody on the other end, or unplugged meanwhile
            os.write(master, data)
