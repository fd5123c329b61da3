"""The stepper link's wire format, host side (docs/serial-protocol.md is the specification).

A frame on the wire is COBS(body + CRC-16) followed by a 0x00 delimiter, so a receiver finds the next
frame after any corruption by waiting for the next zero. body = type (u8), seq (u16 LE), payload.
CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over body, appended little-endian.
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from cobs import cobs

PROTOCOL_VERSION = 1
DELIMITER = b"\x00"  # ends a frame; a lone one ends a frame cut midway (an empty frame is no error)
MAX_FRAME_BYTES = 1024  # longer runs without a delimiter are noise, not frames
SPEED_UNIT_M_S = 1e-4  # int16 payload units: ±3.27 m/s
HEADING_UNIT_RAD = 1e-4  # int16: ±3.27 rad, enough for (-π, π]


class MsgType(IntEnum):
    HELLO = 0x01
    COMMAND = 0x02
    ESTOP = 0x03
    ESTOP_CLEAR = 0x04
    PING = 0x05
    ACK = 0x80
    HELLO_ACK = 0x81
    NACK = 0x82
    FAULT = 0x90


# Controller status flags carried in every ACK.
FLAG_ESTOP = 0x01
FLAG_WATCHDOG = 0x02
FAULT_NAMES = {1: "WATCHDOG", 2: "STALL", 3: "OVERTEMP", 4: "ESTOP_INPUT"}
FAULT_ESTOP_INPUT = 4  # the cell's hardware e-stop chain opened
WHOLE_CONTROLLER = 0xFFFF  # a FAULT's module: the controller as a whole
NACK_ESTOPPED = 1  # a NACK's reason: a COMMAND while the controller's e-stop is latched


class WireError(ValueError):
    """Bytes that are not a valid frame."""


@dataclass(frozen=True)
class Message:
    type: int
    seq: int
    payload: bytes


def crc16(data: bytes) -> int:
    return binascii.crc_hqx(data, 0xFFFF)


def seq_before(seq: int, other: int) -> bool:
    """Whether message seq was sent before message other: sequence numbers count up modulo 2^16."""
    return 0 < (other - seq) & 0xFFFF < 0x8000


def encode(msg_type: int, seq: int, payload: bytes = b"") -> bytes:
    body = struct.pack("<BH", msg_type, seq & 0xFFFF) + payload
    return cobs.encode(body + struct.pack("<H", crc16(body))) + DELIMITER


def decode(packet: bytes) -> Message:
    """One frame from the bytes between two delimiters (without them)."""
    try:
        raw = cobs.decode(packet)
    except cobs.DecodeError as err:
        raise WireError(f"bad COBS: {err}") from None
    if len(raw) < 5:
        raise WireError(f"frame of {len(raw)} bytes is shorter than the 5-byte minimum")
    body, (crc,) = raw[:-2], struct.unpack("<H", raw[-2:])
    if crc16(body) != crc:
        raise WireError("CRC mismatch")
    msg_type, seq = struct.unpack("<BH", body[:3])
    return Message(msg_type, seq, body[3:])


class FrameSplitter:
    """Cuts a byte stream into packets at the 0x00 delimiters."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.overflows = 0

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        *packets, rest = self._buf.split(DELIMITER)
        self._buf = bytearray(rest)
        if len(self._buf) > MAX_FRAME_BYTES:
            self._buf.clear()
            self.overflows += 1
        return [bytes(p) for p in packets if p]  # two delimiters in a row: no frame, no error


def command_payload(speed_m_s: np.ndarray, heading_rad: np.ndarray) -> bytes:
    """COMMAND payload: n (u16), then per module speed and heading as int16 in their units."""
    speed = np.clip(np.round(speed_m_s / SPEED_UNIT_M_S), -32767, 32767).astype("<i2")
    wrapped = heading_rad - 2 * math.pi * np.round(heading_rad / (2 * math.pi))
    heading = np.clip(np.round(wrapped / HEADING_UNIT_RAD), -32767, 32767).astype("<i2")
    pairs = np.stack([speed, heading], axis=1)
    return struct.pack("<H", len(speed)) + pairs.tobytes()


def hello_payload() -> bytes:
    return struct.pack("<B", PROTOCOL_VERSION)


@dataclass(frozen=True)
class HelloAck:
    version: int
    n_modules: int
    firmware: str


def parse_hello_ack(payload: bytes) -> HelloAck:
    if len(payload) < 3:
        raise WireError(f"HELLO_ACK of {len(payload)} bytes, expected at least 3")
    version, n_modules = struct.unpack("<BH", payload[:3])
    return HelloAck(version, n_modules, payload[3:].decode("ascii", errors="replace"))


def parse_ack(payload: bytes) -> int:
    """The controller's status flags."""
    if len(payload) != 1:
        raise WireError(f"ACK payload of {len(payload)} bytes, expected 1")
    return payload[0]


@dataclass(frozen=True)
class Fault:
    code: int
    module: int  # 0xFFFF: the whole controller
    text: str


def parse_fault(payload: bytes) -> Fault:
    if len(payload) < 3:
        raise WireError(f"FAULT of {len(payload)} bytes, expected at least 3")
    code, module = struct.unpack("<BH", payload[:3])
    return Fault(code, module, payload[3:].decode("ascii", errors="replace"))
