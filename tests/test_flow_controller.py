"""The flow controller, pure, on a 12 x 6 table: the intake, each module to at most one piece, flatten then
place then leave in turn, the way kept clear, the exit, and a piece that cannot be flattened rejected."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_cell_controller import _nodes

from clothd.config import CellConfig, ControlConfig, FlowConfig
from clothd.core.control import PoseController
from clothd.core.conveyor import ConveyorLayout
from clothd.core.ekf import UpdateStats
from clothd.core.flow import FlowController
from clothd.core.messages import Estimate
from clothd.core.modes import PieceState
from clothd.core.pieces import Piece
from clothd.core.workspace import Workspace, cloth_corners_m

pytestmark = pytest.mark.clock_free

CELL = CellConfig(modules_x=12, modules_y=6)
LAYOUT = ConveyorLayout.of_cell(CELL)
SIZE_M = (0.25, 0.20)
NX, NY = 12, 12
DT_S = 1 / 30
FLOW = FlowConfig()


def _controller() -> FlowController:
    return FlowController(
        FLOW, ControlConfig(), CELL, LAYOUT, Workspace.of_cell(CELL), DT_S, 0.05, estimates_shape=True
    )


def _estimate(pose: tuple[float, float, float], ridge: bool = False, t_s: float = 0.0) -> Estimate:
    """A tracked piece at pose; with a ridge, one column of edges 40 % short and raised 10 mm."""
    p = np.array(pose)
    nodes = _nodes(p, ridge)
    return Estimate(
        frame_t_s=t_s,
        status="tracking",
        pose=p,
        pose_cov=np.eye(3) * 1e-8,
        nodes_m=nodes,
        outline_m=cloth_corners_m(p, SIZE_M),
        cloth_size_m=SIZE_M,
        feature_id=np.zeros(0, int),
        meas_px=np.zeros((0, 2)),
        pred_px=np.zeros((0, 2)),
        stats=UpdateStats(0, 0, 0.0),
    )


def _tracked(pid: int, pose: tuple[float, float, float], state: PieceState, ridge: bool = False) -> Piece:
    est = _estimate(pose, ridge)
    return Piece(pid, state, 0.0, est.outline_m, 0.0, est, slot=pid, tracked_since_s=0.0)  # type: ignore[arg-type]


def _under(outline_m: np.ndarray, margin_m: float | None = None) -> np.ndarray:
    return PoseController(ControlConfig(), CELL, LAYOUT.centres_m).modules_under(outline_m, margin_m)


def test_an_entering_piece_is_pulled_in_by_the_belts_under_it_alone_until_all_of_it_is_in() -> None:
    flow = _controller()
    outline = cloth_corners_m(np.array([-0.45, 0.0, 0.0]), SIZE_M)  # half of it still off the table
    outline[:, 0] = np.maximum(outline[:, 0], -0.46)  # what the camera sees of it
    piece = Piece(0, PieceState.ENTERING, 0.0, outline, 0.0)
    under = _under(outline)
    assert under.any() and not under.all()
    commands, gone = flow.step([piece], 0.0)
    assert not gone
    assert np.allclose(commands.speed_m_s[under], FLOW.intake_speed_m_s)
    assert np.allclose(np.cos(commands.heading_rad[under]), 1.0)  # +x
    assert not commands.speed_m_s[~under].any()
    assert piece.outline_m[:, 0].min() > outline[:, 0].min()  # it moves on with its belts
    piece.outline_m = cloth_corners_m(np.array([-0.25, 0.0, 0.0]), SIZE_M)  # all of it in
    commands, _ = flow.step([piece], DT_S)
    assert not commands.speed_m_s.any()  # stilled for its tracking to start


def test_a_flat_piece_is_flattened_then_placed_once_the_piece_ahead_is_driven_out() -> None:
    flow = _controller()
    behind = _tracked(1, (-0.25, 0.0, 0.0), PieceState.TRACKED)
    ahead = _tracked(0, (0.10, 0.0, 0.0), PieceState.FLATTENING)
    t_s = 0.0
    while t_s < FLOW.flat_for_s + 0.5:
        flow.step([ahead, behind], t_s)
        t_s += DT_S
    assert behind.state == PieceState.FLATTENING  # flat, but the piece ahead stands in the way
    ahead.enter(PieceState.LEAVING, t_s)
    ahead.estimate = _estimate((0.40, 0.0, 0.0), t_s=t_s)  # its trailing edge 30 mm short of the way
    ahead.outline_m = ahead.estimate.outline_m  # type: ignore[assignment]
    flow.step([ahead, behind], t_s)
    assert behind.state == PieceState.FLATTENING
    ahead.estimate = _estimate((0.44, 0.0, 0.0), t_s=t_s)  # ... and 10 mm past it
    ahead.outline_m = ahead.estimate.outline_m  # type: ignore[assignment]
    flow.step([ahead, behind], t_s)
    assert behind.state == PieceState.PLACING
    commands, _ = flow.step([ahead, behind], t_s + DT_S)
    under_behind = _under(behind.outline_m)
    assert (np.cos(commands.heading_rad[under_behind]) > 0.9).all()  # towards the placement, +x


def test_each_module_goes_to_at_most_one_piece_and_the_modules_between_them_stop() -> None:
    flow = _controller()
    leaving = _tracked(0, (0.16, 0.0, 0.0), PieceState.LEAVING)
    held = _tracked(1, (0.16 - SIZE_M[0] - 0.02, 0.0, 0.0), PieceState.FLATTENING)  # 20 mm behind it
    commands, _ = flow.step([leaving, held], 0.0)
    commands, _ = flow.step([leaving, held], DT_S)
    out, hold = _under(leaving.outline_m), _under(held.outline_m)
    assert out.any() and hold.any() and not (out & hold).any()
    # A piece driven out runs on every belt that reaches under it, not only those it covers the centre
    # of: a stopped belt under its edge brakes it.
    touched = _under(leaving.outline_m, margin_m=-CELL.module_size_m / 2)
    assert (touched & ~out & ~hold).any()
    assert (commands.speed_m_s[touched & ~hold] > 0).all()
    assert np.allclose(commands.speed_m_s[hold], 0.0, atol=1e-3)  # flat and held: no motion
    assert not commands.speed_m_s[~(touched | hold)].any()
    # Outlines that overlap: the modules under both stop.
    overlapping = _tracked(2, (0.16 - 0.1, 0.0, 0.0), PieceState.LEAVING)
    both = out & _under(overlapping.outline_m)
    assert both.any()
    commands, _ = flow.step([leaving, overlapping], 2 * DT_S)
    assert not commands.speed_m_s[both].any()


def test_a_leaving_piece_is_let_go_once_its_centre_is_over_the_outfeed_edge() -> None:
    flow = _controller()
    piece = _tracked(0, (0.40, 0.0, 0.0), PieceState.LEAVING)
    _, gone = flow.step([piece], 0.0)
    assert not gone and piece.state == PieceState.LEAVING
    piece.estimate = _estimate((flow.exit_x_m + 0.005, 0.0, 0.0), t_s=1.0)
    piece.outline_m = piece.estimate.outline_m  # type: ignore[assignment]
    _, gone = flow.step([piece], 1.0)
    assert gone == [piece] and piece.state == PieceState.LEFT and piece.left_s == 1.0


def test_a_piece_that_does_not_flatten_in_time_is_rejected_with_the_reason_and_driven_out() -> None:
    flow = _controller()
    piece = _tracked(0, (-0.2, 0.0, 0.0), PieceState.TRACKED, ridge=True)
    t_s = 0.0
    while piece.state != PieceState.REJECTED and t_s < FLOW.flatten_timeout_s + 1.0:
        piece.estimate = _estimate((-0.2, 0.0, 0.0), ridge=True, t_s=t_s)  # the ridge stays
        flow.step([piece], t_s)
        t_s += DT_S
    assert piece.state == PieceState.REJECTED
    assert piece.reason == f"not flat for {FLOW.flatten_timeout_s:g} s"
    assert t_s > FLOW.flatten_timeout_s
    for _ in range(10):
        commands, _ = flow.step([piece], t_s)
        t_s += DT_S
    under = _under(piece.outline_m)
    assert (commands.speed_m_s[under] > 0).all() and (np.cos(commands.heading_rad[under]) > 0.99).all()


def test_a_flat_piece_waiting_for_its_way_is_not_rejected_for_a_frame_read_not_flat() -> None:
    """Flat and held behind a piece that is not yet out of the way, past the flattening timeout: one
    frame read not flat (noise) is no reason to reject it; only a piece not flat for the whole timeout is."""
    flow = _controller()
    ahead = _tracked(0, (0.05, 0.0, 0.0), PieceState.FLATTENING, ridge=True)  # in the way, not leaving
    piece = _tracked(1, (-0.2, 0.0, 0.0), PieceState.TRACKED)
    t_s = 0.0
    while t_s < FLOW.flatten_timeout_s + 2.0:
        noisy = abs(t_s - (FLOW.flatten_timeout_s + 1.0)) < DT_S / 2  # one frame reads a ridge
        piece.estimate = _estimate((-0.2, 0.0, 0.0), ridge=noisy, t_s=t_s)
        ahead.estimate = _estimate((0.05, 0.0, 0.0), ridge=True, t_s=t_s)
        flow.step([ahead, piece], t_s)
        t_s += DT_S
    assert piece.state == PieceState.FLATTENING  # still waiting for its way, not rejected
    assert ahead.state == PieceState.REJECTED and ahead.reason == f"not flat for {FLOW.flatten_timeout_s:g} s"


def test_stop_stops_every_module() -> None:
    flow = _controller()
    piece = _tracked(0, (0.2, 0.0, 0.0), PieceState.LEAVING)
    for k in range(5):
        commands, _ = flow.step([piece], k * DT_S)
    assert commands.speed_m_s.any()
    assert not flow.stop().speed_m_s.any()


def test_a_folded_over_corner_is_rejected_as_such_and_driven_out_once_the_way_is_clear() -> None:
    """A flap (cloth missing at a corner where the estimate puts it) seen for flap_for_s: rejected with the
    reason, held while a piece ahead is in the way, then driven out."""
    flow = _controller()
    seen = np.ones((NY - 1, NX - 1), bool)
    seen[:3, :3] = False  # the -s-t corner folded over: the belts show there

    def folded(t_s: float) -> Estimate:
        return dataclasses.replace(_estimate((-0.25, 0.0, 0.0), t_s=t_s), quad_seen=seen)

    piece = _tracked(0, (-0.25, 0.0, 0.0), PieceState.TRACKED)
    ahead = _tracked(1, (0.15, 0.0, 0.0), PieceState.FLATTENING, ridge=True)  # not flat: it stays
    t_s = 0.0
    while piece.state != PieceState.REJECTED and t_s < FLOW.flap_for_s + 1.0:
        piece.estimate = folded(t_s)
        flow.step([piece, ahead], t_s)
        t_s += DT_S
    assert piece.state == PieceState.REJECTED and piece.reason == "a corner is folded over"
    assert FLOW.flap_for_s <= t_s < FLOW.flap_for_s + 0.2
    commands, _ = flow.step([piece, ahead], t_s)
    assert not commands.speed_m_s[_under(piece.outline_m)].any()  # the piece ahead is not driven out yet
    ahead.enter(PieceState.LEAVING, t_s)
    ahead.estimate = _estimate((0.44, 0.0, 0.0), t_s=t_s)
    ahead.outline_m = ahead.estimate.outline_m  # type: ignore[assignment]
    for _ in range(10):
        t_s += DT_S
        piece.estimate = folded(t_s)
        commands, _ = flow.step([piece, ahead], t_s)
    under = _under(piece.outline_m)
    assert (commands.speed_m_s[under] > 0).all() and (np.cos(commands.heading_rad[under]) > 0.99).all()
