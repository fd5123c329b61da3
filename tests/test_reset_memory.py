"""Resets free what they allocate: the compute process, re-initialising tracking on the live path
(Compute.tick with reset requests, frames from a FrameSource), does not grow. Each reset used to build a
new MassSpring with new Taichi fields (and a kernel compiled for them): about 2.2 MB a reset, so the 50
resets here would have grown it by some 110 MB. `clothd bench faults` measures the issue's 500."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from recorded_frames import compute_on, tick

from clothd.core.control import Setpoint
from clothd.core.messages import ModuleCommands
from clothd.loop.compute_messages import TickRequest
from clothd.tools.procfs import rss_mb

pytestmark = pytest.mark.clock_free

RESETS = 60
ALLOWED_GROWTH_MB = 20.0


def test_resets_do_not_grow_the_compute(short_recording: Callable[[str], Path]) -> None:
    compute = compute_on(short_recording("translate"))
    idle = Setpoint("idle", None)
    stopped = ModuleCommands.all_stop(compute.spec.layout.n_modules)
    rss: dict[int, float] = {}
    for k in range(1, RESETS + 1):
        tick(compute, TickRequest(idle, stopped, reset=True, want_view=False))  # re-initialises
        reply = tick(compute, TickRequest(idle, stopped, reset=False, want_view=False))  # tracks
        assert reply.estimate is not None and reply.estimate.tracking and reply.estimate.nodes_m is not None
        if k in (10, RESETS):
            rss[k] = rss_mb()
    growth = rss[RESETS] - rss[10]
    print(f"RSS after 10 resets {rss[10]:.1f} MB, after {RESETS} {rss[RESETS]:.1f} MB (+{growth:.1f} MB)")
    assert growth < ALLOWED_GROWTH_MB
