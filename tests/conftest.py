"""Shared fixtures: short recordings of the shipped scenarios, made once per test session; and, per test
module that asks, a live simulated cell (`hwsim serve`) with the daemon running against it."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from live_cell import Cell, Daemon, serve_cell, start_daemon

from hwsim import scenario as scenarios
from hwsim.recording import record

# Long enough to hold at least three 10-frame verify gaps, and for occlude the arm coming and going.
SHORT_DURATION_S = {
    "translate": 1.0,
    "rotate": 1.0,
    "compress": 1.0,
    "occlude": 2.4,
    "random": 1.0,
    # Hard footage: a second of a plain twill turning under side light; the 200 mm/s run whole.
    "twill-turn-left": 1.0,
    "fast-200": 1.35,
    "gingham-fast": 1.0,  # the onset and 0.5 s at 4.5 px a frame
    "gingham-push": 1.0,  # the push's first 0.8 s: where the prediction runs a check ahead of the cloth
}


@pytest.fixture(scope="session")
def short_recording(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    made: dict[str, Path] = {}

    def get(name: str) -> Path:
        if name not in made:
            out = tmp_path_factory.mktemp(f"rec_{name}")
            record(scenarios.load(name, duration_s=SHORT_DURATION_S[name]), out)
            made[name] = out
        return made[name]

    return get


cell = pytest.fixture(scope="module", name="cell")(serve_cell)


@pytest.fixture(scope="module")
def daemon(cell: Cell, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    d = start_daemon(cell, tmp_path_factory.mktemp("daemon"))
    yield d
    d.stop()
