"""Live frame sources for the daemon: any OpenCV VideoCapture source or a directory of images.

A capture thread reads continuously and hands out the newest frame, stamped with the host's monotonic
clock when it arrived (`t_mono_s`), so a tick always gets the freshest image and never a backlog; it
keeps the last few besides, for a further camera's pair (`nearest`). A
source that fails or goes quiet is reopened with exponential backoff; `state` says which. The rate frames
arrive at, and the longest wait between two, over the last RATE_WINDOW_S, show a camera that drops frames
(a saturated USB bus, a slow exposure) before it is lost.
Files and image directories are played at their frame rate, looping, as a camera would deliver them.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

import cv2
import numpy as np

from clothd.config import CameraSourceConfig
from clothd.drivers.footage import DEFAULT_FPS, IMAGE_SUFFIXES, natural_key
from clothd.drivers.ports import KEPT_FRAMES, RATE_WINDOW_S, CameraFrame, FrameSourceHealth
from clothd.drivers.priority import claim_realtime

log = logging.getLogger(__name__)


def redact_source(source: str) -> str:
    """A camera source fit to show: a URL's user name and password become ***
    (rtsp://admin:secret@cam/stream -> rtsp://***@cam/stream); anything else is shown as it is."""
    parts = urlsplit(source)
    if "@" not in parts.netloc:
        return source
    return urlunsplit(parts._replace(netloc="***@" + parts.netloc.rpartition("@")[2]))


class VideoCaptureSource:
    """The FrameSource of a live camera; `latest()` never blocks, the capture runs on its own thread."""

    def __init__(self, cfg: CameraSourceConfig, realtime_priority: int = 0) -> None:
        """realtime_priority: the capture thread's SCHED_FIFO priority (0: the normal class). A frame is
        stamped as it arrives, and the tracker takes the stamp for the time the camera saw it: a capture
        thread that a busy PC held up stamped a backlog of frames a millisecond apart."""
        self.cfg = cfg
        self.realtime_priority = realtime_priority
        self.state = "connecting"  # connecting | streaming | lost
        self.last_error: str | None = None
        self.reconnects = 0
        self.shown = redact_source(cfg.source)  # for logs and status: no credentials
        self._frame: CameraFrame | None = None
        self._recent: deque[CameraFrame] = deque(maxlen=KEPT_FRAMES)  # the newest last
        self._count = 0
        self._arrivals_s: deque[float] = deque()  # arrival times over the last RATE_WINDOW_S
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)  # notified with each new frame
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="camera", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=3)

    def latest(self) -> CameraFrame | None:
        """The newest frame, or None when there is none or it is older than `stale_after_s`."""
        with self._lock:
            frame = self._frame
        if frame is None or time.monotonic() - frame.t_mono_s > self.cfg.stale_after_s:
            return None
        return frame

    def newer_than(self, index: int, timeout_s: float) -> CameraFrame | None:
        """The newest frame once one past `index` is there, waiting up to timeout_s for it to arrive;
        whatever `latest()` gives if none arrives in time."""
        with self._arrived:
            self._arrived.wait_for(lambda: self._frame is not None and self._frame.index > index, timeout_s)
        return self.latest()

    def nearest(self, t_mono_s: float) -> CameraFrame | None:
        """Of the frames kept, the one that arrived nearest t_mono_s; None when `latest()` is."""
        if self.latest() is None:
            return None
        with self._lock:
            recent = list(self._recent)
        return min(recent, key=lambda f: abs(f.t_mono_s - t_mono_s))

    @property
    def healthy(self) -> bool:
        return self.latest() is not None

    def health(self) -> FrameSourceHealth:
        fps = gap_ms = None
        with self._lock:
            arrivals = np.array(self._arrivals_s)
        arrivals = arrivals[arrivals >= time.monotonic() - RATE_WINDOW_S]  # a stalled source's age out
        if len(arrivals) >= 2 and arrivals[-1] > arrivals[0]:
            fps = float((len(arrivals) - 1) / (arrivals[-1] - arrivals[0]))
            gap_ms = float(np.diff(arrivals).max() * 1e3)
        return FrameSourceHealth(self.state, self.healthy, self.last_error, self.reconnects, fps, gap_ms)

    # -- capture ----------------------------------------------------------------------------------

    def _run(self) -> None:
        claim_realtime(self.realtime_priority, "the camera's capture")
        delay = self.cfg.reconnect_initial_s
        while not self._stop.is_set():
            try:
                if self._capture():
                    delay = self.cfg.reconnect_initial_s
            except (cv2.error, OSError) as err:
                self._lost(str(err))
            if self._stop.wait(delay):
                return
            delay = min(delay * 2, self.cfg.reconnect_max_s)
            self.reconnects += 1

    def _capture(self) -> bool:
        """Stream until the source fails; True if it delivered any frame."""
        source = self.cfg.source
        path = Path(source)
        if path.is_dir():
            return self._play_images(path)
        if "://" in source:  # a stream: bound FFmpeg's waits so a silent server counts as lost
            timeout_ms = int(self.cfg.stale_after_s * 2000)
            params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms]
            cap = cv2.VideoCapture(source, cv2.CAP_FFMPEG, params)
        else:
            cap = cv2.VideoCapture(int(source) if source.isdigit() else source)
        try:
            if not cap.isOpened():
                self._lost(f"cannot open camera source {self.shown!r}")
                return False
            # A file plays at its own rate; a live source delivers at its own pace.
            pace_s = 1.0 / (cap.get(cv2.CAP_PROP_FPS) or DEFAULT_FPS) if path.is_file() else 0.0
            delivered = False
            while not self._stop.is_set():
                t0 = time.monotonic()
                ok, image = cap.read()
                if not ok:
                    if path.is_file() and delivered:
                        cap.set(cv2.CAP_PROP_POS_FRAMES, 0)  # loop the file
                        continue
                    self._lost(f"camera source {self.shown!r} stopped delivering frames")
                    return delivered
                self._publish(image)
                delivered = True
                if pace_s:
                    self._stop.wait(max(0.0, pace_s - (time.monotonic() - t0)))
            return delivered
        finally:
            cap.release()

    def _play_images(self, directory: Path) -> bool:
        images = sorted(
            (p for p in directory.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key
        )
        if not images:
            self._lost(f"{directory}: no images")
            return False
        pace_s = 1.0 / DEFAULT_FPS
        while not self._stop.is_set():
            for p in images:
                t0 = time.monotonic()
                image = cv2.imread(str(p), cv2.IMREAD_COLOR)
                if image is None:
                    self._lost(f"{p}: not a readable image")
                    return False
                self._publish(image)
                if self._stop.wait(max(0.0, pace_s - (time.monotonic() - t0))):
                    return True
        return True

    def _publish(self, image: np.ndarray) -> None:
        now = time.monotonic()
        with self._arrived:
            self._frame = CameraFrame(self._count, now, image)
            self._recent.append(self._frame)
            self._count += 1
            self._arrivals_s.append(now)
            while now - self._arrivals_s[0] > RATE_WINDOW_S:
                self._arrivals_s.popleft()
            self._arrived.notify_all()
        if self.state != "streaming":
            log.info("camera streaming from %s", self.shown)
        self.state = "streaming"
        self.last_error = None

    def _lost(self, reason: str) -> None:
        if self.state != "lost" or reason != self.last_error:
            log.warning("camera: %s; reconnecting", reason)
        self.state = "lost"
        self.last_error = reason
