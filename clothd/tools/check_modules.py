"""`clothd check-modules`: drive each module in turn and measure with the camera what its belt did.

Each module runs alone for DRIVE_S at SPEED_M_S towards HEADING_RAD (a drive script, recorded); the
recording's frames show its belt's surface (clothd/core/module_check.py), and the velocity measured
against the command gives its direction, heading offset and speed scale, written as the YAML file that
`cell.module_calibration` names.

hwsim falls behind real time on a loaded machine (its world steps slower, and so do its belts), while
the frames are stamped on the host's clock: against the simulated cell the time between two frames is
taken on hwsim's own clock instead, its camera's frame period (`frame_period_s`), as a real cell's is
on the host's.

A module under the cloth cannot be checked: the belts around it hold the cloth, which then shows nothing
of the one belt beneath (hwsim: 0.02 mm of cloth motion for 20 mm of belt). The check refuses such a
module by name, and one the camera does not see whole; it needs the cloth tracked, so that it knows
where the cloth lies and the daemon can keep its drives off it.
"""

from __future__ import annotations

import datetime
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from clothd.core.conveyor import ConveyorLayout
from clothd.core.drive_script import DriveScript
from clothd.core.module_check import (
    BeltPatch,
    ModuleCalibrationEntry,
    calibration_of,
    mean_velocity_m_s,
    surface_shift_m,
)
from clothd.errors import ClothdError, InputError
from clothd.formats import read_camera, read_commands, read_frame_times, read_layout
from clothd.tools.cell_client import CellClient, CellError

SPEED_M_S = 0.02  # slow: 70 mm of belt in DRIVE_S, and 1.3 mm a frame at 15 frames/s
HEADING_RAD = 0.0
DRIVE_S = 3.5
SETTLE_S = 0.8  # the turntable turns (at most a quarter turn at 3 rad/s) and the belt speeds up first
PATCH_SIDE_M = 0.04  # the belt's middle: inside a 65 mm belt at any heading (half-diagonal 28 mm)
CLEAR_OF_CLOTH_M = 0.005  # the patch stays this far from the cloth's outline
MIN_PAIRS = 8


@dataclass(frozen=True)
class ModuleResult:
    entry: ModuleCalibrationEntry
    speed_m_s: float  # measured
    pairs: int  # frame pairs measured


def _cloth_outline_m(status: dict[str, Any]) -> np.ndarray:
    mesh = status.get("mesh")
    if not mesh:
        raise CellError(
            "the status carries no mesh (tracker.model rigid or none): the check needs the mesh tracker"
        )
    nodes = np.ascontiguousarray(np.asarray(mesh["nodes_m"], dtype=np.float32)[:, :2])
    return np.asarray(cv2.convexHull(nodes)).reshape(-1, 2)


def check_cell_ready(status: dict[str, Any]) -> None:
    """Refuse, with the reason, a cell whose camera or cloth is not there."""
    camera = status.get("camera") or {}
    if not camera.get("healthy"):
        raise CellError(f"the camera is not delivering frames (state {status['state']}): check camera.source")
    if status["state"] != "tracking":
        raise CellError(
            f"the cloth is not tracked (state {status['state']}): lay the cloth on the table; the check "
            "keeps its drives off the cloth by where the tracker sees it"
        )


def modules_to_check(
    status: dict[str, Any],
    layout: ConveyorLayout,
    table_to_pixel: np.ndarray,
    size_px: tuple[int, int],
    asked: list[int] | None,
) -> tuple[list[int], list[str]]:
    """The modules to drive, and why each one left out is (for all modules); asked modules that cannot
    be checked are refused, named."""
    outline = _cloth_outline_m(status).reshape(-1, 1, 2)
    half_diagonal_m = PATCH_SIDE_M / math.sqrt(2.0)
    why: dict[int, str] = {}
    for m, (x, y) in enumerate(layout.centres_m):
        inside_m = cv2.pointPolygonTest(outline, (float(x), float(y)), True)
        if inside_m > -(half_diagonal_m + CLEAR_OF_CLOTH_M):
            why[m] = f"module {m} lies under the cloth (move the cloth off it, or lay a card on it alone)"
            continue
        h = PATCH_SIDE_M / 2
        corners = np.array([[x - h, y - h, 1], [x + h, y - h, 1], [x + h, y + h, 1], [x - h, y + h, 1]])
        px = corners @ table_to_pixel.T
        px = px[:, :2] / px[:, 2:]
        if px.min() < 0 or px[:, 0].max() > size_px[0] - 1 or px[:, 1].max() > size_px[1] - 1:
            why[m] = f"module {m}'s belt is not wholly in the camera's view"
    if asked is not None:
        bad = [f"{why[m]}" for m in asked if m in why]
        missing = [m for m in asked if not 0 <= m < layout.n_modules]
        if missing:
            raise CellError(f"modules {missing} out of range (the cell has {layout.n_modules})")
        if bad:
            raise CellError("; ".join(bad))
        return asked, []
    return [m for m in range(layout.n_modules) if m not in why], list(why.values())


def script_for(module: int) -> DriveScript:
    entry = {"t_s": 0.0, "modules": {"ids": [module]}, "speed_m_s": SPEED_M_S, "heading_rad": HEADING_RAD}
    return DriveScript.model_validate({"duration_s": DRIVE_S, "timeline": [entry]})


def _drive_intervals(
    rows: list[tuple[float, int, float, float]],
) -> dict[int, tuple[float, float, float, float]]:
    """Per module, the first time it ran in the recording: (t_on, t_off, speed, heading) of the command."""
    found: dict[int, tuple[float, float, float, float]] = {}
    running: dict[int, tuple[float, float, float]] = {}
    for t, m, speed, heading in rows:
        if speed > 0 and m not in running and m not in found:
            running[m] = (t, speed, heading)
        elif speed == 0 and m in running:
            t_on, s, h = running.pop(m)
            found[m] = (t_on, t, s, h)
    # The recording may stop before the last drive's stop reaches it: that one runs to the last frame.
    found.update({m: (t_on, math.inf, s, h) for m, (t_on, s, h) in running.items()})
    return found


def measure(recording: Path, modules: list[int], frame_period_s: float | None = None) -> list[ModuleResult]:
    """Each module's calibration from a recording of its drive. With `frame_period_s` (a simulated
    camera's) the time between two frames is that period times the frames the pair spans, not the host's
    time between their arrivals."""
    camera = read_camera(recording / "camera.json")
    layout = read_layout(recording / "table.json")
    times = read_frame_times(recording / "frames.csv")
    if times is None:
        raise InputError(f"{recording}: no frames.csv")
    t_s = np.asarray(times)
    intervals = _drive_intervals(read_commands(recording / "commands.csv", layout.n_modules))
    results = []
    for m in modules:
        if m not in intervals:
            raise InputError(f"{recording}: module {m} was not driven in the recording")
        t_on, t_off, speed, heading = intervals[m]
        ks = np.flatnonzero((t_s >= t_on + SETTLE_S) & (t_s <= t_off))
        patch = BeltPatch.of(camera, layout.centres_m[m], PATCH_SIDE_M)
        patches = [patch.sample(_frame(recording, int(k))) for k in ks]
        dts, shifts = [], []
        for j in range(len(ks) - 1):
            shift = surface_shift_m(patches[j], patches[j + 1], patch.window)
            if shift is not None:
                dts.append(t_s[ks[j + 1]] - t_s[ks[j]])
                shifts.append(shift)
        if len(shifts) < MIN_PAIRS:
            raise InputError(
                f"module {m}: only {len(shifts)} frame pairs measured (at least {MIN_PAIRS} needed)"
            )
        moved_m = np.asarray(shifts)
        between_s = np.asarray(dts) if frame_period_s is None else _frame_steps(moved_m) * frame_period_s
        v = mean_velocity_m_s(between_s, moved_m)
        results.append(ModuleResult(calibration_of(m, speed, heading, v), float(np.hypot(*v)), len(shifts)))
    return results


def _frame_steps(shifts_m: np.ndarray) -> np.ndarray:
    """How many camera frames each pair of received frames spans, for a camera on its own clock: a belt
    at a steady speed moves as far each frame, so a pair the daemon received with a frame missed between
    moved twice the usual (the host's arrival times cannot tell a missed frame from a late one)."""
    length_m = np.hypot(shifts_m[:, 0], shifts_m[:, 1])
    return np.maximum(1, np.round(length_m / np.median(length_m)))


def _frame(recording: Path, index: int) -> np.ndarray:
    path = recording / "frames" / f"{index:06d}.png"
    image = cv2.imread(str(path))
    if image is None:
        raise InputError(f"{path}: not a picture OpenCV can read")
    return np.asarray(image)


def check_modules(
    client: CellClient, asked: list[int] | None, frame_period_s: float | None = None
) -> tuple[list[ModuleResult], list[str], Path]:
    """Drive and measure; the results, the modules left out (why) and the recording. `frame_period_s`: a
    simulated camera's, on its own clock (below)."""
    status = client.status()
    check_cell_ready(status)
    camera = client.http.get("/camera").json()
    table_to_pixel = np.asarray(camera["table_to_pixel"], dtype=float)
    now = datetime.datetime.now(datetime.UTC)
    recording = client.record_start(f"check-modules-{now.strftime('%Y%m%d-%H%M%S-%f')}")
    try:
        layout = read_layout(recording / "table.json")
        modules, left_out = modules_to_check(
            status, layout, table_to_pixel, (int(camera["width"]), int(camera["height"])), asked
        )
        if not modules:
            raise CellError("no module can be checked: " + "; ".join(left_out))
        for m in modules:
            client.play(script_for(m))
    finally:
        client.record_stop()
        _wait_recording_closed(client)
    return measure(recording, modules, frame_period_s), left_out, recording


def _wait_recording_closed(client: CellClient, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not (client.status().get("recording") or {}).get("active"):
            return
        time.sleep(0.1)
    raise ClothdError("the recording did not stop")


def format_results(results: list[ModuleResult]) -> str:
    lines = [f"{'module':>6}  {'reversed':>8}  {'heading offset':>14}  {'speed scale':>11}  {'pairs':>5}"]
    for r in results:
        e = r.entry
        lines.append(
            f"{e.module:>6}  {'yes' if e.reversed else 'no':>8}  {e.heading_offset_deg:>12.2f} °  "
            f"{e.speed_scale:>11.4f}  {r.pairs:>5}"
        )
    return "\n".join(lines)
