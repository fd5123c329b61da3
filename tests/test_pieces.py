"""Several pieces told apart: two flat pieces 20 mm apart on hwsim's flow table, rendered as its camera
sees them, are found as two, each given its own tracker once still, and tracked where hwsim put them."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from recorded_frames import RecordedFrames, tick

from clothd.config import Config, load_config
from clothd.core.camera_model import CameraModel
from clothd.core.control import Setpoint
from clothd.core.conveyor import ConveyorLayout
from clothd.core.flatness import Flatness
from clothd.core.flow_cell import FlowCell
from clothd.core.messages import ModuleCommands
from clothd.core.modes import LoopState, Mode, PieceState
from clothd.core.pieces import LOST_FROM_VIEW, MISSED_LOOKS, Piece, PieceTracking
from clothd.core.segmentation import find_cloths
from clothd.core.tracker import Tracker
from clothd.core.workspace import Workspace
from clothd.drivers.ports import CameraFrame
from clothd.loop.compute import Compute
from clothd.loop.compute_messages import ComputeSpec, TickRequest
from clothd.taichi_runtime import start_taichi
from clothd.tools.lockstep import scenario_cameras
from clothd.tools.lockstep_flow import config_for, flow_scenario
from hwsim.scene import SceneCloth
from hwsim.world import World

pytestmark = pytest.mark.clock_free

GAP_M = 0.020
FLAP_REASON = "a corner is folded over"
SIZE_M = (0.25, 0.20)


def _flat_piece(centre_x_m: float, spacing_m: float) -> np.ndarray:
    """A flat piece's nodes (ny, nx, 3), its s axis along x, centred at (centre_x_m, 0)."""
    nx, ny = round(SIZE_M[0] / spacing_m) + 1, round(SIZE_M[1] / spacing_m) + 1
    x = np.linspace(-SIZE_M[0] / 2, SIZE_M[0] / 2, nx) + centre_x_m
    y = np.linspace(-SIZE_M[1] / 2, SIZE_M[1] / 2, ny)
    xx, yy = np.meshgrid(x, y)
    return np.stack([xx, yy, np.zeros_like(xx)], axis=-1)


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, list[float], object, object]:
    """The flow table's top camera's frame of two pieces GAP_M apart (edges along x), their centres' x,
    the clothd configuration for the table and the camera's model."""
    cfg = load_config(None)
    start_taichi(cfg.taichi.arch)
    sc = flow_scenario(6.0, 0)
    world = World(sc, log_commands=False)
    sensors, models = scenario_cameras(sc, world, 1)
    spacing = sc.cloth.spacing_m
    centres = [-0.5 * (SIZE_M[0] + GAP_M), 0.5 * (SIZE_M[0] + GAP_M)]
    cloths = tuple(SceneCloth(_flat_piece(x, spacing), (spacing, spacing)) for x in centres)
    state = dataclasses.replace(world.scene_state(), cloths=cloths)
    image, _ = sensors[0].renderer.render([state])
    bgr = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return bgr, centres, config_for(cfg, sc), models[0]


def test_two_pieces_20_mm_apart_are_found_as_two(scene: tuple) -> None:
    image, centres, _, model = scene
    regions = find_cloths(image)
    assert len(regions) == 2
    found_x = sorted(
        float(model.backproject_to_plane(r.corners_px.astype(np.float64))[:, 0].mean()) for r in regions
    )
    assert np.allclose(found_x, centres, atol=0.005)
    masks = [r.mask > 0 for r in regions]
    assert not (masks[0] & masks[1]).any()


def test_each_piece_gets_its_own_tracker_and_is_tracked_where_it_lies(scene: tuple) -> None:
    image, centres, cfg, model = scene
    layout = ConveyorLayout.of_cell(cfg.cell)
    tracking = PieceTracking(
        cfg.flow, model, Workspace.of_cell(cfg.cell), lambda: Tracker(cfg.tracker, model, layout)
    )
    period = cfg.loop.period_s
    tracked_per_frame = []
    for k in range(cfg.flow.search_every + 2):  # the second look sees them still
        pieces = tracking.track(image, k * period, None)
        tracked = sum(p.tracking for p in pieces)
        tracking.upkeep()
        tracked_per_frame.append((tracked, sum(p.tracking for p in pieces)))
    # A piece's tracking starts after its frame's commands (upkeep), one piece a frame.
    assert tracked_per_frame[-3:] == [(0, 0), (0, 1), (1, 2)]
    assert len(pieces) == 2 and len({p.id for p in pieces}) == 2
    assert len({p.slot for p in pieces}) == 2
    for piece in pieces:
        assert piece.state == PieceState.TRACKED and piece.tracking
        assert piece.estimate is not None
        x, y, theta = piece.estimate.pose
        nearest = min(centres, key=lambda c: abs(c - x))
        assert abs(x - nearest) < 0.004 and abs(y) < 0.004
        assert abs(math.remainder(theta, math.pi)) < math.radians(1.0)
    # Each piece's features lie on its own piece.
    for piece in pieces:
        assert piece.estimate is not None
        world_x = model.backproject_to_plane(piece.estimate.meas_px)[:, 0]
        own = min(centres, key=lambda c: abs(c - piece.estimate.pose[0]))  # type: ignore[union-attr]
        assert np.all(np.abs(world_x - own) < SIZE_M[0] / 2 + 0.003)


def test_a_piece_that_leaves_frees_its_tracker_for_the_next(scene: tuple) -> None:
    image, _, cfg, model = scene
    layout = ConveyorLayout.of_cell(cfg.cell)
    made: list[Tracker] = []

    def make() -> Tracker:
        made.append(Tracker(cfg.tracker, model, layout))
        return made[-1]

    tracking = PieceTracking(cfg.flow, model, Workspace.of_cell(cfg.cell), make)
    period = cfg.loop.period_s
    for k in range(cfg.flow.search_every + 2):
        tracking.track(image, k * period, None)
        tracking.upkeep()
    first = min(tracking.pieces, key=lambda p: p.centre_m[0])
    tracking.leave(first, 1.0)
    assert first not in tracking.pieces and list(tracking.gone) == [first] and first.slot is None
    # The piece that left is out of view: the frame with it painted out as the deck.
    region = next(r for r in find_cloths(image) if r.mask[:, : image.shape[1] // 2].any())
    deck = cv2.dilate(region.mask, np.ones((9, 9), np.uint8)) > 0
    without = image.copy()
    without[deck] = np.median(image[~deck], axis=0).astype(np.uint8)
    t_s = 2.0
    for _ in range(cfg.flow.search_every + 1):
        tracking.track(without, t_s, None)
        tracking.upkeep()
        t_s += period
    (other,) = tracking.pieces
    assert other.tracking
    # A new piece where the first lay takes the tracker the first gave back.
    for _ in range(2 * cfg.flow.search_every + 1):
        tracking.track(image, t_s, None)
        tracking.upkeep()
        t_s += period
    assert len(made) == 2  # no third tracker was built
    assert len(tracking.pieces) == 2 and all(p.tracking for p in tracking.pieces)
    assert {p.id for p in tracking.pieces} == {other.id, max(first.id, other.id) + 1}


def test_a_piece_lost_from_view_before_it_is_tracked_is_let_go_and_a_new_flow_numbers_from_0(
    scene: tuple,
) -> None:
    """A piece seen coming in (outside a narrow workspace, so never tracked) that no later look sees: held
    as entering, it would claim its modules for ever. MISSED_LOOKS looks without it let it go, rejected."""
    image, _, cfg, model = scene
    layout = ConveyorLayout.of_cell(cfg.cell)
    wide = Workspace.of_cell(cfg.cell)
    narrow = dataclasses.replace(wide, y_min_m=-0.05, y_max_m=0.05)  # no 0.20 m piece lies inside it
    tracking = PieceTracking(cfg.flow, model, narrow, lambda: Tracker(cfg.tracker, model, layout))
    period, every = cfg.loop.period_s, cfg.flow.search_every
    t_s = 0.0
    for _ in range(every + 1):
        tracking.track(image, t_s, None)
        tracking.upkeep()
        t_s += period
    assert [p.state for p in tracking.pieces] == [PieceState.ENTERING] * 2
    empty = np.empty_like(image)
    empty[:] = np.median(image.reshape(-1, 3), axis=0).astype(np.uint8)  # the deck alone
    for _ in range((MISSED_LOOKS - 1) * every):
        tracking.track(empty, t_s, None)
        t_s += period
    assert len(tracking.pieces) == 2  # one look without them: not yet
    for _ in range(every):
        tracking.track(empty, t_s, None)
        t_s += period
    assert (
        tracking.pieces == []
        and [(p.state, p.reason) for p in tracking.gone] == [(PieceState.REJECTED, LOST_FROM_VIEW)] * 2
    )
    tracking.reset()
    assert not tracking.gone
    tracking.track(image, t_s, None)
    assert sorted(p.id for p in tracking.pieces) == [0, 1]


class _Frames(RecordedFrames):
    """One frame over and over, until `lost`: then none (the camera gone)."""

    lost = False

    def latest(self) -> CameraFrame | None:  # type: ignore[override]
        return None if self.lost else super().latest()


def _flow_compute(cfg: Config, model: CameraModel, frames: RecordedFrames) -> tuple[Compute, ConveyorLayout]:
    """A compute over `frames` on the flow table (mode flow ready), and the table's layout."""
    layout = ConveyorLayout.of_cell(cfg.cell)
    spec = ComputeSpec(
        tracker=cfg.tracker,
        control=cfg.control,
        cell=cfg.cell,
        layout=layout,
        camera_model=model,
        period_s=cfg.loop.period_s,
        workspace=Workspace.of_cell(cfg.cell),
        taichi_arch="cpu",
        max_record_bytes=10**6,
        frame_source=lambda: frames,
        starved_s=60.0,
        flow=cfg.flow,
    )
    compute = Compute(spec, frames)
    return compute, layout


def test_the_compute_in_mode_flow_reports_every_piece_and_a_lost_camera_stops_every_module(
    scene: tuple,
) -> None:
    """One piece still coming in over the infeed edge (its belts pull it in), one lying in the middle:
    both reported; then the camera is lost and every module stops, with the reason."""
    _, _, cfg, model = scene
    sc = flow_scenario(6.0, 0)
    world = World(sc, log_commands=False)
    sensors, _ = scenario_cameras(sc, world, 1)
    spacing = sc.cloth.spacing_m
    cloths = tuple(SceneCloth(_flat_piece(x, spacing), (spacing, spacing)) for x in (-0.44, 0.1))
    image, _ = sensors[0].renderer.render([dataclasses.replace(world.scene_state(), cloths=cloths)])
    frames = _Frames([np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)])
    compute, layout = _flow_compute(cfg, model, frames)
    flow = Setpoint(Mode.FLOW, None, started_mono_s=1.0)
    stopped = ModuleCommands.all_stop(layout.n_modules)
    for _ in range(2 * cfg.flow.search_every + 2):
        reply = tick(compute, TickRequest(flow, stopped, False, False))
    assert reply.state == LoopState.TRACKING and reply.pieces is not None
    states = {round(p.pose[0], 1) if p.pose else None: p.state for p in reply.pieces}
    assert len(reply.pieces) == 2 and states[None] == PieceState.ENTERING  # not tracked yet
    assert states[0.1] in (PieceState.FLATTENING, PieceState.PLACING)  # the one in the middle, tracked
    assert np.isclose(reply.commands.speed_m_s, cfg.flow.intake_speed_m_s).any()  # the intake
    frames.lost = True
    reply = tick(compute, TickRequest(flow, reply.commands, False, False))
    assert reply.state == LoopState.CAMERA_LOST and reply.halt_reason == "the camera is lost"
    assert not reply.commands.speed_m_s.any()


def test_a_flow_asked_for_anew_starts_afresh_and_asked_again_goes_on(scene: tuple) -> None:
    """Idle then flow within one tick: no tick sees the idle, yet the new flow finds its pieces afresh
    (their first look is the new flow's). Flow again while flowing, the same setpoint, goes on."""
    image, _, cfg, model = scene
    compute, layout = _flow_compute(cfg, model, _Frames([image]))
    stopped = ModuleCommands.all_stop(layout.n_modules)
    first = Setpoint(Mode.FLOW, None, started_mono_s=1.0)
    for _ in range(cfg.flow.search_every + 1):
        reply = tick(compute, TickRequest(first, stopped, False, False))
    assert reply.pieces is not None and len(reply.pieces) == 2
    found = sorted(p.found_s for p in reply.pieces)
    reply = tick(compute, TickRequest(first, stopped, False, False))
    assert reply.pieces is not None and sorted(p.found_s for p in reply.pieces) == found  # goes on
    anew = Setpoint(Mode.FLOW, None, started_mono_s=2.0)
    reply = tick(compute, TickRequest(anew, stopped, False, False))
    assert reply.pieces is not None and len(reply.pieces) == 2
    assert min(p.found_s for p in reply.pieces) > max(found)  # found again by the new flow's first look


def test_a_piece_not_tracked_reports_no_flatness_as_it_reports_no_pose(
    scene: tuple, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A reject whose tracking was lost showed its last flatness (17.8 mm, not flat) beside a null pose."""
    _, _, cfg, model = scene
    cell = FlowCell(cfg.flow, cfg.tracker, cfg.control, cfg.cell, model, (), cfg.loop.period_s)
    last = Flatness(0.0178, 5.0, False, ())
    monkeypatch.setattr(cell.controller, "flatness", lambda piece: last)
    outline = np.array([[-0.1, -0.1], [0.1, -0.1], [0.1, 0.1], [-0.1, 0.1]])
    cell.tracking.pieces.append(Piece(0, PieceState.REJECTED, 1.0, outline, 0.5, reason=FLAP_REASON))
    (report,) = cell.reports()
    assert (report.pose, report.flat, report.max_height_mm) == (None, None, None)
    assert report.reason == FLAP_REASON


def _square(centre_x_m: float) -> np.ndarray:
    return np.array([[-0.1, -0.1], [0.1, -0.1], [0.1, 0.1], [-0.1, 0.1]]) + np.array([centre_x_m, 0.0])


def test_who_is_let_go_when_no_look_sees_it(scene: tuple) -> None:
    """Unseen for MISSED_LOOKS looks: a reject waiting for its way goes, keeping its reason; one being
    driven out does not (it leaves the view by design); nor does one beside a tracked piece (its region
    may have merged into the tracked one's)."""
    _, _, cfg, model = scene
    tracking = PieceTracking(cfg.flow, model, Workspace.of_cell(cfg.cell), lambda: None)  # type: ignore[arg-type, return-value]
    waiting = Piece(0, PieceState.REJECTED, 1.0, _square(-0.4), 0.5, reason=FLAP_REASON)
    going = Piece(1, PieceState.REJECTED, 1.0, _square(0.4), 0.5, reason=FLAP_REASON, driven_out=True)
    beside = Piece(2, PieceState.ENTERING, 1.0, _square(0.05), 0.5)
    tracked = Piece(3, PieceState.PLACING, 1.0, _square(-0.1), 0.5, slot=0)
    tracked.estimate = SimpleNamespace(tracking=True)  # type: ignore[assignment]
    tracking.pieces += [waiting, going, beside, tracked]
    for k in range(MISSED_LOOKS):
        tracking._look([], (480, 640, 3), 2.0 + k)
    assert [p.id for p in tracking.pieces] == [1, 2, 3]
    assert [(p.id, p.state, p.reason) for p in tracking.gone] == [(0, PieceState.REJECTED, FLAP_REASON)]
