"""`clothd export REC --mcap FILE`: a recording as MCAP, with Foxglove's well-known schemas, to open in
Foxglove: the camera (/camera, CompressedImage), the mesh coloured by height (/mesh, SceneUpdate), the
pose (/pose, PoseInFrame), the module commands (/commands) and a per-frame summary (/status), the last
two as JSON with a JSON schema. Every message is stamped with its frame's time.

REC is a recording directory (`clothd run --record`, `hwsim record`); the estimates are its own
estimates.npz (a live recording writes one) or `--estimates` (a `clothd replay` output's).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import foxglove
import numpy as np
from foxglove import messages as fm
from foxglove.channels import CompressedImageChannel, PoseInFrameChannel, SceneUpdateChannel
from tqdm import tqdm

from clothd.drivers.footage import CommandSchedule, open_footage
from clothd.errors import InputError
from clothd.formats import read_layout

TABLE_FRAME = "table"
JPEG_QUALITY = 85
HEIGHT_FULL_SCALE_M = 0.02  # mesh colour: blue flat, red at 20 mm and above
COMMANDS_SCHEMA = {
    "type": "object",
    "properties": {
        "t_s": {"type": "number"},
        "speed_m_s": {"type": "array", "items": {"type": "number"}},
        "heading_rad": {"type": "array", "items": {"type": "number"}},
    },
}
STATUS_SCHEMA = {
    "type": "object",
    "properties": {
        "t_s": {"type": "number"},
        "tracking": {"type": "boolean"},
        "features": {"type": "integer"},
        "residual_mean_px": {"type": ["number", "null"]},
    },
}


@dataclass(frozen=True)
class ExportCounts:
    frames: int
    messages: dict[str, int]


def _json_schema(name: str, schema: Mapping[str, object]) -> foxglove.Schema:
    return foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode())


def _stamp(log_time_ns: int) -> fm.Timestamp:
    sec, nsec = divmod(log_time_ns, 1_000_000_000)
    return fm.Timestamp(sec, nsec)


def _mesh_lines(nodes_m: np.ndarray) -> fm.LinePrimitive:
    """The mesh's edges as a line list (rows and columns), each end coloured by its height."""
    ny, nx = nodes_m.shape[:2]
    idx = np.arange(nx * ny).reshape(ny, nx)
    pairs = np.concatenate(
        [
            np.stack([idx[:, :-1], idx[:, 1:]], -1).reshape(-1, 2),
            np.stack([idx[:-1], idx[1:]], -1).reshape(-1, 2),
        ]
    )
    flat = nodes_m.reshape(-1, 3)
    ends = flat[pairs.ravel()]
    heat = np.clip(ends[:, 2] / HEIGHT_FULL_SCALE_M, 0.0, 1.0)
    return fm.LinePrimitive(
        type=fm.LinePrimitiveLineType.LineList,
        thickness=0.002,
        points=[fm.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in ends],
        colors=[fm.Color(r=float(h), g=0.3, b=float(1.0 - h), a=1.0) for h in heat],
    )


def _pose(pose: np.ndarray) -> fm.Pose:
    half = float(pose[2]) / 2.0
    return fm.Pose(
        position=fm.Vector3(x=float(pose[0]), y=float(pose[1]), z=0.0),
        orientation=fm.Quaternion(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half)),
    )


def export_mcap(recording: Path, out: Path, estimates_npz: Path | None = None) -> ExportCounts:
    footage = open_footage(recording)
    npz = estimates_npz or recording / "estimates.npz"
    est = np.load(npz) if npz.exists() else None
    layout = read_layout(footage.table_json) if footage.table_json else None
    schedule = (
        CommandSchedule(footage.commands_csv, layout.n_modules) if footage.commands_csv and layout else None
    )
    ctx = foxglove.Context()  # this export's own channels, not the process-wide default
    counts = {topic: 0 for topic in ("/camera", "/mesh", "/pose", "/commands", "/status")}
    camera = CompressedImageChannel("/camera", context=ctx)
    mesh = SceneUpdateChannel("/mesh", context=ctx)
    pose = PoseInFrameChannel("/pose", context=ctx)
    commands = foxglove.Channel(
        "/commands",
        schema=_json_schema("clothd.ModuleCommands", COMMANDS_SCHEMA),
        message_encoding="json",
        context=ctx,
    )
    status = foxglove.Channel(
        "/status",
        schema=_json_schema("clothd.FrameStatus", STATUS_SCHEMA),
        message_encoding="json",
        context=ctx,
    )
    frames = 0
    with foxglove.open_mcap(out, allow_overwrite=True, context=ctx):
        total = footage.frame_count
        for k, (t_s, image) in enumerate(tqdm(footage.frames(), total=total, desc="exporting", disable=None)):
            log_time = round(t_s * 1e9)
            stamp = _stamp(log_time)
            ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise InputError(f"{recording}: frame {k} could not be encoded")
            camera.log(
                fm.CompressedImage(timestamp=stamp, frame_id="camera", data=jpeg.tobytes(), format="jpeg"),
                log_time=log_time,
            )
            counts["/camera"] += 1
            if schedule is not None:
                c = schedule.at(t_s)
                commands.log(
                    {"t_s": t_s, "speed_m_s": c.speed_m_s.tolist(), "heading_rad": c.heading_rad.tolist()},
                    log_time=log_time,
                )
                counts["/commands"] += 1
            if est is not None and k < len(est["t_s"]):
                counts = _log_estimate(est, k, stamp, log_time, mesh, pose, status, counts)
            frames += 1
    return ExportCounts(frames, counts)


def _log_estimate(
    est: np.lib.npyio.NpzFile,
    k: int,
    stamp: fm.Timestamp,
    log_time: int,
    mesh: SceneUpdateChannel,
    pose: PoseInFrameChannel,
    status: foxglove.Channel,
    counts: dict[str, int],
) -> dict[str, int]:
    p = est["pose"][k]
    tracking = bool(np.isfinite(p).all())
    meas, pred = est["meas_px"][k], est["pred_px"][k]
    alive = ~np.isnan(meas[:, 0])
    residual = float(np.linalg.norm(meas[alive] - pred[alive], axis=1).mean()) if alive.any() else None
    t_s = float(est["t_s"][k])
    status.log(
        {"t_s": t_s, "tracking": tracking, "features": int(alive.sum()), "residual_mean_px": residual},
        log_time=log_time,
    )
    counts["/status"] += 1
    if not tracking:
        return counts
    pose.log(fm.PoseInFrame(timestamp=stamp, frame_id=TABLE_FRAME, pose=_pose(p)), log_time=log_time)
    counts["/pose"] += 1
    if "nodes_m" in est.files and np.isfinite(est["nodes_m"][k]).all():
        entity = fm.SceneEntity(
            timestamp=stamp, frame_id=TABLE_FRAME, id="cloth", lines=[_mesh_lines(est["nodes_m"][k])]
        )
        mesh.log(fm.SceneUpdate(entities=[entity]), log_time=log_time)
        counts["/mesh"] += 1
    return counts
