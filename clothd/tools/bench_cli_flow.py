"""`clothd bench flow`: its arguments (the interface of docs/benchmarks.md, "Production flow")."""

from __future__ import annotations

import argparse
from pathlib import Path

from clothd.tools.cli_args import Subparsers, add_cameras


def _rates(text: str) -> list[float]:
    try:
        rates = [float(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"rates: comma-separated pieces per minute, got {text!r}") from None
    if not rates or any(not 0 < r <= 60 for r in rates):
        raise argparse.ArgumentTypeError(f"rates: each above 0 and at most 60 per minute, got {text!r}")
    return rates


def _cmd_bench_flow(args: argparse.Namespace) -> int:
    from clothd.tools.bench_flow import format_result, plot_rates, run_bench, write_json

    if args.realtime:
        return _realtime(args)
    rates = [args.rate] + [r for r in (args.rates or []) if r != args.rate]
    result = run_bench(args.minutes, rates, args.seed, args.cameras)
    print(format_result(result))
    if args.json:
        write_json(result, args.json)
    if args.plot:
        plot_rates(result, args.plot)
    return 0


def _realtime(args: argparse.Namespace) -> int:
    from clothd.tools.bench_flow import write_json
    from clothd.tools.bench_flow_live import format_live, run_flow_live

    if args.rates or args.plot:
        raise SystemExit("clothd bench flow: --realtime runs one rate; --rates and --plot are the lockstep's")
    result = run_flow_live(args.minutes, args.rate, args.seed, args.cameras)
    print(format_live(result))
    if args.json:
        write_json(result, args.json)
    return 0


def add_flow(bsub: Subparsers) -> None:
    bf = bsub.add_parser(
        "flow", help="the production flow in lockstep: pieces in, flattened, placed and out, judged by hwsim"
    )
    bf.add_argument("--minutes", type=float, default=5.0, help="simulated minutes of production")
    bf.add_argument("--rate", type=float, default=6.0, help="pieces laid per minute")
    bf.add_argument("--rates", type=_rates, help="also run these rates (comma-separated) for the sweep")
    bf.add_argument("--seed", type=int, default=0, help="seeds the pieces' draws")
    add_cameras(bf, None, "the flow cell's first N cameras (default: all)")
    bf.add_argument(
        "--realtime",
        action="store_true",
        help="once in real time instead: hwsim serve and clothd run --sim, judged through the API",
    )
    bf.add_argument("--json", type=Path, help="also write the figures and every piece as JSON")
    bf.add_argument("--plot", type=Path, help="also draw success and throughput against the rate (PNG)")
    bf.set_defaults(func=_cmd_bench_flow)
