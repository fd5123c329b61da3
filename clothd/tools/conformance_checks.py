"""The conformance checks, one rule of docs/serial-protocol.md each, in the order they run: every check
leaves the controller in a state the next one can start from (not e-stopped, watchdog fed)."""

from __future__ import annotations

import random
import struct
import time

import numpy as np
from cobs import cobs

from clothd.drivers import wire
from clothd.tools.conformance import NOT_OBSERVABLE, REPLY_TIMEOUT_S, Check, Received, Row, Session

T = wire.MsgType
NACK_ESTOPPED, NACK_BAD_LENGTH, NACK_UNKNOWN_TYPE, NACK_BAD_VERSION = 1, 2, 3, 4
FAULT_WATCHDOG, FAULT_STALL = 1, 2
FAULT_CODES = {1: "WATCHDOG", 2: "STALL", 3: "OVERTEMP", 4: "ESTOP_INPUT"}
WATCHDOG_MS = 250.0
CONTROL_PERIOD_MS = 1000.0 / 30.0  # the host's tick: the watchdog may fire one tick late
UNKNOWN_TYPE = 0x42  # no message of docs/serial-protocol.md
GARBAGE_SEED = 20261127
CRUISE_M_S = 0.05  # a speed that moves something, so that stopping it can be seen
HELLO_TRIES = 4  # 2 s for a port that opens late
SIM_STEPS = 6  # drive model steps of one control period, for the limits on hwsim's drives
TOLERANCE = 1e-6


def _describe(got: Received | None) -> str:
    if got is None:
        return f"no answer within {REPLY_TIMEOUT_S * 1e3:.0f} ms"
    msg = got.msg
    if msg.type == T.NACK and msg.payload:
        return f"NACK reason {msg.payload[0]} (seq {msg.seq})"
    if msg.type == T.ACK and msg.payload:
        return f"ACK flags 0x{msg.payload[0]:02x} (seq {msg.seq})"
    return f"type 0x{msg.type:02x} (seq {msg.seq})"


def _is(got: Received | None, msg_type: int, first_byte: int | None = None) -> bool:
    if got is None or got.msg.type != msg_type:
        return False
    return first_byte is None or got.msg.payload[:1] == bytes([first_byte])


def _flags(got: Received | None) -> int | None:
    """An ACK's status flags; None for anything else."""
    if got is None or got.msg.type != T.ACK:
        return None
    return wire.parse_ack(got.msg.payload)


def _expect(
    s: Session, name: str, msg_type: int, payload: bytes, want: int, reason: int | None = None
) -> Row:
    """Sends one frame; passes when the reply to it is `want` (with that NACK reason)."""
    got, rtt_ms = s.ask(msg_type, payload)
    ok = _is(got, want, reason)
    return Row(name, ok, f"{rtt_ms:.1f} ms", "" if ok else f"got {_describe(got)}")


# -- handshake and PING ----------------------------------------------------------------------------------


def check_handshake_hello(s: Session) -> Row:
    """HELLO, sent again up to HELLO_TRIES times: a port may start reading only after it is opened (QEMU
    notices a new opener up to a second late), and the daemon's link retries its handshake too."""
    got: Received | None = None
    rtt_ms, attempt = 0.0, 0
    while attempt < HELLO_TRIES and (attempt == 0 or got is None):  # again only when nothing came back
        attempt += 1
        got, rtt_ms = s.ask(T.HELLO, wire.hello_payload())
    if got is None or not _is(got, T.HELLO_ACK):
        detail = f"{attempt} HELLOs: the last got {_describe(got)}"
        return Row("handshake.hello", False, f"{rtt_ms:.1f} ms", detail)
    ack = wire.parse_hello_ack(got.msg.payload)
    problems = []
    if ack.version != wire.PROTOCOL_VERSION:
        problems.append(f"version {ack.version}, not {wire.PROTOCOL_VERSION}")
    if s.n_modules is None:
        s.n_modules = ack.n_modules
    elif ack.n_modules != s.n_modules:
        problems.append(f"{ack.n_modules} modules, not the {s.n_modules} of --modules")
        s.stop = (
            f"the board drives {ack.n_modules} modules, --modules says {s.n_modules}: nothing else is checked"
        )
    figure = f"v{ack.version}, {ack.n_modules} modules, {rtt_ms:.1f} ms"
    detail = "; ".join(problems) or f"firmware {ack.firmware!r}"
    if attempt > 1:
        detail += f" (the answer came to HELLO {attempt} of {HELLO_TRIES})"
    return Row("handshake.hello", not problems, figure, detail)


def check_handshake_bad_version(s: Session) -> Row:
    bad_version = bytes([wire.PROTOCOL_VERSION + 1])
    return _expect(s, "handshake.bad_version", T.HELLO, bad_version, T.NACK, NACK_BAD_VERSION)


def check_ping(s: Session) -> Row:
    return _expect(s, "ping", T.PING, b"", T.ACK)


# -- framing: what must be dropped without an answer -------------------------------------------------------


def _ignored(s: Session, name: str, bad: bytes) -> Row:
    """Writes bad bytes, then a PING: the PING's ACK must be the first answer (replies come in order)."""
    s.port.write(bad)
    got, rtt_ms = s.ask(T.PING)
    if s.skipped:
        return Row(name, False, "", f"answered the bad frame: {_describe(s.skipped[0])}")
    if not _is(got, T.ACK):
        return Row(name, False, "", f"the next PING got {_describe(got)}: the controller stopped answering")
    return Row(name, True, f"{rtt_ms:.1f} ms", "dropped; the next PING was ACKed")


def _ping_body(seq: int) -> bytes:
    return struct.pack("<BH", T.PING, seq)


def check_framing_bad_crc(s: Session) -> Row:
    seq = s.next_seq()
    body = _ping_body(seq)
    raw = body + struct.pack("<H", wire.crc16(body) ^ 0x5A5A)
    return _ignored(s, "framing.bad_crc", cobs.encode(raw) + b"\x00")


def check_framing_bad_cobs(s: Session) -> Row:
    seq = s.next_seq()
    packet = bytearray(wire.encode(T.PING, seq)[:-1])
    packet[0] = min(255, len(packet) + 3)  # the first block claims more bytes than the frame has
    return _ignored(s, "framing.bad_cobs", bytes(packet) + b"\x00")


def check_framing_short(s: Session) -> Row:
    seq = s.next_seq()
    body = _ping_body(seq)[:2]  # 4 bytes with the CRC: under the 5-byte minimum, but the CRC is right
    return _ignored(s, "framing.short", cobs.encode(body + struct.pack("<H", wire.crc16(body))) + b"\x00")


def check_framing_garbage(s: Session) -> Row:
    garbage = random.Random(GARBAGE_SEED).randbytes(512)  # line noise, zeros included
    return _ignored(s, "framing.garbage", garbage + b"\x00")


def check_framing_overlong(s: Session) -> Row:
    """1100 bytes without a delimiter, ending in a whole valid PING: one run past 1024 bytes, dropped."""
    seq = s.next_seq()
    run = b"\x55" * (wire.MAX_FRAME_BYTES + 76) + wire.encode(T.PING, seq)
    return _ignored(s, "framing.overlong", run)


# -- sequence numbers ---------------------------------------------------------------------------------------


def _applied(s: Session) -> int | None:
    return s.drives.commands_applied() if s.drives is not None else None


def check_seq_ack(s: Session) -> Row:
    """Two COMMANDs across the wrap (65535, then 0): each ACKed with its own seq."""
    before = _applied(s)
    rtts_ms, problems = [], []
    for seq in (0xFFFF, 0x0000):
        got, rtt_ms = s.ask(T.COMMAND, s.command(), seq=seq)
        rtts_ms.append(rtt_ms)
        if not _is(got, T.ACK):
            problems.append(f"COMMAND seq {seq} got {_describe(got)}")
    s.seq = 0
    after = _applied(s)
    if before is not None and after is not None and not problems and after != before + 2:
        problems.append(f"{after - before} of the 2 applied (the drive bus's count)")
    return Row(
        "seq.ack", not problems, f"{max(rtts_ms):.1f} ms", "; ".join(problems) or "seq 65535 and 0 ACKed"
    )


def check_seq_duplicate(s: Session) -> list[Row]:
    """A retransmit (same seq, same bytes) is ACKed again, and not applied again."""
    seq = s.next_seq()
    payload = s.command(CRUISE_M_S)
    first, _ = s.ask(T.COMMAND, payload, seq=seq)
    before = _applied(s)
    again, rtt_ms = s.ask(T.COMMAND, payload, seq=seq)
    ok = _is(first, T.ACK) and _is(again, T.ACK)
    detail = f"first got {_describe(first)}, the retransmit {_describe(again)}"
    acked = Row("seq.duplicate", ok, f"{rtt_ms:.1f} ms", "ACKed again" if ok else detail)
    after = _applied(s)
    if before is None or after is None:
        return [acked, Row("seq.applied_once", None, "", NOT_OBSERVABLE)]
    once = Row(
        "seq.applied_once", after == before, f"{after - before} more applied", "by the drive bus's count"
    )
    return [acked, once]


def check_seq_unknown_type(s: Session) -> Row:
    return _expect(s, "seq.unknown_type", UNKNOWN_TYPE, b"", T.NACK, NACK_UNKNOWN_TYPE)


def check_seq_bad_length(s: Session) -> Row:
    """One module too many (n and payload agree), then n right but the payload a byte short."""
    n = s.n_modules or 0
    too_many = struct.pack("<H", n + 1) + bytes(4 * (n + 1))
    too_short = s.command()[:-1]
    rows = [
        _expect(s, "seq.bad_length", T.COMMAND, p, T.NACK, NACK_BAD_LENGTH) for p in (too_many, too_short)
    ]
    failed = [f"{what}: {r.detail}" for what, r in zip(("n + 1", "short"), rows, strict=True) if not r.passed]
    return Row("seq.bad_length", not failed, rows[-1].figure, "; ".join(failed))


# -- limits -------------------------------------------------------------------------------------------------


def _full_range(n: int) -> tuple[bytes, np.ndarray, np.ndarray]:
    """A COMMAND at the ends of the int16 fields (±3.2767 m/s, ±3.2767 rad), every sign pairing."""
    k = np.arange(n)
    speed = np.where(k % 2 == 0, 32767, -32767)
    heading = np.where(k % 4 < 2, 32767, -32767)
    pairs = np.stack([speed, heading], axis=1).astype("<i2")
    return (
        struct.pack("<H", n) + pairs.tobytes(),
        speed * wire.SPEED_UNIT_M_S,
        heading * wire.HEADING_UNIT_RAD,
    )


def check_limits(s: Session) -> list[Row]:
    """The full range is accepted (no NACK reason covers a value); on hwsim, a negative speed reaches the
    drives as the same motion with the belt turned half round, and the drives keep their limits."""
    payload, speed_m_s, heading_rad = _full_range(s.n_modules or 0)
    got, rtt_ms = s.ask(T.COMMAND, payload)
    accepted = Row(
        "limits.full_range", _is(got, T.ACK), f"{rtt_ms:.1f} ms", f"±3.2767 m/s and rad: {_describe(got)}"
    )
    if s.drives is None:
        unseen = f"{NOT_OBSERVABLE} (the board's drives)"
        names = ("negative_speed", "speed", "accel", "steer_rate")
        return [accepted, *(Row(f"limits.{name}", None, "", unseen) for name in names)]
    state = s.drives.read()
    asked = speed_m_s[:, None] * np.stack([np.cos(heading_rad), np.sin(heading_rad)], axis=1)
    told = state.speed_m_s[:, None] * np.stack([np.cos(state.heading_rad), np.sin(state.heading_rad)], axis=1)
    error_m_s = float(np.abs(asked - told).max())
    same = Row("limits.negative_speed", error_m_s < 1e-3, f"{error_m_s:.1e} m/s", "same motion vector")
    return [accepted, same, *_drive_limits(s)]


def _drive_limits(s: Session) -> list[Row]:
    """hwsim's drive model, stepped from the drive bus's targets one control period at a time."""
    assert s.drives is not None
    table, dt_s = s.drives.table, CONTROL_PERIOD_MS / 1e3
    spec = table.spec
    top_m_s = accel_m_s2 = steer_rad_s = 0.0
    for _ in range(SIM_STEPS):
        speed_m_s, heading_rad = table.speed_m_s.copy(), table.heading_rad.copy()
        table.step(dt_s)
        turn_rad = np.angle(np.exp(1j * (table.heading_rad - heading_rad)))
        top_m_s = max(top_m_s, float(np.abs(table.speed_m_s).max()))
        accel_m_s2 = max(accel_m_s2, float(np.abs(table.speed_m_s - speed_m_s).max()) / dt_s)
        steer_rad_s = max(steer_rad_s, float(np.abs(turn_rad).max()) / dt_s)
    return [
        _at_most("limits.speed", top_m_s, spec.max_speed_m_s, "m/s"),
        _at_most("limits.accel", accel_m_s2, spec.accel_limit_m_s2, "m/s²"),
        _at_most("limits.steer_rate", steer_rad_s, spec.steer_rate_limit_rad_s, "rad/s"),
    ]


def _at_most(name: str, value: float, limit: float, unit: str) -> Row:
    return Row(
        name, value <= limit + TOLERANCE, f"{value:.3g} {unit}", f"limit {limit:g} {unit} (hwsim's drives)"
    )


# -- e-stop -------------------------------------------------------------------------------------------------


def check_estop(s: Session) -> list[Row]:
    """ESTOP is ACKed with the e-stop flag; the drives are cut at once (no ramp)."""
    if s.drives is not None:
        s.drives.read()  # from here, a cut is the e-stop's
    got, rtt_ms = s.ask(T.ESTOP)
    flags = _flags(got)
    ok = flags is not None and bool(flags & wire.FLAG_ESTOP)
    acked = Row("estop.ack", ok, f"{rtt_ms:.1f} ms", "" if ok else f"got {_describe(got)}, no e-stop flag")
    if s.drives is None:
        return [acked, Row("estop.cut", None, "", f"{NOT_OBSERVABLE} (the board's drives)")]
    state = s.drives.read()
    cut = state.cut and not state.speed_m_s.any()
    return [acked, Row("estop.cut", cut, "", "drives cut at once" if cut else "the drives were not cut")]


def check_estop_refuses(s: Session) -> Row:
    before = _applied(s)
    row = _expect(s, "estop.refuses", T.COMMAND, s.command(CRUISE_M_S), T.NACK, NACK_ESTOPPED)
    after = _applied(s)
    if before is not None and after is not None and after != before:
        return Row(row.name, False, row.figure, f"{row.detail} the COMMAND was applied".strip())
    return row


def check_estop_clear(s: Session) -> Row:
    got, rtt_ms = s.ask(T.ESTOP_CLEAR)
    flags = _flags(got)
    if flags is None or flags & wire.FLAG_ESTOP:
        return Row("estop.clear", False, f"{rtt_ms:.1f} ms", f"ESTOP_CLEAR got {_describe(got)}")
    after, _ = s.ask(T.COMMAND, s.command())
    ok = _is(after, T.ACK)
    return Row(
        "estop.clear", ok, f"{rtt_ms:.1f} ms", "COMMANDs accepted again" if ok else f"got {_describe(after)}"
    )


# -- watchdog and faults ------------------------------------------------------------------------------------


def _next_fault(s: Session, deadline_s: float) -> tuple[Received | None, list[Received]]:
    """The next FAULT before deadline_s (time.monotonic()), and the other frames that came first."""
    others: list[Received] = []
    while (got := s.port.receive(max(0.0, deadline_s - time.monotonic()))) is not None:
        if got.msg.type == T.FAULT:
            s.faults.append(got)
            return got, others
        others.append(got)
    return None, others


def check_watchdog(s: Session) -> list[Row]:
    """After the last COMMAND, silence: a FAULT(WATCHDOG) within the watchdog time plus one period, and
    the drives brought to a controlled stop."""
    if s.drives is not None:
        s.drives.read()  # from here, a cut would be the watchdog's
    return [_watchdog_fault(s), _watchdog_stop(s)]


def _watchdog_fault(s: Session) -> Row:
    got, rtt_ms = s.ask(T.COMMAND, s.command(CRUISE_M_S))
    if got is None or not _is(got, T.ACK):
        return Row("watchdog.fault", False, "", f"the COMMAND before the silence got {_describe(got)}")
    sent_s = got.t_s - rtt_ms / 1e3
    bound_ms = WATCHDOG_MS + CONTROL_PERIOD_MS
    fault, others = _next_fault(s, sent_s + 2 * bound_ms / 1e3)
    if fault is None:
        waited_ms = (time.monotonic() - sent_s) * 1e3
        return Row(
            "watchdog.fault", False, f"> {waited_ms:.0f} ms", "no FAULT: the silent host went unnoticed"
        )
    latency_ms = (fault.t_s - sent_s) * 1e3
    code = wire.parse_fault(fault.msg.payload).code
    problems = [f"code {code}, not WATCHDOG"] if code != FAULT_WATCHDOG else []
    if not WATCHDOG_MS <= latency_ms <= bound_ms:
        problems.append(f"outside {WATCHDOG_MS:.0f}-{bound_ms:.0f} ms")
    problems += [f"sent {_describe(r)} unasked" for r in others]
    detail = "; ".join(problems) or f"bound {WATCHDOG_MS:.0f}-{bound_ms:.0f} ms"
    return Row("watchdog.fault", not problems, f"{latency_ms:.1f} ms", detail)


def _watchdog_stop(s: Session) -> Row:
    if s.drives is None:
        return Row("watchdog.stop", None, "", f"{NOT_OBSERVABLE} (the board's drives)")
    state = s.drives.read()
    if state.cut:
        return Row("watchdog.stop", False, "", "the drives were cut: the watchdog's stop is a ramp")
    moving = int(np.count_nonzero(state.speed_m_s))
    detail = "every target 0, ramped (not cut)" if not moving else "modules still told to move"
    return Row("watchdog.stop", not moving, f"{moving} moving", detail)


def check_watchdog_flag(s: Session) -> Row:
    """The watchdog flag is set in ACKs after the trip, until the next COMMAND."""
    ping, _ = s.ask(T.PING)
    command, rtt_ms = s.ask(T.COMMAND, s.command())
    set_flags, cleared_flags = _flags(ping), _flags(command)
    ok = set_flags is not None and bool(set_flags & wire.FLAG_WATCHDOG)
    ok = ok and cleared_flags is not None and not cleared_flags & wire.FLAG_WATCHDOG
    detail = f"PING got {_describe(ping)}, then COMMAND {_describe(command)}"
    return Row("watchdog.flag", ok, f"{rtt_ms:.1f} ms", "set, then cleared by a COMMAND" if ok else detail)


def _fault_problems(s: Session, fault: wire.Fault) -> list[str]:
    problems = [] if fault.code in FAULT_CODES else [f"unknown code {fault.code}"]
    if fault.module != 0xFFFF and fault.module >= (s.n_modules or 0):
        problems.append(f"module {fault.module} of {s.n_modules}")
    if not fault.text.isascii() or not fault.text.isprintable():
        problems.append(f"text {fault.text!r} is not printable ASCII")
    return problems


def check_fault_format(s: Session) -> Row:
    """The FAULT frames seen so far (the watchdog's at least) parse as code, module and ASCII text."""
    if not s.faults:
        return Row("fault.format", False, "0 seen", "no FAULT arrived (the watchdog's should have)")
    problems = [p for r in s.faults for p in _fault_problems(s, wire.parse_fault(r.msg.payload))]
    return Row("fault.format", not problems, f"{len(s.faults)} seen", "; ".join(problems))


def check_fault_report(s: Session) -> Row:
    """On hwsim, a fault raised inside the firmware reaches the host intact."""
    if s.drives is None:
        return Row("fault.report", None, "", f"{NOT_OBSERVABLE}: the board raises its own faults")
    module = min(7, (s.n_modules or 1) - 1)
    raised = wire.Fault(FAULT_STALL, module, f"conformance: stall on module {module}")
    sent_s = time.monotonic()
    s.drives.firmware.report_fault(raised.code, raised.module, raised.text)
    fault, _ = _next_fault(s, sent_s + 1.0)
    while fault is not None and wire.parse_fault(fault.msg.payload).code == FAULT_WATCHDOG:
        fault, _ = _next_fault(s, sent_s + 1.0)  # the watchdog may trip meanwhile: not this one
    if fault is None:
        return Row("fault.report", False, "", "the raised FAULT did not arrive within 1 s")
    arrived = wire.parse_fault(fault.msg.payload)
    ok = arrived == raised
    detail = f"code {arrived.code}, module {arrived.module}, {arrived.text!r}"
    return Row("fault.report", ok, f"{(fault.t_s - sent_s) * 1e3:.1f} ms", detail if ok else f"got {detail}")


def check_answers_valid(s: Session) -> Row:
    """Every frame the controller sent during the run decoded (COBS, CRC, length)."""
    bad = s.port.invalid_answers
    return Row(
        "framing.answers_valid", bad == 0, f"{bad} invalid", "" if not bad else "frames that do not decode"
    )


CHECKS: list[Check] = [
    check_handshake_hello,
    check_handshake_bad_version,
    check_ping,
    check_framing_bad_crc,
    check_framing_bad_cobs,
    check_framing_short,
    check_framing_garbage,
    check_framing_overlong,
    check_seq_ack,
    check_seq_duplicate,
    check_seq_unknown_type,
    check_seq_bad_length,
    check_limits,
    check_estop,
    check_estop_refuses,
    check_estop_clear,
    check_watchdog,
    check_watchdog_flag,
    check_fault_format,
    check_fault_report,
    check_answers_valid,
]
