"""`clothd bench flatten`: its arguments (the interface of docs/benchmarks.md, "Flattening")."""

from __future__ import annotations

import argparse
from pathlib import Path

from clothd.errors import InvalidRequestError
from clothd.tools.cli_args import Subparsers, add_cameras, skew_ms


def _cmd_bench_flatten(args: argparse.Namespace) -> int:
    from clothd.tools.bench_flatten import format_result, run_bench, write_json

    if args.skew_ms is not None and not args.lockstep:
        raise InvalidRequestError("--skew-ms needs --lockstep: hwsim serve takes its skew from its scenario")
    if args.skew_ms is not None and args.cameras == 1:
        raise InvalidRequestError("--skew-ms needs a second camera: leave out --cameras 1")
    result = run_bench(
        starts=args.starts,
        seed=args.seed,
        flatten_s=args.flatten_seconds,
        lockstep=args.lockstep,
        start=args.start,
        cameras=args.cameras,
        skew_s=None if args.skew_ms is None else args.skew_ms * 1e-3,
    )
    print(format_result(result))
    if args.json:
        write_json(result, args.json)
    return 0


def add_flatten(bsub: Subparsers) -> None:
    bfl = bsub.add_parser("flatten", help="the closed loop flattens wrinkled cloth, judged by hwsim's truth")
    bfl.add_argument(
        "--start",
        choices=["pushed", "laid"],
        default="pushed",
        help="ridges pushed in while tracking (pushed) or laid before it begins, as a piece arrives (laid)",
    )
    add_cameras(bfl, None, "the simulated cell's first N cameras (default: all)")
    bfl.add_argument("--starts", type=int, default=20, help="seeded starting states")
    bfl.add_argument("--seed", type=int, default=0)
    bfl.add_argument(
        "--flatten-seconds", type=float, default=10.0, help="a start succeeds when flat within this"
    )
    bfl.add_argument(
        "--lockstep",
        action="store_true",
        help="hwsim and the tracker and controller in one process, tick by tick, as fast as the CPU allows",
    )
    bfl.add_argument(
        "--skew-ms",
        type=skew_ms,
        help="with --lockstep: every further camera captures this long after the first (0-100 ms)",
    )
    bfl.add_argument("--json", type=Path, help="also write the figures and every run as JSON")
    bfl.set_defaults(func=_cmd_bench_flatten)
