"""Pieces touching (docs/flow.md, "Pieces touching"): two pieces laid edge to edge on hwsim's flow table,
rendered as its camera sees them, come as one region. Beside a tracked piece, the other is told apart
and held; neither tracked, they are rejected as touching rather than tracked as one piece."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_flow_controller import _controller, _tracked
from test_pieces import GAP_M, SIZE_M, _flat_piece

from clothd.config import load_config
from clothd.core.conveyor import ConveyorLayout
from clothd.core.modes import PieceState
from clothd.core.pieces import TOUCHING, Piece, PieceTracking
from clothd.core.segmentation import find_cloths
from clothd.core.tracker import Tracker
from clothd.core.workspace import Workspace
from clothd.taichi_runtime import start_taichi
from clothd.tools.lockstep import scenario_cameras
from clothd.tools.lockstep_flow import LockstepFlow, config_for, flow_scenario
from hwsim import scenario as scenarios
from hwsim.infeed import fabric_spec
from hwsim.pieces import Piece as HwPiece
from hwsim.scenario import Pose
from hwsim.scene import SceneCloth
from hwsim.world import World

pytestmark = pytest.mark.clock_free

LONG_M = 0.25  # test_pieces' pieces: 0.25 x 0.20, their long side along x
CENTRES_M = (-LONG_M / 2, LONG_M / 2)  # edge to edge at x = 0


def _render(world: World, sensor: object, spacing_m: float, centres_m: tuple[float, float]) -> np.ndarray:
    cloths = tuple(SceneCloth(_flat_piece(x, spacing_m), (spacing_m, spacing_m)) for x in centres_m)
    image, _ = sensor.renderer.render([dataclasses.replace(world.scene_state(), cloths=cloths)])  # type: ignore[attr-defined]
    return np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def frames() -> tuple[np.ndarray, np.ndarray, object, object]:
    """The flow table's top camera's frames of two pieces edge to edge and GAP_M apart, the configuration
    and the camera's model."""
    cfg = load_config(None)
    start_taichi(cfg.taichi.arch)
    sc = flow_scenario(6.0, 0)
    world = World(sc, log_commands=False)
    sensors, models = scenario_cameras(sc, world, 1)
    apart = (CENTRES_M[0] - GAP_M / 2, CENTRES_M[1] + GAP_M / 2)
    together = _render(world, sensors[0], sc.cloth.spacing_m, CENTRES_M)
    return together, _render(world, sensors[0], sc.cloth.spacing_m, apart), config_for(cfg, sc), models[0]


@pytest.fixture(scope="module")
def touching(frames: tuple) -> tuple[np.ndarray, object, object]:
    together, _, cfg, model = frames
    return together, cfg, model


def test_two_pieces_touching_come_as_one_region(touching: tuple) -> None:
    image, _, _ = touching
    assert len(find_cloths(image)) == 1  # what the rest is about


def test_a_piece_touching_a_tracked_one_is_told_apart_and_held_not_started(touching: tuple) -> None:
    image, cfg, model = touching
    tracking = PieceTracking(cfg.flow, model, Workspace.of_cell(cfg.cell), lambda: None)  # type: ignore[arg-type, return-value]
    tracked = _tracked(0, (CENTRES_M[0], 0.0, 0.0), PieceState.FLATTENING)
    tracking.pieces.append(tracked)
    tracking._next_id = 1
    regions = find_cloths(image)
    for k in range(2):  # the second look sees it still
        tracking._look(regions, image.shape, 1.0 + k)
    others = [p for p in tracking.pieces if p is not tracked]
    assert len(others) == 1
    other = others[0]
    # Its own outline (less the margin at the seam), not the merged region's nor a stale one.
    x_lo, x_hi = float(other.outline_m[:, 0].min()), float(other.outline_m[:, 0].max())
    assert 0.0 < x_lo < 0.015 and abs(x_hi - LONG_M) < 0.005
    assert other.beside and other.slot is None and other.region is None  # held: its tracking not started
    assert other.state == PieceState.ENTERING and not tracking.gone


def test_two_untracked_pieces_touching_are_rejected_not_tracked_as_one(touching: tuple) -> None:
    image, cfg, model = touching
    layout = ConveyorLayout.of_cell(cfg.cell)
    tracking = PieceTracking(
        cfg.flow, model, Workspace.of_cell(cfg.cell), lambda: Tracker(cfg.tracker, model, layout)
    )
    for k in range(2 * cfg.flow.search_every + 2):
        tracking.track(image, k * cfg.loop.period_s, None)
        tracking.upkeep()
    assert len(tracking.pieces) == 1
    piece = tracking.pieces[0]
    assert piece.slot is None and not piece.tracking
    assert piece.state == PieceState.REJECTED
    assert piece.reason is not None and piece.reason.startswith(TOUCHING)


def test_pieces_that_come_together_are_one_piece_counted_once(frames: tuple) -> None:
    """Seen apart, then as one region (laid edge to edge): one is let go as merged, the other stands for
    both and, larger than a piece, is rejected once still; no piece is left to be lost from view."""
    together, apart, cfg, model = frames
    tracking = PieceTracking(cfg.flow, model, Workspace.of_cell(cfg.cell), lambda: None)  # type: ignore[arg-type, return-value]
    tracking._look(find_cloths(apart), apart.shape, 0.0)
    assert len(tracking.pieces) == 2
    for k in range(3):
        tracking._look(find_cloths(together), together.shape, 1.0 + k)
    assert [(p.id, p.state) for p in tracking.pieces] == [(0, PieceState.REJECTED)]
    assert tracking.pieces[0].reason is not None and tracking.pieces[0].reason.startswith(TOUCHING)
    assert [(p.id, p.reason) for p in tracking.gone] == [(1, f"{TOUCHING}: merged into piece 0")]


def test_an_entering_piece_beside_a_tracked_one_gets_no_intake() -> None:
    ctl = _controller()
    outline = np.array([[-0.55, -0.1], [-0.35, -0.1], [-0.35, 0.1], [-0.55, 0.1]])
    entering = Piece(1, PieceState.ENTERING, 0.0, outline, 0.0)
    commands, _ = ctl.step([entering], 0.0)
    assert commands.speed_m_s.max() > 0.0  # pulled in
    entering.beside = True
    commands, _ = ctl.step([entering], 0.0)
    assert commands.speed_m_s.max() == 0.0  # held, its outline where it was
    assert np.allclose(entering.outline_m, outline + np.array([0.1 / 30, 0.0]))


def test_a_reject_never_tracked_is_driven_out_as_it_is_once_its_way_is_clear() -> None:
    ctl = _controller()
    outline = np.array([[-0.3, -0.1], [0.2, -0.1], [0.2, 0.1], [-0.3, 0.1]])
    touching = Piece(0, PieceState.REJECTED, 0.0, outline, 0.0, reason=f"{TOUCHING}: 500 x 200 mm")
    ahead = _tracked(1, (0.35, 0.0, 0.0), PieceState.FLATTENING)
    commands, _ = ctl.step([touching, ahead], 0.0)
    assert not touching.driven_out  # held while a piece ahead is not driven out
    speeds = []
    for k in range(10):
        commands, _ = ctl.step([touching], (k + 1) / 30)
        speeds.append(float(commands.speed_m_s.max()))
    assert touching.driven_out and speeds[0] > 0.0 and speeds == sorted(speeds)
    assert touching.outline_m[:, 0].min() > -0.3


@pytest.mark.slow
def test_two_pieces_laid_touching_go_out_together_as_a_reject_in_lockstep() -> None:
    """hwsim's flow table with a second piece laid by hand edge to edge behind piece 0, both partly over
    the infeed edge: the cell rejects them as touching and drives them out together; before, it tracked
    one mesh over both, placed it, and let it go with the second piece left lying at the outfeed edge."""
    cfg = load_config(None)
    data = flow_scenario(6.0, 0).model_dump()
    data["infeed"]["first_s"] = 3000.0  # no infeed piece: only the two laid here
    sc = scenarios.parse(data, "flow")
    run = LockstepFlow(cfg, sc, cameras=1)
    world = run.world
    x_min = float(world.pieces[0].cloth.positions_m()[..., 0].min())
    spec = fabric_spec(sc.cloth, "denim", SIZE_M)
    pose = Pose(x_m=x_min - SIZE_M[0] / 2, y_m=0.0, theta_rad=0.0)
    cloth = world.pool.take(spec, pose, 7, world.table.heading_rad)
    world.pieces.append(HwPiece(1, cloth, "denim", 1, world.t_s))
    run.run(16.0)
    assert world.pieces == [] and len(world.outfeed) == 2  # both taken off over the outfeed edge
    let_go = list(run.cell.tracking.gone)
    assert let_go and all(p.reason is not None and p.reason.startswith(TOUCHING) for p in let_go)
    assert all(p.tracked_since_s is None for p in let_go)  # never tracked as one piece
