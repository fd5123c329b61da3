"""clothd bench flatten's starts: seeded, on the table, ridges on the cloth, targets the move can reach."""

from __future__ import annotations

import math

import numpy as np
import pytest

from clothd.config import CellConfig
from clothd.core.workspace import Workspace
from clothd.tools.bench_flatten import laid_ridges_found
from clothd.tools.flatten_starts import (
    MOVE_OFFSET_M,
    MOVE_TURN_RAD,
    RIDGE_INSET_M,
    RIDGES_APART_M,
    SLACK_M,
    cloth_half_m,
    draw_start,
)

pytestmark = pytest.mark.clock_free


def _corners(pose: list[float], half: tuple[float, float]) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    local = np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)]) * half
    return pose[:2] + local @ np.array([[c, s], [-s, c]])


def test_the_same_seed_draws_the_same_start_and_another_draws_another() -> None:
    assert draw_start(np.random.default_rng([0, 3])) == draw_start(np.random.default_rng([0, 3]))
    assert draw_start(np.random.default_rng([0, 3])) != draw_start(np.random.default_rng([0, 4]))


def test_starts_lie_on_the_table_with_ridges_on_the_cloth_and_a_reachable_target() -> None:
    ws = Workspace.of_cell(CellConfig())
    half = cloth_half_m()
    starts = [draw_start(np.random.default_rng([7, k])) for k in range(60)]
    for start in starts:
        for pose in (start["pose"], start["target"]):
            xy = _corners(pose, half)
            assert (xy[:, 0] >= ws.x_min_m).all() and (xy[:, 0] <= ws.x_max_m).all()
            assert (xy[:, 1] >= ws.y_min_m).all() and (xy[:, 1] <= ws.y_max_m).all()
        offset = math.dist(start["pose"][:2], start["target"][:2])
        assert abs(offset - MOVE_OFFSET_M) < 1e-9
        turn = math.remainder(start["target"][2] - start["pose"][2], 2 * math.pi)
        assert abs(abs(turn) - MOVE_TURN_RAD) < 1e-9
        assert 1 <= len(start["pushes"]) <= 2
        for push in start["pushes"]:
            s, t = push["at_cloth_m"]
            assert abs(s) <= half[0] - RIDGE_INSET_M and abs(t) <= half[1] - RIDGE_INSET_M
            assert SLACK_M[0] <= push["slack_m"] <= SLACK_M[1]
    # Any angle, any direction, and both counts of ridges turn up.
    thetas = np.array([s["pose"][2] for s in starts])
    directions = np.array([p["direction_cloth_rad"] for s in starts for p in s["pushes"]])
    assert thetas.min() < -1.0 and thetas.max() > 1.0
    assert np.histogram(directions, bins=4, range=(0, math.pi))[0].min() > 0
    assert {len(s["pushes"]) for s in starts} == {1, 2}


def test_two_ridges_keep_apart() -> None:
    half = np.array(cloth_half_m())
    starts = [draw_start(np.random.default_rng([1, k])) for k in range(80)]
    pairs = [s["pushes"] for s in starts if len(s["pushes"]) == 2]
    assert pairs
    for first, second in pairs:
        # Each line's points on the cloth, 1 mm apart; the nearest pair is at least RIDGES_APART_M apart.
        lines = []
        for push in (first, second):
            u = np.array([math.cos(push["direction_cloth_rad"]), math.sin(push["direction_cloth_rad"])])
            p = np.asarray(push["at_cloth_m"]) + np.arange(-0.2, 0.2, 0.001)[:, None] * u
            lines.append(p[(np.abs(p) <= half).all(axis=1)])
        gap = np.linalg.norm(lines[0][:, None] - lines[1][None], axis=2).min()
        assert gap >= RIDGES_APART_M - 0.0015


def test_a_laid_ridge_is_found_by_a_reported_ridge_near_its_line_in_the_world() -> None:
    # Laid along the cloth's s axis, 30 mm up t, on a cloth turned 90°: in the world, the line x = 0.07.
    pose = [0.1, -0.05, math.pi / 2]
    laid = [
        {"height_m": 0.008, "at_m": [0.0, 0.03], "direction_rad": 0.0},
        {"height_m": 0.002, "at_m": [0.0, -0.03], "direction_rad": 0.0},  # too low to count
    ]
    near = {"x_m": 0.085, "y_m": 0.04}  # 15 mm off the line, anywhere along it
    far = {"x_m": 0.095, "y_m": -0.05}  # 25 mm off
    assert laid_ridges_found(pose, laid, [far, near]) == {"ridges_laid": 1, "ridges_found": 1}
    assert laid_ridges_found(pose, laid, [far]) == {"ridges_laid": 1, "ridges_found": 0}
