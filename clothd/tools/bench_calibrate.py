"""`clothd bench calibrate`: `clothd calibrate` on pictures hwsim renders through a camera it knows,
graded against that camera on the bars below.

- fx, fy, cx, cy: relative error, within 0.5 %.
- Table points over the whole image: every STEP_PX-th pixel, edges included, is back-projected through
  the true camera onto the table (z = 0) and projected through the recovered one; the largest distance
  from where it started is within 0.3 px. It weighs K, distortion and T_cam_world together, where the
  tracker uses them.
- Table plane: the angle between the true and the recovered table normal (camera frame) within 0.1°, and
  the largest distance of a true table point seen in the image from the recovered plane within 1 mm.
  The recovered world origin's distance from the true one is reported beside them (no bar).
- Camera pose in the table frame, reported for every camera: the angle of the rotation between the true
  and the recovered camera (deg) and the distance between their optical centres (mm). With `--cameras N`
  (2 or more) the pictures are rendered through the first N cameras of hwsim's default cell
  (hwsim/scenarios/cell.yaml: one straight down, one oblique), each given the `--dist` lens, calibrated
  together (clothd/tools/calibrate_cameras.py), and every camera is graded on the bars above and on its
  pose: within 0.05° and 0.5 mm. Each pair's epipolar error is reported beside them (no bar).
- With `--tracker SCENARIO`: hwsim records the scenario through the same camera and the tracker (mesh
  model, with input) follows it twice, given the true camera.json and the calibrated one, graded through
  the true camera (`clothd bench accuracy`'s measures). With the calibrated camera, node RMSE and
  mean + 2 x worst feature error are within 10 % of theirs with the true one.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from clothd.config import TrackerConfig
from clothd.core.camera_model import CameraModel
from clothd.errors import InputError
from clothd.formats import read_camera, write_camera
from clothd.tools.bench_accuracy import grade
from clothd.tools.calibrate import read_pictures, solve
from clothd.tools.calibrate_cameras import FURTHER_DIR, camera_dirs, read_rig, solve_rig
from clothd.tools.charuco import Board
from hwsim import scenario as scenarios
from hwsim.calibration_set import FLAT_NAME, centred_origin, middle_on_table, write_calibration_set
from hwsim.camera import Camera
from hwsim.charuco import BoardSpec
from hwsim.recording import record
from hwsim.scenario import CameraSpec, Scenario

STEP_PX = 2.0
BARS = {
    "fx_pct": 0.5,
    "fy_pct": 0.5,
    "cx_pct": 0.5,
    "cy_pct": 0.5,
    "table_reprojection_max_px": 0.3,
    "plane_angle_deg": 0.1,
    "plane_distance_max_mm": 1.0,
}
POSE_BARS = {"pose_deg": 0.05, "pose_mm": 0.5}
TRACKER_RATIO = 1.10
DEFAULT_DIST = (-0.12, 0.05, 0.001, -0.0005, 0.0)


def _table_normal(camera: CameraModel) -> tuple[np.ndarray, float]:
    """The table plane in the camera frame: unit normal n (world z) and offset d, with n · p = d on it."""
    n = camera.T_cam_world[:3, 2]
    return n, float(n @ camera.T_cam_world[:3, 3])


def grade_camera(recovered: CameraModel, truth: CameraModel) -> dict[str, float]:
    """The recovered camera against the true one on the measures above (module notes)."""
    rk, tk = recovered.K, truth.K
    pairs = {"fx_pct": (0, 0), "fy_pct": (1, 1), "cx_pct": (0, 2), "cy_pct": (1, 2)}
    graded = {key: float(100 * abs(rk[ij] - tk[ij]) / tk[ij]) for key, ij in pairs.items()}
    us = np.unique(np.append(np.arange(0.0, truth.width, STEP_PX), truth.width - 1))
    vs = np.unique(np.append(np.arange(0.0, truth.height, STEP_PX), truth.height - 1))
    pixels = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 2)
    table_m = truth.backproject_to_plane(pixels)
    seen = np.all(np.isfinite(table_m), axis=1)
    error_px = np.linalg.norm(recovered.project(table_m[seen]) - pixels[seen], axis=1)
    n_true, _ = _table_normal(truth)
    n_rec, d_rec = _table_normal(recovered)
    off_plane_m = np.abs(truth.to_camera(table_m[seen]) @ n_rec - d_rec)
    origin_m = recovered.T_cam_world[:3, 3] - truth.T_cam_world[:3, 3]
    turn = recovered.T_cam_world[:3, :3] @ truth.T_cam_world[:3, :3].T
    graded |= {
        "table_reprojection_max_px": float(error_px.max()),
        "table_reprojection_mean_px": float(error_px.mean()),
        "plane_angle_deg": math.degrees(math.acos(float(np.clip(n_true @ n_rec, -1.0, 1.0)))),
        "plane_distance_max_mm": float(off_plane_m.max() * 1e3),
        "origin_mm": float(np.linalg.norm(origin_m) * 1e3),
        "pose_deg": math.degrees(math.acos(float(np.clip((np.trace(turn) - 1) / 2, -1.0, 1.0)))),
        "pose_mm": float(np.linalg.norm(recovered.centre_m - truth.centre_m) * 1e3),
    }
    return graded


def tracker_check(out_dir: Path, spec: CameraSpec, scenario: str, cfg: TrackerConfig) -> dict[str, Any]:
    """`scenario` recorded through the camera `spec` into out_dir/rec_SCENARIO, tracked (cfg's model) with
    the true camera and with out_dir/calibrated.json; the figures and their ratios, calibrated to true."""
    recording = out_dir / f"rec_{scenario}"
    shutil.rmtree(recording, ignore_errors=True)
    record(scenarios.load(scenario).model_copy(update={"camera": spec}), recording)
    cameras = {"true": None, "calibrated": out_dir / "calibrated.json"}
    rows = {
        label: grade(recording, scenario, f"{cfg.model}, {label} camera", cfg, cam).row
        for label, cam in cameras.items()
    }
    ratios = {
        "node_rmse": (rows["calibrated"].node_rmse_mm or math.nan) / (rows["true"].node_rmse_mm or math.nan),
        "cost": rows["calibrated"].cost_px / rows["true"].cost_px,
    }
    return {
        "scenario": scenario,
        "rows": {label: asdict(row) for label, row in rows.items()},
        "ratio": ratios,
        "pass": all(r <= TRACKER_RATIO for r in ratios.values()),
    }


def run_bench(
    out_dir: Path,
    views: int = 15,
    seed: int = 0,
    tilt_rad: float = 0.15,
    yaw_rad: float = 0.3,
    dist: tuple[float, float, float, float, float] = DEFAULT_DIST,
    tracker: tuple[str, TrackerConfig] | None = None,
    cameras: int = 1,
) -> dict[str, Any]:
    """Render a calibration set through a tilted, distorted hwsim camera into out_dir, calibrate, grade;
    with `tracker` (a scenario and the tracker's configuration), also `tracker_check`. The camera hangs
    1 m up, moved sideways so that the middle of its picture sees the table's origin, as a real one is
    aimed at the cloth. cameras > 1: `run_rig_bench` (tilt_rad and yaw_rad unused)."""
    if cameras > 1:
        if tracker is not None:
            raise InputError("--tracker grades one camera: leave out --cameras")
        return run_rig_bench(out_dir, cameras, views, seed, dist)
    hung = CameraSpec(tilt_rad=tilt_rad, yaw_rad=yaw_rad, dist=dist)
    x, y = middle_on_table(Camera.from_spec(hung))  # moved so that it looks at the table's middle
    spec = hung.model_copy(
        update={"position_m": (hung.position_m[0] - x, hung.position_m[1] - y, hung.position_m[2])}
    )
    scenario = Scenario(name="calibrate", duration_s=1.0, camera=spec)
    board_spec = BoardSpec()
    origin_m = centred_origin(Camera.from_spec(spec), board_spec)
    write_calibration_set(scenario, out_dir, board_spec, views, origin_m, seed)
    board = _board(board_spec)
    cal = solve(read_pictures(out_dir, board, FLAT_NAME), board, origin_m)
    write_camera(out_dir / "calibrated.json", cal.camera)
    graded = grade_camera(cal.camera, read_camera(out_dir / "camera.json"))
    result = {
        "camera": spec.model_dump(),
        "flat_origin_m": list(origin_m),
        "views_rendered": views + 1,
        "views_used": len(cal.views),
        "rms_px": cal.rms_px,
        "graded": graded,
        "bars": BARS,
        "pass": {key: graded[key] <= bar for key, bar in BARS.items()},
        "pictures": str(out_dir),
    }
    if tracker is not None:
        result["tracker"] = tracker_check(out_dir, spec, *tracker)
    return result


def _board(spec: BoardSpec) -> Board:
    return Board(spec.squares_x, spec.squares_y, spec.square_m, spec.marker_m, spec.dictionary)


def run_rig_bench(
    out_dir: Path,
    cameras: int = 2,
    views: int = 15,
    seed: int = 0,
    dist: tuple[float, float, float, float, float] = DEFAULT_DIST,
) -> dict[str, Any]:
    """Render a calibration set through the first `cameras` cameras of hwsim's default cell, each with the
    lens `dist`, into out_dir (the first's pictures there, the others' in cameras/NAME/), calibrate them
    together, and grade every camera against its truth (module notes)."""
    cell = scenarios.load("cell").camera_specs
    if not 2 <= cameras <= len(cell):
        raise InputError(f"--cameras {cameras}: hwsim's default cell has {len(cell)} cameras")
    specs = [spec.model_copy(update={"dist": dist}) for spec in cell[:cameras]]
    scenario = Scenario(name="calibrate", duration_s=1.0, cameras=specs)
    board_spec = BoardSpec()
    origin_m = centred_origin(Camera.from_spec(specs[0]), board_spec)
    shutil.rmtree(out_dir / FURTHER_DIR, ignore_errors=True)  # a previous run's other cameras
    write_calibration_set(scenario, out_dir, board_spec, views, origin_m, seed)
    board = _board(board_spec)
    rig = solve_rig(read_rig(out_dir, board, FLAT_NAME), board, origin_m)
    bars = BARS | POSE_BARS
    graded_cameras = []
    for (name, path), cal in zip(camera_dirs(out_dir), rig.calibrations, strict=True):
        write_camera(path / "calibrated.json", cal.camera)
        graded = grade_camera(cal.camera, read_camera(path / "camera.json"))
        graded_cameras.append(
            {
                "name": name,
                "views_used": len(cal.views),
                "rms_px": cal.rms_px,
                "graded": graded,
                "pass": {key: graded[key] <= bar for key, bar in bars.items()},
            }
        )
    return {
        "cameras": graded_cameras,
        "specs": [spec.model_dump() for spec in specs],
        "flat_origin_m": list(origin_m),
        "views_rendered": views + 1,
        "views_shared": rig.views_shared,
        "pairs": [
            {"cameras": list(p.cameras), "epipolar_median_px": p.median_px, "epipolar_p95_px": p.p95_px}
            for p in rig.pairs
        ],
        "bars": bars,
        "pictures": str(out_dir),
    }


def _format_rig(result: dict[str, Any]) -> str:
    bars = result["bars"]
    names = [c["name"] for c in result["cameras"]]
    lines = [
        f"hwsim's cell, {len(names)} cameras ({', '.join(names)}), dist "
        f"{', '.join(f'{k:g}' for k in result['specs'][0]['dist'])}; {result['views_shared']} of "
        f"{result['views_rendered'] - 1} held views seen by two cameras or more",
    ]
    for c in result["cameras"]:
        lines.append(f"{c['name']}: {c['views_used']} pictures used, RMS {c['rms_px']:.3f} px")
    lines += ["", f"{'measure':<28} " + " ".join(f"{n:>9}" for n in names) + f" {'bar':>7}"]
    for key in result["cameras"][0]["graded"]:
        values = " ".join(f"{c['graded'][key]:9.4f}" for c in result["cameras"])
        bar = bars.get(key)
        verdict = (
            "" if bar is None else ("  pass" if all(c["pass"][key] for c in result["cameras"]) else "  FAIL")
        )
        lines.append(f"{key:<28} {values} {'' if bar is None else f'{bar:g}':>7}{verdict}")
    lines.append("")
    for p in result["pairs"]:
        a, b = p["cameras"]
        lines.append(
            f"epipolar error {a}-{b}: median {p['epipolar_median_px']:.3f} px, "
            f"p95 {p['epipolar_p95_px']:.3f} px"
        )
    return "\n".join(lines)


def format_result(result: dict[str, Any]) -> str:
    if "cameras" in result:
        return _format_rig(result)
    cam = result["camera"]
    lines = [
        f"hwsim camera: f {cam['f_px']:g} px, tilt {cam['tilt_rad']:g} rad, yaw {cam['yaw_rad']:g} rad, "
        f"dist {', '.join(f'{k:g}' for k in cam['dist'])}",
        f"{result['views_used']} of {result['views_rendered']} pictures used, RMS {result['rms_px']:.3f} px",
        "",
        f"{'measure':<28} {'value':>9} {'bar':>7}",
    ]
    g = result["graded"]
    for key, value in g.items():
        bar = BARS.get(key)
        verdict = "" if bar is None else ("  pass" if result["pass"][key] else "  FAIL")
        shown_bar = "" if bar is None else f"{bar:g}"
        lines.append(f"{key:<28} {value:9.4f} {shown_bar:>7}{verdict}")
    if "tracker" in result:
        t = result["tracker"]
        lines += ["", f"tracker on {t['scenario']}: {'node rmse':>10} {'mean+2w':>8}"]
        for label, row in t["rows"].items():
            lines.append(f"  {label + ' camera':<22} {row['node_rmse_mm']:7.3f} mm {row['cost_px']:5.3f} px")
        r = t["ratio"]
        verdict = f"(bar {TRACKER_RATIO:g}) {'pass' if t['pass'] else 'FAIL'}"
        lines.append(f"  calibrated / true       {r['node_rmse']:10.4f} {r['cost']:8.4f}  {verdict}")
    return "\n".join(lines)


def write_json(result: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(result, indent=2) + "\n")
