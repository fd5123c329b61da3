"""A compute process's parts on recorded frames: a FrameSource that hands out a recording's frames in
turn, and a Compute built over it as `clothd run` builds one (in this process, Taichi started)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from clothd.config import CellConfig, ControlConfig, TrackerConfig
from clothd.core.conveyor import ConveyorLayout
from clothd.core.workspace import Workspace
from clothd.drivers.footage import open_footage
from clothd.drivers.ports import CameraFrame, FrameSourceHealth
from clothd.formats import read_camera
from clothd.loop.compute import Compute
from clothd.loop.compute_messages import ComputeSpec, TickReply, TickRequest
from clothd.taichi_runtime import start_taichi


class RecordedFrames:
    """A FrameSource that hands out a recording's frames in turn, each one new."""

    def __init__(self, images: list[np.ndarray]) -> None:
        self.images = images
        self.index = -1
        self.last: CameraFrame | None = None

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def latest(self) -> CameraFrame:
        self.index += 1
        self.last = CameraFrame(self.index, time.monotonic(), self.images[self.index % len(self.images)])
        return self.last

    def newer_than(self, index: int, timeout_s: float) -> CameraFrame:
        return self.latest()  # every frame is new

    def nearest(self, t_mono_s: float) -> CameraFrame:
        return self.last or self.latest()

    def health(self) -> FrameSourceHealth:
        return FrameSourceHealth("streaming", True, None, 0)


def compute_on(recording: Path, frames: int = 4, cell: CellConfig | None = None, **spec: Any) -> Compute:
    """A Compute on the first `frames` frames of `recording`, looped; `spec` replaces ComputeSpec fields."""
    start_taichi("cpu")
    images = [img for _, (_, img) in zip(range(frames), open_footage(recording).frames(), strict=False)]
    cell = cell or CellConfig()
    built = ComputeSpec(
        tracker=TrackerConfig(model="mesh"),
        control=ControlConfig(),
        cell=cell,
        layout=ConveyorLayout.of_cell(cell),
        camera_model=read_camera(recording / "camera.json"),
        period_s=1 / 30,
        workspace=Workspace.of_cell(cell),
        taichi_arch="cpu",
        max_record_bytes=10**6,
        frame_source=lambda: RecordedFrames(images),
        starved_s=60.0,  # a test drives the compute at its own pace: no pause of it is a silent daemon
    )
    built = dataclasses.replace(built, **spec)
    return Compute(built, built.frame_source())


def tick(compute: Compute, req: TickRequest) -> TickReply:
    """One tick as the compute process serves it: the reply, then the work left for after it and for
    between the ticks (a tracked frame's heights, from its pair)."""
    reply = compute.tick(req)
    compute.after_reply()
    compute.measure_heights(wait=True)
    return reply
