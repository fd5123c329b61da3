"""The offline tracking loop, written once: recorded footage through the tracker, frame by frame, with the
recording's camera, module layout and commands, as the daemon would have tracked it live. Replay and the
benchmarks all track through this."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from tqdm import tqdm

from clothd.config import TrackerConfig
from clothd.core.camera_model import CameraModel
from clothd.core.messages import Estimate, PairedView
from clothd.core.tracker import Clock, Tracker
from clothd.drivers.footage import CommandSchedule, Footage, open_footage, recorded_skews_s
from clothd.errors import InputError
from clothd.formats import read_camera, read_layout


class OfflineTracking:
    """Iterate to get (frame_t_s, BGR image, estimate) for every frame of `source` (a video, an image
    directory or a recording).

    camera_json / commands_csv override the recording's own; without any camera.json the camera is ideal
    (tracker.camera in the config) at the footage's image size. read_ahead decodes frames on a second
    thread (benchmarks that time the tracker's stages turn it off, to keep a core to the tracker).
    progress: a label for a progress bar, shown on a terminal only. cameras: a recording's first this many
    (None: all; the further ones under cameras/NAME/, in name order, each with its camera.json), paired
    by frame index (docs/recording-format.md)."""

    def __init__(
        self,
        source: Path,
        cfg: TrackerConfig,
        camera_json: Path | None = None,
        commands_csv: Path | None = None,
        roi: str = "auto",
        read_ahead: bool = True,
        clock: Clock = time.perf_counter,
        progress: str | None = None,
        cameras: int | None = 1,
    ) -> None:
        self.progress = progress
        self.footage = open_footage(source)
        self._frames = self.footage.frames(read_ahead=read_ahead)
        try:
            self._first = next(self._frames)
        except StopIteration:
            raise InputError(f"{source}: no frames") from None
        self.frame_shape = self._first[1].shape[:2]
        self.camera_model, self.camera_source = self._camera(camera_json, cfg)
        table = self.footage.table_json
        self.layout = read_layout(table) if table else None
        commands = commands_csv or self.footage.commands_csv
        self.schedule = CommandSchedule(commands, self.layout.n_modules) if commands and self.layout else None
        available = further_camera_dirs(source)
        if cameras is not None and len(available) < cameras - 1:
            raise InputError(f"{source}: {cameras} cameras asked for, the recording has {len(available) + 1}")
        further = available if cameras is None else available[: cameras - 1]
        self._others = further_frames(source, further, self.footage, read_ahead)
        models = [read_camera(p / "camera.json") for p in further]
        self.tracker = Tracker(
            cfg, self.camera_model, self.layout, roi=roi, clock=clock, other_cameras=models
        )

    def _camera(self, override: Path | None, cfg: TrackerConfig) -> tuple[CameraModel, str]:
        """The camera, and which it is: a user must know when one was assumed."""
        path = override or self.footage.camera_json
        if path is not None:
            return read_camera(path), str(path)
        h, w = self.frame_shape
        c = cfg.camera
        source = (
            f"assumed ideal (no camera.json): straight down from {c.distance_m} m onto the table, f "
            f"{c.f_px} px, principal point at the centre of the {w}x{h} image, no distortion "
            "(tracker.camera; --camera FILE for a calibrated one)"
        )
        return CameraModel.ideal(w, h, c.f_px, c.distance_m), source

    @property
    def views_given(self) -> dict[str, int]:
        """Each further camera's name and how many of the frames tracked so far had a view of it."""
        return {other.name: other.views_given for other in self._others}

    def __iter__(self) -> Iterator[tuple[float, np.ndarray, Estimate]]:
        frames = itertools.chain([self._first], self._frames)
        if self.progress is not None:  # a bar on a terminal only: tqdm is silent elsewhere
            total = self.footage.frame_count
            frames = tqdm(frames, desc=self.progress, total=total, unit="frame", disable=None, leave=False)
        for k, (t_s, image) in enumerate(frames):
            commands = self.schedule.at(t_s) if self.schedule else None
            views = [other.view_of(self.footage.frame_index(k)) for other in self._others]
            yield t_s, image, self.tracker.step(image, t_s, commands, views)


def further_camera_dirs(recording: Path) -> list[Path]:
    """A recording's further cameras' directories (cameras/NAME/), in their names' order."""
    return sorted(p for p in (recording / "cameras").glob("*") if p.is_dir())


def further_frames(
    recording: Path, dirs: list[Path], first: Footage, read_ahead: bool
) -> list[FurtherFrames]:
    """Each of those cameras' frames, paired with the first camera's `first` by frame index (an hwsim
    recording's at its scenario's capture skew)."""
    skews_s = recorded_skews_s(recording)
    return [FurtherFrames(p, read_ahead, first, skews_s.get(p.name, 0.0)) for p in dirs]


class FurtherFrames:
    """A further camera's frames in a recording, each under the first camera's frame index it goes with:
    an hwsim recording has one for every frame, captured skew_s after the first camera's; a live one has
    those the tracker was given (maybe none), each with its own capture time."""

    def __init__(self, directory: Path, read_ahead: bool, first: Footage, skew_s: float = 0.0) -> None:
        self.name = directory.name
        self.views_given = 0  # first-camera frames this camera had a view for
        self._frames: Iterator[tuple[int, float, np.ndarray]] = iter(())
        frames_dir = directory / "frames"
        if not frames_dir.is_dir() or any(frames_dir.iterdir()):  # a live recording's may hold none
            self._frames = self._indexed(open_footage(directory), read_ahead, first, skew_s)
        self._next = next(self._frames, None)

    @staticmethod
    def _indexed(
        footage: Footage, read_ahead: bool, first: Footage, skew_s: float
    ) -> Iterator[tuple[int, float, np.ndarray]]:
        for k, (t_s, image) in enumerate(footage.frames(read_ahead=read_ahead)):
            index = footage.frame_index(k)
            yield index, t_s if footage.has_capture_times else first.t_s(index) + skew_s, image

    def view_of(self, index: int) -> PairedView | None:
        """The view paired with the first camera's frame `index` (asked in increasing order); None: none."""
        while self._next is not None and self._next[0] < index:
            self._next = next(self._frames, None)
        if self._next is None or self._next[0] != index:
            return None
        _, t_s, image = self._next
        self.views_given += 1
        return PairedView(image, t_s)
