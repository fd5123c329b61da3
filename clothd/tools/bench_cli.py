"""`clothd bench ...`: the benchmarks' subcommands and what each runs."""

from __future__ import annotations

import argparse
from pathlib import Path

from clothd.config import load_config, with_overrides
from clothd.errors import InvalidRequestError
from clothd.tools.bench_cli_flatten import add_flatten
from clothd.tools.bench_cli_flow import add_flow
from clothd.tools.bench_estop import add_estop
from clothd.tools.cli_args import (
    TUNE_TRIALS,
    Subparsers,
    add_cameras,
    dist,
    mesh_size,
    positive_int,
    skew_ms,
)


def _cmd_bench_loop(args: argparse.Namespace) -> int:
    from clothd.tools import bench_hog
    from clothd.tools.bench_loop import format_result, run_bench, write_json

    if args.hog is not None:
        result = bench_hog.run_bench(args.hog, args.config)
        print(bench_hog.format_result(result))
    else:
        result = run_bench(
            args.config, args.run_seconds, args.load_seconds, opcua=args.opcua, cameras=args.cameras
        )
        print(format_result(result))
    if args.json:
        write_json(result, args.json)
    return 0


def _cmd_bench_drift(args: argparse.Namespace) -> int:
    from clothd.tools.bench_drift import format_result, run_bench, write_json

    result = run_bench(args.config, args.rest_seconds, args.drive_seconds, args.sample_seconds, args.seed)
    print(format_result(result))
    if args.json:
        write_json(result, args.json)
    return 0


def _cmd_bench_faults(args: argparse.Namespace) -> int:
    import json

    from clothd.tools.bench_faults import format_result, run_bench

    result = run_bench(resets=args.resets)
    print(format_result(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


def _cmd_bench_abuse(args: argparse.Namespace) -> int:
    import json

    from clothd.tools.bench_abuse import FLOODS, format_rows, run_bench

    floods = tuple(args.floods or FLOODS)
    unknown = [f for f in floods if f not in FLOODS]
    if unknown:
        raise InvalidRequestError(f"--floods: unknown {', '.join(unknown)}; choose from {', '.join(FLOODS)}")
    rows = run_bench(args.connections, args.seconds, floods, token=not args.without_token)
    print(format_rows(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


def _cmd_bench_accuracy(args: argparse.Namespace) -> int:
    import itertools
    import json

    from clothd.taichi_runtime import start_taichi
    from clothd.tools.bench_accuracy import MODES, format_table, grade, plot, rows_json
    from clothd.tools.recordings import scenario_recording

    if args.skew_ms is not None and args.cameras < 2:
        raise InvalidRequestError("--skew-ms needs a second camera: add --cameras 2")
    cfg = load_config(args.config)
    start_taichi(cfg.taichi.arch)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scenario in args.scenarios:
        skew_s = None if args.skew_ms is None else args.skew_ms * 1e-3
        rec = scenario_recording(args.cache, scenario, args.duration, args.cameras, skew_s)
        graded = {}
        oracles = (False, True) if args.oracle else (False,)
        for (label, model, use_input), oracle in itertools.product(MODES, oracles):
            if args.modes and label not in args.modes:
                continue
            mode_cfg = with_overrides(cfg, {"tracker": {"model": model, "use_input": use_input}})
            label += ", oracle" if oracle else ""
            graded[label] = grade(rec, scenario, label, mode_cfg.tracker, cameras=args.cameras, oracle=oracle)
            rows.append(graded[label].row)
        plot(scenario, graded, 30.0, args.out / f"{scenario}.png")
    print(format_table(rows))
    print(f"\nplots in {args.out}/")
    if args.json:
        args.json.write_text(json.dumps(rows_json(rows), indent=1) + "\n")
    return 0


def _cmd_bench_robustness(args: argparse.Namespace) -> int:
    import json

    from clothd.taichi_runtime import start_taichi
    from clothd.tools.bench_accuracy import MODES, grade
    from clothd.tools.bench_robustness import (
        SETS,
        format_speed_table,
        format_table,
        plot_speed,
        rows_json,
    )
    from clothd.tools.recordings import recorded_exposure_s, scenario_recording

    cfg = load_config(args.config)
    start_taichi(cfg.taichi.arch)
    names = args.scenarios or [name for s in args.sets for name in SETS[s]]
    rows = []
    for scenario in names:
        rec = scenario_recording(args.cache, scenario)
        # The tracker is told the camera's exposure, as an integrator sets tracker.ekf.exposure_s.
        exposure = {} if args.no_exposure else {"ekf": {"exposure_s": recorded_exposure_s(rec)}}
        for label, model, use_input in MODES:
            if label not in args.modes:
                continue
            mode_cfg = with_overrides(cfg, {"tracker": {"model": model, "use_input": use_input, **exposure}})
            rows.append(grade(rec, scenario, label, mode_cfg.tracker).row)
    print(format_table(rows))
    if any(r.scenario in SETS["fast"] for r in rows):
        for mode in dict.fromkeys(r.mode for r in rows):
            print("\n" + format_speed_table(rows, mode))
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        plot_speed(rows, args.plot)
        print(f"\nplot: {args.plot}")
    if args.json:
        args.json.write_text(json.dumps(rows_json(rows), indent=1) + "\n")
    return 0


def _cmd_bench_speed(args: argparse.Namespace) -> int:
    import json
    import os

    # The tracker timed as the daemon's compute process runs it (compute_process.py, compute.py): one BLAS
    # thread, loop.compute_threads OpenCV threads and the GIL's switch interval bounded. BLAS reads this
    # when numpy first loads, below.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import cv2

    from clothd.drivers.priority import bound_gil_wait
    from clothd.taichi_runtime import start_taichi
    from clothd.tools.bench_speed import (
        DEFAULT_BUDGETS,
        DEFAULT_MESHES,
        format_rows,
        plot,
        read_rows,
        rows_json,
        run_speed,
    )
    from clothd.tools.recordings import scenario_recording

    cfg = load_config(args.config)
    cv2.setNumThreads(cfg.loop.compute_threads)
    bound_gil_wait()
    start_taichi(cfg.taichi.arch)
    recording = scenario_recording(args.cache, args.scenario, cameras=args.cameras)
    budgets = tuple(args.features) if args.features else DEFAULT_BUDGETS
    meshes = tuple(args.mesh) if args.mesh else DEFAULT_MESHES
    rows = run_speed(recording, budgets, meshes, frames=args.frames, cameras=args.cameras)
    baseline = read_rows(args.baseline, " before") if args.baseline else None
    print(format_rows(rows + [r for r in baseline or [] if r.impl == "clothd before"]))
    if args.json:
        args.json.write_text(json.dumps(rows_json(rows), indent=1) + "\n")
    if args.plot:
        plot(rows, args.plot, baseline)
        print(f"plot: {args.plot}")
    return 0


def _cmd_bench_tune(args: argparse.Namespace) -> int:
    from clothd.tools.bench_tune import format_result, run_bench, write_json

    workers, counts = tuple(args.workers), tuple(args.trial_counts)
    result = run_bench(args.cache, args.out, args.trials, args.seed, args.fabric, workers, counts)
    print(format_result(result))
    if args.json:
        write_json(result, args.json)
    return 0


def _cmd_bench_calibrate(args: argparse.Namespace) -> int:
    from clothd.tools.bench_calibrate import format_result, run_bench, write_json

    tracker = None
    if args.tracker:
        from clothd.taichi_runtime import start_taichi

        cfg = load_config(args.config)
        start_taichi(cfg.taichi.arch)
        tracker = (
            args.tracker,
            with_overrides(cfg, {"tracker": {"model": "mesh", "use_input": True}}).tracker,
        )
    result = run_bench(
        args.out, args.views, args.seed, args.tilt_rad, args.yaw_rad, args.dist, tracker, args.cameras
    )
    print(format_result(result))
    if args.json:
        write_json(result, args.json)
    return 0


def _add_speed(bsub: Subparsers) -> None:
    bs = bsub.add_parser("speed", help="per-stage tick time by feature count and mesh size, beside filterpy")
    bs.add_argument("--frames", type=int, default=60, help="ticks per configuration")
    bs.add_argument(
        "--features", type=int, nargs="+", action="extend", metavar="N", help="feature budgets (repeatable)"
    )
    bs.add_argument(
        "--mesh", type=mesh_size, nargs="+", action="extend", metavar="NXxNY", help="mesh sizes (repeatable)"
    )
    bs.add_argument(
        "--cache", type=Path, default=Path("out/bench"), help="where shipped scenarios are recorded"
    )
    bs.add_argument(
        "--scenario",
        default="translate",
        help="the shipped scenario tracked: translate (250 x 200 mm, ~900 corners) or panel (500 x 360 mm, "
        "enough corners for a 2000-feature budget)",
    )
    bs.add_argument("--config", type=Path, help="taichi.arch and loop.compute_threads are taken from it")
    add_cameras(bs, 1, "2: the recording's second camera too (hwsim's cell's oblique one)")
    bs.add_argument("--json", type=Path)
    bs.add_argument("--plot", type=Path, metavar="PNG", help="the tick against the node count, drawn here")
    bs.add_argument(
        "--baseline",
        type=Path,
        metavar="JSON",
        help="an earlier run's --json (e.g. the previous code's): its rows are listed as 'clothd before' "
        "and its tick drawn dashed in --plot",
    )
    bs.set_defaults(func=_cmd_bench_speed)


def _add_accuracy(bsub: Subparsers) -> None:
    ba = bsub.add_parser("accuracy", help="every mode on the shipped scenarios, against hwsim's truth")
    ba.add_argument(
        "--scenarios", nargs="+", default=["translate", "rotate", "compress", "occlude", "random"]
    )
    ba.add_argument("--modes", nargs="+", help="a subset of: none predict rigid 'rigid --no-input' mesh ...")
    ba.add_argument("--duration", type=float, help="record shorter scenarios (a quick look, not the bar)")
    ba.add_argument(
        "--cache", type=Path, default=Path("out/bench"), help="where shipped scenarios are recorded"
    )
    ba.add_argument("--out", type=Path, default=Path("out/bench/accuracy"), help="where the plots go")
    ba.add_argument("--oracle", action="store_true", help="each mode again, features at their true pixels")
    add_cameras(ba, 1, "2: the recordings' second camera too (hwsim's cell's oblique one)")
    ba.add_argument(
        "--skew-ms", type=skew_ms, help="with --cameras 2: the second captures this long after the first"
    )
    ba.add_argument("--config", type=Path)
    ba.add_argument("--json", type=Path)
    ba.set_defaults(func=_cmd_bench_accuracy)


def _add_robustness(bsub: Subparsers) -> None:
    brb = bsub.add_parser(
        "robustness", help="periodic weaves (plain twill, side light, turns) and fast belts, graded"
    )
    brb.add_argument("--sets", nargs="+", choices=["weaves", "fast"], default=["weaves", "fast"])
    brb.add_argument("--scenarios", nargs="+", help="these scenarios instead of the sets")
    brb.add_argument("--modes", nargs="+", default=["mesh"], help="as bench accuracy's (default: mesh)")
    brb.add_argument("--cache", type=Path, default=Path("out/bench"), help="where scenarios are recorded")
    brb.add_argument(
        "--plot", type=Path, default=Path("out/bench/robustness_speed.png"), help="accuracy vs belt speed"
    )
    brb.add_argument(
        "--no-exposure", action="store_true", help="do not tell the tracker the recordings' exposure time"
    )
    brb.add_argument("--config", type=Path)
    brb.add_argument("--json", type=Path)
    brb.set_defaults(func=_cmd_bench_robustness)


def _add_loop(bsub: Subparsers) -> None:
    bl = bsub.add_parser("loop", help="the closed loop against hwsim serve: settling, missed ticks, load")
    bl.add_argument("--config", type=Path, help="configuration for the daemon (default: every default)")
    bl.add_argument("--run-seconds", type=float, default=60.0, help="how long to count missed ticks")
    bl.add_argument("--load-seconds", type=float, default=30.0, help="how long to load the API")
    bl.add_argument(
        "--opcua",
        action="store_true",
        help="add an OPC UA client subscribed to the Cell at 10 Hz to the load",
    )
    bl.add_argument(
        "--hog",
        type=int,
        metavar="N",
        help="instead: 10 moves beside N busy processes and a headless browser started 3 times",
    )
    add_cameras(bl, None, "run the daemon with the simulated cell's first N cameras (default: all)")
    bl.add_argument("--json", type=Path, help="also write the figures as JSON")
    bl.set_defaults(func=_cmd_bench_loop)


def _add_drift(bsub: Subparsers) -> None:
    bdr = bsub.add_parser(
        "drift", help="the live tracker over a shift: pose and residual at rest, node error after moves"
    )
    bdr.add_argument("--config", type=Path, help="configuration for the daemon (default: every default)")
    bdr.add_argument("--rest-seconds", type=float, default=600.0, help="at rest, every module stopped")
    bdr.add_argument("--drive-seconds", type=float, default=600.0, help="then random moves (0: none)")
    bdr.add_argument("--sample-seconds", type=float, default=5.0, help="how often the rest is sampled")
    bdr.add_argument("--seed", type=int, default=0, help="seeds the random moves")
    bdr.add_argument("--json", type=Path, help="also write the figures and every sample as JSON")
    bdr.set_defaults(func=_cmd_bench_drift)


def _add_faults(bsub: Subparsers) -> None:
    bf = bsub.add_parser(
        "faults", help="faults injected into a live simulated cell: detection, stop, no restart; reset memory"
    )
    bf.add_argument("--resets", type=int, default=500, help="POST /reset this many times (10 a second)")
    bf.add_argument("--json", type=Path, help="also write the figures as JSON")
    bf.set_defaults(func=_cmd_bench_faults)


def _add_calibrate(bsub: Subparsers) -> None:
    bc = bsub.add_parser(
        "calibrate", help="calibrate on pictures hwsim renders through a tilted, distorted camera it knows"
    )
    bc.add_argument("--views", type=int, default=15, help="tilted views besides the flat one")
    bc.add_argument(
        "--cameras", type=positive_int, default=1, help="N > 1: hwsim's cell's first N cameras, with --dist"
    )
    bc.add_argument("--seed", type=int, default=0)
    bc.add_argument("--tilt-rad", type=float, default=0.15, help="hwsim camera tilt about world x")
    bc.add_argument("--yaw-rad", type=float, default=0.3, help="hwsim camera yaw about its view axis")
    bc.add_argument("--dist", type=dist, default=(-0.12, 0.05, 0.001, -0.0005, 0.0), metavar="K1,K2,P1,P2,K3")
    bc.add_argument(
        "--out", type=Path, default=Path("out/bench/calibrate"), help="where the pictures and cameras go"
    )
    bc.add_argument(
        "--tracker",
        metavar="SCENARIO",
        help="also track this shipped scenario through that camera, given the true and the calibrated one",
    )
    bc.add_argument("--config", type=Path, help="the tracker's configuration, with --tracker (model: mesh)")
    bc.add_argument("--json", type=Path, help="also write the figures as JSON")
    bc.set_defaults(func=_cmd_bench_calibrate)


def _add_tune(bsub: Subparsers) -> None:
    btn = bsub.add_parser(
        "tune",
        help="clothd tune on hwsim's shirting or lining: held-out node error, default and tuned constants, "
        "and the speed-up from --workers 2",
    )
    btn.add_argument(
        "--trials",
        type=positive_int,
        default=TUNE_TRIALS,
        help=f"trials of each search (default {TUNE_TRIALS})",
    )
    btn.add_argument("--seed", type=int, default=0)
    btn.add_argument(
        "--fabric",
        choices=["shirting", "lining"],
        default="shirting",
        help="hwsim's fabric (default shirting)",
    )
    btn.add_argument(
        "--workers",
        type=positive_int,
        nargs="+",
        default=[1, 2],
        help="a tune from scratch with each (default 1 2); the first one's design is graded",
    )
    btn.add_argument(
        "--trial-counts",
        type=positive_int,
        nargs="+",
        default=[],
        metavar="N",
        help="also what tunes of N trials per search would have given, read from the first tune's "
        "(--workers 1 first)",
    )
    btn.add_argument(
        "--cache", type=Path, default=Path("out/bench"), help="where the shirting scenarios are recorded"
    )
    btn.add_argument("--out", type=Path, default=Path("out/bench/tune"), help="where the tunes' outputs go")
    btn.add_argument("--json", type=Path, help="also write the figures as JSON")
    btn.set_defaults(func=_cmd_bench_tune)


def _add_abuse(bsub: Subparsers) -> None:
    bab = bsub.add_parser("abuse", help="HTTP, WebSocket and OPC UA floods: e-stop round trip, missed ticks")
    bab.add_argument("--connections", type=int, default=1100, help="sockets held open by the HTTP floods")
    bab.add_argument("--floods", nargs="+", help="which floods (default: all; the bench lists them)")
    bab.add_argument("--without-token", action="store_true", help="the daemon with no api.token")
    bab.add_argument("--seconds", type=float, default=20.0, help="how long each flood lasts")
    bab.add_argument("--json", type=Path, help="also write the figures as JSON")
    bab.set_defaults(func=_cmd_bench_abuse)


def add_commands(sub: Subparsers) -> None:
    b = sub.add_parser("bench", help="benchmarks against hwsim")
    bsub = b.add_subparsers(dest="bench", required=True)
    for add in (_add_speed, _add_accuracy, _add_robustness, _add_loop, add_flatten, add_flow, _add_drift):
        add(bsub)
    for add in (_add_faults, _add_calibrate, _add_tune, _add_abuse, add_estop):
        add(bsub)
