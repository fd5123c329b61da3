"""The benches' reading of /proc: which spawned children a process has, by name."""

from __future__ import annotations

import multiprocessing
import os
from multiprocessing.synchronize import Event
from pathlib import Path

from clothd.tools.procfs import spawned_children


def _named(name: str, ready: Event, stop: Event) -> None:
    Path("/proc/self/comm").write_text(name)
    ready.set()
    stop.wait(30)


def test_spawned_children_are_found_by_their_names_and_only_the_spawned() -> None:
    ctx = multiprocessing.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    child = ctx.Process(target=_named, args=("clothd-probe", ready, stop))
    child.start()
    try:
        assert ready.wait(60) and child.pid is not None
        found = spawned_children(os.getpid())
        assert found.get(child.pid) == "clothd-probe"
        assert os.getpid() not in found  # itself is no child of its own
    finally:
        stop.set()
        child.join(10)
    assert child.pid not in spawned_children(os.getpid())  # gone
