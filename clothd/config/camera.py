"""The cameras' sections of the configuration: `camera:` (the settings every camera shares, and the one
camera's source and calibration when there is one) and `cameras:` (a list, one entry per camera, when
there are several). `cameras_of` resolves the two into one list, first camera first.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pydantic import Field

from clothd.config.strict import Strict

MAX_CAMERAS = 4
# A further camera's stream (hwsim's /video/NAME.mjpg, a recording's cameras/NAME/) is named by this.
CAMERA_NAME_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"


def default_camera_name(index: int) -> str:
    """cam0, cam1, ...: hwsim's names for a cell's cameras."""
    return f"cam{index}"


class CameraSourceConfig(Strict):
    """Where frames come from: a device index ("0"), a device path, a video file, a stream URL or a
    directory of images."""

    source: str = Field("0", min_length=1, max_length=1024)
    calibration: Path | None = Field(None, description="camera.json (K, dist, T_cam_world); else ideal")
    reconnect_initial_s: float = Field(0.5, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)
    stale_after_s: float = Field(1.0, gt=0, le=60, description="no new frame for this long: camera lost")


class CameraConfig(Strict):
    """One camera of `cameras:`; the reconnect and stale settings are camera:'s, shared."""

    name: str | None = Field(
        None, pattern=CAMERA_NAME_PATTERN, description="shown in status and metrics; default cam0, cam1, ..."
    )
    source: str = Field(min_length=1, max_length=1024, description="as camera.source")
    calibration: Path | None = Field(
        None, description="camera.json (K, dist, T_cam_world); a further camera needs one"
    )


@dataclass(frozen=True)
class NamedCamera:
    """A camera resolved from the configuration: its name and the whole source section it opens with."""

    name: str
    source: CameraSourceConfig


def check_cameras(camera: CameraSourceConfig, cameras: list[CameraConfig] | None) -> None:
    """Raise ValueError naming the keys when `cameras` and `camera` say different things, a further
    camera has no calibration, or two cameras share a name."""
    if cameras is None:
        return
    both = sorted({"source", "calibration"} & camera.model_fields_set)
    if both:
        keys = " and ".join(f"camera.{k}" for k in both)
        raise ValueError(
            f"{keys} and cameras are both set: with a cameras list, each camera's source and calibration "
            "go in its entry (cameras.N.source, cameras.N.calibration), and camera keeps only the settings "
            f"they share (reconnect_initial_s, reconnect_max_s, stale_after_s); remove {keys}"
        )
    for i, entry in enumerate(cameras[1:], start=1):
        if entry.calibration is None:
            raise ValueError(
                f"cameras.{i}.calibration: a further camera needs its camera.json: its pose in the table "
                "frame is what relates its view to the first camera's"
            )
    names = [entry.name or default_camera_name(i) for i, entry in enumerate(cameras)]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise ValueError(f"cameras.{i}.name: {name!r} is taken by an earlier camera")
    if len(cameras) > 1 and cameras[0].calibration is None:
        raise ValueError(
            "cameras.0.calibration: with further cameras the first needs its camera.json too (an ideal "
            "camera assumed for it would not stand where the further cameras' poses were measured from)"
        )
    paths = [entry.calibration for entry in cameras]
    for i, path in enumerate(paths):
        if path is not None and path in paths[:i]:
            raise ValueError(
                f"cameras.{i}.calibration: {path} is cameras.{paths.index(path)}'s too: each camera has its "
                "own (clothd calibrate writes camera.json for the first and NAME.json for each further one)"
            )


def cameras_of(camera: CameraSourceConfig, cameras: list[CameraConfig] | None) -> tuple[NamedCamera, ...]:
    """Every camera, first first: `cameras`' entries with camera's shared settings, or camera alone."""
    if cameras is None:
        return (NamedCamera(default_camera_name(0), camera),)
    return tuple(
        NamedCamera(
            entry.name or default_camera_name(i),
            camera.model_copy(update={"source": entry.source, "calibration": entry.calibration}),
        )
        for i, entry in enumerate(cameras)
    )
