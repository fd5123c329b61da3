"""Recorded footage for offline replay: a video file, a directory of images, or an hwsim recording.

Images in a directory are taken in natural numeric order (img_2 before img_10). A recording directory
(one with frames/ and camera.json) also supplies its camera, module layout and commands; its
truth.npz is never opened here.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from clothd.core.messages import ModuleCommands
from clothd.errors import InputError
from clothd.formats import read_commands, read_frame_rows

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp"}
DEFAULT_FPS = 30.0
_READ_AHEAD = 3
_SAME_TIME_S = 1e-9  # a command stamped with a frame's time holds for that frame, whatever the rounding


def natural_key(path: Path) -> list[object]:
    """Sort key that orders embedded numbers by value: img_2 < img_10."""
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


@dataclass(frozen=True)
class Footage:
    source: Path
    fps: float
    camera_json: Path | None
    table_json: Path | None
    commands_csv: Path | None
    _images: tuple[Path, ...] | None  # None for a video
    _times_s: tuple[float, ...] | None = None  # a live recording's capture times (frames.csv)
    _indices: tuple[int, ...] | None = None  # ... and its frames' indices (a further camera's have gaps)

    @property
    def frame_count(self) -> int | None:
        """How many frames, where that is known without decoding (image sequences)."""
        return None if self._images is None else len(self._images)

    def frame_index(self, k: int) -> int:
        """The k-th frame's index: frames.csv's (a further camera's names the first camera's frame it was
        paired with), else k."""
        return self._indices[k] if self._indices is not None else k

    @property
    def has_capture_times(self) -> bool:
        """Whether each frame's time was recorded (a live recording's frames.csv), not index / fps."""
        return self._times_s is not None

    def _t(self, k: int) -> float:
        return self._times_s[k] if self._times_s is not None else k / self.fps

    def t_s(self, index: int) -> float:
        """Frame `index`'s time (its position in the footage, for a first camera)."""
        return self._t(index)

    def frames(self, read_ahead: bool = True) -> Iterator[tuple[float, np.ndarray]]:
        """(t_s, BGR image) in order; t_s = index / fps, or the capture time a live recording kept.
        Without read_ahead, image files are decoded on the caller's thread (benchmarks that time the
        tracker's own stages want the core to themselves)."""
        if self._images is not None and not read_ahead:
            for k, path in enumerate(self._images):
                img = cv2.imread(str(path), cv2.IMREAD_COLOR)
                if img is None:
                    raise InputError(f"{path}: not a readable image")
                yield self._t(k), img
            return
        if self._images is not None:
            # Decode a few frames ahead on a second thread (PNG decoding releases the GIL): at 640x480
            # it costs about as much as a tracker tick.
            with ThreadPoolExecutor(max_workers=1) as pool:
                ahead: deque[Future[np.ndarray | None]] = deque()
                paths = iter(self._images)
                for path in paths:
                    ahead.append(pool.submit(cv2.imread, str(path), cv2.IMREAD_COLOR))
                    if len(ahead) > _READ_AHEAD:
                        break
                k = 0
                while ahead:
                    img = ahead.popleft().result()
                    nxt = next(paths, None)
                    if nxt is not None:
                        ahead.append(pool.submit(cv2.imread, str(nxt), cv2.IMREAD_COLOR))
                    if img is None:
                        raise InputError(f"{self._images[k]}: not a readable image")
                    yield self._t(k), img
                    k += 1
            return
        cap = cv2.VideoCapture(str(self.source))
        try:
            k = 0
            while True:
                ok, img = cap.read()
                if not ok:
                    return
                yield self._t(k), img
                k += 1
        finally:
            cap.release()


def open_footage(source: Path) -> Footage:
    if source.is_dir():
        frames_dir = source / "frames"
        if frames_dir.is_dir():
            images = _images_in(frames_dir)
            rows = read_frame_rows(source / "frames.csv")
            indices, times = rows if rows is not None else (None, None)
            if indices is not None and times is not None:  # cut short: only frames with a capture time count
                images, indices, times = images[: len(times)], indices[: len(images)], times[: len(images)]
            return Footage(
                source,
                _recording_fps(source, times),
                _existing(source / "camera.json"),
                _existing(source / "table.json"),
                _existing(source / "commands.csv"),
                images,
                times,
                indices,
            )
        return Footage(source, DEFAULT_FPS, None, None, None, _images_in(source))
    if not source.exists():
        raise InputError(f"{source}: no such file or directory")
    if source.suffix.lower() == ".mcap":
        raise InputError(
            f"{source}: an MCAP recording (recording.format mcap) is for Foxglove and cannot be replayed;"
            " record with recording.format dir for that"
        )
    cap = cv2.VideoCapture(str(source))
    opened, fps = cap.isOpened(), cap.get(cv2.CAP_PROP_FPS)
    cap.release()
    if not opened:
        raise InputError(f"{source}: not a video OpenCV can read")
    return Footage(source, fps if fps and fps > 0 else DEFAULT_FPS, None, None, None, None)


def recorded_skews_s(recording: Path) -> dict[str, float]:
    """An hwsim recording's further cameras' capture skews by name (scenario.yaml's `cameras`: frame k of
    each shows the world capture_skew_s after the first camera's frame k); empty for any other."""
    scenario = recording / "scenario.yaml"
    data = yaml.safe_load(scenario.read_text()) if scenario.exists() else None
    cameras = data.get("cameras") if isinstance(data, dict) else None
    if not isinstance(cameras, list):
        return {}
    skews = {}
    for index, cam in enumerate(cameras):
        if isinstance(cam, dict) and isinstance(cam.get("capture_skew_s"), int | float):
            skews[str(cam.get("name") or f"cam{index}")] = float(cam["capture_skew_s"])
    return skews


def _existing(path: Path) -> Path | None:
    return path if path.exists() else None


def _images_in(directory: Path) -> tuple[Path, ...]:
    images = sorted((p for p in directory.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
    if not images:
        raise InputError(f"{directory}: no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
    return tuple(images)


def _recording_fps(recording: Path, times_s: tuple[float, ...] | None) -> float:
    """A live recording's mean frame rate over its capture times (a live camera's rate is its own, 15 fps
    from hwsim serve); an hwsim recording's scenario.yaml fps; else DEFAULT_FPS."""
    if times_s is not None and len(times_s) > 1 and times_s[-1] > times_s[0]:
        return (len(times_s) - 1) / (times_s[-1] - times_s[0])
    scenario = recording / "scenario.yaml"
    if scenario.exists():
        data = yaml.safe_load(scenario.read_text())
        if isinstance(data, dict) and isinstance(data.get("fps"), int | float):
            return float(data["fps"])
    return DEFAULT_FPS


class CommandSchedule:
    """commands.csv (t_s, module, speed_m_s, heading_rad) as a function of time: each module holds its
    last command; modules never commanded stand still."""

    def __init__(self, path: Path, n_modules: int) -> None:
        self._rows = read_commands(path, n_modules)
        self._next = 0
        self._speed = np.zeros(n_modules)
        self._heading = np.zeros(n_modules)

    def at(self, t_s: float) -> ModuleCommands:
        """Commands in force at t_s; call with non-decreasing times."""
        while self._next < len(self._rows) and self._rows[self._next][0] <= t_s + _SAME_TIME_S:
            _, m, speed, heading = self._rows[self._next]
            self._speed[m], self._heading[m] = speed, heading
            self._next += 1
        return ModuleCommands(self._speed.copy(), self._heading.copy())
