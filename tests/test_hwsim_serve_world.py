"""`hwsim serve`'s world thread takes what each frame sees holding the world's lock, as the HTTP handlers
hold it to push or lay the cloth: a push must not land between a step and its exposure. Pushes sent
meanwhile leave the world thread running and the frames coming; a world thread that fails says so to
whoever runs the cell (`hwsim serve` ends with the error)."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest
from small_scenarios import two_cameras

import hwsim.serve
from hwsim import scenario as scenarios
from hwsim.scenario import Push
from hwsim.serve import Cell

pytestmark = pytest.mark.clock_free

FRAMES = 12


def _cell(state_dir: Path) -> Cell:
    return Cell(scenarios.parse(two_cameras(name="served", duration_s=3600.0)), state_dir, camera_fps=15.0)


def test_frames_are_taken_under_the_worlds_lock_while_pushes_come(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cell = _cell(tmp_path / "state")
    held: list[bool] = []
    taken = threading.Event()
    frame_states = hwsim.serve.frame_states

    def watched(world: Any, skew_s: float = 0.0) -> Any:
        if threading.current_thread().name == "world":
            held.append(cell.lock.locked())
            if len(held) >= FRAMES:
                taken.set()
        return frame_states(world, skew_s)

    monkeypatch.setattr(hwsim.serve, "frame_states", watched)
    cell.start()
    try:
        assert all(camera._proc.is_alive() for camera in cell.cameras)
        first = cell.streams[0].frame
        push = Push.model_validate({"at_m": [-0.03, 0.02], "direction_rad": 1.0, "slack_m": 0.004})
        while not taken.wait(0.05):
            assert cell._thread.is_alive(), "the world thread died"
            with cell.lock:  # as the HTTP handler for POST /cloth/push does
                cell.world.push(push)
        assert cell._thread.is_alive()
        last = cell.streams[0].frame
    finally:
        cell.stop()
    assert len(held) >= FRAMES and all(held)
    assert first is not None and last is not None and last.index > first.index  # the frames came
    assert not any(camera._proc.is_alive() for camera in cell.cameras)  # stopped with the cell


def test_a_world_thread_that_fails_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cell = _cell(tmp_path / "state")
    died: list[BaseException] = []
    ended = threading.Event()

    def world_died(err: BaseException) -> None:
        died.append(err)
        ended.set()

    def broken() -> None:
        raise RuntimeError("a world bug")

    cell.world_died = world_died
    monkeypatch.setattr(cell.world, "step", broken)
    cell.start()
    try:
        assert ended.wait(30), "the world thread's failure was not reported"
    finally:
        cell.stop()
    assert [str(err) for err in died] == ["a world bug"]
