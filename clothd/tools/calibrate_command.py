"""`clothd calibrate`'s work, from its parsed arguments: one camera (DIR's pictures) or several (DIR's and
each DIR/cameras/NAME/'s, clothd/tools/calibrate_cameras.py). Nothing is written until every camera is
solved."""

from __future__ import annotations

import argparse
import json

from clothd.errors import InputError
from clothd.formats import write_camera
from clothd.tools.calibrate import read_pictures, solve
from clothd.tools.calibrate_cameras import camera_dirs, further_out, read_rig, solve_rig
from clothd.tools.calibration_report import (
    format_report,
    format_rig_report,
    picture_path,
    plot_report,
    report_json,
    rig_report_json,
)
from clothd.tools.charuco import Board


def calibrate_command(args: argparse.Namespace) -> int:
    squares_x, squares_y = args.board
    board = Board(squares_x, squares_y, args.square_m, args.marker_m, args.dictionary)
    if args.camera is not None:
        from clothd.tools.calibrate_live import capture_views

        capture_views(args.camera, board, args.images, args.flat, args.views, args.timeout_s)
    elif args.images.is_dir() and len(camera_dirs(args.images)) > 1:
        return _several(args, board)
    cal = solve(read_pictures(args.images, board, args.flat), board, args.flat_origin_m, fit_k3=args.k3)
    write_camera(args.out, cal.camera)
    picture = picture_path(args.out)
    plot_report(cal, picture)
    print(format_report(cal))
    print(f"\ncamera written to {args.out}, residuals and coverage to {picture}")
    if args.json:
        args.json.write_text(json.dumps(report_json(cal) | {"picture": str(picture)}, indent=2) + "\n")
    return 0


def _several(args: argparse.Namespace, board: Board) -> int:
    """Every camera of DIR and DIR/cameras/: the first to --out, the others beside it as NAME.json."""
    rig = solve_rig(read_rig(args.images, board, args.flat), board, args.flat_origin_m, fit_k3=args.k3)
    outs = [args.out, *(further_out(args.out, name) for name in rig.names[1:])]
    if args.out in outs[1:]:
        raise InputError(
            f"--out {args.out}: a further camera's calibration is written there; name it otherwise"
        )
    for cal, out in zip(rig.calibrations, outs, strict=True):
        write_camera(out, cal.camera)
        plot_report(cal, picture_path(out))
    print(format_rig_report(rig, outs))
    written = ", ".join(f"{name} to {out}" for name, out in zip(rig.names, outs, strict=True))
    print(f"\ncameras written: {written}; residuals and coverage beside each as NAME-calibration.png")
    if args.json:
        report = rig_report_json(rig, outs) | {"picture": str(picture_path(args.out))}
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0
