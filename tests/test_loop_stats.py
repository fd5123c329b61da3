"""The loop's rolling figures: full garbage collections are timed (they hold the GIL, so the tick waits
them out), the others are not; the frame-to-command latency's tail is told apart into its parts."""

from __future__ import annotations

import gc
from collections.abc import Iterator

import pytest

from clothd.loop.loop_stats import LoopStats

pytestmark = pytest.mark.clock_free


@pytest.fixture
def stats() -> Iterator[LoopStats]:
    s = LoopStats()
    s.watch_full_collections()
    yield s
    gc.callbacks.remove(s._on_gc)


def test_full_collections_are_timed_and_partial_ones_are_not(stats: LoopStats) -> None:
    gc.collect(0)
    gc.collect(1)
    assert len(stats.gc_pause) == 0
    gc.collect()
    gc.collect(2)
    assert len(stats.gc_pause) == 2
    pause = stats.summary()["gc_pause"]
    assert isinstance(pause, dict) and pause["max_ms"] is not None and pause["max_ms"] >= 0.0


def test_no_collection_yet_reads_as_none() -> None:
    assert LoopStats().summary()["gc_pause"] == {
        "mean_ms": None,
        "p50_ms": None,
        "p99_ms": None,
        "max_ms": None,
    }


def test_the_latency_tail_is_split_into_its_parts() -> None:
    """95 frames arrive just after their tick asked and compute 9 ms; 5 arrive 20 ms before their tick
    asked and are computed only then: the tail says they waited, for their tick."""
    stats = LoopStats()
    for k in range(100):
        arrived = float(k)
        asked = arrived + (0.020 if k % 20 == 0 else -0.001)
        start = max(asked, arrived) + 0.0002
        stats.latency.add(arrived, asked, (start, start + 0.009), start + 0.009 + 0.0005)
    summary = stats.summary()
    tail = summary["frame_to_command_tail"]
    assert isinstance(tail, dict)
    assert tail["frames"] == 5
    assert tail["wait_ms"] == pytest.approx(20.2)
    assert tail["tick_ms"] == pytest.approx(20.0)
    assert tail["compute_ms"] == pytest.approx(9.0)
    assert tail["delivery_ms"] == pytest.approx(0.5)
    assert summary["frame_to_command"]["p50_ms"] == pytest.approx(9.7)  # type: ignore[index]


def test_a_frame_without_compute_times_counts_in_the_latency_not_its_tail() -> None:
    stats = LoopStats()
    stats.latency.add(0.0, None, None, 0.012)
    assert stats.summary()["frame_to_command_tail"] == {
        "frames": 0,
        "wait_ms": None,
        "compute_ms": None,
        "delivery_ms": None,
        "tick_ms": None,
    }
    assert stats.latency.total.summary()["max_ms"] == pytest.approx(12.0)
