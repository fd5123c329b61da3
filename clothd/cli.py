"""The `clothd` command."""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import version
from pathlib import Path

from clothd.config import load_config
from clothd.errors import ClothdError
from clothd.tools.bench_cli import add_commands as add_bench_commands
from clothd.tools.cli_args import TUNE_TRIALS, Subparsers, board_size, glue_signed_lists, positive_int, xy_m
from clothd.tools.commissioning_cli import add_commands as add_commissioning_commands
from clothd.tools.conformance_cli import add_commands as add_conformance_commands


def _cmd_check_config(args: argparse.Namespace) -> int:
    from clothd.formats import read_referenced_files

    read = read_referenced_files(load_config(args.file))
    print(f"{args.file}: OK" + (f" (and {', '.join(map(str, read))})" if read else ""))
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from clothd.logs import configure_logging
    from clothd.run import run

    configure_logging()
    flags = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    opcua = {"endpoint": args.opcua_endpoint} if args.opcua_endpoint else {}
    cfg = load_config(args.config, {"api": flags, "opcua": opcua})
    return run(cfg, args.sim, args.record, args.cameras, args.sim_controllers)


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
        args.source,
        out,
        tracker_cfg,
        roi=args.roi,
        camera_json=args.camera,
        commands_csv=args.commands,
        cameras=args.cameras,
    )
    source_input = "on" if tracker_cfg.use_input else "off"
    print(f"camera: {result.camera}")
    for name, views in result.views.items():
        heights = "" if views else ": tracked on the first camera alone, heights inferred"
        print(f"camera {name}: a view for {views} of {result.frames} frames{heights}")
    print(
        f"replayed {result.frames} frames ({tracker_cfg.model}, input {source_input}) "
        f"in {result.wall_s:.1f} s, {result.realtime_factor:.1f}x real time "
        f"({result.steady_realtime_factor:.1f}x after start-up) -> {out}"
    )
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from clothd.tools.calibrate_command import calibrate_command

    return calibrate_command(args)


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


def _add_check_config(sub: Subparsers) -> None:
    c = sub.add_parser("check-config", help="validate a configuration file")
    c.add_argument("file", type=Path)
    c.set_defaults(func=_cmd_check_config)


def _add_run(sub: Subparsers) -> None:
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
        "--sim-controllers",
        type=positive_int,
        default=1,
        metavar="N",
        help="with --sim: the cell's modules split among N stepper controllers, each on its own pty "
        "(stepper.controllers; default 1)",
    )
    rn.add_argument(
        "--cameras",
        type=positive_int,
        metavar="N",
        help="only the first N cameras: the configuration's, or with --sim the cell's (1: one view)",
    )
    rn.add_argument(
        "--record",
        type=Path,
        metavar="DIR",
        help="record the session into DIR (a new directory; with recording.format mcap, the file DIR.mcap)",
    )
    rn.set_defaults(func=_cmd_run)


def _add_replay(sub: Subparsers) -> None:
    r = sub.add_parser("replay", help="track recorded footage offline")
    r.add_argument("source", type=Path, help="a video file, an image directory, or a recording directory")
    r.add_argument("--out", type=Path, help="where to write (default: out/replay/NAME, the source's name)")
    r.add_argument("--model", choices=["none", "predict", "rigid", "mesh"])
    r.add_argument("--no-input", action="store_true", help="the model takes the modules as stopped")
    r.add_argument("--roi", choices=["auto", "full"], default="auto")
    r.add_argument("--camera", type=Path, help="camera.json (default: the recording's, else an ideal camera)")
    r.add_argument("--commands", type=Path, help="commands.csv (default: the recording's)")
    r.add_argument(
        "--cameras",
        type=positive_int,
        metavar="N",
        help="a recording's first N cameras (default: every one it holds; 1: the first view only)",
    )
    r.add_argument("--config", type=Path)
    r.set_defaults(func=_cmd_replay)


def _add_export(sub: Subparsers) -> None:
    e = sub.add_parser("export", help="a recording as MCAP for Foxglove")
    e.add_argument("recording", type=Path, help="a recording directory (clothd run --record, hwsim record)")
    e.add_argument("--mcap", type=Path, required=True, help="the MCAP file to write")
    e.add_argument("--estimates", type=Path, help="estimates.npz (default: the recording's own)")
    e.set_defaults(func=_cmd_export)


def _add_picture(sub: Subparsers) -> None:
    pic = sub.add_parser("picture", help="a picture drawn from an MCAP file: camera, mesh, pose and timeline")
    pic.add_argument("mcap", type=Path, help="clothd export's or a live MCAP recording's file")
    pic.add_argument("--out", type=Path, required=True, help="the PNG to write")
    pic.add_argument(
        "--at-s", type=float, help="seconds after the first frame (default: where the mesh stands highest)"
    )
    pic.set_defaults(func=_cmd_picture)


def _add_calibrate(sub: Subparsers) -> None:
    cal = sub.add_parser(
        "calibrate",
        help="the camera (K, distortion) and the table's pose from pictures of a ChArUco board",
        description="Writes camera.json as the tracker reads it, and NAME-calibration.png beside it "
        "(coverage and residuals). With DIR/cameras/NAME/ (each further camera's pictures of the same "
        "views) every camera is solved together, each further one written beside --out as NAME.json. "
        "docs/commissioning.md describes the pictures to take.",
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
        "--board", type=board_size, default=(9, 6), metavar="NXxNY", help="squares (default 9x6)"
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
        type=xy_m,
        required=True,
        metavar="X,Y",
        help="world x, y of ChArUco corner id 0 in the flat picture, metres",
    )
    cal.add_argument("--k3", action="store_true", help="also fit k3 (wide-angle lenses; default k3 = 0)")
    cal.add_argument("--out", type=Path, required=True, metavar="CAMERA_JSON")
    cal.add_argument("--json", type=Path, help="also write the report as JSON")
    cal.set_defaults(func=_cmd_calibrate)


def _add_tune(sub: Subparsers) -> None:
    tn = sub.add_parser(
        "tune",
        help="fit the cloth model's constants to recorded footage (the report's Table 2)",
        description="Searches the mass-spring constants (tracker.physics, within its bounds) with "
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
        type=positive_int,
        default=TUNE_TRIALS,
        help=f"trials to run now in each search (default {TUNE_TRIALS})",
    )
    tn.add_argument(
        "--workers", type=positive_int, default=1, help="local processes sharing the study (default 1)"
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
    tn.add_argument("--top", type=positive_int, default=5, help="designs in the printed table")
    tn.add_argument("--config", type=Path, help="where the search starts, and the tracker's other settings")
    tn.set_defaults(func=_cmd_tune)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="clothd", description="Real-time cloth tracking and control.")
    p.add_argument("--version", action="version", version=f"%(prog)s {version('clothd')}")
    sub = p.add_subparsers(dest="command", required=True)
    _add_check_config(sub)
    _add_run(sub)
    _add_replay(sub)
    add_commissioning_commands(sub)
    add_conformance_commands(sub)
    _add_export(sub)
    _add_picture(sub)
    _add_calibrate(sub)
    _add_tune(sub)
    add_bench_commands(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(glue_signed_lists(sys.argv[1:] if argv is None else argv))
    try:
        return int(args.func(args))
    except ClothdError as err:
        print(f"clothd: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a file or folder given that cannot be written or read: its name and why
        where = f"{err.filename}: " if err.filename else ""
        print(f"clothd: {where}{err.strerror or err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # a Ctrl-C before the daemon's own handlers are up: what was started is stopped
        return 130


if __name__ == "__main__":
    sys.exit(main())
