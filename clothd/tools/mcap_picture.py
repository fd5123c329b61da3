"""`clothd picture FILE.mcap --out PNG`: one picture drawn from an MCAP file's own messages, as Foxglove
would lay them out: the camera frame (annotated, where the file has that channel), the tracked mesh
from above coloured by height with the pose's track, and the residual and module speeds over time with
a cursor at the chosen frame.

It reads what `clothd export` and a live MCAP recording write (outputs/foxglove_channels.py), decoding the
protobuf messages from the schemas the file carries, so it also shows that a file is complete without
Foxglove at hand.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.decoder import DecoderFactory
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory

from clothd.errors import InputError
from clothd.outputs.foxglove_channels import HEIGHT_FULL_SCALE_M


class _JsonDecoderFactory(DecoderFactory):
    """The JSON channels (/commands, /status); mcap decodes only what a factory offers."""

    def decoder_for(self, message_encoding: str, schema: Schema | None) -> Callable[[bytes], Any] | None:
        return json.loads if message_encoding == "json" else None


@dataclass
class MeshFrame:
    t_ns: int
    ends_m: np.ndarray  # (2k, 3) the line list's ends, pairs in order, table frame
    colors: np.ndarray  # (2k, 4) RGBA per end, as written


@dataclass
class CellLog:
    """An MCAP file's cell channels, decoded, each in log-time order."""

    camera: list[tuple[int, bytes]] = field(default_factory=list)  # (log time ns, JPEG)
    annotated: list[tuple[int, bytes]] = field(default_factory=list)  # (log time ns, JPEG)
    mesh: list[MeshFrame] = field(default_factory=list)
    pose: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (log time ns, [x_m, y_m, theta_rad])
    commands: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    status: list[tuple[int, dict[str, Any]]] = field(default_factory=list)


def _theta_rad(q: Any) -> float:
    """Yaw of a quaternion turned about z only, as /pose writes it."""
    return 2.0 * math.atan2(q.z, q.w)


def read_cell_mcap(path: Path) -> CellLog:
    if not path.is_file():
        raise InputError(f"{path}: no such MCAP file")
    log = CellLog()
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[ProtobufDecoderFactory(), _JsonDecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            t = message.log_time
            if channel.topic == "/camera":
                log.camera.append((t, bytes(decoded.data)))
            elif channel.topic == "/camera/annotated":
                log.annotated.append((t, bytes(decoded.data)))
            elif channel.topic == "/mesh":
                lines = decoded.entities[0].lines[0]
                ends = np.array([(p.x, p.y, p.z) for p in lines.points], dtype=np.float64)
                colors = np.array([(c.r, c.g, c.b, c.a) for c in lines.colors], dtype=np.float64)
                log.mesh.append(MeshFrame(t, ends, colors))
            elif channel.topic == "/pose":
                p = decoded.pose
                log.pose.append((t, np.array([p.position.x, p.position.y, _theta_rad(p.orientation)])))
            elif channel.topic == "/commands":
                log.commands.append((t, decoded))
            elif channel.topic == "/status":
                log.status.append((t, decoded))
    if not log.camera:
        raise InputError(f"{path}: no /camera messages; is it a clothd export or MCAP recording?")
    return log


def highest_mesh_t_ns(log: CellLog) -> int:
    """The log time of the frame whose mesh stands highest (a fold, if there is one), else the last
    camera frame's."""
    if not log.mesh:
        return log.camera[-1][0]
    return max(log.mesh, key=lambda m: float(m.ends_m[:, 2].max())).t_ns


def after_first_frame_ns(log: CellLog, at_s: float) -> int:
    """The log time at_s seconds after the first camera frame; refused outside the frames' span, where
    the nearest frame would be drawn under a time it does not have."""
    first_ns, last_ns = log.camera[0][0], log.camera[-1][0]
    span_s = (last_ns - first_ns) / 1e9
    if not 0.0 <= at_s <= span_s:
        raise InputError(f"--at-s {at_s:g}: the file's camera frames span 0 to {span_s:.2f} s")
    return first_ns + round(at_s * 1e9)


def _nearest(times_ns: list[int], t_ns: int) -> int:
    return int(np.argmin(np.abs(np.asarray(times_ns, dtype=np.int64) - t_ns)))


def draw_picture(log: CellLog, out: Path, at_ns: int) -> int:
    """The picture at the camera frame nearest at_ns, written to `out`; that frame's log time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    t0 = log.camera[0][0]
    fig = plt.figure(figsize=(12, 7.5), dpi=100)
    grid = fig.add_gridspec(2, 2, height_ratios=[2.2, 1.0])

    cam = fig.add_subplot(grid[0, 0])
    topic, frames = ("/camera/annotated", log.annotated) if log.annotated else ("/camera", log.camera)
    t_cam, jpeg = frames[_nearest([t for t, _ in frames], at_ns)]
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(f"the {topic} frame at {(t_cam - t0) / 1e9:.2f} s is not a readable JPEG")
    cam.imshow(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
    cam.set_title(f"{topic} at {(t_cam - t0) / 1e9:.2f} s")
    cam.axis("off")

    top = fig.add_subplot(grid[0, 1])
    if log.mesh:
        m = log.mesh[_nearest([m.t_ns for m in log.mesh], at_ns)]
        segments = m.ends_m[:, :2].reshape(-1, 2, 2) * 1e3
        # Each segment takes its higher end's colour, so a ridge shows at its full height.
        higher = np.where(m.ends_m[0::2, 2] >= m.ends_m[1::2, 2], 0, 1)
        colors = m.colors.reshape(-1, 2, 4)[np.arange(len(segments)), higher]
        top.add_collection(LineCollection(list(segments), colors=colors, linewidths=1.2))
        peak_mm = float(m.ends_m[:, 2].max()) * 1e3
        top.set_title(
            f"/mesh from above, peak {peak_mm:.1f} mm (blue flat, red >= {HEIGHT_FULL_SCALE_M * 1e3:.0f} mm)"
        )
    if log.pose:
        xy_mm = np.array([p[:2] for _, p in log.pose]) * 1e3
        top.plot(xy_mm[:, 0], xy_mm[:, 1], color="0.4", lw=1, label="/pose track")
        _, pose = log.pose[_nearest([t for t, _ in log.pose], at_ns)]
        arrow_mm = 40.0
        top.annotate(
            "",
            xy=(pose[0] * 1e3 + arrow_mm * math.cos(pose[2]), pose[1] * 1e3 + arrow_mm * math.sin(pose[2])),
            xytext=(pose[0] * 1e3, pose[1] * 1e3),
            arrowprops={"arrowstyle": "->", "color": "k", "lw": 1.5},
        )
        top.legend(loc="upper right", fontsize=8)
    top.set_xlabel("x [mm], table frame")
    top.set_ylabel("y [mm]")
    top.set_aspect("equal")
    top.autoscale_view()
    top.grid(alpha=0.3)

    timeline = fig.add_subplot(grid[1, :])
    if log.status:
        ts = np.array([(t - t0) / 1e9 for t, _ in log.status])
        residual = np.array([s["residual_mean_px"] for _, s in log.status], dtype=np.float64)  # None: NaN
        timeline.plot(ts, residual, color="tab:red", lw=1, label="/status residual_mean_px")
    timeline.set_xlabel("time [s]")
    timeline.set_ylabel("residual [px]", color="tab:red")
    if log.commands:
        speeds = timeline.twinx()
        tc = np.array([(t - t0) / 1e9 for t, _ in log.commands])
        mean_mm_s = np.array([np.mean(np.abs(c["speed_m_s"])) * 1e3 for _, c in log.commands])
        speeds.plot(tc, mean_mm_s, color="tab:blue", lw=1)
        speeds.set_ylabel("/commands mean |speed| [mm/s]", color="tab:blue")
    timeline.axvline((t_cam - t0) / 1e9, color="k", lw=1, ls="--")
    timeline.grid(alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return t_cam
