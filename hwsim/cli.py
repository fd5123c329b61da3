"""The `hwsim` command: record, verify, preview and benchmark the simulated cell."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from hwsim import scenario as scenarios


def _cmd_record(args: argparse.Namespace) -> int:
    from hwsim.recording import record

    sc = scenarios.load(args.scenario, duration_s=args.duration)
    stats = record(sc, args.out, arch=args.arch)
    print(
        f"recorded {sc.name}: {stats.frames} frames to {args.out} in {stats.wall_s:.1f} s "
        f"(physics {stats.physics_ms:.1f} ms/frame, render {stats.render_ms:.1f} ms/frame)"
    )
    return 0


def _cmd_verify(args: argparse.Namespace) -> int:
    from hwsim.verify import NCC_MIN, PASS_FRACTION, verify

    result = verify(args.recording)
    print(
        f"{args.recording}: {result.points} points, {result.pairs} patch pairs, "
        f"{result.pass_fraction:.1%} with NCC >= {NCC_MIN} (need {PASS_FRACTION:.0%}); "
        f"NCC median {result.ncc_median:.3f}, 5th percentile {result.ncc_p05:.3f} -> "
        f"{'PASS' if result.ok else 'FAIL'}"
    )
    if args.json:
        args.json.write_text(json.dumps(result.to_json(), indent=2) + "\n")
    return 0 if result.ok else 1


def _cmd_preview(args: argparse.Namespace) -> int:
    from hwsim.preview import write_preview

    out = write_preview(args.recording, args.out)
    print(f"preview written to {out}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from hwsim.bench import format_bench, run_bench

    result = run_bench(args.scenario, record_s=args.record_seconds)
    print(format_bench(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


def _cmd_ridges(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from hwsim.ridge_hold import format_holds, ridge_holds

    rows = []
    for row in ridge_holds(args.scenario, args.hold_s, args.pushes, args.seed):
        rows.append(row)
        print(f"{row.case}: {row.settled_m * 1e3:.2f} -> {row.lowest_m * 1e3:.2f} mm", file=sys.stderr)
    print(format_holds(rows))
    if args.json:
        args.json.write_text(json.dumps([asdict(r) | {"kept": r.kept} for r in rows], indent=2) + "\n")
    return 0


def _cmd_stretch(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from hwsim.stretch import format_stretch, stretch_under_turn

    rows = []
    for config in args.config:
        substep_ms, sweeps = config.split(":")
        rows.append(stretch_under_turn(args.scenario, float(substep_ms) / 1e3, int(sweeps)))
    print(format_stretch(rows, args.scenario))
    if args.json:
        args.json.write_text(json.dumps([asdict(r) for r in rows], indent=2) + "\n")
    return 0


def _cmd_charuco(args: argparse.Namespace) -> int:
    from hwsim.calibration_set import FLAT_NAME, centred_origin, write_calibration_set
    from hwsim.camera import Camera
    from hwsim.charuco import BoardSpec

    sc = scenarios.load(args.scenario)
    squares_x, squares_y = args.board
    board = BoardSpec(squares_x, squares_y, args.square_m, args.marker_m, args.dictionary)
    origin = args.flat_origin_m or centred_origin(Camera.from_spec(sc.camera), board)
    names = write_calibration_set(sc, args.out, board, args.views, origin, args.seed)
    x, y = origin
    print(
        f"rendered {len(names)} pictures of a {board.squares_x}x{board.squares_y} ChArUco board through "
        f"{sc.name}'s {'cameras' if len(sc.camera_specs) > 1 else 'camera'} to {args.out} (true camera: "
        f"{args.out / 'camera.json'}); calibrate with\n"
        f"  clothd calibrate --images {args.out} --board {board.squares_x}x{board.squares_y} "
        f"--square-m {board.square_m:g} --marker-m {board.marker_m:g} --dictionary {board.dictionary} "
        f"--flat {FLAT_NAME} --flat-origin-m={x:g},{y:g} --out camera.json"
    )
    return 0


def _board_size(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6) squares, for --board."""
    nx, sep, ny = text.lower().partition("x")
    if not (sep and nx.isdigit() and ny.isdigit() and 3 <= int(nx) <= 40 and 3 <= int(ny) <= 40):
        raise argparse.ArgumentTypeError(f"{text!r}: a board is SQUARES_XxSQUARES_Y, each 3..40 (e.g. 9x6)")
    return int(nx), int(ny)


def _xy_m(text: str) -> tuple[float, float]:
    """'-0.21,0.12' -> (-0.21, 0.12); write it --flat-origin-m=-0.21,0.12 when it starts with a minus."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: X,Y in metres (e.g. -0.21,0.12)") from None
    return x, y


def _cmd_serve(args: argparse.Namespace) -> int:
    import contextlib
    import signal
    import tempfile

    from hwsim.serve import serve

    def _terminate(signum: int, frame: object) -> None:
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, _terminate)
    if args.exit_with_parent:
        _exit_with_parent(signal.SIGTERM)
    sc = scenarios.load(args.scenario)
    state_dir = args.state_dir or Path(tempfile.mkdtemp(prefix="hwsim-"))
    with contextlib.suppress(KeyboardInterrupt):
        serve(sc, state_dir, args.port, args.camera_fps, args.arch, args.other_cameras_fps, args.controllers)
    return 0


def _exit_with_parent(signum: int) -> None:
    """Have Linux send `signum` when the parent process dies (prctl PR_SET_PDEATHSIG), so that a parent
    killed with -9 does not leave the cell running on its own; a parent already gone ends us now."""
    import ctypes
    import os

    parent = os.getppid()
    pr_set_pdeathsig = 1
    if ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signum) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent or parent == 1:
        raise SystemExit(0)


def _add_serve(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    s = sub.add_parser("serve", help="run the cell in real time: firmware on a pty, camera over HTTP")
    s.add_argument("--scenario", default="cell", help="a scenario file or shipped name (default: cell)")
    s.add_argument("--port", type=int, default=0, help="HTTP port on 127.0.0.1 (default: any free one)")
    s.add_argument("--state-dir", type=Path, help="for the pty link and camera.json (default: temp)")
    s.add_argument("--camera-fps", type=float, default=15.0, help="frames served per second")
    s.add_argument(
        "--other-cameras-fps",
        type=float,
        help="frames per second of every camera but the first (default: --camera-fps)",
    )
    s.add_argument(
        "--exit-with-parent", action="store_true", help="stop when the process that started it dies (Linux)"
    )
    s.add_argument(
        "--controllers",
        type=int,
        default=1,
        help="stepper controllers, each its own firmware process on its own pty driving an equal share "
        "of the modules by id (default: 1)",
    )
    s.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "vulkan"], help="Taichi backend")
    s.set_defaults(func=_cmd_serve)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hwsim", description="The simulated textile cell.")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("record", help="run a scenario and write a recording")
    r.add_argument(
        "scenario", help=f"a scenario file, or a shipped name ({', '.join(scenarios.shipped_names())})"
    )
    r.add_argument("--out", type=Path, required=True, help="recording directory")
    r.add_argument("--duration", type=float, help="override the scenario's duration_s")
    r.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "vulkan"], help="Taichi backend")
    r.set_defaults(func=_cmd_record)
    v = sub.add_parser("verify", help="check that truth and pixels agree")
    v.add_argument("recording", type=Path)
    v.add_argument("--json", type=Path, help="also write the figures as JSON")
    v.set_defaults(func=_cmd_verify)
    pv = sub.add_parser("preview", help="write a video of a recording with the truth mesh")
    pv.add_argument("recording", type=Path)
    pv.add_argument("--out", type=Path, help="video file (default RECORDING/preview.mp4)")
    pv.set_defaults(func=_cmd_preview)
    b = sub.add_parser("bench", help="physics, render and record speed")
    b.add_argument("--scenario", default="compress")
    b.add_argument("--record-seconds", type=float, default=10.0)
    b.add_argument("--json", type=Path)
    b.set_defaults(func=_cmd_bench)
    st = sub.add_parser("stretch", help="the truth solver's stretch of a rigidly turned cloth, per substep")
    st.add_argument("--scenario", default="cell")
    st.add_argument(
        "--config",
        nargs="+",
        default=["2:5", "1:5", "1:2", "0.75:2", "0.5:1", "0.5:2"],
        help="substep ms:sweeps per substep, one or more",
    )
    st.add_argument("--json", type=Path)
    st.set_defaults(func=_cmd_stretch)
    rh = sub.add_parser("ridges", help="which ridges the cloth keeps on still belts, in every direction")
    rh.add_argument("--scenario", default="cell", help="whose cloth (default: the live cell's)")
    rh.add_argument("--hold-s", type=float, default=10.0, help="how long each ridge is held")
    rh.add_argument("--pushes", type=int, default=12, help="ridges pushed in by the hands along random lines")
    rh.add_argument("--seed", type=int, default=0, help="the pushes' lines")
    rh.add_argument("--json", type=Path)
    rh.set_defaults(func=_cmd_ridges)
    ch = sub.add_parser(
        "charuco", help="render ChArUco calibration pictures through a scenario's camera, with the truth"
    )
    ch.add_argument("--scenario", default="cell", help="whose camera, noise and light (default: cell)")
    ch.add_argument("--out", type=Path, required=True, help="directory for the pictures and camera.json")
    ch.add_argument("--views", type=int, default=15, help="tilted views besides the flat one")
    ch.add_argument(
        "--board", type=_board_size, default=(9, 6), metavar="NXxNY", help="squares (default 9x6)"
    )
    ch.add_argument("--square-m", type=float, default=0.060)
    ch.add_argument("--marker-m", type=float, default=0.045)
    ch.add_argument("--dictionary", default="DICT_5X5_100")
    ch.add_argument(
        "--flat-origin-m",
        type=_xy_m,
        metavar="X,Y",
        help="world x, y of corner id 0 in the flat view (default: the board centred in the picture)",
    )
    ch.add_argument("--seed", type=int, default=0, help="poses and sensor noise")
    ch.set_defaults(func=_cmd_charuco)
    _add_serve(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except scenarios.ScenarioError as err:
        print(f"hwsim: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
