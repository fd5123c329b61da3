"""Session recording, in the format `clothd replay` reads (docs/recording-format.md) and writes:

DIR/frames/NNNNNN.png   every new camera frame, lossless
DIR/frames.csv          index, t_s: each frame's capture time, seconds since the first frame's
DIR/camera.json         the camera model the daemon ran with
DIR/table.json          the module layout
DIR/commands.csv        t_s, module, speed_m_s, heading_rad: the commands sent, as they changed
DIR/estimates.npz       what the tracker believed live (replay's format, its t_s as frames.csv's), written
                        when recording stops
DIR/cameras/NAME/       each further camera's views the tracker was given, in the same layout: a view is
                        numbered as the first camera's frame it was paired with (frames.csv: that index
                        and the view's own capture time), and a frame tracked without one has none

The recording's time origin is its first frame's capture time, as frame 0 of an hwsim recording is at
0 s: the first frame may have been captured before the recording was asked for (a frame already
waiting for its tick), and a time before the origin is no time an MCAP file can stamp.

A frame's PNG is written before its frames.csv row, and both files are flushed as they grow, so a
recording cut short (process killed, disk full, size limit) replays up to its last complete frame.
Recording stops by itself at `max_bytes` or on any write error, with the reason in its status; the
loop goes on either way.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from clothd.config import RecordingFormat
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout
from clothd.core.messages import Estimate, ModuleCommands, PairedView
from clothd.errors import InvalidRequestError, RequestError, StorageError
from clothd.formats import FrameTimesLog, RecordingLog, write_camera, write_estimates, write_layout

log = logging.getLogger(__name__)
_PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1]
# The recent frames whose index a further camera's views can still be recorded under.
RECENT_FRAMES = 8


class FrameSink(Protocol):
    """Where each tracked frame goes after its tick's reply: a directory recording (Recorder), and the live
    Foxglove server and its MCAP recordings (foxglove_live.LiveFoxglove), which only queue it."""

    def add(self, image: np.ndarray, t_mono_s: float, commands: ModuleCommands, est: Estimate | None) -> None:
        """The frame, when it was captured, the commands in force meanwhile, and its estimate."""


@dataclass(frozen=True)
class RecordingStatus:
    active: bool
    dir: str | None  # the recording's directory, or its .mcap file
    frames: int
    bytes: int
    max_bytes: int
    stopped_reason: str | None
    format: RecordingFormat = RecordingFormat.DIRECTORY
    dropped_frames: int = 0  # frames an MCAP recording's writer was too far behind to take


def recording_path(recording_dir: Path, requested: str | None, suffix: str = "") -> Path:
    """Where a recording asked for over the API goes: a timestamped directory by default, else the name
    or relative path given, which must stay inside recording_dir once symlinks are resolved; `suffix`
    (".mcap") is added when the name does not end in it."""
    name = requested or time.strftime("%Y%m%d-%H%M%S")
    if not name.endswith(suffix):
        name += suffix
    if "\0" in name:
        raise InvalidRequestError("a recording name cannot hold a NUL character")
    root = recording_dir.resolve()
    path = (root / name).resolve()
    if path == root or root not in path.parents:
        raise InvalidRequestError(
            f"a recording goes inside the recording directory {recording_dir} (recording.dir): "
            "give a name or a path relative to it"
        )
    return path


def make_recording_place(out: Path, form: RecordingFormat) -> Path:
    """Make the new directory, or with format mcap the new .mcap file (the suffix added when missing),
    that a recording goes into, and return it: a place that cannot be written is refused here and now
    (RequestError when it exists, StorageError for a full disk, InvalidRequestError otherwise)."""
    if out.suffix != form.suffix:
        out = out.with_name(out.name + form.suffix)
    try:
        if form == RecordingFormat.MCAP:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.touch(exist_ok=False)  # O_EXCL: neither an existing file nor a symlink is reused
        else:
            out.mkdir(parents=True)
    except FileExistsError:
        raise RequestError(f"{out} exists: a recording needs a new {form.noun}") from None
    except OSError as err:  # a full disk is the daemon's trouble (507); anything else is the place's
        error = StorageError if err.errno in (errno.ENOSPC, errno.EDQUOT) else InvalidRequestError
        raise error(f"cannot create {out}: {err.strerror or err}") from None
    return out


def remove_recording_place(out: Path) -> None:
    """Remove a place `make_recording_place` made that no recording took (the request was refused)."""
    with contextlib.suppress(OSError):  # a place something else has written to since stays
        if out.is_dir():
            out.rmdir()
        elif out.stat().st_size == 0:
            out.unlink()


class _FurtherCamera:
    """DIR/cameras/NAME/: a further camera's views, each under its first-camera frame's index."""

    def __init__(self, directory: Path, camera: CameraModel) -> None:
        self.frames_dir = directory / "frames"
        self.frames_dir.mkdir(parents=True)
        write_camera(directory / "camera.json", camera)
        self.times: FrameTimesLog | None = None  # opened with the recording's other logs


class Recorder:
    def __init__(
        self,
        out_dir: Path,
        camera: CameraModel,
        layout: ConveyorLayout,
        max_bytes: int,
        further: Sequence[tuple[str, CameraModel]] = (),
    ) -> None:
        """further: each further camera's name and model; its views are recorded under cameras/NAME/."""
        self.dir = out_dir
        self.max_bytes = max_bytes
        self.t0_mono_s: float | None = None  # the first frame's capture time, host monotonic
        self.frames = 0
        self.bytes = 0
        self.active = True
        self.stopped_reason: str | None = None
        self._estimates: list[Estimate] = []
        (out_dir / "frames").mkdir(parents=True, exist_ok=False)
        write_camera(out_dir / "camera.json", camera)
        write_layout(out_dir / "table.json", layout)
        self._further = [_FurtherCamera(out_dir / "cameras" / name, model) for name, model in further]
        self._log = RecordingLog(out_dir)  # the files left open, last: nothing after them can fail
        try:
            for cam in self._further:
                cam.times = FrameTimesLog(cam.frames_dir.parent / "frames.csv")
        except OSError:
            self._close_logs()
            raise
        self._recent_frames: OrderedDict[float, int] = OrderedDict()  # capture time -> index

    def status(self) -> RecordingStatus:
        return RecordingStatus(
            self.active, str(self.dir), self.frames, self.bytes, self.max_bytes, self.stopped_reason
        )

    def add(self, image: np.ndarray, t_mono_s: float, commands: ModuleCommands, est: Estimate | None) -> None:
        """One new frame, the commands in force with it, and the estimate made from it."""
        if not self.active:
            return
        if self.t0_mono_s is None:
            self.t0_mono_s = t_mono_s
        png = self._png(image)
        if png is None:
            return
        try:
            (self.dir / "frames" / f"{self.frames:06d}.png").write_bytes(png)
            self._log.add_frame(self.frames, t_mono_s - self.t0_mono_s, commands)
        except OSError as err:
            self.stop(f"write failed: {err.strerror or err}")
            return
        self.bytes += len(png)
        self._recent_frames[t_mono_s] = self.frames
        while len(self._recent_frames) > RECENT_FRAMES:
            self._recent_frames.popitem(last=False)
        self.frames += 1
        # In mode flow the pieces are tracked apart: the frame's row in estimates.npz says lost.
        self._estimates.append(est if est is not None else Estimate.lost(t_mono_s, {}))

    def index_of(self, t_mono_s: float) -> int | None:
        """The index of the recent frame captured at t_mono_s; None if none was recorded (yet)."""
        return self._recent_frames.get(t_mono_s)

    def add_views(self, index: int, views: Sequence[PairedView | None]) -> None:
        """The further cameras' views (one each, None: none) that recorded frame `index` was tracked with."""
        if not self.active:
            return
        assert self.t0_mono_s is not None  # a frame was recorded
        for camera, view in zip(self._further, views, strict=True):
            if view is None:
                continue
            png = self._png(view.image)
            if png is None:
                return
            try:
                (camera.frames_dir / f"{index:06d}.png").write_bytes(png)
                assert camera.times is not None  # opened in __init__
                camera.times.add(index, view.t_s - self.t0_mono_s)
            except OSError as err:
                self.stop(f"write failed: {err.strerror or err}")
                return
            self.bytes += len(png)

    def _png(self, image: np.ndarray) -> bytes | None:
        """The image as PNG; None (and the recording stopped) when it cannot be, or would cross max_bytes."""
        ok, png = cv2.imencode(".png", image, _PNG_PARAMS)
        if not ok:
            self.stop("could not encode a frame")
            return None
        if self.bytes + len(png) > self.max_bytes:
            self.stop(f"size limit reached ({self.max_bytes} bytes)")
            return None
        return bytes(png.tobytes())

    def stop(self, reason: str = "stopped") -> None:
        """Close the files and write the estimates; safe to call twice."""
        if not self.active:
            return
        self.active = False
        self.stopped_reason = reason
        log.info("recording %s stopped: %s (%d frames)", self.dir, reason, self.frames)
        for error in self._close_logs():
            log.warning("recording: %s", error)
        if self._estimates and self.t0_mono_s is not None:
            try:
                write_estimates(self.dir / "estimates.npz", self._estimates, self.t0_mono_s)
            except OSError as err:  # the disk is full: the frames and commands stay replayable
                self.stopped_reason = f"{reason}; estimates not written: {err.strerror or err}"

    def _close_logs(self) -> list[str]:
        """Close the growing files; the errors met, as text."""
        errors = self._log.close()
        for cam in self._further:
            errors += cam.times.close() if cam.times is not None else []
        return errors
