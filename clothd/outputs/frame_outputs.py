"""Where the compute's tracked frames go: a directory recording (Recorder) and the live Foxglove output
(its server, and its MCAP recordings when `recording.format` is mcap), started and stopped by the ticks'
requests."""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clothd.config import FoxgloveConfig, RecordingFormat
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout
from clothd.core.messages import Estimate, ModuleCommands, PairedView
from clothd.outputs.foxglove_live import LiveFoxglove
from clothd.outputs.recorder import RECENT_FRAMES, FrameSink, Recorder, RecordingStatus

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecordingSpec:
    """What a recording is made of: the cameras (the first's model, each further one's name and model),
    the module layout, its size bound and its format."""

    camera: CameraModel
    further: Sequence[tuple[str, CameraModel]]
    layout: ConveyorLayout
    max_bytes: int
    format: RecordingFormat


class FrameOutputs:
    """The compute's outputs. A frame's further views are paired after the frame was tracked, sometimes
    before the tick that records it (a frame tracked ahead), sometimes after (between ticks): they wait
    here until the frame is recorded, and `after_reply` writes them, so no view is encoded while a
    request may be waiting."""

    def __init__(self, spec: RecordingSpec, foxglove: FoxgloveConfig | None) -> None:
        self.spec = spec
        self.recorder: Recorder | None = None  # a directory recording
        # Views by their first-camera frame's capture time, not yet written: kept for the recent frames
        # only, and across a recording's start (its first frame may have been paired before it).
        self._views: OrderedDict[float, Sequence[PairedView | None]] = OrderedDict()
        serves = foxglove is not None and foxglove.enabled
        needs_live = serves or spec.format == RecordingFormat.MCAP
        self.foxglove = LiveFoxglove(foxglove) if needs_live else None

    def start(self) -> None:
        if self.foxglove is not None:
            self.foxglove.start()

    def close(self, reason: str) -> None:
        if self.recorder is not None:
            self.write_views()
            self.recorder.stop(reason)
        if self.foxglove is not None:
            self.foxglove.close(reason)

    def requests(self, record_start: Path | None, record_stop: bool) -> None:
        """A tick's recording requests: stop the one running, start one in record_start."""
        if record_stop and self.recorder is not None:
            self.write_views()  # the last frame's, paired since the last reply
            self.recorder.stop()
        if record_stop and self.foxglove is not None:
            self.foxglove.stop_recording()
        if record_start is None:
            return
        if self.foxglove is not None and self.spec.format == RecordingFormat.MCAP:
            self.foxglove.start_recording(record_start, self.spec.max_bytes)
            return
        if self.recorder is not None:
            self.recorder.stop("a new recording started")
        s = self.spec
        try:
            self.recorder = Recorder(record_start, s.camera, s.layout, s.max_bytes, s.further)
        except OSError as err:
            log.warning("cannot start recording in %s: %s", record_start, err)

    def status(self) -> RecordingStatus | None:
        if self.recorder is not None:
            return self.recorder.status()
        return None if self.foxglove is None else self.foxglove.recording_status()

    @property
    def sinks(self) -> list[FrameSink]:
        return [s for s in (self.recorder, self.foxglove) if s is not None]

    def add(self, image: np.ndarray, t_mono_s: float, commands: ModuleCommands, est: Estimate | None) -> None:
        """A tracked frame, the commands in force while it was captured, and its estimate (None: its pieces
        were tracked apart, mode flow)."""
        for sink in self.sinks:
            sink.add(image, t_mono_s, commands, est)

    def add_views(self, t0_mono_s: float, views: Sequence[PairedView | None]) -> None:
        """The further cameras' views the frame captured at t0_mono_s was tracked with: the directory
        recording keeps them (Foxglove shows the first camera only), written by `write_views`."""
        if not self.spec.further:
            return
        self._views[t0_mono_s] = views
        while len(self._views) > RECENT_FRAMES:
            self._views.popitem(last=False)

    def write_views(self) -> bool:
        """Write the waiting views whose frames are recorded (after a tick's reply); whether any were."""
        recorder = self.recorder
        if recorder is None:
            return False
        written = [(t0, index) for t0 in self._views if (index := recorder.index_of(t0)) is not None]
        for t0, index in written:
            recorder.add_views(index, self._views.pop(t0))
        return bool(written)
