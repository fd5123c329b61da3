"""The commissioning commands on the command line: `clothd drive` and `clothd check-modules`
(docs/commissioning.md). Both talk to a running daemon over its HTTP API; `check-modules --sim` starts
one against hwsim first."""

from __future__ import annotations

import argparse
import datetime
import tempfile
from pathlib import Path

# The commands' modules (OpenCV, httpx) are imported when one runs: the CLI starts quickly for the others.
DEFAULT_URL = "http://127.0.0.1:8080"
SIM_SCENARIO = "cell-miscalibrated"  # hwsim's live cell with module 9 wired wrong (docs/scenarios.md)
SIM_FRAME_PERIOD_S = 1.0 / 15.0  # hwsim serve's camera (--camera-fps 15, as clothd run --sim starts it)


def _cmd_drive(args: argparse.Namespace) -> int:
    from clothd.tools.cell_client import CellClient
    from clothd.tools.drive import drive, load_script

    script = load_script(args.script)
    client = CellClient(args.url, args.token)
    try:
        where = drive(client, script, args.record)
    finally:
        client.close()
    print(f"played {args.script} ({script.duration_s:g} s)" + (f"; recorded into {where}" if where else ""))
    return 0


def _cmd_check_modules(args: argparse.Namespace) -> int:
    from clothd.tools.sim_daemon import sim_daemon

    if args.sim is None:
        return _check(args, args.url, None)
    with (
        tempfile.TemporaryDirectory(prefix="clothd-check-modules-") as tmp,
        sim_daemon(args.sim, Path(tmp)) as url,
    ):
        return _check(args, url, SIM_FRAME_PERIOD_S)


def _check(args: argparse.Namespace, url: str, frame_period_s: float | None) -> int:
    from clothd.formats import write_module_calibration
    from clothd.tools.cell_client import CellClient
    from clothd.tools.check_modules import check_modules, format_results

    client = CellClient(url, args.token)
    try:
        results, left_out, recording = check_modules(client, args.modules, frame_period_s)
    finally:
        client.close()
    print(format_results(results))
    for why in left_out:
        print(f"not checked: {why}")
    when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    write_module_calibration(
        args.out, [r.entry for r in results], f"clothd check-modules, {when}, from {recording}"
    )
    print(f"written to {args.out}: name it as cell.module_calibration in the configuration")
    return 0


def add_commands(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    d = sub.add_parser(
        "drive", help="play a drive script (chosen modules over time) on a running daemon's cell"
    )
    d.add_argument("script", type=Path, help="a drive script, YAML (docs/api.md, 'Drive scripts')")
    d.add_argument("--record", metavar="DIR", help="record it into DIR, inside the daemon's recording.dir")
    d.add_argument("--url", default=DEFAULT_URL, help=f"the daemon's API (default {DEFAULT_URL})")
    d.add_argument("--token", help="api.token, when the daemon has one")
    d.set_defaults(func=_cmd_drive)
    c = sub.add_parser(
        "check-modules",
        help="drive each module alone and measure its direction, heading offset and speed scale",
    )
    c.add_argument(
        "--modules", type=int, nargs="+", metavar="ID", help="these modules (default: every one it can)"
    )
    c.add_argument("--out", type=Path, default=Path("module_calibration.yaml"), help="the file to write")
    c.add_argument("--url", default=DEFAULT_URL, help=f"the daemon's API (default {DEFAULT_URL})")
    c.add_argument("--token", help="api.token, when the daemon has one")
    c.add_argument(
        "--sim",
        nargs="?",
        const=SIM_SCENARIO,
        metavar="SCENARIO",
        help=f"start clothd run --sim SCENARIO (default {SIM_SCENARIO}) and check its cell",
    )
    c.set_defaults(func=_cmd_check_modules)
