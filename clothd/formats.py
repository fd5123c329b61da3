"""clothd's files, read and written in one place (docs/recording-format.md, docs/replay-format.md).

- camera.json: the camera model (K, dist, T_cam_world, width, height);
- table.json: the module layout;
- frames.csv and commands.csv: a recording's capture times and the commands sent as they changed;
- estimates.npz: what the tracker believed, frame by frame;
- module calibration (YAML): what `clothd check-modules` found each module does with a command;
- and every file a configuration names (`read_referenced_files`, for `clothd check-config`).

The core never opens a file: footage, the recorder, replay and the composition root go through here and
hand the core objects. Any problem reading is an InputError that names the file and what is wrong.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np
import yaml

from clothd.config import Config, yaml_problem
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout
from clothd.core.messages import Estimate, ModuleCommands, feature_detections
from clothd.core.module_check import ModuleCalibrationEntry
from clothd.errors import InputError

CAMERA_KEYS = ("K", "dist", "T_cam_world", "width", "height")
CALIBRATION_KEYS = {"module", "reversed", "heading_offset_deg", "speed_scale"}
SPEED_SCALE_RANGE = (0.25, 4.0)  # beyond this a module is broken, not miscalibrated
FRAMES_CSV_HEADER = "index,t_s\n"
COMMANDS_CSV_HEADER = "t_s,module,speed_m_s,heading_rad\n"


def _read_json(path: Path) -> Any:
    try:
        return json.loads(Path(path).read_text())
    except OSError as err:
        raise InputError(f"{path}: cannot read: {err.strerror}") from None
    except json.JSONDecodeError as err:
        raise InputError(f"{path}: not valid JSON: {err}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file, so not JSON (a picture?)") from None


def _write_json(path: Path, obj: Any) -> None:
    path.write_text(json.dumps(obj, indent=2) + "\n")


# -- camera.json -----------------------------------------------------------------------------------


def read_camera(path: Path) -> CameraModel:
    """camera.json -> CameraModel. Any problem -> InputError."""
    d = _read_json(path)
    if not isinstance(d, dict):
        raise InputError(f"{path}: expected a JSON object with keys {', '.join(CAMERA_KEYS)}")
    for key in CAMERA_KEYS:
        if key not in d:
            raise InputError(f"{path}: missing key '{key}'")
    try:
        return CameraModel(
            np.asarray(d["K"], dtype=float),
            np.asarray(d["dist"], dtype=float),
            np.asarray(d["T_cam_world"], dtype=float),
            int(d["width"]),
            int(d["height"]),
        )
    except (TypeError, ValueError) as err:
        raise InputError(f"{path}: {err}") from None


def camera_dict(camera: CameraModel) -> dict[str, object]:
    """camera.json's content (the keys read_camera reads)."""
    return {
        "K": camera.K.tolist(),
        "dist": camera.dist.tolist(),
        "T_cam_world": camera.T_cam_world.tolist(),
        "width": camera.width,
        "height": camera.height,
    }


def write_camera(path: Path, camera: CameraModel) -> None:
    _write_json(path, camera_dict(camera))


# -- table.json ------------------------------------------------------------------------------------


def read_layout(path: Path) -> ConveyorLayout:
    """table.json -> ConveyorLayout. Any problem -> InputError."""
    d = _read_json(path)
    try:
        return ConveyorLayout(
            int(d["modules_x"]), int(d["modules_y"]), float(d["pitch_m"]), float(d["module_size_m"])
        )
    except (KeyError, ValueError, TypeError) as err:
        raise InputError(f"{path}: not a usable table layout ({err})") from None


def write_layout(path: Path, layout: ConveyorLayout) -> None:
    _write_json(
        path,
        {
            "modules_x": layout.modules_x,
            "modules_y": layout.modules_y,
            "pitch_m": layout.pitch_m,
            "module_size_m": layout.module_size_m,
            "centres_m": layout.centres_m.tolist(),
        },
    )


# -- frames.csv and commands.csv ---------------------------------------------------------------------


def read_frame_rows(path: Path) -> tuple[tuple[int, ...], tuple[float, ...]] | None:
    """frames.csv (index, t_s) of a live recording: each row's frame index and capture time; None when
    there is none. A further camera's rows name the first camera's frames they were paired with."""
    if not path.exists():
        return None
    try:
        with path.open(newline="") as f:
            rows = [(int(r["index"]), float(r["t_s"])) for r in csv.DictReader(f)]
    except (OSError, KeyError, ValueError) as err:
        raise InputError(f"{path}: not a usable frame-time file ({err})") from None
    return tuple(i for i, _ in rows), tuple(t for _, t in rows)


def read_frame_times(path: Path) -> tuple[float, ...] | None:
    """frames.csv's capture times; None when there is none."""
    rows = read_frame_rows(path)
    return None if rows is None else rows[1]


def read_commands(path: Path, n_modules: int) -> list[tuple[float, int, float, float]]:
    """commands.csv rows (t_s, module, speed_m_s, heading_rad), sorted by time."""
    rows: list[tuple[float, int, float, float]] = []
    try:
        with path.open(newline="") as f:
            for r in csv.DictReader(f):
                rows.append(
                    (float(r["t_s"]), int(r["module"]), float(r["speed_m_s"]), float(r["heading_rad"]))
                )
    except (OSError, KeyError, ValueError) as err:
        raise InputError(f"{path}: not a usable commands file ({err})") from None
    bad = [m for _, m, _, _ in rows if not 0 <= m < n_modules]
    if bad:
        raise InputError(f"{path}: module ids {sorted(set(bad))[:5]} outside 0..{n_modules - 1}")
    return sorted(rows)


class FrameTimesLog:
    """frames.csv, growing a row per frame and flushed row by row."""

    def __init__(self, path: Path) -> None:
        self._file: IO[str] = path.open("w", newline="")
        self._file.write(FRAMES_CSV_HEADER)

    def add(self, index: int, t_s: float) -> None:
        """Frame `index` captured at t_s. OSError on a failed write."""
        self._file.write(f"{index},{t_s:.6f}\n")
        self._file.flush()

    def close(self) -> list[str]:
        return _close_all([self._file])


class RecordingLog:
    """A recording's two growing CSV files, flushed row by row so that a recording cut short replays up
    to its last complete frame: frames.csv (a frame's capture time) and commands.csv (each module's
    command whenever it changes)."""

    def __init__(self, directory: Path) -> None:
        self._times = FrameTimesLog(directory / "frames.csv")
        self._commands: IO[str] = (directory / "commands.csv").open("w", newline="")
        self._commands.write(COMMANDS_CSV_HEADER)
        self._last: ModuleCommands | None = None

    def add_frame(self, index: int, t_s: float, commands: ModuleCommands) -> None:
        """Frame `index` captured at t_s with `commands` in force. OSError on a failed write."""
        self._times.add(index, t_s)
        last = self._last
        changed = (
            np.ones(commands.n_modules, bool)
            if last is None
            else (commands.speed_m_s != last.speed_m_s) | (commands.heading_rad != last.heading_rad)
        )
        w = csv.writer(self._commands)
        for m in np.flatnonzero(changed):
            w.writerow(
                [f"{t_s:.6f}", int(m), f"{commands.speed_m_s[m]:.6f}", f"{commands.heading_rad[m]:.6f}"]
            )
        self._commands.flush()
        self._last = commands

    def close(self) -> list[str]:
        """Close both files; the errors met, as text (a full disk fails on close too)."""
        return self._times.close() + _close_all([self._commands])


def _close_all(files: list[IO[str]]) -> list[str]:
    errors = []
    for f in files:
        try:
            f.close()
        except OSError as err:
            errors.append(f"closing {f.name} failed: {err}")
    return errors


# -- estimates.npz ---------------------------------------------------------------------------------


def write_estimates(path: Path, estimates: list[Estimate], t0_s: float = 0.0) -> None:
    """t_s (F,) (the frames' times less t0_s), pose (F, 3), feature_id (n,), meas_px and pred_px (F, n, 2)
    (NaN where a feature is not alive), detect_frame (n,) and detect_px (n, 2) (the frame and pixel each
    feature was detected at; -1 and NaN if before the first frame), and nodes_m (F, ny, nx, 3) when every
    estimate with nodes has the same mesh."""
    ids = np.unique(np.concatenate([e.feature_id for e in estimates])) if estimates else np.zeros(0, np.int64)
    col = {int(i): k for k, i in enumerate(ids)}
    F, n = len(estimates), len(ids)
    meas = np.full((F, n, 2), np.nan, np.float32)
    pred = np.full((F, n, 2), np.nan, np.float32)
    for f, e in enumerate(estimates):
        cols = np.array([col[int(i)] for i in e.feature_id], dtype=np.int64)
        if len(cols):
            meas[f, cols] = e.meas_px
            pred[f, cols] = e.pred_px
    detect_frame = np.full(n, -1, np.int64)
    detect_px = np.full((n, 2), np.nan, np.float32)
    for fid, (k, px) in feature_detections(estimates).items():
        detect_frame[col[fid]], detect_px[col[fid]] = k, px
    arrays: dict[str, np.ndarray] = {
        "t_s": np.array([e.frame_t_s - t0_s for e in estimates]),
        "pose": np.array([e.pose for e in estimates]),
        "feature_id": ids,
        "meas_px": meas,
        "pred_px": pred,
        "detect_frame": detect_frame,
        "detect_px": detect_px,
    }
    shapes = {e.nodes_m.shape for e in estimates if e.nodes_m is not None}
    if len(shapes) == 1:
        shape = shapes.pop()
        arrays["nodes_m"] = np.array(
            [e.nodes_m if e.nodes_m is not None else np.full(shape, np.nan) for e in estimates], np.float32
        )
    # Written beside and renamed into place: a full disk leaves no half-written (or 0-byte) file behind.
    partial = path.with_name(path.name + ".partial")
    try:
        with partial.open("wb") as out:
            np.savez_compressed(out, allow_pickle=False, **arrays)
        partial.replace(path)
    except OSError:
        partial.unlink(missing_ok=True)
        raise


def write_module_calibration(path: Path, entries: list[ModuleCalibrationEntry], note: str) -> None:
    """The modules' calibration as YAML, `note` (what measured it, when) as its first comment."""
    rows = [
        {
            "module": e.module,
            "reversed": e.reversed,
            "heading_offset_deg": round(e.heading_offset_deg, 2),
            "speed_scale": round(e.speed_scale, 4),
        }
        for e in entries
    ]
    path.write_text(f"# {note}\n" + yaml.safe_dump({"modules": rows}, sort_keys=False))


def read_module_calibration(path: Path, n_modules: int) -> list[ModuleCalibrationEntry]:
    """A module calibration file; anything unusable is an InputError naming the entry and the key."""
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as err:
        raise InputError(f"{path}: cannot read a module calibration ({err.strerror})") from None
    except yaml.YAMLError as err:
        raise InputError(f"{path}: not valid YAML: {yaml_problem(err)}") from None
    rows = data.get("modules") if isinstance(data, dict) else None
    if not isinstance(rows, list):
        raise InputError(f"{path}: a module calibration is a mapping with a list under 'modules'")
    entries = []
    for i, row in enumerate(rows):
        where = f"{path}: modules[{i}]"
        if not isinstance(row, dict) or set(row) != CALIBRATION_KEYS:
            raise InputError(f"{where}: needs exactly {', '.join(sorted(CALIBRATION_KEYS))}")
        try:
            e = ModuleCalibrationEntry(
                int(row["module"]),
                bool(row["reversed"]),
                float(row["heading_offset_deg"]),
                float(row["speed_scale"]),
            )
        except (TypeError, ValueError) as err:
            raise InputError(f"{where}: {err}") from None
        if not 0 <= e.module < n_modules:
            raise InputError(f"{where}.module: {e.module} out of range (the cell has {n_modules})")
        if not abs(e.heading_offset_deg) <= 180:
            raise InputError(f"{where}.heading_offset_deg: {e.heading_offset_deg} is not within ±180")
        if not SPEED_SCALE_RANGE[0] <= e.speed_scale <= SPEED_SCALE_RANGE[1]:
            raise InputError(f"{where}.speed_scale: {e.speed_scale} is not within {SPEED_SCALE_RANGE}")
        entries.append(e)
    return entries


def read_referenced_files(cfg: Config) -> list[Path]:
    """Read every file the configuration names as `clothd run` reads it (each camera's calibration, the
    modules' calibration), so that one missing or malformed is found before the daemon starts: an
    InputError naming its key and the file. The files read. A relative path is read from the working
    directory, as the daemon reads it."""
    named: list[tuple[str, Path, Callable[[Path], object]]] = []
    for k, camera in enumerate(cfg.all_cameras):
        if camera.source.calibration is not None:
            key = "camera.calibration" if cfg.cameras is None else f"cameras.{k}.calibration"
            named.append((key, camera.source.calibration, read_camera))
    if cfg.cell.module_calibration is not None:
        n_modules = ConveyorLayout.of_cell(cfg.cell).n_modules
        modules = cfg.cell.module_calibration
        named.append(("cell.module_calibration", modules, lambda p: read_module_calibration(p, n_modules)))
    for key, path, read in named:
        try:
            read(path)
        except InputError as err:
            raise InputError(f"{key}: {err}") from None
    return [path for _, path, _ in named]
