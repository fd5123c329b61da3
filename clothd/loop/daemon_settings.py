"""The daemon's settings, from the configuration (clothd/run.py builds them)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from clothd.config import CellConfig, RecordingFormat
from clothd.core.conveyor import ConveyorLayout
from clothd.core.module_calibration import ModuleCalibration
from clothd.core.workspace import Workspace


@dataclass(frozen=True)
class DaemonSettings:
    period_s: float  # the fixed tick
    max_stale_ticks: int  # ticks in a row without the compute's answer before the modules stop
    n_modules: int
    workspace: Workspace
    view_period_s: float  # the annotated view's frame interval
    recording_dir: Path  # where recordings go by default
    camera_source: str  # as shown in the status
    link_port: str
    estimates_shape: bool  # the tracker's model follows the cloth's shape: flatten is possible
    recording_format: RecordingFormat = RecordingFormat.DIRECTORY
    frame_lock: bool = False  # loop.frame_lock: the tick's phase follows the camera (loop/frame_phase.py)
    frame_lead_s: float = 0.001
    frame_wait_s: float = 0.012
    phase_step_s: float = 0.001
    layout: ConveyorLayout = field(default_factory=lambda: ConveyorLayout.of_cell(CellConfig()))  # for drives
    max_speed_m_s: float = 0.2  # cell.max_speed_m_s: the most a drive script may ask of a module
    module_calibration: ModuleCalibration | None = None  # cell.module_calibration: corrected on the wire
    cameras: tuple[tuple[str, str], ...] = ()  # every camera's name and source as shown, first first
    flow_ready: bool = False  # flow.warm_at_start: the compute built the pieces' trackers at start
