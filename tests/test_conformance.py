"""`clothd conformance`: hwsim's firmware passes every check, and a controller that breaks one rule of
docs/serial-protocol.md fails the check for that rule (and only the checks that depend on it)."""

from __future__ import annotations

import contextlib
import json
import struct
from collections.abc import Iterator
from pathlib import Path

import pytest
from firmware_links import check_conformance

from clothd.cli import main
from hwsim.firmware import ACK, HELLO, Firmware, TableDrives, _cobs_decode, _crc_ccitt, frame
from hwsim.scenario import TableSpec
from hwsim.table import Table

# What a real port cannot show: the board's drives, and faults only the board can raise.
NOT_OBSERVABLE = {
    "seq.applied_once",
    "limits.negative_speed",
    "limits.speed",
    "limits.accel",
    "limits.steer_rate",
    "estop.cut",
    "watchdog.stop",
    "fault.report",
}


def _run(argv: list[str], json_path: Path) -> tuple[int, dict[str, dict[str, object]]]:
    code = main(["conformance", *argv, "--json", str(json_path)])
    rows = json.loads(json_path.read_text())["checks"]
    return code, {row["name"]: row for row in rows}


def test_hwsims_firmware_passes_every_check(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, rows = _run(["--sim"], tmp_path / "sim.json")
    table = capsys.readouterr().out
    check_conformance(code, list(rows.values()))
    assert not any(row["passed"] is None for row in rows.values()), table
    assert set(rows) > NOT_OBSERVABLE  # with the drive bus, what a port cannot show is checked too
    assert "handshake.hello" in table and "48 modules" in table


class _SilentWatchdog(Firmware):
    """A controller that never trips its watchdog: a silent host leaves the modules running."""

    def _check_watchdog(self) -> None:
        pass


class _AcksBadCrc(Firmware):
    """A controller that skips the CRC check: a corrupted frame is acknowledged."""

    def _handle(self, packet: bytes) -> None:
        raw = _cobs_decode(packet)
        if raw is not None and len(raw) >= 5 and _crc_ccitt(raw[:-2]) != struct.unpack("<H", raw[-2:])[0]:
            _, seq = struct.unpack("<BH", raw[:3])
            self._send(frame(ACK, seq, bytes([self._flags()])))
            return
        super()._handle(packet)


class _DeafAtFirst(Firmware):
    """A controller whose port reads nothing at first (QEMU notices a new opener up to a second late)."""

    def _handle(self, packet: bytes) -> None:
        raw = _cobs_decode(packet)
        if raw is not None and raw[0] == HELLO and not getattr(self, "heard", False):
            self.heard = True
            return
        super()._handle(packet)


@pytest.fixture
def table() -> Table:
    return Table(TableSpec())


@contextlib.contextmanager
def _controller(kind: type[Firmware], table: Table, tmp_path: Path) -> Iterator[Path]:
    firmware = kind(TableDrives(table), tmp_path / "ttyBROKEN")
    firmware.start()
    try:
        yield firmware.link_path
    finally:
        firmware.stop()


@pytest.mark.parametrize(
    ("kind", "failing"),
    [
        (_SilentWatchdog, {"watchdog.fault", "watchdog.flag", "fault.format"}),
        (_AcksBadCrc, {"framing.bad_crc"}),
        (Firmware, set()),  # the same firmware unbroken, on a port: passes
    ],
)
def test_a_broken_controller_fails_the_check_for_its_rule(
    kind: type[Firmware], failing: set[str], table: Table, tmp_path: Path
) -> None:
    with _controller(kind, table, tmp_path) as port:
        code, rows = _run(["--port", str(port)], tmp_path / "port.json")
    assert {name for name, row in rows.items() if row["passed"] is False} == failing
    assert {name for name, row in rows.items() if row["passed"] is None} == NOT_OBSERVABLE
    assert code == (1 if failing else 0)


def test_a_module_count_other_than_the_boards_fails_the_handshake(table: Table, tmp_path: Path) -> None:
    with _controller(Firmware, table, tmp_path) as port:
        code, rows = _run(["--port", str(port), "--modules", "12"], tmp_path / "port.json")
    assert code == 1
    hello = rows["handshake.hello"]
    assert hello["passed"] is False and "not the 12" in str(hello["detail"])
    # The count is the board's: every check after would drive the wrong modules, so none runs.
    assert list(rows) == ["handshake.hello", "handshake.modules"]
    assert "48 modules, --modules says 12" in str(rows["handshake.modules"]["detail"])


def test_a_port_that_misses_the_first_hello_is_asked_again(table: Table, tmp_path: Path) -> None:
    with _controller(_DeafAtFirst, table, tmp_path) as port:
        code, rows = _run(["--port", str(port)], tmp_path / "port.json")
    hello = rows["handshake.hello"]
    assert hello["passed"] is True and "the answer came to HELLO 2 of 4" in str(hello["detail"])
    assert code == 0
