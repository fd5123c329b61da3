"""`hwsim serve`'s cameras render in processes of their own: a frame is the one the world thread's scene
shows, bit for bit as rendered in the cell's own process, and reaches its clients when it is due (the
frames due together at once), not when its render is done; a camera whose render falls behind renders
the newest shot and counts the rest dropped."""

from __future__ import annotations

import threading
import time

import pytest
from small_scenarios import two_cameras

from hwsim import scenario as scenarios
from hwsim.camera import Camera
from hwsim.camera_process import CameraProcess, FrameClock, Shot, VideoFrame, _Latest
from hwsim.recording import frame_states
from hwsim.sensor import Sensor
from hwsim.taichi_runtime import ensure_taichi
from hwsim.world import World

pytestmark = pytest.mark.clock_free


def _shot(k: int) -> Shot:
    return Shot(k, k, 0.0, [], 0.0)


def test_a_camera_behind_renders_the_newest_shot_and_counts_the_rest() -> None:
    latest = _Latest()
    for k in range(3):
        latest.put(_shot(k))
    taken = latest.take()
    assert taken is not None and taken[0].k == 2 and taken[1] == 2
    latest.put(_shot(3))
    taken = latest.take()
    assert taken is not None and taken[0].k == 3 and taken[1] == 0
    latest.put(None)
    assert latest.take() is None


def test_a_frame_is_rendered_apart_as_at_home() -> None:
    sc = scenarios.parse(two_cameras(name="apart"))
    ensure_taichi("cpu", cpu_threads=1)
    world = World(sc)
    world.step()
    states = frame_states(world)
    at_home = Sensor(sc, Camera.from_spec(sc.camera_specs[1]), world.cloth.grid, 1)
    rendered: list[tuple[int, float, VideoFrame]] = []
    came = threading.Event()

    def handed_on(instant: int, due_s: float, frame: VideoFrame) -> None:
        rendered.append((instant, due_s, frame))
        came.set()

    died: list[BaseException] = []
    camera = CameraProcess(sc, world.cloth.grid, "cpu", 1, handed_on, died.append)
    try:
        camera.shoot(Shot(8, 4, world.t_s, states, 0.0))
        first = camera.first()  # compiled, and back before first() returns
        camera.start()
        camera.shoot(Shot(10, 5, world.t_s, states, 12.5))
        assert came.wait(60.0)
    finally:
        camera.stop()
    assert not died
    assert first.index == 4 and first.jpeg == at_home.encode(states, 4)
    ((instant, due_s, frame),) = rendered
    assert instant == 10 and due_s == 12.5 and frame.index == 5 and frame.t_s == world.t_s
    assert frame.jpeg == at_home.encode(states, 5)


def test_frames_reach_the_host_when_due_an_instants_once_all_are_rendered() -> None:
    """Instant 1 shoots both cameras, instant 2 only the first; camera 1 skips instant 3's frame for 4's.
    Camera 0's frames of instants 1 and 2 wait for camera 1's of instant 1 (a stream never goes back);
    frames due together go out together; a frame skipped for a newer one holds nothing up."""
    calls: list[tuple[float, list[tuple[int, int]]]] = []
    delivered = threading.Condition()

    def deliver(frames: list[tuple[int, VideoFrame]]) -> None:
        with delivered:
            calls.append((time.monotonic(), [(stream, f.index) for stream, f in frames]))
            delivered.notify()

    clock = FrameClock(deliver)
    clock.start()
    now = time.monotonic()
    frame = {k: VideoFrame(k, b"", 0.0) for k in range(1, 5)}
    try:
        for instant, streams in ((1, [0, 1]), (2, [0]), (3, [0, 1]), (4, [0, 1])):
            clock.expect(instant, streams)
        clock.put(0, 1, now + 0.1, frame[1])
        clock.put(0, 2, now + 0.2, frame[2])
        time.sleep(max(0.0, now + 0.4 - time.monotonic()))
        with delivered:
            assert not calls  # both due, both held for camera 1's frame of instant 1
        clock.put(1, 1, now + 0.1, frame[1])
        clock.put(0, 3, now + 0.6, frame[3])
        clock.put(0, 4, now + 0.7, frame[4])
        clock.put(1, 4, now + 0.7, frame[4])
        with delivered:
            assert delivered.wait_for(lambda: len(calls) == 3, 10.0)
    finally:
        clock.stop()
    assert [c for _, c in calls] == [[(0, 1), (1, 1), (0, 2)], [(0, 3)], [(0, 4), (1, 4)]]
    assert calls[1][0] >= now + 0.6 and calls[2][0] >= now + 0.7  # held until due
