"""What the daemon and the compute process say to each other (clothd/loop/compute.py): one TickRequest
and one TickReply per tick, InForce between them, and the ComputeSpec the process is built from."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from clothd.config import (
    CellConfig,
    ControlConfig,
    FlowConfig,
    FoxgloveConfig,
    RecordingFormat,
    TrackerConfig,
)
from clothd.core.camera_model import CameraModel
from clothd.core.control import Setpoint
from clothd.core.conveyor import ConveyorLayout
from clothd.core.flatness import Flatness
from clothd.core.messages import Estimate, ModuleCommands
from clothd.core.modes import LoopState
from clothd.core.pieces import PieceReport
from clothd.core.workspace import Workspace
from clothd.drivers.ports import FrameSource, FrameSourceHealth
from clothd.loop.pairing import CameraReport, FurtherCamera
from clothd.outputs.recorder import RecordingStatus


@dataclass(frozen=True)
class TickRequest:
    setpoint: Setpoint
    commands_in_force: ModuleCommands  # what the modules were told since the last request: the model's input
    reset: bool
    want_view: bool  # draw the annotated view this tick
    record_start: Path | None = None  # begin recording into this new directory (or .mcap file)
    record_stop: bool = False
    # Wait until this time (host monotonic) for a frame not yet used: the tick started as one was due.
    frame_wait_until_mono_s: float | None = None
    sent_mono_s: float = field(default_factory=time.monotonic)  # when the daemon made it


@dataclass(frozen=True)
class InForce:
    """What the daemon has just told the modules (sent after each tick's send, no reply): the input a
    frame that arrives before the next request is tracked with."""

    commands: ModuleCommands
    sent_mono_s: float = field(default_factory=time.monotonic)  # when the daemon made it


@dataclass(frozen=True, kw_only=True)
class TickReply:
    state: LoopState
    estimate: Estimate | None
    commands: ModuleCommands
    new_frame: bool
    frame_t_mono_s: float | None  # capture time of the frame this tick used
    camera: FrameSourceHealth
    cameras: tuple[CameraReport, ...] = ()  # the further cameras': health and pairing
    timing_s: dict[str, float] = field(default_factory=dict)
    view_jpeg: bytes | None = None
    recording: RecordingStatus | None = None
    halt_reason: str | None = None  # the commands stopped the modules for a fault of this tick
    flatness: Flatness | None = None  # of this tick's estimate, when it has a mesh and tracks
    compute_mono_s: tuple[float, float] | None = None  # host monotonic: the compute began, and replied
    starved_ms: float | None = None  # the daemon was silent this long: the tracker started afresh
    pieces: tuple[PieceReport, ...] | None = None  # in flow: every piece on the table, and those gone


@dataclass(frozen=True)
class ComputeSpec:
    """What the compute process is built from; it crosses into the process by pickling, so the frame
    source travels as a factory and is opened there."""

    tracker: TrackerConfig
    control: ControlConfig
    cell: CellConfig
    layout: ConveyorLayout
    camera_model: CameraModel
    period_s: float
    workspace: Workspace
    taichi_arch: str
    max_record_bytes: int
    frame_source: Callable[[], FrameSource]
    recording_format: RecordingFormat = RecordingFormat.DIRECTORY
    foxglove: FoxgloveConfig | None = None  # the live server's section (None: off)
    track_ahead: bool = True  # loop.track_ahead: track a frame as it arrives, not when its tick asks
    opencv_threads: int = 2  # loop.compute_threads
    starved_s: float = 0.25  # loop.starved_ms
    other_cameras: tuple[FurtherCamera, ...] = ()  # the cameras after the first (cameras:)
    flow: FlowConfig = field(default_factory=FlowConfig)  # the production flow (mode flow)
