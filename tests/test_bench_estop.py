"""`clothd bench estop`: what it reads off the line, and one short run against the firmware's host build
(the figures are printed, held to their order, never to a wall-clock bound)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from clothd.cli import build_parser
from clothd.drivers import wire
from clothd.tools.bench_estop import FIRMWARE, Line, format_result, run_bench

T = wire.MsgType


def test_the_line_takes_the_estops_from_the_host_even_split_across_reads() -> None:
    line = Line()
    estop = wire.encode(T.ESTOP, 7)
    line.seen(True, wire.encode(T.COMMAND, 6, bytes(10)) + estop[:3], 1.0)
    line.seen(False, wire.encode(T.ESTOP, 8), 1.5)  # from the controller: not the host's e-stop
    line.seen(True, estop[3:], 2.0)  # whole once its last byte is read
    line.seen(True, wire.encode(T.ESTOP, 9), 3.0)
    assert line.estops == [2.0, 3.0]
    assert line.first_after(0.5) == 2.0 and line.first_after(2.5) == 3.0


def test_the_command_line_names_the_bench() -> None:
    args = build_parser().parse_args(["bench", "estop", "--samples", "3"])
    assert args.samples == 3 and args.firmware == FIRMWARE


@pytest.mark.slow
def test_a_short_run_against_the_host_firmware() -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    firmware_dir = Path(__file__).resolve().parents[1] / "deploy" / "firmware"
    subprocess.run(["make", "-s", "-C", str(firmware_dir), "host"], check=True, env=env, timeout=120)
    r = run_bench(3)
    print("\n" + format_result(r))
    assert r["samples"] == 3
    for what in ("post_to_wire", "post_to_response"):
        assert 0 < r[f"{what}_p50_ms"] <= r[f"{what}_p99_ms"] <= r[f"{what}_max_ms"]
