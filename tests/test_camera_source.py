"""The live frame source: newest frame only, stamped at capture; a missing source is reported and
retried with backoff."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from clothd.config import CameraSourceConfig
from clothd.drivers import camera as camera_module
from clothd.drivers.camera import VideoCaptureSource
from clothd.drivers.footage import DEFAULT_FPS


def _wait(check: object, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():  # type: ignore[operator]
        assert time.monotonic() < deadline
        time.sleep(0.01)


def test_an_image_directory_plays_as_a_camera(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    for k in (1, 2, 10):
        cv2.imwrite(str(tmp_path / f"img_{k}.png"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    cam = VideoCaptureSource(CameraSourceConfig(source=str(tmp_path)))
    cam.start()
    try:
        _wait(lambda: cam.latest() is not None)
        first = cam.latest()
        assert first is not None and first.image.shape == (48, 64, 3)
        _wait(lambda: (f := cam.latest()) is not None and f.index > first.index)
        later = cam.latest()
        assert later is not None and later.t_mono_s > first.t_mono_s
        assert cam.state == "streaming" and cam.healthy
    finally:
        cam.stop()


def test_the_capture_thread_takes_the_realtime_priority_it_is_given(tmp_path: Path) -> None:
    """A frame's stamp is its arrival: the capture thread must not wait behind other programs."""
    cv2.imwrite(str(tmp_path / "img_1.png"), np.zeros((48, 64, 3), np.uint8))
    cam = VideoCaptureSource(CameraSourceConfig(source=str(tmp_path)), realtime_priority=4)
    cam.start()
    try:
        _wait(lambda: cam.latest() is not None)
        tid = cam._thread.native_id
        assert tid is not None and tid != threading.get_native_id()
        assert (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority) == (os.SCHED_FIFO, 4)
        assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the caller's own class is untouched
    finally:
        cam.stop()


def test_a_missing_source_is_reported_and_retried(tmp_path: Path) -> None:
    cfg = CameraSourceConfig(source=str(tmp_path / "nope.mp4"), reconnect_initial_s=0.05, reconnect_max_s=0.1)
    cam = VideoCaptureSource(cfg)
    cam.start()
    try:
        _wait(lambda: cam.reconnects >= 2)
        assert cam.state == "lost" and cam.latest() is None and not cam.healthy
        assert "nope.mp4" in (cam.last_error or "")
    finally:
        cam.stop()


def test_newer_than_returns_a_frame_as_it_arrives_and_gives_up_at_its_bound(tmp_path: Path) -> None:
    """The compute waits for a due frame this way: woken by the frame, not by its bound, and given the
    newest frame when the one it waits for never comes."""
    rng = np.random.default_rng(6)
    cv2.imwrite(str(tmp_path / "img_1.png"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    cam = VideoCaptureSource(CameraSourceConfig(source=str(tmp_path)))  # plays at DEFAULT_FPS
    cam.start()
    try:
        _wait(lambda: cam.latest() is not None)
        seen = cam.latest()
        assert seen is not None
        got = cam.newer_than(seen.index, timeout_s=5.0)
        # Woken by the next frame: waiting out the 5 s bound would have let ~5 x DEFAULT_FPS frames by.
        assert got is not None and seen.index < got.index < seen.index + DEFAULT_FPS
        never = got.index + 10**6
        newest = cam.newer_than(never, timeout_s=0.05)  # no such frame comes: the newest instead
        assert newest is not None and got.index <= newest.index < never
    finally:
        cam.stop()


def test_health_gives_the_rate_frames_arrive_at_and_the_longest_wait(monkeypatch: pytest.MonkeyPatch) -> None:
    """A camera dropping frames shows as a lower rate and a long gap before it is lost; frames older than
    the window age out, so a stalled camera reports no rate."""
    now = [0.0]
    # The camera module's clock only: threads elsewhere keep the real one.
    monkeypatch.setattr(camera_module, "time", SimpleNamespace(monotonic=lambda: now[0]))
    cam = VideoCaptureSource(CameraSourceConfig(source="unused", stale_after_s=30.0))  # never started
    image = np.zeros((4, 4, 3), np.uint8)
    assert cam.health().fps is None and cam.health().longest_gap_ms is None
    for t_s in (0.0, 1 / 15, 2 / 15, 0.2 + 2 / 15):  # 15 frames/s, then one frame dropped and another
        now[0] = t_s
        cam._publish(image)
    now[0] = 0.4
    health = cam.health()
    assert health.fps == pytest.approx(3 / (0.2 + 2 / 15))
    assert health.longest_gap_ms == pytest.approx(200.0)
    now[0] = 0.2 + 2 / 15 + 5.5  # nothing new for longer than the window
    assert cam.health().fps is None and cam.health().longest_gap_ms is None
