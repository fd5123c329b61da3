"""`clothd conformance` on the command line: takes a stepper controller through every rule of
docs/serial-protocol.md (docs/conformance.md). `--sim` checks hwsim's firmware."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from clothd.errors import HardwareError
from clothd.tools.cli_args import Subparsers, positive_int


def _cmd_conformance(args: argparse.Namespace) -> int:
    # Imported when the command runs: hwsim and pyserial stay out of the other commands' start.
    from clothd.tools.conformance import Port, Session, format_rows, run_checks, sim_session, write_json
    from clothd.tools.conformance_checks import CHECKS
    from hwsim.firmware_process import FirmwareProcess
    from hwsim.scenario import TableSpec

    if args.sim:
        spec = TableSpec()
        with tempfile.TemporaryDirectory(prefix="clothd-conformance-") as tmp:
            n_modules = spec.modules_x * spec.modules_y
            firmware = FirmwareProcess(n_modules, Path(tmp) / "ttyCELL", Path(tmp) / "drives.bin")
            try:
                session = sim_session(firmware, spec)
                where = f"hwsim's firmware ({firmware.link_path})"
                rows = run_checks(session, CHECKS)
                session.port.close()
            finally:
                firmware.stop()
    else:
        try:
            session = Session(Port(args.port), args.modules)
        except HardwareError as err:  # no check ran: still a failed conformance run, exit code 1
            print(f"clothd: {err}", file=sys.stderr)
            return 1
        where = args.port
        try:
            rows = run_checks(session, CHECKS)
        finally:
            session.port.close()
    print(f"conformance of {where} to docs/serial-protocol.md")
    print(format_rows(rows))
    if args.json:
        write_json(args.json, where, rows)
    return 0 if all(r.passed is not False for r in rows) else 1


def add_commands(sub: Subparsers) -> None:
    c = sub.add_parser(
        "conformance",
        help="check a stepper controller against the serial protocol (docs/conformance.md)",
        description="Takes a stepper controller through every rule of docs/serial-protocol.md and prints "
        "a pass/fail table with figures. Exit code 0 when every check passes.",
    )
    where = c.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", metavar="DEV", help="the controller's serial device (a pty path works too)")
    where.add_argument("--sim", action="store_true", help="start hwsim's firmware and check it")
    c.add_argument(
        "--modules", type=positive_int, help="the module count to expect (default: what HELLO_ACK reports)"
    )
    c.add_argument("--json", type=Path, metavar="F", help="also write the results to F as JSON")
    c.set_defaults(func=_cmd_conformance)
