"""The cell controller, pure: what each state and mode tells the modules, the workspace's edge, a drive
script's timeline, flatten's one meaning, and a mode entered afresh."""

from __future__ import annotations

import numpy as np
import pytest

from clothd.config import CellConfig, ControlConfig
from clothd.core.cell_controller import CellController, ControlStep
from clothd.core.control import Setpoint
from clothd.core.conveyor import ConveyorLayout
from clothd.core.drive_script import DrivePlan
from clothd.core.ekf import UpdateStats
from clothd.core.messages import Estimate
from clothd.core.modes import LoopState, Mode
from clothd.core.workspace import Workspace, cloth_corners_m

pytestmark = pytest.mark.clock_free

CELL = CellConfig()
LAYOUT = ConveyorLayout.of_cell(CELL)
SIZE_M = (0.25, 0.20)
NX, NY = 12, 12
DT_S = 1 / 30


def _controller(flatten: bool = True) -> CellController:
    cfg = ControlConfig(flatten=flatten)
    return CellController(cfg, CELL, LAYOUT, Workspace.of_cell(CELL), DT_S, 0.05, estimates_shape=True)


def _nodes(pose: np.ndarray, ridge: bool) -> np.ndarray:
    """A 12 x 12 mesh of the cloth at `pose`; with a ridge, one column of edges 40 % short and raised."""
    dx = np.full(NX - 1, SIZE_M[0] / (NX - 1))
    if ridge:
        dx[5] *= 0.6
    x = np.concatenate([[0.0], np.cumsum(dx)])
    x -= x.mean()
    y = (np.arange(NY) - (NY - 1) / 2) * SIZE_M[1] / (NY - 1)
    xx, yy = np.meshgrid(x, y)
    zz = np.zeros_like(xx)
    if ridge:
        zz[:, 6] = 0.01
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.stack([pose[0] + c * xx - s * yy, pose[1] + s * xx + c * yy, zz], axis=-1)


def _estimate(pose: tuple[float, float, float] = (0.0, 0.0, 0.0), ridge: bool = False) -> Estimate:
    p = np.array(pose)
    return Estimate(
        frame_t_s=0.0,
        status="tracking",
        pose=p,
        pose_cov=np.eye(3) * 1e-8,
        nodes_m=_nodes(p, ridge),
        outline_m=cloth_corners_m(p, SIZE_M),
        cloth_size_m=SIZE_M,
        feature_id=np.zeros(0, int),
        meas_px=np.zeros((0, 2)),
        pred_px=np.zeros((0, 2)),
        stats=UpdateStats(0, 0, 0.0),
    )


def _step(
    c: CellController, est: Estimate | None, sp: Setpoint, now_s: float = 0.0, frame: bool = True
) -> ControlStep:
    flatness = c.read_flatness(est) if est is not None else None
    return c.step(frame, est, sp, flatness, now_s)


def test_without_a_frame_or_a_track_every_module_stops_and_the_reason_is_given() -> None:
    c = _controller()
    move = Setpoint(Mode.MOVE, np.array([0.05, 0.0, 0.0]), started_mono_s=1.0)
    lost_camera = _step(c, _estimate(), move, frame=False)
    assert lost_camera.state == LoopState.CAMERA_LOST and lost_camera.halt_reason == "the camera is lost"
    assert not lost_camera.commands.speed_m_s.any()
    lost = Estimate(**{**_estimate().__dict__, "status": "lost"})
    lost_track = _step(c, lost, move)
    assert (
        lost_track.state == LoopState.TRACKING_LOST and lost_track.halt_reason == "the cloth is not tracked"
    )
    assert not lost_track.commands.speed_m_s.any()


def test_a_move_drives_the_modules_under_the_cloth_towards_the_target_and_idle_stops_them() -> None:
    c = _controller()
    step = _step(c, _estimate(), Setpoint(Mode.MOVE, np.array([0.05, 0.0, 0.0]), started_mono_s=1.0))
    assert step.state == LoopState.TRACKING and step.halt_reason is None
    moving = step.commands.speed_m_s > 0
    under = c.pose.modules_under(cloth_corners_m(np.zeros(3), SIZE_M))
    assert moving.any() and not (moving & ~under).any()
    heading = step.commands.heading_rad[moving]
    assert np.all(np.abs(np.angle(np.exp(1j * heading))) < 0.05)  # along +x
    idle = _step(c, _estimate(), Setpoint(Mode.IDLE, None))
    assert idle.state == LoopState.TRACKING and not idle.commands.speed_m_s.any()


def test_past_the_workspace_edge_a_move_further_out_stops_with_the_edge_as_the_reason() -> None:
    c = _controller()
    space = c.workspace
    at_edge = (space.x_max_m - SIZE_M[0] / 2 + 0.01, 0.0, 0.0)  # its right edge 10 mm past
    out = _step(c, _estimate(at_edge), Setpoint(Mode.MOVE, np.array([0.5, 0.0, 0.0]), started_mono_s=1.0))
    assert out.halt_reason is not None and out.halt_reason.startswith("at the workspace's edge")
    assert not out.commands.speed_m_s.any()
    back = _step(c, _estimate(at_edge), Setpoint(Mode.MOVE, np.zeros(3), started_mono_s=2.0))
    assert back.halt_reason is None and back.commands.speed_m_s.any()


def test_a_drive_plays_its_script_from_when_it_was_set() -> None:
    n = LAYOUT.n_modules
    speeds = np.zeros((2, n))
    speeds[0, 3], speeds[1, 4] = 0.02, 0.03
    plan = DrivePlan(np.array([0.0, 1.0]), speeds, np.zeros((2, n)), 2.0)
    c = _controller()
    drive = Setpoint(Mode.DRIVE, None, plan, started_mono_s=100.0)
    assert _step(c, _estimate(), drive, now_s=100.5).commands.speed_m_s[3] == 0.02
    assert _step(c, _estimate(), drive, now_s=101.5).commands.speed_m_s[4] == 0.03
    assert not _step(c, _estimate(), drive, now_s=102.5).commands.speed_m_s.any()


def test_flatten_takes_the_slack_out_and_hold_does_so_only_with_control_flatten() -> None:
    pose = np.zeros(3)
    ridged = _estimate(ridge=True)
    plain = _controller(flatten=False)
    hold = _step(plain, ridged, Setpoint(Mode.HOLD, pose, started_mono_s=1.0)).commands.speed_m_s
    flatten = _step(plain, ridged, Setpoint(Mode.FLATTEN, pose, started_mono_s=2.0)).commands.speed_m_s
    assert not hold.any() and flatten.any()  # held where it lies: only the slack moves modules
    shaping = _controller(flatten=True)
    assert _step(shaping, ridged, Setpoint(Mode.HOLD, pose, started_mono_s=1.0)).commands.speed_m_s.any()


def test_a_new_setpoint_starts_the_regulator_afresh_and_the_same_one_does_not() -> None:
    c = _controller()
    resets: list[int] = []
    reset = c.regulator.reset

    def counted_reset() -> None:
        resets.append(1)
        reset()

    c.regulator.reset = counted_reset  # type: ignore[method-assign]
    flatten = Setpoint(Mode.FLATTEN, np.zeros(3), started_mono_s=1.0)
    for _ in range(3):
        _step(c, _estimate(ridge=True), flatten)
    assert len(resets) == 1
    _step(c, _estimate(ridge=True), Setpoint(Mode.FLATTEN, np.zeros(3), started_mono_s=2.0))
    assert len(resets) == 2
