"""Pairing the further cameras' frames with the first camera's, by arrival time: no hardware trigger.

Each source keeps its last few frames (drivers/camera.py), stamped with the host's monotonic clock as
they arrived. For a first-camera frame at t0, each further camera's frame nearest t0 is taken; when it is
older than t0 by more than half that camera's frame period, its next frame is the nearer one, and it is
`due` while it can still arrive within `max_skew_s` of t0. `views` waits for it (`newer_than`), never
past t0 + max_skew_s, or with wait=False takes what is there: the compute waits only when tracking
begins, and otherwise tracks the first camera's frame at once and pairs it once nothing is due
(clothd/loop/compute.py). Whatever is nearest is handed to the tracker, which refuses a pair further
apart than tracker.stereo.max_skew_ms itself; a camera with no fresh frame gives None (one view).

The skew (t_k - t0) of every pair is kept over the last `WINDOW` first-camera frames: its median and its
95th percentile of magnitude, and the share of frames paired within max_skew_s, for the status.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from clothd.core.camera_model import CameraModel
from clothd.core.messages import PairedView
from clothd.drivers.ports import CameraFrame, FrameSource, FrameSourceHealth

WINDOW = 90  # first-camera frames the skew and the paired share are taken over (6 s at 15 frames/s)
PERIODS_KEPT = 16  # frame-period estimates each camera's period is the median of


@dataclass(frozen=True)
class PairingStats:
    """A further camera's pairing over the recent first-camera frames; None before any."""

    skew_ms: float | None  # median of t_k - t0
    skew_p95_ms: float | None  # 95th percentile of |t_k - t0|
    paired_pct: float | None  # share of first-camera frames with a frame of this one within max_skew


class _Camera:
    """One further camera: its source, the period its frames arrive at, its recent skews."""

    def __init__(self, source: FrameSource) -> None:
        self.source = source
        self.seen: CameraFrame | None = None  # the newest frame looked at
        self.periods_s: deque[float] = deque(maxlen=PERIODS_KEPT)
        self.skews_s: deque[float | None] = deque(maxlen=WINDOW)  # None: no frame to pair

    def look(self, frame: CameraFrame | None) -> None:
        """Learn the frame period from frames looked at: their index counts the frames in between."""
        seen = self.seen
        if frame is None or (seen is not None and frame.index <= seen.index):
            return
        if seen is not None and frame.t_mono_s > seen.t_mono_s:
            self.periods_s.append((frame.t_mono_s - seen.t_mono_s) / (frame.index - seen.index))
        self.seen = frame

    @property
    def period_s(self) -> float | None:
        return float(np.median(self.periods_s)) if self.periods_s else None


class FramePairing:
    """The further cameras' frames for each first-camera frame; `clock` is the frames' (monotonic)."""

    def __init__(
        self,
        sources: Sequence[FrameSource],
        max_skew_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cameras = [_Camera(s) for s in sources]
        self.max_skew_s = max_skew_s
        self.clock = clock
        self._later_s: float | None = None  # a first-camera frame tracked before its pair: its t0

    def to_track(self, t0_s: float, begins: bool) -> list[PairedView | None] | None:
        """The views a first-camera frame that arrived at t0_s is tracked with: when tracking `begins`,
        `views`, waited for (the surface is measured then); otherwise None, and `later_views` pairs it.
        A frame still unpaired is paired now with what there is, for the statistics."""
        if self._later_s is not None:
            self.views(self._later_s, wait=False)
        self._later_s = None if begins or not self.cameras else t0_s
        return self.views(t0_s) if begins else None

    def later_views(self, wait: bool = False) -> tuple[float, list[PairedView | None]] | None:
        """The frame `to_track` left unpaired: its t0 and its `views`, once no frame nearer it is `due`
        (wait: waiting for one, as `views` does); None while one is, or when no frame is to pair."""
        t0_s = self._later_s
        if t0_s is None or (not wait and self.due(t0_s)):
            return None
        self._later_s = None
        return t0_s, self.views(t0_s, wait)

    def views(self, t0_s: float, wait: bool = True) -> list[PairedView | None]:
        """One view per further camera for a first-camera frame that arrived at t0_s; each skew kept (call
        it once per frame). wait: for a frame still `due` (False: the newest there is)."""
        out: list[PairedView | None] = []
        for cam in self.cameras:
            frame = self._nearest(cam, t0_s, wait)
            cam.skews_s.append(None if frame is None else frame.t_mono_s - t0_s)
            out.append(None if frame is None else PairedView(frame.image, frame.t_mono_s))
        return out

    def due(self, t0_s: float) -> bool:
        """A further camera's frame nearer t0_s than its newest can still arrive within max_skew_s of
        t0_s: `views` would wait for it."""
        for cam in self.cameras:
            frame = cam.source.latest()
            cam.look(frame)
            if self._wait_s(cam, frame, t0_s) > 0:
                return True
        return False

    def _wait_s(self, cam: _Camera, frame: CameraFrame | None, t0_s: float) -> float:
        """How long to wait for the frame after `frame`, cam's newest, to pair t0_s (0: not at all)."""
        period_s = cam.period_s
        if frame is None or period_s is None or frame.t_mono_s - t0_s >= -0.5 * period_s:
            return 0.0
        if frame.t_mono_s + period_s - t0_s > self.max_skew_s:  # the next one is due too late to pair
            return 0.0
        return max(min(t0_s + self.max_skew_s - self.clock(), self.max_skew_s), 0.0)

    def _nearest(self, cam: _Camera, t0_s: float, wait: bool) -> CameraFrame | None:
        cam.look(cam.source.latest())
        # Not the newest: paired after the camera's next frame came (a compute held up), the newest was a
        # period off, and a live recording paired half its frames so.
        frame = cam.source.nearest(t0_s)
        wait_s = self._wait_s(cam, frame, t0_s) if wait else 0.0
        if frame is None or wait_s <= 0:
            return frame
        newer = cam.source.newer_than(frame.index, wait_s)
        cam.look(newer)
        if newer is not None and abs(newer.t_mono_s - t0_s) < abs(frame.t_mono_s - t0_s):
            return newer
        return frame

    def stats(self) -> tuple[PairingStats, ...]:
        return tuple(self._stats(cam) for cam in self.cameras)

    def reports(self) -> tuple[CameraReport, ...]:
        return tuple(CameraReport(cam.source.health(), self._stats(cam)) for cam in self.cameras)

    def start(self) -> None:
        for cam in self.cameras:
            cam.source.start()

    def stop(self) -> None:
        for cam in self.cameras:
            cam.source.stop()

    def _stats(self, cam: _Camera) -> PairingStats:
        if not cam.skews_s:
            return PairingStats(None, None, None)
        skews_ms = np.array([s for s in cam.skews_s if s is not None]) * 1e3
        paired = int(np.count_nonzero(np.abs(skews_ms) <= self.max_skew_s * 1e3))
        paired_pct = 100.0 * paired / len(cam.skews_s)
        if not len(skews_ms):
            return PairingStats(None, None, paired_pct)
        return PairingStats(
            float(np.median(skews_ms)), float(np.percentile(np.abs(skews_ms), 95)), paired_pct
        )


@dataclass(frozen=True)
class FurtherCamera:
    """A camera after the first, as the compute process is given it: its name, its model, and its source
    as a factory (opened in the compute process)."""

    name: str  # its `cameras:` entry's (a recording's cameras/NAME/)
    camera_model: CameraModel
    frame_source: Callable[[], FrameSource]


@dataclass(frozen=True)
class CameraReport:
    """A further camera's health and pairing, as a tick's reply carries it."""

    health: FrameSourceHealth
    pairing: PairingStats
