"""`clothd export REC --mcap FILE`: a recording as MCAP, with Foxglove's well-known schemas, to open in
Foxglove: the camera (/camera, CompressedImage), the frame with the estimate drawn on
(/camera/annotated, where the recording has a camera.json), the mesh coloured by height (/mesh,
SceneUpdate), the pose (/pose, PoseInFrame), the module commands (/commands), a per-frame summary
(/status), the last two as JSON with a JSON schema, and each further camera's views (/cameras/NAME).
Every message is stamped with its frame's time; a further camera's view with its own.

REC is a recording directory (`clothd run --record`, `hwsim record`); the estimates are its own
estimates.npz (a live recording writes one) or `--estimates` (a `clothd replay` output's).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import foxglove
import numpy as np
from tqdm import tqdm

from clothd.drivers.footage import CommandSchedule, open_footage
from clothd.errors import InputError
from clothd.formats import read_camera, read_layout
from clothd.outputs.foxglove_channels import CellChannels, encode_jpeg, residual_mean_px
from clothd.outputs.view import draw_tracking
from clothd.tools.offline import FurtherFrames, further_camera_dirs, further_frames


@dataclass(frozen=True)
class ExportCounts:
    frames: int
    messages: dict[str, int]


def export_mcap(recording: Path, out: Path, estimates_npz: Path | None = None) -> ExportCounts:
    footage = open_footage(recording)
    npz = estimates_npz or recording / "estimates.npz"
    est = np.load(npz) if npz.exists() else None
    layout = read_layout(footage.table_json) if footage.table_json else None
    schedule = (
        CommandSchedule(footage.commands_csv, layout.n_modules) if footage.commands_csv and layout else None
    )
    camera_model = read_camera(footage.camera_json) if footage.camera_json and est is not None else None
    ctx = foxglove.Context()  # this export's own channels, not the process-wide default
    further = further_frames(recording, further_camera_dirs(recording), footage, read_ahead=False)
    channels = CellChannels(ctx, annotated=camera_model is not None, further=[f.name for f in further])
    frames = 0
    out.parent.mkdir(parents=True, exist_ok=True)
    with foxglove.open_mcap(out, allow_overwrite=True, context=ctx):
        total = footage.frame_count
        for k, (t_s, image) in enumerate(tqdm(footage.frames(), total=total, desc="exporting", disable=None)):
            log_time = round(t_s * 1e9)
            jpeg = encode_jpeg(image)
            if jpeg is None:
                raise InputError(f"{recording}: frame {k} could not be encoded")
            channels.log_camera(jpeg, log_time)
            _log_views(channels, further, footage.frame_index(k), recording)
            if schedule is not None:
                c = schedule.at(t_s)
                channels.log_commands(c.speed_m_s, c.heading_rad, log_time)
            if est is not None and k < len(est["t_s"]):
                meas_px, pred_px = est["meas_px"][k], est["pred_px"][k]
                features, residual = residual_mean_px(meas_px, pred_px)
                nodes = est["nodes_m"][k] if "nodes_m" in est.files else None
                channels.log_estimate(est["pose"][k], nodes, features, residual, log_time)
                if camera_model is not None:
                    shown = nodes if nodes is not None and np.isfinite(nodes).all() else None
                    label = f"t {t_s:6.2f} s  features {features}"
                    drawn = draw_tracking(image, shown, meas_px, pred_px, camera_model, label)
                    annotated = encode_jpeg(drawn)
                    if annotated is None:
                        raise InputError(f"{recording}: frame {k}'s annotated view could not be encoded")
                    channels.log_annotated(annotated, log_time)
            frames += 1
    return ExportCounts(frames, dict(channels.counts))


def _log_views(channels: CellChannels, further: list[FurtherFrames], index: int, recording: Path) -> None:
    """Each further camera's view of first-camera frame `index`, at its own capture time (a view taken
    just before the recording's first frame at 0: an MCAP file holds no earlier time)."""
    for camera in further:
        view = camera.view_of(index)
        if view is None:
            continue
        jpeg = encode_jpeg(view.image)
        if jpeg is None:
            raise InputError(
                f"{recording}: camera {camera.name}'s view of frame {index} could not be encoded"
            )
        channels.log_further(camera.name, jpeg, max(round(view.t_s * 1e9), 0))
