"""The cell's cameras as `hwsim serve` streams them: their rates and their latest frames."""

from __future__ import annotations

from dataclasses import dataclass

from hwsim.camera import Camera
from hwsim.camera_process import VideoFrame


@dataclass
class Stream:
    """One camera of the cell: how many world steps apart its frames are, its latest frame."""

    name: str
    camera: Camera
    skew_s: float  # its exposure after the world's instant
    every: int
    json_name: str  # its camera.json in the state directory
    frame: VideoFrame | None = None
    readers: int = 0  # clients streaming it now (under the cell's frame_cond)


def frame_intervals(
    world_fps: float, n_cameras: int, camera_fps: float, others_fps: float | None
) -> list[int]:
    """World steps between frames, per camera. The others' are whole multiples of the first's, so that
    each of their frames is taken with one of the first camera's (stereo needs simultaneous pairs)."""
    first = max(1, round(world_fps / camera_fps))
    other = first * max(1, round(world_fps / (others_fps or camera_fps) / first))
    return [first] + [other] * (n_cameras - 1)
