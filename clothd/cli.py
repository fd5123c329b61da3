"""The `clothd` command."""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import version
from pathlib import Path

from clothd.config import load_config, with_overrides
from clothd.errors import ClothdError, InvalidRequestError
from clothd.tools.commissioning_cli import add_commands as add_commissioning_commands


def _cmd_check_config(args: argparse.Namespace) -> int:
    load_config(args.file)
    print(f"{args.file}: OK")
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from clothd.logs import configure_logging
    from clothd.run import run

    configure_logging()
    flags = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    opcua = {"endpoint": args.opcua_endpoint} if args.opcua_endpoint else {}
    cfg = load_config(args.config, {"api": flags, "opcua": opcua})
    return run(cfg, args.sim, args.record)


def _cmd_bench_loop(args: argparse.Namespace) -> int:
    from clothd.tools import bench_hog
    from clothd.tools.bench_loop import format_result, run_bench, write_json

    if args.hog is not None:
        result = bench_hog.run_bench(args.hog, args.config)
        print(bench_hog.format_result(result))
    else:
        result = run_bench(args.config, run_s=args.run_seconds, load_s=args.load_seconds, opcua=args.opcua)
        print(format_result(result))
    if args.json:
        write_json(result, args.json)
    return 0


def _cmd_bench_flatten(args: argparse.Namespace) -> int:
    from clothd.tools.bench_flatten import format_result, run_bench, write_json

    result = run_bench(
        starts=args.starts, seed=args.seed, flatten_s=args.flatten_seconds, lockstep=args.lockstep
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


def _cmd_export(args: argparse.Namespace) -> int:
    from clothd.tools.export import export_mcap

    counts = export_mcap(args.recording, args.mcap, args.estimates)
    listed = ", ".join(f"{topic} {n}" for topic, n in counts.messages.items())
    print(f"exported {counts.frames} frames to {args.mcap}: {listed}")
    return 0


def _cmd_picture(args: argparse.Namespace) -> int:
    from clothd.tools.mcap_picture import (
        after_first_frame_ns,
        draw_picture,
        highest_mesh_t_ns,
        read_cell_mcap,
    )

    log = read_cell_mcap(args.mcap)
    at_ns = highest_mesh_t_ns(log) if args.at_s is None else after_first_frame_ns(log, args.at_s)
    drawn_ns = draw_picture(log, args.out, at_ns)
    print(f"drew {args.mcap} at {(drawn_ns - log.camera[0][0]) / 1e9:.2f} s -> {args.out}")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from clothd.taichi_runtime import start_taichi
    from clothd.tools.replay import replay

    overrides: dict[str, object] = {"model": args.model} if args.model else {}
    if args.no_input:
        overrides["use_input"] = False
    cfg = load_config(args.config, {"tracker": overrides})
    tracker_cfg = cfg.tracker
    start_taichi(cfg.taichi.arch)
    out = args.out or Path("out/replay") / args.source.stem
    result = replay(
        args.source, out, tracker_cfg, roi=args.roi, camera_json=args.camera, commands_csv=args.commands
    )
    source_input = "on" if tracker_cfg.use_input else "off"
    print(f"camera: {result.camera}")
    print(
        f"replayed {result.frames} frames ({tracker_cfg.model}, input {source_input}) "
        f"in {result.wall_s:.1f} s, {result.realtime_factor:.1f}x real time "
        f"({result.steady_realtime_factor:.1f}x after start-up) -> {out}"
    )
    return 0


def _cmd_bench_accuracy(args: argparse.Namespace) -> int:
    import json

    from clothd.taichi_runtime import start_taichi
    from clothd.tools.bench_accuracy import MODES, format_table, grade, plot, rows_json
    from clothd.tools.recordings import scenario_recording

    cfg = load_config(args.config)
    start_taichi(cfg.taichi.arch)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scenario in args.scenarios:
        rec = scenario_recording(args.cache, scenario, args.duration)
        graded = {}
        for label, model, use_input in MODES:
            if args.modes and label not in args.modes:
                continue
            mode_cfg = with_overrides(cfg, {"tracker": {"model": model, "use_input": use_input}})
            graded[label] = grade(rec, scenario, label, mode_cfg.tracker)
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
    # thread, and loop.compute_threads OpenCV threads. BLAS reads this when numpy first loads, below.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import cv2

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
    start_taichi(cfg.taichi.arch)
    recording = scenario_recording(args.cache, args.scenario)
    budgets = tuple(args.features) if args.features else DEFAULT_BUDGETS
    meshes = tuple(args.mesh) if args.mesh else DEFAULT_MESHES
    rows = run_speed(recording, budgets, meshes, frames=args.frames)
    baseline = read_rows(args.baseline, " before") if args.baseline else None
    print(format_rows(rows + [r for r in baseline or [] if r.impl == "clothd before"]))
    if args.json:
        args.json.write_text(json.dumps(rows_json(rows), indent=1) + "\n")
    if args.plot:
        plot(rows, args.plot, baseline)
        print(f"plot: {args.plot}")
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    import json

    from clothd.formats import write_camera
    from clothd.tools.calibrate import read_pictures, solve
    from clothd.tools.calibration_report import format_report, picture_path, plot_report, report_json
    from clothd.tools.charuco import Board

    squares_x, squares_y = args.board
    board = Board(squares_x, squares_y, args.square_m, args.marker_m, args.dictionary)
    if args.camera is not None:
        from clothd.tools.calibrate_live import capture_views

        capture_views(args.camera, board, args.images, args.flat, args.views, args.timeout_s)
    cal = solve(read_pictures(args.images, board, args.flat), board, args.flat_origin_m, fit_k3=args.k3)
    write_camera(args.out, cal.camera)
    picture = picture_path(args.out)
    plot_report(cal, picture)
    print(format_report(cal))
    print(f"\ncamera written to {args.out}, residuals and coverage to {picture}")
    if args.json:
        args.json.write_text(json.dumps(report_json(cal) | {"picture": str(picture)}, indent=2) + "\n")
    return 0


# clothd tune's trials per search, and clothd bench tune's: the one count that met the held-out bar on every
# seed tried (docs/commissioning.md, "How many trials").
TUNE_TRIALS = 100


def _cmd_tune(args: argparse.Namespace) -> int:
    from clothd.tools.tune import tune
    from clothd.tools.tune_report import BEST_YAML, POPULATION_CSV, format_table, write_outputs
    from clothd.tools.tune_verdict import VERDICT_JSON, format_verdict, write_verdict

    cfg = load_config(args.config)
    run = tune(
        args.recordings,
        args.out,
        cfg,
        args.trials,
        args.workers,
        args.storage,
        args.model,
        args.timeout_s,
        args.seed,
        args.study_name,
    )
    recordings = ", ".join(str(r) for r in args.recordings)
    written = run.verdict.generalises
    designs = write_outputs(
        run.study, cfg.tracker.physics, args.out, f"{args.model} on {recordings}", written
    )
    write_verdict(run.verdict, written, args.out / VERDICT_JSON)
    print(format_table(designs, args.top))
    print(f"\n{format_verdict(run.verdict)}")
    print(
        f"\n{run.trials_run} trials in {run.wall_s:.1f} s on {args.workers} worker(s), "
        f"{len(run.searches)} search(es); {len(designs)} designs in study {run.study.study_name!r}"
    )
    if written:
        print(f"best design (trial {designs[0].trial}) written to {args.out / BEST_YAML}")
    print(
        f"population in {args.out / POPULATION_CSV}, the verdict in {args.out / VERDICT_JSON}, "
        f"plots in {args.out}/"
    )
    return 0 if written else 1


def _cmd_bench_tune(args: argparse.Namespace) -> int:
    from clothd.tools.bench_tune import format_result, run_bench, write_json

    workers, counts = tuple(args.workers), tuple(args.trial_counts)
    result = run_bench(args.cache, args.out, args.trials, args.seed, args.fabric, workers, counts)
    print(format_result(result))
    if args.json:
        write_json(result, args.json)
    return 0


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number, at least 1")
    return value


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
    result = run_bench(args.out, args.views, args.seed, args.tilt_rad, args.yaw_rad, args.dist, tracker)
    print(format_result(result))
    if args.json:
        write_json(result, args.json)
    return 0


def _numbers(text: str, count: int) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count:
        raise argparse.ArgumentTypeError(f"{text!r}: {count} numbers separated by commas")
    return values


def _xy_m(text: str) -> tuple[float, float]:
    """'-0.21,0.12' -> (-0.21, 0.12), for --flat-origin-m."""
    x, y = _numbers(text, 2)
    return x, y


def _dist(text: str) -> tuple[float, float, float, float, float]:
    """'k1,k2,p1,p2,k3', for --dist."""
    k1, k2, p1, p2, k3 = _numbers(text, 5)
    return k1, k2, p1, p2, k3


def _board_size(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6) squares, for --board."""
    nx, sep, ny = text.lower().partition("x")
    if not (sep and nx.isdigit() and ny.isdigit() and 3 <= int(nx) <= 40 and 3 <= int(ny) <= 40):
        raise argparse.ArgumentTypeError(f"{text!r}: a board is SQUARES_XxSQUARES_Y, each 3..40 (e.g. 9x6)")
    return int(nx), int(ny)


# Options whose value is a comma-separated list that may start with a minus sign.
_SIGNED_LISTS = ("--flat-origin-m", "--dist")


def _glue_signed_lists(argv: list[str]) -> list[str]:
    """argparse reads '-0.21,0.12' as an unknown option, not a value: join it to its flag with '='."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1] in _SIGNED_LISTS and arg.startswith("-") and "," in arg:
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def _mesh_size(text: str) -> tuple[int, int]:
    """'32x24' -> (32, 24), for --mesh."""
    nx, sep, ny = text.lower().partition("x")
    if not (sep and nx.isdigit() and ny.isdigit() and 2 <= int(nx) <= 64 and 2 <= int(ny) <= 64):
        raise argparse.ArgumentTypeError(f"{text!r}: a mesh is NXxNY, each 2..64 (e.g. 32x24)")
    return int(nx), int(ny)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="clothd", description="Real-time cloth tracking and control.")
    p.add_argument("--version", action="version", version=f"%(prog)s {version('clothd')}")
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("check-config", help="validate a configuration file")
    c.add_argument("file", type=Path)
    c.set_defaults(func=_cmd_check_config)
    rn = sub.add_parser("run", help="run the daemon: camera, tracker, control, steppers, API")
    rn.add_argument("--config", type=Path, help="configuration file (default: every default)")
    rn.add_argument("--host", help="API address (overrides api.host)")
    rn.add_argument("--port", type=int, help="API port (overrides api.port)")
    rn.add_argument(
        "--opcua-endpoint",
        metavar="URL",
        help="OPC UA endpoint, opc.tcp://HOST:PORT/PATH (overrides opcua.endpoint)",
    )
    rn.add_argument(
        "--sim",
        nargs="?",
        const="cell",
        metavar="SCENARIO",
        help="start hwsim serve (default scenario: cell) and run against it",
    )
    rn.add_argument(
        "--record",
        type=Path,
        metavar="DIR",
        help="record the session into DIR (a new directory; with recording.format mcap, the file DIR.mcap)",
    )
    rn.set_defaults(func=_cmd_run)
    r = sub.add_parser("replay", help="track recorded footage offline")
    r.add_argument("source", type=Path, help="a video file, an image directory, or a recording directory")
    r.add_argument("--out", type=Path, help="where to write (default: out/replay/NAME, the source's name)")
    r.add_argument("--model", choices=["none", "predict", "rigid", "mesh"])
    r.add_argument("--no-input", action="store_true", help="the model takes the modules as stopped")
    r.add_argument("--roi", choices=["auto", "full"], default="auto")
    r.add_argument("--camera", type=Path, help="camera.json (default: the recording's, else an ideal camera)")
    r.add_argument("--commands", type=Path, help="commands.csv (default: the recording's)")
    r.add_argument("--config", type=Path)
    r.set_defaults(func=_cmd_replay)
    add_commissioning_commands(sub)
    e = sub.add_parser("export", help="a recording as MCAP for Foxglove")
    e.add_argument("recording", type=Path, help="a recording directory (clothd run --record, hwsim record)")
    e.add_argument("--mcap", type=Path, required=True, help="the MCAP file to write")
    e.add_argument("--estimates", type=Path, help="estimates.npz (default: the recording's own)")
    e.set_defaults(func=_cmd_export)
    pic = sub.add_parser("picture", help="a picture drawn from an MCAP file: camera, mesh, pose and timeline")
    pic.add_argument("mcap", type=Path, help="clothd export's or a live MCAP recording's file")
    pic.add_argument("--out", type=Path, required=True, help="the PNG to write")
    pic.add_argument(
        "--at-s", type=float, help="seconds after the first frame (default: where the mesh stands highest)"
    )
    pic.set_defaults(func=_cmd_picture)
    cal = sub.add_parser(
        "calibrate",
        help="the camera (K, distortion) and the table's pose from pictures of a ChArUco board",
        description="Writes camera.json as the tracker reads it, and NAME-calibration.png beside it "
        "(coverage and residuals). docs/commissioning.md describes the pictures to take.",
    )
    cal.add_argument(
        "--images",
        type=Path,
        required=True,
        metavar="DIR",
        help="the pictures (with --camera: where to save them)",
    )
    cal.add_argument(
        "--camera",
        metavar="SOURCE",
        help="take the pictures live: a device index, device, stream URL, video file or image directory",
    )
    cal.add_argument(
        "--views", type=int, default=15, help="with --camera: pictures to take, the flat one first"
    )
    cal.add_argument(
        "--timeout-s", type=float, default=600.0, help="with --camera: stop taking pictures after this"
    )
    cal.add_argument(
        "--board", type=_board_size, default=(9, 6), metavar="NXxNY", help="squares (default 9x6)"
    )
    cal.add_argument("--square-m", type=float, default=0.060, help="side of a square, metres (default 0.060)")
    cal.add_argument("--marker-m", type=float, default=0.045, help="side of a marker, metres (default 0.045)")
    cal.add_argument(
        "--dictionary", default="DICT_5X5_100", help="cv2.aruco dictionary (default DICT_5X5_100)"
    )
    cal.add_argument(
        "--flat", required=True, metavar="NAME", help="the picture with the board flat on the table"
    )
    cal.add_argument(
        "--flat-origin-m",
        type=_xy_m,
        required=True,
        metavar="X,Y",
        help="world x, y of ChArUco corner id 0 in the flat picture, metres",
    )
    cal.add_argument("--k3", action="store_true", help="also fit k3 (wide-angle lenses; default k3 = 0)")
    cal.add_argument("--out", type=Path, required=True, metavar="CAMERA_JSON")
    cal.add_argument("--json", type=Path, help="also write the report as JSON")
    cal.set_defaults(func=_cmd_calibrate)
    tn = sub.add_parser(
        "tune",
        help="fit the cloth model's constants to recorded footage (the report's Table 2)",
        description="Searches the mass-spring constants (tracker.physics, within config.py's bounds) with "
        "Optuna's CMA-ES for the least mean + 2 x worst feature pixel error of the model's prediction. "
        "With two recordings it searches on the first and keeps the second out; with three or more it "
        "cross-validates. Writes DIR/best.yaml (a config fragment for --config) only when the best design "
        "beats the start on the held-out footage (exit status 1 otherwise, with the reason), and "
        "DIR/verdict.json, DIR/population.csv, history.png and importance.png; keeps the studies in "
        "DIR/study.db so that a stopped tune resumes. docs/commissioning.md, 'Tune', describes the "
        "recordings to make.",
    )
    tn.add_argument(
        "recordings",
        type=Path,
        nargs="*",
        metavar="REC",
        help="hwsim recordings or clothd run --record sessions",
    )
    tn.add_argument("--out", type=Path, required=True, metavar="DIR")
    tn.add_argument(
        "--trials",
        type=_positive_int,
        default=TUNE_TRIALS,
        help=f"trials to run now in each search (default {TUNE_TRIALS})",
    )
    tn.add_argument(
        "--workers", type=_positive_int, default=1, help="local processes sharing the study (default 1)"
    )
    tn.add_argument("--timeout-s", type=float, help="stop starting trials after this many seconds")
    tn.add_argument(
        "--storage",
        metavar="URL",
        help="Optuna storage shared with other machines: an RDB URL (postgresql://..., sqlite:///...) or "
        "a journal file's path (default: DIR/study.db)",
    )
    tn.add_argument(
        "--model",
        choices=["predict", "mesh"],
        default="predict",
        help="predict: the model alone, as the report tuned it (default); mesh: the whole tracker, "
        "over its residuals (slower)",
    )
    tn.add_argument("--study-name", default="tune", help="the study in the storage (default tune)")
    tn.add_argument("--seed", type=int, default=0, help="CMA-ES's seed (worker w uses seed + w)")
    tn.add_argument("--top", type=_positive_int, default=5, help="designs in the printed table")
    tn.add_argument("--config", type=Path, help="where the search starts, and the tracker's other settings")
    tn.set_defaults(func=_cmd_tune)
    b = sub.add_parser("bench", help="benchmarks against hwsim")
    bsub = b.add_subparsers(dest="bench", required=True)
    bs = bsub.add_parser("speed", help="per-stage tick time by feature count and mesh size, beside filterpy")
    bs.add_argument("--frames", type=int, default=60, help="ticks per configuration")
    bs.add_argument(
        "--features", type=int, nargs="+", action="extend", metavar="N", help="feature budgets (repeatable)"
    )
    bs.add_argument(
        "--mesh", type=_mesh_size, nargs="+", action="extend", metavar="NXxNY", help="mesh sizes (repeatable)"
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
    ba.add_argument("--config", type=Path)
    ba.add_argument("--json", type=Path)
    ba.set_defaults(func=_cmd_bench_accuracy)
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
    bl.add_argument("--json", type=Path, help="also write the figures as JSON")
    bl.set_defaults(func=_cmd_bench_loop)
    bfl = bsub.add_parser(
        "flatten", help="the closed loop flattens pushed-in ridges, judged by hwsim's truth"
    )
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
    bfl.add_argument("--json", type=Path, help="also write the figures and every run as JSON")
    bfl.set_defaults(func=_cmd_bench_flatten)
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
    bf = bsub.add_parser(
        "faults", help="faults injected into a live simulated cell: detection, stop, no restart; reset memory"
    )
    bf.add_argument("--resets", type=int, default=500, help="POST /reset this many times (10 a second)")
    bf.add_argument("--json", type=Path, help="also write the figures as JSON")
    bf.set_defaults(func=_cmd_bench_faults)
    bc = bsub.add_parser(
        "calibrate", help="calibrate on pictures hwsim renders through a tilted, distorted camera it knows"
    )
    bc.add_argument("--views", type=int, default=15, help="tilted views besides the flat one")
    bc.add_argument("--seed", type=int, default=0)
    bc.add_argument("--tilt-rad", type=float, default=0.15, help="hwsim camera tilt about world x")
    bc.add_argument("--yaw-rad", type=float, default=0.3, help="hwsim camera yaw about its view axis")
    bc.add_argument(
        "--dist", type=_dist, default=(-0.12, 0.05, 0.001, -0.0005, 0.0), metavar="K1,K2,P1,P2,K3"
    )
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
    btn = bsub.add_parser(
        "tune",
        help="clothd tune on hwsim's shirting or lining: held-out node error, default and tuned constants, "
        "and the speed-up from --workers 2",
    )
    btn.add_argument(
        "--trials",
        type=_positive_int,
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
        type=_positive_int,
        nargs="+",
        default=[1, 2],
        help="a tune from scratch with each (default 1 2); the first one's design is graded",
    )
    btn.add_argument(
        "--trial-counts",
        type=_positive_int,
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
    bab = bsub.add_parser("abuse", help="HTTP, WebSocket and OPC UA floods: e-stop round trip, missed ticks")
    bab.add_argument("--connections", type=int, default=1100, help="sockets held open by the HTTP floods")
    bab.add_argument("--floods", nargs="+", help="which floods (default: all; the bench lists them)")
    bab.add_argument("--without-token", action="store_true", help="the daemon with no api.token")
    bab.add_argument("--seconds", type=float, default=20.0, help="how long each flood lasts")
    bab.add_argument("--json", type=Path, help="also write the figures as JSON")
    bab.set_defaults(func=_cmd_bench_abuse)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(_glue_signed_lists(sys.argv[1:] if argv is None else argv))
    try:
        return int(args.func(args))
    except ClothdError as err:
        print(f"clothd: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
