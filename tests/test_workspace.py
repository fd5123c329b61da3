"""The workspace: an outline past its edge may still be moved back in, never further out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from clothd.core.workspace import Workspace, cloth_corners_m, rigid_step

pytestmark = pytest.mark.clock_free

BOX = Workspace(-0.3, 0.3, -0.2, 0.2)
SIZE_M = (0.25, 0.20)
DT_S = 1 / 30


def test_excess_is_how_far_each_point_lies_outside() -> None:
    points = np.array([[0.0, 0.0], [0.31, 0.0], [0.0, -0.23], [0.33, 0.24]])
    np.testing.assert_allclose(BOX.excess_m(points), [0.0, 0.01, 0.03, math.hypot(0.03, 0.04)])


def test_a_rigid_step_turns_about_the_centre_then_moves() -> None:
    points = np.array([[1.0, 0.0]])
    moved = rigid_step(points, np.zeros(2), np.array([0.0, 0.3, math.pi / 2]), 1.0)
    np.testing.assert_allclose(moved, [[0.0, 1.3]], atol=1e-12)


@pytest.mark.parametrize(
    ("twist", "back"),
    [
        ([0.0, -0.01, 0.0], True),  # inward, slowly: the first tick after a halt
        ([-0.05, -0.05, 0.0], True),  # towards the centre
        ([0.0, 0.01, 0.0], False),  # further out
        ([0.05, 0.0, 0.0], False),  # along the edge: no closer
        ([0.0, 0.0, 0.0], False),  # holding still past the edge
    ],
)
def test_an_outline_past_the_edge_comes_back_only_when_moved_inward(twist: list[float], back: bool) -> None:
    pose = np.array([0.05, 0.103, 0.0])  # its top edge 3 mm past y = 0.2
    outline = cloth_corners_m(pose, SIZE_M)
    assert BOX.leaves(outline) is not None
    assert BOX.comes_back(outline, pose, np.array(twist), DT_S) is back


def test_a_turn_that_swings_a_corner_further_out_does_not_come_back() -> None:
    pose = np.array([0.0, 0.103, 0.0])
    outline = cloth_corners_m(pose, SIZE_M)
    # Inward by 0.1 mm a tick, but turning 0.5 rad/s lifts one top corner 2 mm a tick (the other sinks).
    assert not BOX.comes_back(outline, pose, np.array([0.0, -0.003, 0.5]), DT_S)
