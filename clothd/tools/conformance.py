"""`clothd conformance`: takes a stepper controller through every rule of docs/serial-protocol.md and
reports a pass/fail table with figures (docs/conformance.md).

The checks (clothd/tools/conformance_checks.py) talk to the controller through a `Session`: the serial
port, the sequence counter, and the FAULT frames that arrived meanwhile. Against hwsim's firmware
(`--sim`) the session also has `SimDrives`, which reads what the firmware told the drives through
hwsim's drive bus: what a vendor's board does to its drives cannot be seen over the wire.
"""

from __future__ import annotations

import json
import select
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import serial

from clothd.drivers import wire
from clothd.errors import HardwareError
from hwsim.firmware_process import FirmwareProcess
from hwsim.scenario import TableSpec
from hwsim.table import Table

BAUD = 921600  # the daemon's stepper.baud default; a pty or USB CDC port ignores it
REPLY_TIMEOUT_S = 0.5  # later than this is no answer; generous for a loaded PC (the host gives up at 150 ms)
FIRST_SEQ = 65530  # near the wrap, so that the run crosses it (seq wraps at 65536)
NOT_OBSERVABLE = "not observable over the wire"


@dataclass(frozen=True)
class Row:
    """One check's result: passed is None where the rule cannot be observed over the wire."""

    name: str
    passed: bool | None
    figure: str = ""
    detail: str = ""


@dataclass(frozen=True)
class Received:
    msg: wire.Message
    t_s: float  # arrival, time.monotonic()


class Port:
    """The controller's serial device in raw mode, read frame by frame with deadlines."""

    def __init__(self, path: str) -> None:
        self.path = path
        try:
            self._serial = serial.Serial(path, baudrate=BAUD, timeout=0, write_timeout=1.0)
        except serial.SerialException as err:
            raise HardwareError(f"cannot open the controller's port {path}: {err}") from None
        self._splitter = wire.FrameSplitter()
        self._pending: list[bytes] = []
        self.invalid_answers = 0  # frames from the controller that did not decode

    def write(self, data: bytes) -> float:
        """Writes data; returns when it left, time.monotonic()."""
        self._serial.write(data)
        return time.monotonic()

    def receive(self, timeout_s: float) -> Received | None:
        """The next valid frame from the controller, or None after timeout_s."""
        deadline = time.monotonic() + timeout_s
        while True:
            while self._pending:
                try:
                    return Received(wire.decode(self._pending.pop(0)), time.monotonic())
                except wire.WireError:
                    self.invalid_answers += 1
            left_s = deadline - time.monotonic()
            if left_s <= 0:
                return None
            ready, _, _ = select.select([self._serial.fileno()], [], [], left_s)
            if ready:
                self._pending += self._splitter.feed(self._serial.read(4096))

    def close(self) -> None:
        self._serial.close()


@dataclass(frozen=True)
class DriveState:
    """What the firmware last told the drives, before the drives' own limits."""

    speed_m_s: np.ndarray
    heading_rad: np.ndarray
    cut: bool  # drivers disabled (the e-stop's stop, no ramp) since the last read


class _TargetsTable(Table):
    """hwsim's table that also keeps the targets the drive bus gives it, before it clips them."""

    def __init__(self, spec: TableSpec) -> None:
        super().__init__(spec)
        self.targets = (np.zeros(self.n_modules), np.zeros(self.n_modules))

    def command(
        self, ids: np.ndarray, speed_m_s: np.ndarray | float, heading_rad: np.ndarray | float
    ) -> None:
        self.targets = (np.array(speed_m_s, dtype=float), np.array(heading_rad, dtype=float))
        super().command(ids, speed_m_s, heading_rad)


class SimDrives:
    """hwsim's drives behind its firmware's process, read through the drive bus."""

    def __init__(self, firmware: FirmwareProcess, spec: TableSpec) -> None:
        self.firmware = firmware
        self.table = _TargetsTable(spec)

    def read(self) -> DriveState:
        # A cut zeroes the drives' speeds at once: a sentinel speed shows whether one came.
        speed_m_s = self.table.speed_m_s.copy()
        self.table.speed_m_s[:] = 1.0
        self.firmware.bus.apply_to(self.table)
        cut = not self.table.speed_m_s.any()
        self.table.speed_m_s[:] = 0.0 if cut else speed_m_s
        target_m_s, target_rad = self.table.targets
        return DriveState(target_m_s, target_rad, cut)

    def commands_applied(self) -> int:
        return int(self.firmware.counters()["commands_applied"] or 0)


@dataclass
class Session:
    """What every check shares: the port, the module count, the drives where they can be read."""

    port: Port
    n_modules: int | None  # from --modules, else HELLO_ACK's
    drives: SimDrives | None = None
    faults: list[Received] = field(default_factory=list)  # FAULT frames, oldest first
    skipped: list[Received] = field(default_factory=list)  # replies the last ask() passed over
    seq: int = FIRST_SEQ
    stop: str | None = None  # why no further check can mean anything (a board of another size)

    def next_seq(self) -> int:
        self.seq = (self.seq + 1) & 0xFFFF
        return self.seq

    def send(self, msg_type: int, payload: bytes = b"", seq: int | None = None) -> tuple[int, float]:
        """Sends a frame; returns its seq and when it left."""
        seq = self.next_seq() if seq is None else seq
        return seq, self.port.write(wire.encode(msg_type, seq, payload))

    def next_reply(self, timeout_s: float = REPLY_TIMEOUT_S) -> Received | None:
        """The next frame that is not a FAULT (those are kept in `faults`)."""
        deadline = time.monotonic() + timeout_s
        while (got := self.port.receive(max(0.0, deadline - time.monotonic()))) is not None:
            if got.msg.type != wire.MsgType.FAULT:
                return got
            self.faults.append(got)
        return None

    def ask(
        self, msg_type: int, payload: bytes = b"", seq: int | None = None
    ) -> tuple[Received | None, float]:
        """Sends a frame and waits for the reply that carries its seq; returns it and the round trip in ms."""
        seq, sent_s = self.send(msg_type, payload, seq)
        deadline = sent_s + REPLY_TIMEOUT_S
        self.skipped = []
        while (got := self.next_reply(max(0.0, deadline - time.monotonic()))) is not None:
            if got.msg.seq == seq:
                return got, (got.t_s - sent_s) * 1e3
            self.skipped.append(got)
        return None, (time.monotonic() - sent_s) * 1e3

    def command(self, speed_m_s: float | np.ndarray = 0.0, heading_rad: float | np.ndarray = 0.0) -> bytes:
        """A COMMAND payload for every module."""
        n = self.n_modules or 0
        speed, heading = np.broadcast_to(speed_m_s, n), np.broadcast_to(heading_rad, n)
        return wire.command_payload(np.asarray(speed, dtype=float), np.asarray(heading, dtype=float))


Check = Callable[[Session], Row | list[Row]]  # a check may report a rule per row


def run_checks(session: Session, checks: list[Check]) -> list[Row]:
    """Every check in order; one that raises is a FAIL with the error, and the run goes on."""
    rows = []
    for check in checks:
        try:
            got = check(session)
            rows += got if isinstance(got, list) else [got]
        except Exception as err:  # a vendor's controller may answer anything: report it, go on
            name = check.__name__.removeprefix("check_")
            where = traceback.extract_tb(err.__traceback__)[-1]
            rows.append(Row(name, False, "", f"{type(err).__name__}: {err} (line {where.lineno})"))
        if session.n_modules is None or session.stop is not None:
            why = session.stop or "no module count: nothing else can be checked"
            rows.append(Row("handshake.modules", False, "", why))
            break
    return rows


def format_rows(rows: list[Row]) -> str:
    words = {True: "pass", False: "FAIL", None: "n/o"}
    name_w = max(len("check"), *(len(r.name) for r in rows))
    fig_w = max(len("figure"), *(len(r.figure) for r in rows))
    lines = [f"{'check':<{name_w}}  result  {'figure':<{fig_w}}  detail"]
    lines += [
        f"{r.name:<{name_w}}  {words[r.passed]:<6}  {r.figure:<{fig_w}}  {r.detail}".rstrip() for r in rows
    ]
    failed = sum(r.passed is False for r in rows)
    unseen = sum(r.passed is None for r in rows)
    lines.append(f"{len(rows) - failed - unseen} passed, {failed} failed, {unseen} {NOT_OBSERVABLE} (n/o)")
    return "\n".join(lines)


def write_json(path: Path, port: str, rows: list[Row]) -> None:
    passed = not any(r.passed is False for r in rows)
    doc = {"port": port, "passed": passed, "checks": [asdict(r) for r in rows]}
    path.write_text(json.dumps(doc, indent=2) + "\n")


def sim_session(firmware: FirmwareProcess, spec: TableSpec) -> Session:
    return Session(Port(str(firmware.link_path)), None, SimDrives(firmware, spec))
