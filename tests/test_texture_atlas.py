"""clothd.core.texture_atlas: a new feature placed on the cloth by texture, not by a wrong estimate, and one
on an occluder told apart."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from clothd.config import MeshConfig, TrackerConfig
from clothd.core.binding import cloth_coordinates
from clothd.core.camera_model import CameraModel
from clothd.core.estimators import make_estimator
from clothd.core.feature_set import FeatureSet
from clothd.core.mesh import QuadMesh
from clothd.core.texture_atlas import MAX_PLACED_PER_UPKEEP, NewFeatureBinding, TextureAtlas, atlas_holds
from clothd.taichi_runtime import start_taichi

pytestmark = pytest.mark.clock_free

TEXTURE_M = 0.00025  # a texture pixel
CLOTH = (np.array([-0.09, -0.07]), np.array([0.09, 0.07]))  # the cloth's rectangle at rest, table metres


def _texture(seed: int) -> np.ndarray:
    """A denim-like grey texture over the cloth: noise at several scales, uint8, TEXTURE_M a pixel."""
    rng = np.random.default_rng(seed)
    lo, hi = CLOTH
    h, w = (np.ceil((hi - lo)[::-1] / TEXTURE_M)).astype(int) + 1
    out = np.zeros((h, w), np.float32)
    for sigma, gain in ((2.0, 1.0), (8.0, 3.0), (30.0, 6.0)):
        out += gain * cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
    out = (out - out.mean()) / out.std()
    return np.clip(128 + 40 * out, 0, 255).astype(np.uint8)


def _render(camera: CameraModel, texture: np.ndarray, shift_m: np.ndarray) -> np.ndarray:
    """The cloth moved by shift_m on the table, seen by the camera (640 x 480 grey); the table is 30."""
    u, v = np.meshgrid(np.arange(640, dtype=np.float64), np.arange(480, dtype=np.float64))
    table = camera.backproject_to_plane(np.stack([u.ravel(), v.ravel()], axis=1))[:, :2] - shift_m
    tex = ((table - CLOTH[0]) / TEXTURE_M).astype(np.float32).reshape(480, 640, 2)
    return cv2.remap(texture, tex[..., 0], tex[..., 1], cv2.INTER_LINEAR, borderValue=30)


def _setup() -> tuple[CameraModel, np.ndarray, QuadMesh, np.ndarray, TextureAtlas]:
    camera = CameraModel.ideal(640, 480, 900.0, 1.0)
    texture = _texture(3)
    lo, hi = CLOTH
    mesh = QuadMesh.covering(np.array([lo, [hi[0], lo[1]], hi, [lo[0], hi[1]]]), 9, 7)
    rest = mesh.rest_nodes_m().reshape(-1, 2)
    nodes_px = camera.project(np.column_stack([rest, np.zeros(len(rest))]))
    atlas = TextureAtlas(mesh, _render(camera, texture, np.zeros(2)), nodes_px, np.ones(len(rest), bool))
    return camera, texture, mesh, nodes_px, atlas


def _inner_points(camera: CameraModel, shift_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (k, 2) of cloth points well inside the cloth, moved by shift_m, and those points (k, 2)."""
    s, t = np.meshgrid(np.linspace(-0.06, 0.06, 5), np.linspace(-0.045, 0.045, 4))
    material = np.stack([s.ravel(), t.ravel()], axis=1)
    table = material + shift_m
    return camera.project(np.column_stack([table, np.zeros(len(table))])), material


def test_a_feature_is_placed_where_its_texture_is_not_where_a_wrong_estimate_binds_it() -> None:
    camera, texture, mesh, nodes_px, atlas = _setup()
    shift = np.array([0.004, -0.003])  # the cloth moved 5 mm; the estimate (nodes_px) did not follow
    frame = _render(camera, texture, shift)
    px, material = _inner_points(camera, shift)
    flat = np.ones(mesh.n_nodes, bool)
    bound, on = cloth_coordinates(mesh, nodes_px, px)
    assert on.all()
    np.testing.assert_allclose(np.linalg.norm(bound - material, axis=1), 0.005, atol=1e-4)
    placed, unlike = atlas.relocate(frame, nodes_px, flat, bound)
    assert not unlike.any()
    assert np.linalg.norm(placed - material, axis=1).max() < 3e-4
    assert atlas_holds(atlas, frame, nodes_px, flat, bound)


def test_a_feature_on_an_occluder_matches_nothing() -> None:
    camera, texture, mesh, nodes_px, atlas = _setup()
    frame = _render(camera, texture, np.zeros(2))
    px, material = _inner_points(camera, np.zeros(2))
    arm = _render(camera, _texture(8), np.zeros(2))  # something else with texture, over half the points
    covered = px[:, 0] > 320
    cover = np.zeros(frame.shape, np.uint8)
    for x, y in px[covered]:
        cv2.circle(cover, (int(x), int(y)), 20, 255, -1)
    frame = np.where(cover > 0, arm, frame)
    flat = np.ones(mesh.n_nodes, bool)
    placed, unlike = atlas.relocate(frame, nodes_px, flat, material)
    np.testing.assert_array_equal(unlike, covered)
    assert np.linalg.norm(placed[~covered] - material[~covered], axis=1).max() < 3e-4
    np.testing.assert_array_equal(placed[covered], material[covered])  # the estimate's binding stands


def test_a_cloth_that_looks_different_everywhere_does_not_hold_the_atlas() -> None:
    camera, _, mesh, nodes_px, atlas = _setup()
    _, material = _inner_points(camera, np.zeros(2))
    other = _render(camera, _texture(5), np.zeros(2))
    assert not atlas_holds(atlas, other, nodes_px, np.ones(mesh.n_nodes, bool), material)


def test_a_fold_is_not_judged() -> None:
    camera, _, mesh, nodes_px, atlas = _setup()
    frame = _render(camera, _texture(6), np.zeros(2))  # looks like nothing the atlas holds
    _, material = _inner_points(camera, np.zeros(2))
    placed, unlike = atlas.relocate(frame, nodes_px, np.zeros(mesh.n_nodes, bool), material)
    assert not unlike.any()
    np.testing.assert_array_equal(placed, material)


def test_a_frame_places_at_most_its_share_of_new_features_the_strongest_first() -> None:
    start_taichi()
    camera, texture, mesh, _, _ = _setup()
    estimator = make_estimator(TrackerConfig(mesh=MeshConfig(nodes_x=9, nodes_y=7)), camera)
    rest = mesh.rest_nodes_m()
    estimator.start(
        mesh,
        np.array([*mesh.centre_m, mesh.theta_rad]),
        np.column_stack([rest.reshape(-1, 2), np.zeros(mesh.n_nodes)]),
    )
    frame = _render(camera, texture, np.zeros(2))
    binding = NewFeatureBinding(estimator, mesh, frame)
    s, t = np.meshgrid(np.linspace(-0.07, 0.07, 12), np.linspace(-0.05, 0.05, 10))
    material = np.stack([s.ravel(), t.ravel()], axis=1)  # 120 points, more than a frame places
    px = camera.project(np.column_stack([material, np.zeros(len(material))]))
    held = FeatureSet(mesh)
    held.add(px[:40], material[:40], np.ones(40, bool))
    _, taken = binding.bind(frame, px, held)
    assert taken.sum() == MAX_PLACED_PER_UPKEEP < len(px)
    assert taken[:MAX_PLACED_PER_UPKEEP].all()  # in the detector's order, the strongest corners first
