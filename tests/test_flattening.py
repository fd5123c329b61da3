"""The flattening regulator against a synthetic ridge: which modules pull which way and how fast, no net
rigid motion, and the strain guard (core/flattening.py, docs/flattening.md); the ridge in the live view."""

import math

import cv2
import numpy as np
import pytest

from clothd.config import CellConfig, FlatnessConfig, FlattenConfig
from clothd.core.camera_model import CameraModel
from clothd.core.control import Setpoint
from clothd.core.conveyor import ConveyorLayout
from clothd.core.ekf import UpdateStats
from clothd.core.flatness import FlatnessMonitor
from clothd.core.flattening import WIDEST_HOLD_S, FlatteningRegulator, rigid_part
from clothd.core.messages import Estimate
from clothd.outputs.view import ViewRenderer

pytestmark = pytest.mark.clock_free

CELL = CellConfig()
LAYOUT = ConveyorLayout.of_cell(CELL)
SIZE_M = (0.25, 0.20)
NX, NY = 12, 12
SPACING_M = (SIZE_M[0] / (NX - 1), SIZE_M[1] / (NY - 1))
STRAIN_LIMIT = 0.05


def _mesh(
    theta_rad: float, ridge_col: int | None, shortening: float = 0.4, stretch: float = 0.0
) -> np.ndarray:
    """A mesh centred on the origin; the edges of column ridge_col are `shortening` shorter in x, the rest
    stretched by `stretch`; turned by theta."""
    dx = np.full(NX - 1, SPACING_M[0] * (1 + stretch))
    if ridge_col is not None:
        dx[ridge_col] = SPACING_M[0] * (1 - shortening)
    x = np.concatenate([[0.0], np.cumsum(dx)])
    x -= x.mean()
    y = (np.arange(NY) - (NY - 1) / 2) * SPACING_M[1]
    xx, yy = np.meshgrid(x, y)
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    z = np.zeros_like(xx)
    if ridge_col is not None:
        z[:, ridge_col + 1] = 0.01
    return np.stack([c * xx - s * yy, s * xx + c * yy, z], axis=-1)


def _field(nodes: np.ndarray, cfg: FlattenConfig | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    cfg = cfg or FlattenConfig()
    flatness = FlatnessMonitor(FlatnessConfig()).update(nodes, SIZE_M)
    regulator = FlatteningRegulator(cfg, LAYOUT.centres_m, LAYOUT.module_size_m, STRAIN_LIMIT)
    # Modules under the cloth: within its rest rectangle (turned with it).
    under = np.abs(LAYOUT.centres_m[:, 0]) < 0.12
    under &= np.abs(LAYOUT.centres_m[:, 1]) < 0.10
    slack = flatness.ridges[0].slack_m if flatness.ridges else 0.0
    return regulator.velocities(flatness, nodes, SIZE_M, under, np.zeros(3), 0.0), under, slack


def test_the_two_sides_of_a_ridge_are_pulled_apart_across_it() -> None:
    v, under, slack = _field(_mesh(0.0, ridge_col=7))
    assert slack == pytest.approx(0.4 * SPACING_M[0], rel=0.1)
    ridge_x = float(_mesh(0.0, 7)[0, 7:9, 0].mean())
    pulling = np.linalg.norm(v, axis=1) > 1e-9
    assert pulling.sum() >= 4 and not pulling[~under].any()
    for m in np.flatnonzero(pulling):
        side = np.sign(LAYOUT.centres_m[m, 0] - ridge_x)
        # Across the ridge (x), away from it; the rigid part taken out leaves the difference across it.
        assert v[m, 0] * side > 0 and abs(v[m, 1]) < 1e-9
    left, right = (
        v[pulling & (LAYOUT.centres_m[:, 0] < ridge_x), 0],
        v[pulling & (LAYOUT.centres_m[:, 0] > ridge_x), 0],
    )
    cfg = FlattenConfig()
    speed = float(np.clip(slack / (2 * cfg.time_constant_s), cfg.min_speed_m_s, cfg.max_speed_m_s))
    assert right.mean() - left.mean() == pytest.approx(2 * speed, rel=1e-6)


def test_the_field_has_no_rigid_part_and_turns_with_the_ridge() -> None:
    v, under, _ = _field(_mesh(0.3, ridge_col=4))
    assert np.abs(rigid_part(v[under], LAYOUT.centres_m[under], np.zeros(2))).max() < 1e-12
    # Across the ridge (its compressed direction, turned by 0.3 rad), each side moves away from the other.
    nodes = _mesh(0.3, ridge_col=4)
    across = np.array([math.cos(0.3), math.sin(0.3)])
    ridge_s = float(nodes[:, 4:6, :2].reshape(-1, 2).mean(axis=0) @ across)
    side = np.sign(LAYOUT.centres_m[under] @ across - ridge_s)
    along_c = v[under] @ across
    assert along_c[side > 0].mean() - along_c[side < 0].mean() > 0.005


def test_no_ridge_no_pull_and_a_stretched_cloth_is_not_pulled() -> None:
    v, _, _ = _field(_mesh(0.0, ridge_col=None))
    assert not v.any()

    # Rows that are, as a whole, at the strain limit (the ridge's slack more than paid for): no pull.
    def stretch_for(row_strain: float) -> float:  # the other edges' stretch that gives rows this strain
        return (row_strain * (NX - 1) + 0.4) / (NX - 2)

    v, _, _ = _field(_mesh(0.0, ridge_col=7, stretch=stretch_for(STRAIN_LIMIT)))
    assert not v.any()
    half = _field(_mesh(0.0, ridge_col=7, stretch=stretch_for(0.75 * STRAIN_LIMIT)))[0]
    full = _field(_mesh(0.0, ridge_col=7))[0]
    assert np.abs(half).max() == pytest.approx(0.5 * np.abs(full).max(), rel=0.1)


def test_the_pull_is_limited_and_fades_with_the_slack_down_to_its_floor() -> None:
    cfg = FlattenConfig(max_speed_m_s=0.01, min_speed_m_s=0.0, time_constant_s=0.1)
    v, _, _ = _field(_mesh(0.0, ridge_col=7), cfg)
    assert np.linalg.norm(v, axis=1).max() <= 2 * cfg.max_speed_m_s  # each side's pull, less the rigid part
    proportional = FlattenConfig(min_speed_m_s=0.0)
    big = np.abs(_field(_mesh(0.0, ridge_col=7, shortening=0.4), proportional)[0]).max()
    small = np.abs(_field(_mesh(0.0, ridge_col=7, shortening=0.2), proportional)[0]).max()
    assert small == pytest.approx(big / 2, rel=0.1)
    # A ridge held by the yarns' friction comes down only under enough tension: while it is seen, it is
    # pulled at min_speed_m_s at least (4.5 mm of slack would ask for 4.5 mm/s).
    floored = np.abs(_field(_mesh(0.0, ridge_col=7, shortening=0.2))[0]).max()
    assert floored == pytest.approx(small * FlattenConfig().min_speed_m_s / 0.0045, rel=0.15)


def test_the_live_view_draws_each_ridge_along_its_line() -> None:
    nodes = _mesh(0.0, ridge_col=7)
    flatness = FlatnessMonitor(FlatnessConfig()).update(nodes, SIZE_M)
    camera = CameraModel.ideal(640, 480, 900.0, 1.0)
    est = Estimate(
        frame_t_s=0.0,
        status="tracking",
        pose=np.zeros(3),
        pose_cov=np.eye(3),
        nodes_m=nodes,
        outline_m=None,
        cloth_size_m=SIZE_M,
        feature_id=np.zeros(0, int),
        meas_px=np.zeros((0, 2)),
        pred_px=np.zeros((0, 2)),
        stats=UpdateStats(0, 0, 0.0),
    )
    grey = np.full((480, 640, 3), 90, np.uint8)
    setpoint = Setpoint("flatten", np.zeros(3))
    renderer = ViewRenderer(camera)
    with_ridge = cv2.imdecode(
        np.frombuffer(renderer.render(grey, est, setpoint, flatness) or b"", np.uint8), 1
    )
    without = cv2.imdecode(np.frombuffer(renderer.render(grey, est, setpoint) or b"", np.uint8), 1)
    magenta = (with_ridge[..., 0] > 200) & (with_ridge[..., 1] < 80) & (with_ridge[..., 2] > 200)
    assert not ((without[..., 0] > 200) & (without[..., 1] < 80) & (without[..., 2] > 200)).any()
    # A line along the ridge: image columns where the ridge's world x projects, across many rows.
    ridge_x_px = camera.project(np.array([[float(nodes[0, 7:9, 0].mean()), 0.0, 0.0]]))[0, 0]
    rows, cols = np.nonzero(magenta)
    near = np.abs(cols - ridge_x_px) < 15
    assert near.sum() > 100 and np.ptp(rows[near]) > 100
    # The edges beside the raised node column (10 mm) are drawn red-orange; a flat mesh has none.
    red = (without[..., 2] > 200) & (without[..., 1] < 150) & (without[..., 0] < 60)
    rows, cols = np.nonzero(red)
    assert red.sum() > 100 and np.abs(cols - ridge_x_px).max() < 40 and np.ptp(rows) > 100
    flat_est = Estimate(**{**est.__dict__, "nodes_m": _mesh(0.0, ridge_col=None)})
    flat_img = cv2.imdecode(np.frombuffer(renderer.render(grey, flat_est, setpoint) or b"", np.uint8), 1)
    assert not ((flat_img[..., 2] > 200) & (flat_img[..., 1] < 150) & (flat_img[..., 0] < 60)).any()


def test_the_modules_under_a_flap_are_left_alone() -> None:
    nodes = _mesh(0.0, ridge_col=7)
    seen = np.ones((NY - 1, NX - 1), dtype=bool)
    seen[-3:, -3:] = False  # the +x +y corner folded over
    flatness = FlatnessMonitor(FlatnessConfig()).update(nodes, SIZE_M, seen)
    assert len(flatness.flaps) == 1
    regulator = FlatteningRegulator(FlattenConfig(), LAYOUT.centres_m, LAYOUT.module_size_m, STRAIN_LIMIT)
    under = (np.abs(LAYOUT.centres_m[:, 0]) < 0.12) & (np.abs(LAYOUT.centres_m[:, 1]) < 0.10)
    v = regulator.velocities(flatness, nodes, SIZE_M, under, np.zeros(3), 0.0)
    flap_xy = flatness.flaps[0].quad_centres_m
    gap = np.linalg.norm(LAYOUT.centres_m[:, None] - flap_xy[None], axis=-1).min(axis=1)
    near = gap <= LAYOUT.module_size_m / 2 + FlattenConfig().ridge_margin_m
    assert (near & under).any()
    assert np.all(v[near] == 0.0)
    # The ridge is still pulled, by the modules away from the flap.
    assert np.abs(v[under & ~near]).max() > 0.0
    without_flap = FlatnessMonitor(FlatnessConfig()).update(nodes, SIZE_M)
    v_all = regulator.velocities(without_flap, nodes, SIZE_M, under, np.zeros(3), 0.0)
    assert np.abs(v_all[near & under]).max() > 0.0  # without the flap those modules would pull


def test_a_ridge_lost_from_sight_is_pulled_on_for_finish_s_where_the_cloth_took_it() -> None:
    """Below a few millimetres the estimate no longer sees a ridge that the yarns' friction still holds:
    the regulator keeps pulling it at full speed for finish_s, in the cloth's frame, then stops."""
    cfg = FlattenConfig()
    regulator = FlatteningRegulator(cfg, LAYOUT.centres_m, LAYOUT.module_size_m, STRAIN_LIMIT)
    under = (np.abs(LAYOUT.centres_m[:, 0]) < 0.20) & (np.abs(LAYOUT.centres_m[:, 1]) < 0.10)
    wrinkled, flat = _mesh(0.0, ridge_col=7), _mesh(0.0, ridge_col=None)
    monitor = FlatnessMonitor(FlatnessConfig())
    seen, gone = monitor.update(wrinkled, SIZE_M), monitor.update(flat, SIZE_M)
    assert seen.ridges and not gone.ridges
    ridge_x = float(wrinkled[0, 7:9, 0].mean())
    v_seen = regulator.velocities(seen, wrinkled, SIZE_M, under, np.zeros(3), 0.0)
    assert v_seen.any()
    # The cloth has moved 40 mm along x since: the remembered line moved with it.
    shift_m = 0.04
    v = regulator.velocities(gone, flat, SIZE_M, under, np.array([shift_m, 0.0, 0.0]), 0.1)
    pulling = np.linalg.norm(v, axis=1) > 1e-9
    assert pulling.sum() >= 4
    side = np.sign(LAYOUT.centres_m[pulling, 0] - (ridge_x + shift_m))
    assert np.all(v[pulling, 0] * side > 0)
    # At full speed, not at the slack's pace (slack / 2 tau = 9 mm/s here, against 40).
    assert np.abs(v).max() > 3 * np.abs(v_seen).max()
    # Seen on a cloth turned by 0.3 rad, lost after it moved and turned 60° more: the line went with it.
    seen_at, lost_at = np.array([0.02, 0.01, 0.3]), np.array([0.03, -0.02, 0.3 + math.pi / 3])
    turned = FlatteningRegulator(cfg, LAYOUT.centres_m, LAYOUT.module_size_m, STRAIN_LIMIT)
    seen_turned = _mesh(0.3, ridge_col=7) + np.array([seen_at[0], seen_at[1], 0.0])
    turned.velocities(monitor.update(seen_turned, SIZE_M), seen_turned, SIZE_M, under, seen_at, 0.0)
    under_turned = np.linalg.norm(LAYOUT.centres_m - lost_at[:2], axis=1) < 0.12
    v = turned.velocities(gone, flat, SIZE_M, under_turned, lost_at, 0.1)[under_turned]
    c, s = math.cos(lost_at[2]), math.sin(lost_at[2])
    across, along = np.array([c, s]), np.array([-s, c])
    line_m = lost_at[:2] + ridge_x * across  # the cloth's point (ridge_x, 0), where the cloth is now
    s_m = (LAYOUT.centres_m[under_turned] - line_m) @ across
    assert (v @ across)[s_m > 0].mean() > 0.01 and (v @ across)[s_m < 0].mean() < -0.01
    assert np.abs(v @ along).max() < 0.1 * np.abs(v @ across).max()
    # Still within finish_s, then no more.
    later = 0.1 + cfg.finish_s
    assert regulator.velocities(gone, flat, SIZE_M, under, np.zeros(3), later - 0.01).any()
    assert not regulator.velocities(gone, flat, SIZE_M, under, np.zeros(3), later + 0.01).any()
    # A ridge last seen long before (the regulator idle in between) is forgotten, not finished.
    regulator.velocities(seen, wrinkled, SIZE_M, under, np.zeros(3), 10.0)
    assert not regulator.velocities(gone, flat, SIZE_M, under, np.zeros(3), 12.0).any()
    # Reset forgets it too.
    regulator.velocities(seen, wrinkled, SIZE_M, under, np.zeros(3), 20.0)
    regulator.reset()
    assert not regulator.velocities(gone, flat, SIZE_M, under, np.zeros(3), 20.1).any()


def _partly(wrinkled: np.ndarray, flat: np.ndarray, rows: int) -> np.ndarray:
    """The ridge of `wrinkled` along its first `rows` rows only: the estimate of a ridge coming down."""
    nodes = flat.copy()
    nodes[:rows] = wrinkled[:rows]
    return nodes


def test_a_ridge_is_pulled_along_the_widest_it_was_seen() -> None:
    """An estimate stops seeing a ridge held by friction from its ends inwards, long before the cloth
    there is flat: the modules beside the whole line it was seen along keep pulling, and its finishing pull
    covers that line too."""
    wrinkled, flat = _mesh(0.0, ridge_col=7), _mesh(0.0, ridge_col=None)
    shrunk = _partly(wrinkled, flat, rows=4)
    under = (np.abs(LAYOUT.centres_m[:, 0]) < 0.20) & (np.abs(LAYOUT.centres_m[:, 1]) < 0.10)

    def regulator() -> FlatteningRegulator:
        return FlatteningRegulator(FlattenConfig(), LAYOUT.centres_m, LAYOUT.module_size_m, STRAIN_LIMIT)

    monitor = FlatnessMonitor(FlatnessConfig())
    first, later, gone = (monitor.update(n, SIZE_M) for n in (wrinkled, shrunk, flat))
    # The modules that the whole ridge pulls, beside the half of its line the shrunk one no longer holds.
    whole = regulator().velocities(first, wrinkled, SIZE_M, under, np.zeros(3), 0.0)
    far_end = (np.abs(whole[:, 0]) > 1e-3) & (LAYOUT.centres_m[:, 1] > 0.0)
    assert far_end.sum() >= 2
    assert len(later.ridges) == 1
    assert len(later.ridges[0].quad_centres_m) < len(first.ridges[0].quad_centres_m)
    only_shrunk = regulator().velocities(later, shrunk, SIZE_M, under, np.zeros(3), 0.0)
    assert np.abs(only_shrunk[far_end]).max() <= 1e-9  # seen alone, the shrunk ridge ends short of there

    watched = regulator()
    watched.velocities(first, wrinkled, SIZE_M, under, np.zeros(3), 0.0)
    v = watched.velocities(later, shrunk, SIZE_M, under, np.zeros(3), 0.05)
    assert np.abs(v[far_end, 0]).min() > 1e-3
    v = watched.velocities(gone, flat, SIZE_M, under, np.zeros(3), 0.1)
    assert np.abs(v[far_end, 0]).min() > 1e-3


def test_a_line_seen_once_stops_pulling_on_the_fragment_left_of_it_after_widest_hold_s() -> None:
    """A one-camera estimate showed a 13-quad line once in a move, then only a quad of it at the cloth's
    edge, for good: pulled along the whole line, the piece stalled 2.3 mm short of its placement. The
    widest extent is held for WIDEST_HOLD_S after it was last seen that wide, then the fragment is the
    ridge."""
    wrinkled, flat = _mesh(0.0, ridge_col=7), _mesh(0.0, ridge_col=None)
    shrunk = _partly(wrinkled, flat, rows=4)
    under = (np.abs(LAYOUT.centres_m[:, 0]) < 0.20) & (np.abs(LAYOUT.centres_m[:, 1]) < 0.10)
    monitor = FlatnessMonitor(FlatnessConfig())
    first, later = (monitor.update(n, SIZE_M) for n in (wrinkled, shrunk))
    regulator = FlatteningRegulator(FlattenConfig(), LAYOUT.centres_m, LAYOUT.module_size_m, STRAIN_LIMIT)
    whole = regulator.velocities(first, wrinkled, SIZE_M, under, np.zeros(3), 0.0)
    far_end = (np.abs(whole[:, 0]) > 1e-3) & (LAYOUT.centres_m[:, 1] > 0.0)
    assert far_end.sum() >= 2
    t_s = 0.0
    while t_s < WIDEST_HOLD_S - 0.1:  # seen shrunk every tick: still pulled along its widest
        t_s += 0.1
        v = regulator.velocities(later, shrunk, SIZE_M, under, np.zeros(3), t_s)
        assert np.abs(v[far_end, 0]).min() > 1e-3, t_s
    v = regulator.velocities(later, shrunk, SIZE_M, under, np.zeros(3), WIDEST_HOLD_S + 0.1)
    assert np.abs(v[far_end]).max() <= 1e-9
    assert np.abs(v).max() > 1e-3  # the fragment itself is still pulled
