"""Pairing further cameras' frames with the first camera's by arrival time (clothd/loop/pairing.py), on
fake frame sources that deliver on a schedule and a fake clock that a wait moves forward."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from recorded_frames import RecordedFrames, compute_on, tick

from clothd.core.control import Setpoint
from clothd.core.messages import ModuleCommands, PairedView
from clothd.drivers.footage import open_footage
from clothd.drivers.ports import KEPT_FRAMES, CameraFrame, FrameSourceHealth
from clothd.formats import read_camera
from clothd.loop.compute_messages import TickRequest
from clothd.loop.pairing import FramePairing, FurtherCamera

pytestmark = pytest.mark.clock_free

PERIOD_S = 1 / 15
MAX_SKEW_S = 0.020


class Clock:
    def __init__(self, now_s: float = 0.0) -> None:
        self.now_s = now_s

    def __call__(self) -> float:
        return self.now_s


class ScheduledFrames:
    """A FrameSource whose frame i arrives at arrivals_s[i]; `newer_than` waits on the fake clock."""

    def __init__(self, clock: Clock, arrivals_s: list[float]) -> None:
        self.clock = clock
        self.arrivals_s = arrivals_s
        self.waited_s: list[float] = []

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def latest(self) -> CameraFrame | None:
        arrived = [i for i, t in enumerate(self.arrivals_s) if t <= self.clock.now_s]
        if not arrived:
            return None
        i = arrived[-1]
        return CameraFrame(i, self.arrivals_s[i], np.full((2, 2, 3), i, np.uint8))

    def nearest(self, t_mono_s: float) -> CameraFrame | None:
        newest = self.latest()
        if newest is None:
            return None
        kept = range(max(0, newest.index - KEPT_FRAMES + 1), newest.index + 1)
        i = min(kept, key=lambda k: abs(self.arrivals_s[k] - t_mono_s))
        return CameraFrame(i, self.arrivals_s[i], np.full((2, 2, 3), i, np.uint8))

    def newer_than(self, index: int, timeout_s: float) -> CameraFrame | None:
        later = [t for t in self.arrivals_s[index + 1 :] if t <= self.clock.now_s + timeout_s]
        until = max(self.clock.now_s, later[0]) if later else self.clock.now_s + timeout_s
        self.waited_s.append(until - self.clock.now_s)
        self.clock.now_s = until
        return self.latest()

    def health(self) -> FrameSourceHealth:
        return FrameSourceHealth("streaming", True, None, 0)


def _grid(offset_s: float, n: int = 40) -> list[float]:
    return [offset_s + k * PERIOD_S for k in range(n)]


def _first_frames(pairing: FramePairing, clock: Clock, times_s: list[float], after_s: float = 0.001) -> list:
    """Pair a first-camera frame at each time, each looked at `after_s` after it arrived."""
    out = []
    for t0 in times_s:
        clock.now_s = max(clock.now_s, t0 + after_s)
        out.append(pairing.views(t0))
    return out


def test_the_newest_frame_is_taken_when_it_is_the_nearest_and_its_skew_is_kept() -> None:
    clock = Clock()
    cam = ScheduledFrames(clock, _grid(0.004))  # 4 ms after the first camera's frames
    pairing = FramePairing([cam], MAX_SKEW_S, clock)
    views = _first_frames(pairing, clock, _grid(0.0, 20)[1:], after_s=0.006)
    assert all(v[0] is not None for v in views)
    assert views[-1][0].t_s == pytest.approx(0.004 + 19 * PERIOD_S)  # the frame of the same capture
    assert views[-1][0].image[0, 0, 0] == 19
    (stats,) = pairing.stats()
    assert stats.skew_ms == pytest.approx(4.0) and stats.skew_p95_ms == pytest.approx(4.0)
    assert stats.paired_pct == 100.0
    assert not cam.waited_s  # nothing to wait for: the nearest frame was there


def test_a_pair_taken_after_the_next_frame_came_still_finds_its_own() -> None:
    """Each first-camera frame paired 80 ms after it arrived (a compute held up by a recording): the
    further camera's next frame is there by then, and its own, 4 ms from t0, is still taken."""
    clock = Clock()
    cam = ScheduledFrames(clock, _grid(0.004))
    pairing = FramePairing([cam], MAX_SKEW_S, clock)
    views = _first_frames(pairing, clock, _grid(0.0, 20)[1:], after_s=0.080)
    assert [v[0].image[0, 0, 0] for v in views] == list(range(1, 20))
    (stats,) = pairing.stats()
    assert stats.skew_ms == pytest.approx(4.0) and stats.paired_pct == 100.0


def test_a_frame_due_within_the_bound_is_waited_for_and_the_wait_is_bounded() -> None:
    clock = Clock()
    cam = ScheduledFrames(clock, _grid(0.012))  # arrives 12 ms after the first camera's
    pairing = FramePairing([cam], MAX_SKEW_S, clock)
    views = _first_frames(pairing, clock, _grid(0.0, 20)[1:])
    # Once the period is known, each newest frame is 55 ms old at t0: the one due 12 ms later is nearer.
    assert views[-1][0].t_s == pytest.approx(0.012 + 19 * PERIOD_S)
    assert pairing.stats()[0].skew_ms == pytest.approx(12.0)
    assert cam.waited_s and max(cam.waited_s) <= MAX_SKEW_S + 1e-12
    assert pytest.approx(0.011) in cam.waited_s  # from t0 + 1 ms until it arrived


def test_a_frame_due_past_the_bound_is_not_waited_for() -> None:
    clock = Clock()
    cam = ScheduledFrames(clock, _grid(0.030))  # 30 ms after: past the 20 ms bound
    pairing = FramePairing([cam], MAX_SKEW_S, clock)
    views = _first_frames(pairing, clock, _grid(0.0, 20)[2:])
    assert not cam.waited_s
    # What there is: the previous frame, 37 ms early, handed on (the tracker refuses it) and counted.
    assert views[-1][0].t_s == pytest.approx(0.030 + 18 * PERIOD_S)
    stats = pairing.stats()[0]
    assert stats.skew_ms == pytest.approx((0.030 - PERIOD_S) * 1e3)
    assert stats.paired_pct == 0.0


def test_a_camera_without_frames_gives_none_and_another_still_pairs() -> None:
    clock = Clock()
    silent = ScheduledFrames(clock, [])
    live = ScheduledFrames(clock, _grid(-0.002))
    pairing = FramePairing([silent, live], MAX_SKEW_S, clock)
    views = _first_frames(pairing, clock, _grid(0.0, 10))
    assert all(v[0] is None and v[1] is not None for v in views)
    none_stats, live_stats = pairing.stats()
    assert (none_stats.skew_ms, none_stats.skew_p95_ms, none_stats.paired_pct) == (None, None, 0.0)
    assert live_stats.skew_ms == pytest.approx(-2.0) and live_stats.paired_pct == 100.0


def test_stats_are_the_median_and_the_95th_percentile_over_recent_pairs() -> None:
    clock = Clock()
    rng = np.random.default_rng(0)
    offsets_s = rng.uniform(-0.006, 0.006, 60)
    cam = ScheduledFrames(clock, [k * PERIOD_S + o for k, o in enumerate(offsets_s)])
    pairing = FramePairing([cam], MAX_SKEW_S, clock)
    _first_frames(pairing, clock, _grid(0.0, 60)[1:], after_s=0.007)
    stats = pairing.stats()[0]
    skews_ms = offsets_s[1:] * 1e3
    assert stats.skew_ms == pytest.approx(np.median(skews_ms))
    assert stats.skew_p95_ms == pytest.approx(np.percentile(np.abs(skews_ms), 95))
    assert stats.paired_pct == 100.0


def test_before_any_first_camera_frame_there_are_no_stats() -> None:
    pairing = FramePairing([ScheduledFrames(Clock(), [])], MAX_SKEW_S, Clock())
    assert [(s.skew_ms, s.paired_pct) for s in pairing.stats()] == [(None, None)]


def test_the_compute_hands_the_tracker_a_view_per_further_camera_and_reports_each(
    short_recording: Callable[[str], Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The plumbing only: the views the tracker is given and the reply's reports, not what it does with
    them (the tracker's own tests). Tracking begins with the pair; after that a frame is tracked with its
    views to come (None), and they reach `measure_heights` between the ticks."""
    rec = short_recording("translate")
    images = [img for _, (_, img) in zip(range(4), open_footage(rec).frames(), strict=False)]
    side = FurtherCamera("side", read_camera(rec / "camera.json"), lambda: RecordedFrames(images))
    compute = compute_on(rec, other_cameras=(side,))
    given: list[tuple[float, Sequence[PairedView | None] | None]] = []
    later: list[Sequence[PairedView | None]] = []
    track = compute.tracker.track

    def seen(image: np.ndarray, frame_t_s: float, commands: ModuleCommands | None, views: Any = ()) -> Any:
        given.append((frame_t_s, views))
        # One view: what the tracker does with two is not tested here.
        return track(image, frame_t_s, commands, None if views is None else ())

    monkeypatch.setattr(compute.tracker, "track", seen)
    monkeypatch.setattr(compute.tracker.second_view, "awaits_pair", lambda t_s, views: False)
    monkeypatch.setattr(compute.tracker, "measure_heights", later.append)
    stopped = ModuleCommands.all_stop(compute.spec.layout.n_modules)
    replies = [
        tick(compute, TickRequest(Setpoint("idle", None), stopped, reset=False, want_view=False))
        for _ in range(4)
    ]
    assert len(given) == 4
    (begun_t_s, begun_views), *tracked = given
    assert begun_views is not None and len(begun_views) == 1 and begun_views[0] is not None
    assert begun_views[0].image.shape == images[0].shape and begun_views[0].t_s >= begun_t_s
    assert "pair_wait" in replies[0].timing_s
    assert all(views is None for _, views in tracked)  # once tracking, no tick waits for the pair
    assert len(later) == 3 and all(len(views) == 1 for views in later)
    for (frame_t_s, _), (view,) in zip(tracked, later, strict=True):
        assert view is not None and view.t_s >= frame_t_s  # the side camera's frame, taken after
    assert all("pair_wait" not in r.timing_s for r in replies[1:])
    (report,) = replies[-1].cameras
    assert report.health.healthy and report.pairing.paired_pct is not None  # a frame for each of four
    assert report.pairing.skew_ms is not None and report.pairing.skew_ms >= 0


def test_once_tracking_a_frame_is_not_waited_for_and_is_paired_once_its_pair_has_arrived() -> None:
    clock = Clock()
    cam = ScheduledFrames(clock, _grid(0.012))  # arrives 12 ms after the first camera's
    pairing = FramePairing([cam], MAX_SKEW_S, clock)
    _first_frames(pairing, clock, _grid(0.0, 10)[1:])  # the period learnt
    waited = len(cam.waited_s)
    t0 = 10 * PERIOD_S
    clock.now_s = t0 + 0.001
    assert pairing.to_track(t0, begins=False) is None  # tracked at once
    assert pairing.due(t0) and pairing.later_views() is None  # its pair is still to come
    clock.now_s = t0 + 0.013
    paired = pairing.later_views()
    assert paired is not None and paired[0] == t0
    views = paired[1]
    assert views[0] is not None and views[0].t_s == pytest.approx(t0 + 0.012)
    assert pairing.later_views() is None  # paired once
    assert len(cam.waited_s) == waited  # and never waited for
    assert pairing.stats()[0].skew_ms == pytest.approx(12.0)
    # When tracking begins, the pair is waited for, as `views` does.
    t1 = 11 * PERIOD_S
    clock.now_s = t1 + 0.001
    (view,) = pairing.to_track(t1, begins=True) or [None]
    assert view is not None and view.t_s == pytest.approx(t1 + 0.012)
    assert cam.waited_s[-1] == pytest.approx(0.011) and pairing.later_views(wait=True) is None


def test_a_pair_that_does_not_come_is_paired_with_what_there_is_after_the_bound() -> None:
    clock = Clock()
    arrivals = _grid(0.012)
    del arrivals[10]  # frame 10's never comes
    cam = ScheduledFrames(clock, arrivals)
    pairing = FramePairing([cam], MAX_SKEW_S, clock)
    _first_frames(pairing, clock, _grid(0.0, 10)[1:])  # 8 of 9 paired: the first, before the period
    t0 = 10 * PERIOD_S
    clock.now_s = t0 + 0.001
    pairing.to_track(t0, begins=False)
    clock.now_s = t0 + 0.019
    assert pairing.later_views() is None  # still due within the bound
    clock.now_s = t0 + MAX_SKEW_S + 0.001
    paired = pairing.later_views()
    assert paired is not None and paired[0] == t0
    views = paired[1]
    assert views[0] is not None  # the frame before: the tracker refuses it
    assert views[0].t_s == pytest.approx(0.012 + 9 * PERIOD_S)
    assert pairing.stats()[0].paired_pct == pytest.approx(100 * 8 / 10)
    # A frame still unpaired when the next is tracked is paired then, with what there is: counted once.
    t1 = 11 * PERIOD_S
    clock.now_s = t1 + 0.001
    pairing.to_track(t1, begins=False)
    clock.now_s = t1 + PERIOD_S + 0.001
    pairing.to_track(t1 + PERIOD_S, begins=False)
    assert pairing.stats()[0].paired_pct == pytest.approx(100 * 9 / 11)
    assert len(cam.waited_s) == 8  # only the first-camera frames paired with `views` waited


def test_each_recorded_frame_keeps_the_views_it_was_tracked_with(
    short_recording: Callable[[str], Path], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Through the compute as it serves ticks: the pair waited for as tracking begins, then pairs made
    between the ticks, each written after a reply under its frame's index (the last as recording stops)."""
    rec = short_recording("translate")
    images = [img for _, (_, img) in zip(range(4), open_footage(rec).frames(), strict=False)]
    side = FurtherCamera("side", read_camera(rec / "camera.json"), lambda: RecordedFrames(images))
    compute = compute_on(rec, other_cameras=(side,), max_record_bytes=100_000_000)
    track = compute.tracker.track

    def one_view(
        image: np.ndarray, frame_t_s: float, commands: ModuleCommands | None, views: Any = ()
    ) -> Any:
        return track(image, frame_t_s, commands, None if views is None else ())  # the plumbing only

    monkeypatch.setattr(compute.tracker, "track", one_view)
    monkeypatch.setattr(compute.tracker.second_view, "awaits_pair", lambda t_s, views: False)
    monkeypatch.setattr(compute.tracker, "measure_heights", lambda views: None)
    stopped = ModuleCommands.all_stop(compute.spec.layout.n_modules)
    out = tmp_path / "session"
    for k in range(5):
        start, stop = (out if k == 0 else None), k == 4
        req = TickRequest(Setpoint("idle", None), stopped, False, False, record_start=start, record_stop=stop)
        tick(compute, req)
    with (out / "frames.csv").open() as f:
        first_s = [float(line.split(",")[1]) for line in f.readlines()[1:]]
    with (out / "cameras" / "side" / "frames.csv").open() as f:
        rows = [(int(i), float(t)) for i, t in (line.split(",") for line in f.readlines()[1:])]
    assert len(first_s) == 4 and [i for i, _ in rows] == [0, 1, 2, 3]
    assert all(t_s >= first_s[i] for i, t_s in rows)  # each the side camera's frame taken after its own
    assert len(list((out / "cameras" / "side" / "frames").glob("*.png"))) == 4
