"""Seeded starting states for `clothd bench flatten`: the cloth anywhere on the table at any angle, one or
two ridges at random positions (through the middle of the cloth) and in random directions, and a move
target 100 mm and 30° away.

Ridges are given as hand pushes in the cloth's frame (s along its long side, t across, metres from its
centre), so hwsim's hands make them on the tracked cloth (hwsim's POST /cloth/push). The sizes come from
hwsim's live cell (hwsim/scenarios/cell.yaml) and the daemon's default workspace; a start whose cloth or
target would leave the workspace (with room for a ridge's slack to come out) is drawn again.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from clothd.config import CellConfig
from clothd.core.workspace import Workspace
from hwsim import scenario as scenarios

MOVE_OFFSET_M = 0.10
MOVE_TURN_RAD = math.radians(30.0)
SLACK_M = (0.002, 0.014)  # pushed-in slack: ridges of about 5-20 mm
LAID_HEIGHT_M = (0.005, 0.020)  # ridges laid before tracking begins (--start laid)
LAID_SIGMA_M = 0.012  # their Gaussian width (hwsim's default), widened where a ridge would overhang
LAID_WIDTH_PER_HEIGHT = 0.66  # hwsim lays no ridge narrower than 0.65 x its height (it would overhang)
RIDGE_INSET_M = 0.06  # a ridge's line passes this far inside the cloth's edges (docs/benchmarks.md)
RIDGES_APART_M = 0.065  # a second push's hands (reach 45 mm) stay off the first ridge (about 20 mm wide)
FLATTEN_ROOM_M = 0.02  # the outline grows by the slack pulled out: keep this clear of the workspace's edge
_TRIES = 200


def cloth_half_m() -> tuple[float, float]:
    """Half the live cell cloth's sides (s, t), metres."""
    s, t = scenarios.load("cell").cloth.size_m
    return s / 2, t / 2


def _fits(pose: tuple[float, float, float], half: tuple[float, float], ws: Workspace, room_m: float) -> bool:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    for ds, dt in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        x = pose[0] + c * ds * half[0] - s * dt * half[1]
        y = pose[1] + s * ds * half[0] + c * dt * half[1]
        if not (
            ws.x_min_m + room_m <= x <= ws.x_max_m - room_m
            and ws.y_min_m + room_m <= y <= ws.y_max_m - room_m
        ):
            return False
    return True


def _line_in_cloth(at: np.ndarray, direction_rad: float, half: tuple[float, float]) -> np.ndarray:
    """Points along the part of the line that lies on the cloth, (n, 2), 1 mm apart."""
    u = np.array([math.cos(direction_rad), math.sin(direction_rad)])
    reach = math.hypot(*half)
    p = at + np.arange(-reach, reach, 0.001)[:, None] * u
    return p[(np.abs(p[:, 0]) <= half[0]) & (np.abs(p[:, 1]) <= half[1])]


def _push(rng: np.random.Generator, half: tuple[float, float]) -> dict[str, Any]:
    at = (rng.uniform(-1, 1) * (half[0] - RIDGE_INSET_M), rng.uniform(-1, 1) * (half[1] - RIDGE_INSET_M))
    return {
        "at_cloth_m": at,
        "direction_cloth_rad": rng.uniform(0, math.pi),
        "slack_m": rng.uniform(*SLACK_M),
    }


def _pushes(rng: np.random.Generator, half: tuple[float, float]) -> list[dict[str, Any]]:
    first = _push(rng, half)
    if rng.random() < 0.5:
        return [first]
    line = _line_in_cloth(np.asarray(first["at_cloth_m"]), first["direction_cloth_rad"], half)
    for _ in range(_TRIES):
        second = _push(rng, half)
        other = _line_in_cloth(np.asarray(second["at_cloth_m"]), second["direction_cloth_rad"], half)
        if np.min(np.linalg.norm(line[:, None] - other[None], axis=2)) >= RIDGES_APART_M:
            return [first, second]
    return [first]


def _pose_and_target(
    rng: np.random.Generator, half: tuple[float, float], ws: Workspace
) -> tuple[list[float], list[float]]:
    for _ in range(_TRIES):
        # A rectangle turned by theta + pi lies as one turned by theta, and the tracker frames a cloth by its
        # outline: these are all the placements.
        theta = rng.uniform(-math.pi / 2, math.pi / 2)
        pose = (rng.uniform(ws.x_min_m, ws.x_max_m), rng.uniform(ws.y_min_m, ws.y_max_m), theta)
        if not _fits(pose, half, ws, FLATTEN_ROOM_M):
            continue
        for _ in range(_TRIES):
            heading = rng.uniform(-math.pi, math.pi)
            turn = MOVE_TURN_RAD * rng.choice([-1.0, 1.0])
            target = (
                pose[0] + MOVE_OFFSET_M * math.cos(heading),
                pose[1] + MOVE_OFFSET_M * math.sin(heading),
                math.remainder(theta + turn, 2 * math.pi),
            )
            if _fits(target, half, ws, FLATTEN_ROOM_M):
                return list(pose), list(target)
    raise RuntimeError("no cloth pose with a reachable target fits the workspace")


def draw_start(rng: np.random.Generator) -> dict[str, Any]:
    """A seeded start: the cloth's pose, one or two ridge pushes (cloth frame), and the move's target."""
    half = cloth_half_m()
    pose, target = _pose_and_target(rng, half, Workspace.of_cell(CellConfig()))
    return {"pose": pose, "pushes": _pushes(rng, half), "target": target}


def laid_ridges(start: dict[str, Any], rng: np.random.Generator) -> list[dict[str, Any]]:
    """The start's ridges laid into the cloth before tracking begins (hwsim's Pose.ridges, cloth frame):
    along its pushes' lines, each of a height drawn from LAID_HEIGHT_M."""
    ridges = []
    for push in start["pushes"]:
        height = float(rng.uniform(*LAID_HEIGHT_M))
        ridges.append(
            {
                "height_m": height,
                "sigma_m": max(LAID_SIGMA_M, LAID_WIDTH_PER_HEIGHT * height),
                "at_m": list(push["at_cloth_m"]),
                "direction_rad": push["direction_cloth_rad"],
            }
        )
    return ridges
