"""The second view: triangulation, the epipolar check, the height field, unfolding, and the tracker laying
its mesh over a cloth that arrives wrinkled (hwsim's default cell, two cameras)."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from clothd.config import Config
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout
from clothd.core.flatness import FlatnessMonitor
from clothd.core.mesh import QuadMesh
from clothd.core.messages import ModuleCommands, PairedView
from clothd.core.modes import FlatnessBasis
from clothd.core.second_view import FeatureHeights
from clothd.core.stereo import (
    backed_heights,
    crest_heights,
    epipolar_distance_px,
    fit_height_field,
    measure_surface,
    quad_highest,
    triangulate,
)
from clothd.core.tracker import Tracker
from clothd.core.unfold import outline_rectangle, unfold
from clothd.formats import read_camera
from clothd.taichi_runtime import start_taichi
from hwsim import scenario as scenarios
from hwsim.camera import Camera
from hwsim.firmware import drive_targets
from hwsim.scenario import Pose
from hwsim.sensor import Sensor
from hwsim.world import World

pytestmark = pytest.mark.clock_free

RIDGE_SIGMA_M = 0.012


def _oblique(tilt_rad: float, offset_y_m: float) -> CameraModel:
    """A camera 1 m from the table's centre, turned tilt_rad about x and looking at it from -y."""
    down = CameraModel.ideal(640, 480, 900.0, 1.0)
    c, s = math.cos(tilt_rad), math.sin(tilt_rad)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    R = turn @ down.T_cam_world[:3, :3]
    centre = np.array([0.0, offset_y_m, math.sqrt(1.0 - offset_y_m**2)])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ centre
    dist = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
    return CameraModel(down.K, dist, T, 640, 480)


def _gaussian_ridge(xy_m: np.ndarray, height_m: float) -> np.ndarray:
    return np.asarray(height_m * np.exp(-0.5 * (xy_m[:, 0] / RIDGE_SIGMA_M) ** 2))


def test_triangulation_recovers_points_seen_by_two_cameras() -> None:
    rng = np.random.default_rng(0)
    top, side = CameraModel.ideal(640, 480, 900.0, 1.0), _oblique(0.436, -0.423)
    points = np.column_stack([rng.uniform(-0.1, 0.1, (50, 2)), rng.uniform(0.0, 0.03, 50)])
    px0, px1 = top.project(points), side.project(points)
    np.testing.assert_allclose(triangulate(top, px0, side, px1), points, atol=1e-9)
    assert epipolar_distance_px(top, px0, side, px1, 0.05).max() < 0.05
    # A match slid across its epipolar line is off it by about as much.
    off = epipolar_distance_px(top, px0, side, px1 + np.array([2.0, 0.0]), 0.05)
    assert off.min() > 0.5


def test_height_field_follows_a_ridge_through_scattered_points() -> None:
    rng = np.random.default_rng(1)
    footprint = QuadMesh.covering(np.array([[-0.12, -0.1], [0.12, -0.1], [0.12, 0.1], [-0.12, 0.1]]), 12, 12)
    xy = rng.uniform([-0.12, -0.1], [0.12, 0.1], (600, 2))
    z = _gaussian_ridge(xy, 0.012) + rng.normal(0.0, 0.0004, len(xy))
    z[:5] += 0.03  # stray matches
    field = fit_height_field(np.column_stack([xy, z]), footprint)
    probe = np.column_stack([np.linspace(-0.1, 0.1, 81), np.zeros(81)])
    assert abs(field.at(probe).max() - 0.012) < 0.001
    assert np.abs(field.at(probe) - _gaussian_ridge(probe, 0.012)).max() < 0.0015


def test_a_quads_height_is_its_two_highest_points_and_its_neighbours_where_it_has_none() -> None:
    quads = np.array([0, 0, 0, 4, 4, 8])
    z = np.array([0.001, 0.004, 0.002, 0.003, 0.0, 0.002])
    heights = quad_highest(quads, z, (3, 3))
    # Each quad the mean of its two highest points; the empty ones the highest around them.
    expected = [[0.003, 0.003, 0.0015], [0.003, 0.0015, 0.002], [0.0015, 0.002, 0.002]]
    np.testing.assert_allclose(heights, expected)
    np.testing.assert_allclose(quad_highest(np.zeros(0, int), np.zeros(0), (2, 2)), 0.0)


def _quads_of(xy_m: np.ndarray, nodes_m: np.ndarray) -> np.ndarray:
    """Flat indices of the quads of a regular, axis-aligned mesh's nodes (ny, nx, 3) holding points (n, 2)."""
    origin, pitch = nodes_m[0, 0, :2], nodes_m[1, 1, :2] - nodes_m[0, 0, :2]
    ij = np.clip(
        np.floor((xy_m - origin) / pitch).astype(int), 0, [nodes_m.shape[1] - 2, nodes_m.shape[0] - 2]
    )
    return np.asarray(ij[:, 1] * (nodes_m.shape[1] - 1) + ij[:, 0])


def test_a_quad_counts_as_high_as_a_neighbour_backs_it_and_nothing_past_the_edge_does() -> None:
    q = np.zeros((4, 5))
    q[0, 2] = 0.001  # alone, on the cloth's edge row
    assert backed_heights(q).max() == 0.0
    q[1, 3] = 0.0008  # a neighbour inside, diagonally
    assert backed_heights(q)[0, 2] == pytest.approx(0.0008)


def test_a_crest_between_the_points_is_read_from_the_surface_through_them() -> None:
    rng = np.random.default_rng(3)
    jj, ii = np.meshgrid(np.linspace(-0.1, 0.1, 12), np.linspace(-0.12, 0.12, 12), indexing="ij")
    nodes = np.stack([ii, jj, np.zeros_like(ii)], axis=-1)
    # Points 7 mm apart, none nearer the crest (x = 0) than 3.5 mm: a 12 mm ridge of sigma 8 mm.
    gx, gy = np.meshgrid(np.arange(-0.1155, 0.12, 0.007), np.arange(-0.098, 0.1, 0.007))
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    z = 0.012 * np.exp(-0.5 * (xy[:, 0] / 0.008) ** 2) + rng.normal(0.0, 0.0001, len(xy))
    points = np.column_stack([xy, z])
    quads = quad_highest(_quads_of(xy, nodes), z, (11, 11))
    assert 0.012 - quads.max() > 0.0008  # the two highest points of the crest's quads
    assert abs(crest_heights(quads, points, nodes).max() - 0.012) < 0.0005
    # A flat cloth's points, an edge's stray pair among them: the surface adds little to what they read.
    flat = np.column_stack([xy, rng.normal(0.0, 0.0002, len(xy))])
    flat[np.argsort(xy[:, 0])[-2:], 2] = 0.0016
    flat_quads = quad_highest(_quads_of(xy, nodes), flat[:, 2], (11, 11))
    assert np.all(crest_heights(flat_quads, flat, nodes) - flat_quads < 0.0002)
    # A 0.9 mm crease of sigma 5 mm, where flatness is decided: the surface reads it nearer its crest.
    crease_z = 0.0009 * np.exp(-0.5 * (xy[:, 0] / 0.005) ** 2) + rng.normal(0.0, 5e-5, len(xy))
    crease_quads = quad_highest(_quads_of(xy, nodes), crease_z, (11, 11))
    crease_read = crest_heights(crease_quads, np.column_stack([xy, crease_z]), nodes).max()
    assert 0.0009 - crease_quads.max() > 0.0001 and abs(crease_read - 0.0009) < 0.0001
    # A flank rising towards the +x edge whose points stop 30 mm short of it: the field runs on up the
    # slope past the last point (0.36 mm higher); the crest is read only near points.
    rising = np.column_stack([xy, 0.3 * np.clip(xy[:, 0] - 0.07, 0.0, None)])
    rising = rising[rising[:, 0] < 0.09]
    rising_quads = quad_highest(_quads_of(rising[:, :2], nodes), rising[:, 2], (11, 11))
    assert crest_heights(rising_quads, rising, nodes).max() < rising[:, 2].max() + 0.0002


def test_measured_heights_make_a_ridge_that_shortening_alone_does_not_show() -> None:
    cfg = Config().control.flatness
    ny, nx = 8, 10
    jj, ii = np.meshgrid(np.arange(ny) * 0.02, np.arange(nx) * 0.02, indexing="ij")
    nodes = np.stack([ii, jj, np.zeros_like(ii)], axis=-1)  # at rest, not shortened anywhere
    size = (0.02 * (nx - 1), 0.02 * (ny - 1))
    heights = np.full((ny - 1, nx - 1), 0.0003)  # the field's noise
    level = FlatnessMonitor(cfg).update(nodes, size, basis=FlatnessBasis.MEASURED, quad_height_m=heights)
    assert level.flat and not level.ridges and level.max_height_m == pytest.approx(0.0003)
    # A ridge along the second axis: its quads 1.5 % shorter across it, a third of what shortening alone
    # counts (the slack of a 5 mm ridge of the rest shape measured when tracking began).
    nodes[:, 5:, 0] -= 0.0003
    heights[:, 4] = 0.005
    ridged = FlatnessMonitor(cfg).update(nodes, size, basis=FlatnessBasis.MEASURED, quad_height_m=heights)
    assert not ridged.flat and len(ridged.ridges) == 1
    assert ridged.max_height_m == pytest.approx(0.005) and ridged.ridges[0].height_m == pytest.approx(0.005)
    assert ridged.ridges[0].position_m[0] == pytest.approx(0.09, abs=0.011)
    assert FlatnessMonitor(cfg).update(nodes, size).flat  # without the heights: nothing to see


def test_unfolding_lays_the_slack_of_a_ridge_out_flat() -> None:
    footprint = QuadMesh.covering(np.array([[-0.12, -0.1], [0.12, -0.1], [0.12, 0.1], [-0.12, 0.1]]), 12, 12)
    rng = np.random.default_rng(2)
    xy = rng.uniform([-0.12, -0.1], [0.12, 0.1], (2000, 2))
    height = 0.012
    field = fit_height_field(np.column_stack([xy, _gaussian_ridge(xy, height)]), footprint)
    outline = np.array([_on_rectangle(p, 0.24, 0.2) for p in np.linspace(0.0, 0.88, 880, endpoint=False)])
    material, nodes = unfold(footprint, field, outline)
    slack = height**2 * math.sqrt(math.pi) / (4.0 * RIDGE_SIGMA_M)  # ½∫z'² across a Gaussian
    assert material.width_m - footprint.width_m == pytest.approx(slack, rel=0.25)
    assert material.height_m == pytest.approx(footprint.height_m, abs=2e-4)  # along the ridge: none
    # The nodes lie on the footprint, on the surface (those nearest the crest 11 mm either side of it).
    assert np.abs(nodes[:, :2]).max(axis=0) == pytest.approx([0.12, 0.1], abs=0.002)
    np.testing.assert_allclose(nodes[:, 2], field.at(nodes[:, :2]))
    assert 0.5 * height < nodes[:, 2].max() <= height
    flat = fit_height_field(np.column_stack([xy, np.zeros(len(xy))]), footprint)
    same, lying = unfold(footprint, flat, outline)
    assert same.width_m == pytest.approx(footprint.width_m, abs=1e-6)
    np.testing.assert_allclose(lying[:, :2], footprint.rest_nodes_m().reshape(-1, 2), atol=1e-6)


def _wrinkled_cell(
    ridge_height_m: float, skew_s: float = 0.0
) -> tuple[World, list[CameraModel], list[Sensor]]:
    world, cameras, sensors = _default_cell(skew_s)
    ridge = {"height_m": ridge_height_m, "at_m": [0.03, 0.01], "direction_rad": 1.2}
    world.lay(Pose.model_validate({"x_m": 0.03, "y_m": -0.02, "theta_rad": 0.3, "ridges": [ridge]}))
    return world, cameras, sensors


def _default_cell(skew_s: float = 0.0) -> tuple[World, list[CameraModel], list[Sensor]]:
    sc = scenarios.load("cell")
    world = World(sc, log_commands=False)
    cameras, sensors = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i, spec in enumerate(sc.camera_specs):
            camera = Camera.from_spec(spec)
            camera.save(Path(tmp) / f"camera{i}.json")  # the interface between them, as live
            cameras.append(read_camera(Path(tmp) / f"camera{i}.json"))
            sensors.append(Sensor(sc, camera, world.cloth.grid, i, skew_s if i else 0.0))
    return world, cameras, sensors


@pytest.mark.parametrize("n_cameras", [1, 2])
def test_a_ridge_laid_before_tracking_is_seen_only_with_a_second_view(n_cameras: int) -> None:
    cfg = Config()
    start_taichi(cfg.taichi.arch)
    world, cameras, sensors = _wrinkled_cell(0.012)
    layout = ConveyorLayout.of_cell(cfg.cell)
    tracker = Tracker(cfg.tracker, cameras[0], layout, other_cameras=cameras[1:n_cameras])
    monitor = FlatnessMonitor(cfg.control.flatness)
    stopped = ModuleCommands.all_stop(layout.n_modules)
    for k in range(15):  # 1 s at 15 frames/s
        world.step()
        world.step()
        images = [cv2.imdecode(np.frombuffer(s.jpeg(world, k), np.uint8), cv2.IMREAD_COLOR) for s in sensors]
        views = [PairedView(image, world.t_s) for image in images[1:n_cameras]]
        est = tracker.track(images[0], world.t_s, stopped, views)
        assert est.tracking and est.nodes_m is not None and est.cloth_size_m is not None
        flatness = monitor.update(
            est.nodes_m, est.cloth_size_m, est.quad_seen, est.flatness_basis, est.quad_height_m
        )
    truth_height_m = world.sheet_measures()["max_height_m"]
    assert truth_height_m > 0.01
    if n_cameras == 1:
        assert flatness.basis == FlatnessBasis.SINCE_START
        # The first frame's footprint is the rest shape: the ridge is not seen at all.
        assert flatness.max_height_m < 0.001 and not flatness.ridges
        return
    assert flatness.basis == FlatnessBasis.MEASURED
    assert not flatness.flat and flatness.ridges
    assert abs(flatness.max_height_m - truth_height_m) < 0.0015  # measured every frame, not inferred
    # The ridge's line in the world: through the cloth point (0.03, 0.01) at 1.2 rad in the cloth, turned 0.3.
    c, s = math.cos(0.3), math.sin(0.3)
    on_line = np.array([0.03 + c * 0.03 - s * 0.01, -0.02 + s * 0.03 + c * 0.01])
    along = np.array([math.cos(1.5), math.sin(1.5)])
    off = np.asarray(flatness.ridges[0].position_m) - on_line
    assert abs(off[0] * along[1] - off[1] * along[0]) < 0.02


def _frames(world: World, sensors: list[Sensor], n: int) -> list[tuple[float, list[np.ndarray]]]:
    """n frames of every camera, 15 frames/s, each with its time."""
    out = []
    for k in range(n):
        world.step()
        world.step()
        images = [cv2.imdecode(np.frombuffer(s.jpeg(world, k), np.uint8), cv2.IMREAD_COLOR) for s in sensors]
        out.append((world.t_s, images))
    return out


def test_a_flat_cloth_reads_flat_whichever_frame_tracking_begins_on() -> None:
    """Each frame's sensor noise differs: tracking begun on frame 1, 3 or 6 of the default cell once kept
    a look-alike match on one feature's epipolar line that read 3.3 mm high in every frame after."""
    cfg = Config()
    start_taichi(cfg.taichi.arch)
    world, cameras, sensors = _default_cell()
    frames = _frames(world, sensors, 15)
    layout = ConveyorLayout.of_cell(cfg.cell)
    stopped = ModuleCommands.all_stop(layout.n_modules)
    for first in (1, 3, 6):
        tracker = Tracker(cfg.tracker, cameras[0], layout, other_cameras=cameras[1:])
        monitor = FlatnessMonitor(cfg.control.flatness)
        heights_mm = []
        for t_s, images in frames[first : first + 9]:  # the noise repeats every 8 frames
            est = tracker.track(images[0], t_s, stopped, [PairedView(images[1], t_s)])
            assert est.nodes_m is not None and est.cloth_size_m is not None
            f = monitor.update(
                est.nodes_m, est.cloth_size_m, est.quad_seen, est.flatness_basis, est.quad_height_m
            )
            heights_mm.append(f.max_height_m * 1e3)
        assert f.basis == FlatnessBasis.MEASURED
        assert max(heights_mm) < 1.0 and f.flat and f.compressed_area_pct == 0.0, (first, heights_mm)


def test_heights_hold_with_the_second_capture_10_ms_late_on_belts_at_100_mm_s() -> None:
    cfg = Config()
    start_taichi(cfg.taichi.arch)
    skew_s, speed_m_s = 0.010, 0.1
    world, cameras, sensors = _wrinkled_cell(0.012, skew_s)
    layout = ConveyorLayout.of_cell(cfg.cell)
    tracker = Tracker(cfg.tracker, cameras[0], layout, other_cameras=cameras[1:])
    monitor = FlatnessMonitor(cfg.control.flatness)
    # Along +y: along the baseline, where a point moved between the two captures reads as height.
    running = ModuleCommands(np.full(layout.n_modules, speed_m_s), np.full(layout.n_modules, math.pi / 2))
    ids = np.arange(world.table.n_modules)
    world.table.command(ids, *drive_targets(running.speed_m_s, running.heading_rad))
    errors_m = []
    for k in range(15):  # 1 s, the cloth carried 100 mm along +y
        world.step()
        world.step()
        images = [cv2.imdecode(np.frombuffer(s.jpeg(world, k), np.uint8), cv2.IMREAD_COLOR) for s in sensors]
        est = tracker.track(images[0], world.t_s, running, [PairedView(images[1], world.t_s + skew_s)])
        assert est.tracking and est.nodes_m is not None and est.cloth_size_m is not None
        assert (k >= 2) == ("heights" in est.timing_s)  # the last frame's, measured beside this one
        flatness = monitor.update(
            est.nodes_m, est.cloth_size_m, est.quad_seen, est.flatness_basis, est.quad_height_m
        )
        if k >= 3:  # the belts up to speed
            errors_m.append(flatness.max_height_m - world.sheet_measures()["max_height_m"])
    assert flatness.basis == FlatnessBasis.MEASURED and world.cloth_pose()[1] > 0.06
    assert np.abs(errors_m).max() < 0.0015


def test_a_frames_heights_are_the_same_measured_with_it_or_after_its_estimate() -> None:
    """The live loop tracks a frame at once and measures its heights once its pair has arrived (`track`
    with views None, then `measure_heights`); a frame tracked with its pair has them measured on their own
    thread while the next is tracked. Either way a frame's heights are the same, and the next frame's
    estimate carries them."""
    cfg = Config()
    start_taichi(cfg.taichi.arch)
    skew_s, speed_m_s = 0.010, 0.1
    world, cameras, sensors = _wrinkled_cell(0.012, skew_s)
    layout = ConveyorLayout.of_cell(cfg.cell)
    now, later = (Tracker(cfg.tracker, cameras[0], layout, other_cameras=cameras[1:]) for _ in range(2))
    running = ModuleCommands(np.full(layout.n_modules, speed_m_s), np.full(layout.n_modules, math.pi / 2))
    world.table.command(
        np.arange(world.table.n_modules), *drive_targets(running.speed_m_s, running.heading_rad)
    )
    measured_before = None
    for k in range(8):
        world.step()
        world.step()
        images = [cv2.imdecode(np.frombuffer(s.jpeg(world, k), np.uint8), cv2.IMREAD_COLOR) for s in sensors]
        views = [PairedView(images[1], world.t_s + skew_s)]
        with_pair = now.track(images[0], world.t_s, running, views)
        begins = later.initialising
        est = later.track(images[0], world.t_s, running, views if begins else None)
        assert est.flatness_basis == FlatnessBasis.MEASURED and est.quad_height_m is not None
        assert with_pair.quad_height_m is not None
        np.testing.assert_allclose(with_pair.quad_height_m, est.quad_height_m, atol=1e-9)
        if not begins:  # the last frame's heights, held until this one's are measured
            np.testing.assert_array_equal(est.quad_height_m, measured_before)
            later.measure_heights(views)
        measured = now.quad_height_m  # this frame's, once its thread is done
        assert measured is not None and measured.max() > 0.008
        np.testing.assert_allclose(later.quad_height_m, measured, atol=1e-9)
        measured_before = later.quad_height_m
    later.measure_heights(views)  # measured once: nothing left to measure, the heights stay
    np.testing.assert_array_equal(later.quad_height_m, measured_before)


def test_a_tall_ridge_laid_across_the_weave_is_measured_to_its_crest_and_unfolded_to_the_cloths_size() -> (
    None
):
    """The default cloth's twill repeats every ~5 px, while a 17 mm ridge shifts a point ~6.5 px along its
    epipolar line: matched in one pass, a third of the ridge's points ended a period off, and the mesh's
    highest node stood at 4 mm."""
    cfg = Config()
    start_taichi(cfg.taichi.arch)
    world, cameras, sensors = _wrinkled_cell(0.017)
    layout = ConveyorLayout.of_cell(cfg.cell)
    tracker = Tracker(cfg.tracker, cameras[0], layout, other_cameras=cameras[1:])
    world.step()
    images = [cv2.imdecode(np.frombuffer(s.jpeg(world, 0), np.uint8), cv2.IMREAD_COLOR) for s in sensors]
    stopped = ModuleCommands.all_stop(layout.n_modules)
    est = tracker.track(images[0], world.t_s, stopped, [PairedView(images[1], world.t_s)])
    assert est.tracking and est.nodes_m is not None and est.cloth_size_m is not None
    assert est.flatness_basis == FlatnessBasis.MEASURED
    assert est.nodes_m[..., 2].max() > 0.85 * world.sheet_measures()["max_height_m"]
    rest_m = np.array(world.cloth.grid.st_m[-1, -1] - world.cloth.grid.st_m[0, 0])  # the cloth's, 250 x 200
    np.testing.assert_allclose(est.cloth_size_m, rest_m, atol=0.005)


def test_the_rectangle_an_outline_traces_lies_through_its_sides_not_its_bumps() -> None:
    rng = np.random.default_rng(5)
    width, height, turn = 0.25, 0.2, 0.3
    perimeter = np.linspace(0.0, 2 * (width + height), 900, endpoint=False)
    local = np.array([_on_rectangle(p, width, height) for p in perimeter])
    # The cut edge as a camera outlines it: a wave of a pixel or so, and every fifth point 3 mm proud.
    outward = np.sign(local) * (np.abs(local) / [width / 2, height / 2] > 0.999)
    local += outward * (
        0.0005 * rng.standard_normal((len(local), 1)) + 0.003 * (rng.random((len(local), 1)) < 0.2)
    )
    c, s = math.cos(turn), math.sin(turn)
    outline = local @ np.array([[c, s], [-s, c]]) + [0.05, -0.03]
    corners = outline_rectangle(outline)
    mesh = QuadMesh.covering(corners, 4, 4)
    assert mesh.width_m == pytest.approx(width, abs=0.001) and mesh.height_m == pytest.approx(
        height, abs=0.001
    )
    assert mesh.theta_rad == pytest.approx(turn, abs=math.radians(0.2))
    np.testing.assert_allclose(mesh.centre_m, [0.05, -0.03], atol=0.0005)
    # The minimum-area rectangle lies on the bumps.
    (_, _), (w, h), _ = cv2.minAreaRect(outline.astype(np.float32))
    assert min(w, h) > height + 0.004


def _on_rectangle(p: float, width: float, height: float) -> tuple[float, float]:
    """The point at perimeter distance p round a width x height rectangle about the origin."""
    if p < width:
        return (p - width / 2, -height / 2)
    if p < width + height:
        return (width / 2, p - width - height / 2)
    if p < 2 * width + height:
        return (width / 2 - (p - width - height), height / 2)
    return (-width / 2, height / 2 - (p - 2 * width - height))


def test_a_feature_measured_far_from_where_the_estimate_puts_it_is_searched_for_afresh() -> None:
    """The estimate's node heights can be wrong: an inferred fold once lifted a flat edge quad's nodes
    17 mm, and from there two of its features matched a look-alike of the weave 21 mm up. A feature the
    last frame measured far from where the estimate puts it is searched for over the whole height, so a
    flat cloth reads flat whatever height the nodes claim (from the lifted nodes: 24 mm)."""
    cfg = Config()
    start_taichi(cfg.taichi.arch)
    world, cameras, sensors = _default_cell()
    layout = ConveyorLayout.of_cell(cfg.cell)
    stopped = ModuleCommands.all_stop(layout.n_modules)
    tracker = Tracker(cfg.tracker, cameras[0], layout, other_cameras=cameras[1:])
    frames = _frames(world, sensors, 4)
    for t_s, images in frames[:3]:
        est = tracker.track(images[0], t_s, stopped, [PairedView(images[1], t_s)])
    assert tracker.features is not None and est.nodes_m is not None
    assert tracker.quad_height_m is not None and tracker.quad_height_m.max() < 0.0015
    lifted = est.nodes_m + np.array([0.0, 0.0, 0.017])
    t_s, images = frames[3]
    gray = cv2.cvtColor(images[0], cv2.COLOR_BGR2GRAY)
    tracker.second_view.heights_now(gray, tracker.features, lifted, t_s, [PairedView(images[1], t_s)])
    heights, _ = tracker.second_view.collect()
    assert heights is not None and heights.max() < 0.0015


def test_points_whose_height_is_not_known_are_searched_for_beside_those_started_at_theirs() -> None:
    """On a 17 mm ridge: the points without a height are searched for exactly as when none has one, and
    those started at the heights that search found stay there."""
    cfg = Config()
    start_taichi(cfg.taichi.arch)
    world, cameras, sensors = _wrinkled_cell(0.017)
    layout = ConveyorLayout.of_cell(cfg.cell)
    tracker = Tracker(cfg.tracker, cameras[0], layout, other_cameras=cameras[1:])
    ((t_s, images),) = _frames(world, sensors, 1)
    views = [PairedView(images[1], t_s)]
    tracker.track(images[0], t_s, ModuleCommands.all_stop(layout.n_modules), views)
    assert tracker.features is not None
    px = tracker.features.px.astype(np.float64)
    gray = cv2.cvtColor(images[0], cv2.COLOR_BGR2GRAY)
    searched = measure_surface(gray, px, t_s, cameras[0], cameras[1:], views, cfg.tracker.stereo)
    assert searched is not None
    all_points, all_ok = searched
    assert all_points[:, 2].max() > 0.012  # the ridge's points among them
    guess_m = np.full((len(px), 3), np.nan)
    guess_m[all_ok] = all_points
    unknown = (np.arange(len(px)) % 2 == 1) | ~all_ok
    guess_m[unknown] = np.nan
    found = measure_surface(gray, px, t_s, cameras[0], cameras[1:], views, cfg.tracker.stereo, guess_m)
    assert found is not None
    points, ok = found
    np.testing.assert_array_equal(ok[unknown], all_ok[unknown])
    z, all_z = np.full(len(px), np.nan), np.full(len(px), np.nan)
    z[ok], all_z[all_ok] = points[:, 2], all_points[:, 2]
    np.testing.assert_array_equal(z[unknown], all_z[unknown])
    known = ~unknown
    assert ok[known].mean() > 0.95 and np.nanmax(np.abs(z[known] - all_z[known])) < 0.0005


def test_feature_heights_are_looked_up_by_id_and_nan_for_the_rest() -> None:
    heights = FeatureHeights.of(np.array([5, 2, 9]), np.array([0.005, 0.002, 0.009]))
    np.testing.assert_array_equal(
        heights.at(np.array([2, 3, 9, 100, 0])), [0.002, np.nan, 0.009, np.nan, np.nan]
    )
    assert np.isnan(FeatureHeights.of(np.zeros(0, int), np.zeros(0)).at(np.array([1]))).all()
