"""Resets free what they allocate: the compute process, re-initialising tracking on the live path
(Compute.tick with reset requests, frames from a FrameSource), does not grow. Each reset used to build a
new MassSpring with new Taichi fields (and a kernel compiled for them): about 2.2 MB a reset, so the 50
resets here would have grown it by some 110 MB. `clothd bench faults` measures the issue's 500."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from clothd.compute import Compute, ComputeSpec, TickRequest
from clothd.config import CellConfig, ControlConfig, TrackerConfig
from clothd.core.control import Setpoint
from clothd.core.conveyor import ConveyorLayout
from clothd.core.messages import ModuleCommands
from clothd.core.workspace import Workspace
from clothd.drivers.footage import open_footage
from clothd.drivers.ports import CameraFrame, FrameSourceHealth
from clothd.formats import read_camera
from clothd.taichi_runtime import start_taichi

RESETS = 60
ALLOWED_GROWTH_MB = 20.0


class RecordedFrames:
    """A FrameSource that hands out a recording's frames in turn, each one new."""

    def __init__(self, images: list[np.ndarray]) -> None:
        self.images = images
        self.index = -1

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def latest(self) -> CameraFrame:
        self.index += 1
        return CameraFrame(self.index, time.monotonic(), self.images[self.index % len(self.images)])

    def health(self) -> FrameSourceHealth:
        return FrameSourceHealth("streaming", True, None, 0)


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def test_resets_do_not_grow_the_compute(short_recording: Callable[[str], Path]) -> None:
    start_taichi("cpu")
    rec = short_recording("translate")
    images = [img for _, (_, img) in zip(range(4), open_footage(rec).frames(), strict=False)]
    cell = CellConfig()
    spec = ComputeSpec(
        tracker=TrackerConfig(model="mesh"),
        control=ControlConfig(),
        cell=cell,
        layout=ConveyorLayout.of_cell(cell),
        camera_model=read_camera(rec / "camera.json"),
        period_s=1 / 30,
        workspace=Workspace.of_cell(cell),
        taichi_arch="cpu",
        max_record_bytes=10**6,
        frame_source=lambda: RecordedFrames(images),
    )
    compute = Compute(spec, spec.frame_source())
    idle = Setpoint("idle", None)
    stopped = ModuleCommands.all_stop(spec.layout.n_modules)
    rss: dict[int, float] = {}
    for k in range(1, RESETS + 1):
        compute.tick(TickRequest(idle, stopped, reset=True, want_view=False))  # re-initialises
        reply = compute.tick(TickRequest(idle, stopped, reset=False, want_view=False))  # tracks
        assert reply.estimate is not None and reply.estimate.tracking and reply.estimate.nodes_m is not None
        if k in (10, RESETS):
            rss[k] = _rss_mb()
    growth = rss[RESETS] - rss[10]
    print(f"RSS after 10 resets {rss[10]:.1f} MB, after {RESETS} {rss[RESETS]:.1f} MB (+{growth:.1f} MB)")
    assert growth < ALLOWED_GROWTH_MB
