"""The loop's rolling figures: full garbage collections are timed (they hold the GIL, so the tick waits
them out), the others are not."""

from __future__ import annotations

import gc
from collections.abc import Iterator

import pytest

from clothd.loop_stats import LoopStats


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
