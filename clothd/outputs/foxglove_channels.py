"""The Foxglove channels clothd writes, defined once: `clothd export` (tools/export.py), a live MCAP
recording (`recording.format: mcap`) and the live Foxglove WebSocket server (foxglove_live.py) all log
these topics, with these schemas, through `CellChannels`:

/camera    foxglove.CompressedImage   the camera frame as JPEG, frame id "camera"
/camera/annotated  foxglove.CompressedImage  the frame with the estimate drawn on (clothd.outputs.view), JPEG;
           written by `clothd export` where the recording has a camera.json and estimates
/mesh      foxglove.SceneUpdate       the tracked mesh in the "table" frame, a line list coloured by height
/pose      foxglove.PoseInFrame       the cloth's pose in the "table" frame, while tracked
/commands  clothd.ModuleCommands      JSON: t_s, speed_m_s, heading_rad (the commands in force)
/status    clothd.FrameStatus         JSON: t_s, tracking, features, residual_mean_px

Every message of a frame carries the same log time, and the JSON messages' t_s is that time in seconds.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence

import cv2
import foxglove
import numpy as np
from foxglove import messages as fm
from foxglove.channels import CompressedImageChannel, PoseInFrameChannel, SceneUpdateChannel

TABLE_FRAME = "table"
CAMERA_FRAME = "camera"
JPEG_QUALITY = 85
HEIGHT_FULL_SCALE_M = 0.02  # mesh colour: blue flat, red at 20 mm and above
TOPICS = ("/camera", "/camera/annotated", "/mesh", "/pose", "/commands", "/status")
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


def encode_jpeg(image: np.ndarray) -> bytes | None:
    """image (h, w, 3) BGR uint8 as the /camera channel's JPEG; None if OpenCV cannot encode it."""
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    return jpeg.tobytes() if ok else None


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


class CellChannels:
    """The channels on one foxglove.Context; whichever sinks that context has (an MCAP writer, a
    WebSocket server) get every message. /camera/annotated exists only when `annotated` (an export that
    can draw it), so that no sink is offered a channel that stays empty. `counts` holds the messages
    logged per topic."""

    def __init__(
        self, context: foxglove.Context, annotated: bool = False, further: Sequence[str] = ()
    ) -> None:
        """further: the further cameras' names, each a channel /cameras/NAME (an export's)."""
        self.camera = CompressedImageChannel("/camera", context=context)
        self.further = {name: CompressedImageChannel(f"/cameras/{name}", context=context) for name in further}
        self.annotated = CompressedImageChannel("/camera/annotated", context=context) if annotated else None
        self.mesh = SceneUpdateChannel("/mesh", context=context)
        self.pose = PoseInFrameChannel("/pose", context=context)
        self.commands = foxglove.Channel(
            "/commands",
            schema=_json_schema("clothd.ModuleCommands", COMMANDS_SCHEMA),
            message_encoding="json",
            context=context,
        )
        self.status = foxglove.Channel(
            "/status",
            schema=_json_schema("clothd.FrameStatus", STATUS_SCHEMA),
            message_encoding="json",
            context=context,
        )
        self.counts = {topic: 0 for topic in TOPICS if annotated or topic != "/camera/annotated"}
        self.counts.update({f"/cameras/{name}": 0 for name in further})

    def has_sinks(self) -> bool:
        """Anything listens: an MCAP writer, or a WebSocket client subscribed to any topic."""
        channels = (self.camera, self.annotated, self.mesh, self.pose, self.commands, self.status)
        return any(ch is not None and ch.has_sinks() for ch in channels)

    def log_camera(self, jpeg: bytes, log_time: int) -> None:
        msg = fm.CompressedImage(timestamp=_stamp(log_time), frame_id=CAMERA_FRAME, data=jpeg, format="jpeg")
        self.camera.log(msg, log_time=log_time)
        self.counts["/camera"] += 1

    def log_further(self, name: str, jpeg: bytes, log_time: int) -> None:
        """A further camera's view, frame id NAME."""
        msg = fm.CompressedImage(timestamp=_stamp(log_time), frame_id=name, data=jpeg, format="jpeg")
        self.further[name].log(msg, log_time=log_time)
        self.counts[f"/cameras/{name}"] += 1

    def log_annotated(self, jpeg: bytes, log_time: int) -> None:
        if self.annotated is None:
            raise RuntimeError("these channels were made without /camera/annotated")
        msg = fm.CompressedImage(timestamp=_stamp(log_time), frame_id=CAMERA_FRAME, data=jpeg, format="jpeg")
        self.annotated.log(msg, log_time=log_time)
        self.counts["/camera/annotated"] += 1

    def log_commands(self, speed_m_s: np.ndarray, heading_rad: np.ndarray, log_time: int) -> None:
        msg = {"t_s": log_time / 1e9, "speed_m_s": speed_m_s.tolist(), "heading_rad": heading_rad.tolist()}
        self.commands.log(msg, log_time=log_time)
        self.counts["/commands"] += 1

    def log_estimate(
        self,
        pose: np.ndarray,
        nodes_m: np.ndarray | None,
        features: int,
        residual_mean_px: float | None,
        log_time: int,
    ) -> None:
        """One frame's estimate: /status always; /pose while tracked (a finite pose), /mesh while the mesh
        is finite too."""
        tracking = bool(np.isfinite(pose).all())
        status = {
            "t_s": log_time / 1e9,
            "tracking": tracking,
            "features": features,
            "residual_mean_px": residual_mean_px,
        }
        self.status.log(status, log_time=log_time)
        self.counts["/status"] += 1
        if not tracking:
            return
        stamp = _stamp(log_time)
        self.pose.log(
            fm.PoseInFrame(timestamp=stamp, frame_id=TABLE_FRAME, pose=_pose(pose)), log_time=log_time
        )
        self.counts["/pose"] += 1
        if nodes_m is not None and np.isfinite(nodes_m).all():
            entity = fm.SceneEntity(
                timestamp=stamp, frame_id=TABLE_FRAME, id="cloth", lines=[_mesh_lines(nodes_m)]
            )
            self.mesh.log(fm.SceneUpdate(entities=[entity]), log_time=log_time)
            self.counts["/mesh"] += 1


def residual_mean_px(meas_px: np.ndarray, pred_px: np.ndarray) -> tuple[int, float | None]:
    """The features measured this frame (meas_px (n, 2), NaN where not) and their mean distance from
    where the estimate placed them (pred_px (n, 2)); None when none was measured."""
    alive = ~np.isnan(meas_px[:, 0])
    if not alive.any():
        return 0, None
    return int(alive.sum()), float(np.linalg.norm(meas_px[alive] - pred_px[alive], axis=1).mean())
