"""One tracker tick: frame -> features -> estimator (predict, correct) -> resample -> Estimate.

The modes are the original report's six variants: no model, the mesh model predicted only, and the rigid
and the mesh EKF, each with the conveyor input or without it. What differs between them lives in the
estimator (clothd/core/estimators); the tracker only composes.

Features keep their identity from detection until they are dropped: by the forward–backward check, by
the estimator's gate, or by leaving the cloth. When fewer than a fraction of `max_features` remain, or a
part of the cloth has none, new ones are detected inside the current outline and bound to cloth space
through the current estimate.

The core is pure: a `clock` is injected only to time the stages.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import cv2
import numpy as np

from clothd.config import TrackerConfig
from clothd.core.anchors import AnchorFrames
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import BeltField, ConveyorLayout, ModuleModel
from clothd.core.ekf import UpdateStats
from clothd.core.estimators import Measurements, StateEstimate, make_estimator
from clothd.core.feature_set import FeatureSet
from clothd.core.features import (
    FeatureEngine,
    GrayFrame,
    aperture_whitening,
    classify_texture,
    coverage_holes,
)
from clothd.core.mesh import QuadMesh
from clothd.core.messages import Detections, Estimate, ModuleCommands, PairedView
from clothd.core.modes import FlatnessBasis
from clothd.core.outline_edges import OutlineEdges
from clothd.core.second_view import SecondView
from clothd.core.segmentation import (
    ClothColour,
    ClothRegion,
    cloth_mask_from_outline,
    find_cloth,
    full_frame_region,
)
from clothd.core.texture_atlas import NewFeatureBinding
from clothd.core.unfold import unfold

Clock = Callable[[], float]
MIN_DT_S = 1e-3  # two frames with the same time stamp still advance the model a little
MIN_FEATURES_ALIVE = 6  # fewer than this (or 2 % of the budget) and the cloth is lost
MIN_FEATURES_TO_RESAMPLE = 3  # an outline through fewer features means nothing
# On a repeating pattern, a feature whose two LK starts land this far apart landed on two look-alikes.
AMBIGUOUS_PX = 1.0
AMBIGUOUS_NEAR_PX = 2.0  # ... and is kept if one of them lies this near where the others put the cloth


class Tracker:
    """Follows one cloth through the frames of one camera.

    camera_model: the camera's geometry over the table; layout: the module array under the cloth (None
    when the footage has no conveyor input); roi "auto" finds the cloth in the first frame, "full" takes
    the whole frame as the cloth. `step` is called once per frame, in order; `reset` forgets the cloth.
    A live loop calls `track` and, once the estimate's commands are out, `upkeep`: `step` is the two.
    """

    def __init__(
        self,
        cfg: TrackerConfig,
        camera_model: CameraModel,
        layout: ConveyorLayout | None,
        roi: str = "auto",
        clock: Clock | None = None,
        other_cameras: Sequence[CameraModel] = (),
    ) -> None:
        self.cfg = cfg
        self.camera_model = camera_model
        self._belts: BeltField | None = None  # under the cloth at the frame being tracked
        self.layout = layout
        self.roi = roi
        self.clock = clock or (lambda: 0.0)
        others = other_cameras if cfg.estimates_shape else ()
        self.second_view = SecondView(camera_model, others, cfg.stereo, self.clock)
        # Where the cloth is in the first frame: several pieces' trackers each take theirs (core/pieces.py).
        self.find_region: Callable[[np.ndarray], ClothRegion | None] = find_cloth
        self._engine_default = FeatureEngine(cfg.features)
        # A periodic weave's stripes need a wider LK window, and its measurements count across them only.
        f = cfg.features
        periodic = {
            "lk_window_px": f.periodic_lk_window_px,
            "aperture_max_ratio": max(f.aperture_max_ratio, f.periodic_aperture_max_ratio),
        }
        self._engine_periodic = FeatureEngine(f.model_copy(update=periodic))
        # A repeating pattern's look-alikes blur together on a coarser level.
        self._engine_repetitive = FeatureEngine(f.model_copy(update={"lk_levels": f.repetitive_lk_levels}))
        self.engine = self._engine_default
        self.anchors = AnchorFrames(cfg.features)
        self.estimator = make_estimator(cfg, camera_model)
        self.features: FeatureSet | None = None
        self.restart()

    def restart(self) -> None:
        """Track a cell as built: its modules stopped and straight, its clock from zero. A `reset` keeps
        the modules' model: they keep moving whatever the tracker believes."""
        layout = self.layout
        self.modules = None if layout is None else ModuleModel.stopped(layout.n_modules, self.cfg.modules)
        self._modules_t_s: float | None = None
        self.features = None
        self._next_feature_id = 0
        self.reset()

    def reset(self) -> None:
        """Forget the cloth; the next frame initialises again."""
        if self.features is not None:  # the next cloth's features number on: an id names one patch
            self._next_feature_id = self.features.next_id
        self.prev: GrayFrame | None = None
        self.prev_t_s = 0.0
        self.mesh: QuadMesh | None = None
        self.features = None
        self.colour: ClothColour | None = None  # the cloth's colour against the background, from the start
        self.initial_features = 0  # what the first frame's detection found on the whole cloth
        self.outline: OutlineEdges | None = None  # the outline's edge points (clothd/core/outline_edges.py)
        self.periodic = False  # the cloth is a periodic weave (FeatureConfig.periodic_ratio)
        # The cloth is a repeating pattern with corners, a check (FeatureConfig.repetitive_ncc).
        self.repetitive = False
        self.engine = self._engine_default
        self.flatness_basis = FlatnessBasis.SINCE_START  # the rest shape: the first frame's, or measured
        self._quad_height_m: np.ndarray | None = None  # `quad_height_m`'s
        self.anchors.reset()
        self.second_view.reset()
        self._upkeep_frame: GrayFrame | None = None  # the tracked frame whose upkeep is still to do
        self._detected: list[Detections] = []  # features detected since the last estimate

    def step(
        self,
        image: np.ndarray,
        frame_t_s: float,
        commands: ModuleCommands | None,
        views: Sequence[PairedView | None] = (),
    ) -> Estimate:
        """Track one BGR frame captured at frame_t_s, with `commands` the modules' commands in force while
        it was taken (None: not known). The first frame, and the first after a loss, initialises. views:
        the further cameras' frames paired with it, one per `other_cameras` (None: none paired)."""
        estimate = self.track(image, frame_t_s, commands, views)
        upkeep_s = self.upkeep() or 0.0
        if "tick" in estimate.timing_s:
            estimate.timing_s["resample"] = upkeep_s
            estimate.timing_s["tick"] += upkeep_s
        return estimate

    @property
    def initialising(self) -> bool:
        """The next frame begins tracking afresh (the further cameras' views are used then)."""
        return self.features is None or self.prev is None

    def upkeep(self) -> float | None:
        """The last tracked frame's upkeep, which its estimate does not need: new features where the cloth
        has too few, and the new features' anchors. Its time in seconds; None when there was none to do."""
        frame, self._upkeep_frame = self._upkeep_frame, None
        if frame is None:
            return None
        t0 = self.clock()
        self._resample(frame)
        if self.cfg.features.anchor:
            assert self.features is not None
            self.anchors.adopt(frame, self.features)
        return self.clock() - t0

    def track(
        self,
        image: np.ndarray,
        frame_t_s: float,
        commands: ModuleCommands | None,
        views: Sequence[PairedView | None] | None = (),
    ) -> Estimate:
        """`step` up to the estimate; `upkeep` does the rest (or the next call, if it was not called)."""
        self.upkeep()
        timing: dict[str, float] = {}
        t0 = self.clock()
        frame = self.engine.prepare(image)
        u = self._belts = self._advance_modules(frame_t_s, commands)
        if self.features is None or self.prev is None:
            return self._initialise(frame, image, frame_t_s, views or (), timing, t0)
        features = self.features
        dt_s = max(frame_t_s - self.prev_t_s, MIN_DT_S)
        t1 = self.clock()
        self.estimator.predict(u, dt_s)
        guess = self.estimator.feature_pixels(features)
        t2 = self.clock()
        result = self.engine.track(self.prev, frame, features.px, guess_px=guess)
        measured = result.px
        if self.cfg.features.anchor:
            measured, _ = self.anchors.refine(self.engine, frame, features, result.px, result.ok)
        t3 = self.clock()
        self._collect_heights(timing)  # the last frame's, measured on their thread meanwhile
        keep = result.ok
        ambiguous = np.zeros(len(keep), bool)
        if self.repetitive:
            from_rest_px, from_rest_ok = self.engine.track_from_rest(self.prev, frame, features.px)
            ambiguous = keep & from_rest_ok & (np.linalg.norm(from_rest_px - measured, axis=1) > AMBIGUOUS_PX)
        stats = UpdateStats(int(keep.sum()), 0, 0.0)
        if keep.any():
            whiten = None
            f = self.engine.cfg
            if f.aperture_max_ratio > 1.0:
                whiten = aperture_whitening(frame.gray, measured, f.lk_window_px, f.aperture_max_ratio)
            edges = None
            if self.outline is not None:
                outline = self.outline
                edges = lambda nodes_m: outline.measure(image, nodes_m)  # noqa: E731
            shape_sigma_m = self.cfg.ekf.periodic_shape_sigma_m if self.periodic or self.repetitive else 0.0
            first = Measurements(
                features, measured, keep & ~ambiguous, whiten, edges, shape_sigma_m, self._quad_height_m
            )
            stats, accepted = self.estimator.correct(first)
            if ambiguous.any():
                more, also, measured = self._settle_look_alikes(first, from_rest_px, ambiguous)
                stats, accepted = stats + more, accepted & also
            keep = keep & accepted
        t4 = self.clock()
        meas = measured[keep]
        features.keep(keep, measured)
        state = self.estimator.estimate()  # once: the heights and the estimate read the same belief
        estimate = self._estimate(frame_t_s, meas, stats, timing, image, state)
        if self._diverged(stats):
            self.reset()
            estimate = Estimate.lost(frame_t_s, timing)
        else:
            self._upkeep_frame = frame
            if self.flatness_basis == FlatnessBasis.MEASURED and state.nodes_m is not None:
                self.second_view.heights_now(frame.gray, features, state.nodes_m, frame_t_s, views)
        self.prev, self.prev_t_s = frame, frame_t_s
        t5 = self.clock()
        timing.update(
            prepare=t1 - t0, predict=t2 - t1, klt=t3 - t2, update=t4 - t3, estimate=t5 - t4, tick=t5 - t0
        )
        return estimate

    def _settle_look_alikes(
        self, first: Measurements, from_rest_px: np.ndarray, ambiguous: np.ndarray
    ) -> tuple[UpdateStats, np.ndarray, np.ndarray]:
        """A repeating pattern, and the two LK starts of the `ambiguous` features landed on different
        look-alikes: the prediction was off by half a period or more somewhere. Of the two, take the one
        nearer where the unambiguous features (already corrected with) have put the cloth; if even that is
        not near, neither is trusted (the feature is dropped and found afresh). Correct with those too.
        `first`: the measurements corrected with already. The statistics, which features stay (n,), and
        the measurements as chosen (n, 2)."""
        measured = first.px
        placed = self.estimator.feature_pixels(first.features)
        if placed is None:  # no model to settle it: the prediction's answer stands
            return UpdateStats(0, 0, 0.0), np.ones(len(measured), bool), measured
        to_rest = np.linalg.norm(from_rest_px - placed, axis=1)
        to_predicted = np.linalg.norm(measured - placed, axis=1)
        chosen = np.where((ambiguous & (to_rest < to_predicted))[:, None], from_rest_px, measured)
        near = np.minimum(to_rest, to_predicted) < AMBIGUOUS_NEAR_PX
        stats, accepted = self.estimator.correct(replace(first, px=chosen, ok=ambiguous & near, edges=None))
        return stats, accepted & (near | ~ambiguous), chosen

    def _advance_modules(self, t_s: float, commands: ModuleCommands | None) -> BeltField | None:
        """What the modules did over the tick ending at t_s, from their commands: the input u."""
        if self.modules is None or self.layout is None or commands is None:
            return None
        dt = max(t_s - self._modules_t_s, 0.0) if self._modules_t_s is not None else 0.0
        self._modules_t_s = t_s
        speed, heading = self.modules.advance(commands.speed_m_s, commands.heading_rad, dt)
        return BeltField(self.layout, speed, heading)

    def _initialise(
        self,
        frame: GrayFrame,
        image: np.ndarray,
        t_s: float,
        views: Sequence[PairedView | None],
        timing: dict[str, float],
        t0: float,
    ) -> Estimate:
        h, w = image.shape[:2]
        region = full_frame_region(w, h) if self.roi == "full" else self.find_region(image)
        if region is None or self.second_view.awaits_pair(t_s, views):
            return Estimate.lost(t_s, timing)
        f = self.cfg.features
        # Features on the cloth seen, not on all its rectangle holds (a folded-over corner's place: belts).
        outline_mask = cloth_mask_from_outline(region.corners_px, w, h, int(f.edge_margin_px))
        mask = cv2.bitwise_and(outline_mask, region.mask)
        px = self.engine.detect(frame, mask, f.max_features).astype(np.float64)
        self.initial_features = len(px)
        nodes_m = self._lay_mesh(frame, region, px, t_s, views)
        assert self.mesh is not None
        if nodes_m is not None:  # first frame's quads: their 2nd-highest corner (the highest: flat read 1.8)
            z = nodes_m[:, 2].reshape(self.mesh.ny, self.mesh.nx)
            self._quad_height_m = np.sort([z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]], axis=0)[-2]
        self.estimator.start(self.mesh, np.array([*self.mesh.centre_m, self.mesh.theta_rad]), nodes_m)
        self.features = FeatureSet(self.mesh, self._next_feature_id)
        self.prev, self.prev_t_s = frame, t_s
        self.new_features = NewFeatureBinding(self.estimator, self.mesh, frame.gray)  # texture_atlas.py
        self.colour = region.colour
        self.periodic, self.repetitive = classify_texture(frame.gray, px, f)
        if self.periodic or self.repetitive:
            self.engine = self._engine_periodic if self.periodic else self._engine_repetitive
        state = self.estimator.estimate()
        if (
            self.periodic
            and f.outline_per_side > 0
            and region.colour is not None
            and state.nodes_m is not None
        ):
            self.outline = OutlineEdges(
                self.mesh, region.colour, self.camera_model, f.outline_per_side, f.outline_search_px, 100.0
            )
            self.outline.measure(image, state.nodes_m.reshape(-1, 3))  # the points' offsets at the start
        if nodes_m is None:  # cloth space is where the cloth lies now
            self._add_features(
                px, self.camera_model.backproject_to_plane(px)[:, :2], np.ones(len(px), bool), t_s
            )
        else:  # ... or where the measured surface's material points lie flat
            self._add_features(px, *self.estimator.cloth_coordinates(px), t_s)
        if f.anchor:
            self.anchors.adopt(frame, self.features)
        timing["tick"] = self.clock() - t0
        stats = UpdateStats(len(self.features), 0, 0.0)
        return self._estimate(t_s, self.features.px.astype(np.float64), stats, timing, image, state)

    @property
    def quad_height_m(self) -> np.ndarray | None:
        """Each quad's highest point (ny-1, nx-1) as a further view last measured it (where the rest shape was
        too: they agree with its lengths only then), a frame being measured waited for; None: none yet."""
        return self._collect_heights()

    def _collect_heights(self, timing: dict[str, float] | None = None) -> np.ndarray | None:
        """Take (and give) the heights last measured; timing["heights"]: their time on their own thread."""
        measured, took_s = self.second_view.collect()
        self._quad_height_m = self._quad_height_m if measured is None else measured
        if timing is not None and took_s is not None:
            timing["heights"] = took_s
        return self._quad_height_m

    def measure_heights(self, views: Sequence[PairedView | None]) -> None:
        """The last frame's heights, tracked with views None once tracking (they come later), from its
        views now; the next estimate carries them, and a frame they do not pair keeps the last."""
        self.second_view.heights_later(views)

    def _lay_mesh(
        self,
        frame: GrayFrame,
        region: ClothRegion,
        px: np.ndarray,
        t_s: float,
        views: Sequence[PairedView | None],
    ) -> np.ndarray | None:
        """The tracking mesh (self.mesh) over the cloth found in the first frame: over its footprint, or,
        where a second view measures the surface, over the cloth as it would lie flat. The nodes' positions
        now (n, 3) in the second case, None in the first (they lie on the footprint)."""
        to_table = self.camera_model.backproject_to_plane
        corners_world = to_table(region.corners_px.astype(np.float64))[:, :2]
        footprint = QuadMesh.covering(corners_world, self.cfg.mesh.nodes_x, self.cfg.mesh.nodes_y)
        self.mesh, self.flatness_basis = footprint, FlatnessBasis.SINCE_START
        # Where the cloth lies on running belts, it moves with them between the two captures.
        velocity = None if self._belts is None else self._belts.velocity_at(to_table(px))[0]
        field = self.second_view.surface(frame.gray, px, velocity, t_s, views, footprint)
        if field is None:
            return None
        self.mesh, nodes_m = unfold(footprint, field, to_table(region.outline_px()))
        self.flatness_basis = FlatnessBasis.MEASURED
        return nodes_m

    def _diverged(self, stats: UpdateStats) -> bool:
        """Lost: too few features survive, or the innovations are far beyond what the filter expects."""
        assert self.features is not None
        alive = len(self.features)
        too_few = alive < max(MIN_FEATURES_ALIVE, self.cfg.features.max_features // 50)
        return too_few or stats.nis_per_measurement > self.cfg.ekf.divergence_nis

    def _resample(self, frame: GrayFrame) -> None:
        """Detect new features where the cloth has too few, and bind them through the estimate."""
        features = self.features
        assert features is not None
        f = self.cfg.features
        h, w = frame.gray.shape[:2]
        if len(features) < MIN_FEATURES_TO_RESAMPLE:
            return
        outline = self.estimator.outline_px()
        if outline is None:  # no model: the features' hull is all there is
            outline = cv2.convexHull(features.px).reshape(-1, 2).astype(np.float64)
        mask = cloth_mask_from_outline(outline, w, h, int(f.edge_margin_px))
        holes = coverage_holes(mask, features.px, f.resample_cell_px)
        # A budget the cloth could not fill even at the start (fewer than resample_below_fraction of it)
        # would keep the tracker "short", detecting over the whole cloth every tick for nothing (2000
        # features on a cloth with ~1000 corners: ~4 ms a tick); short is then judged against what the
        # cloth offered. A budget filled at the start is left as it was, so occlusions refill as before.
        budget = f.max_features
        if self.initial_features < f.resample_below_fraction * f.max_features:
            budget = self.initial_features
        short = len(features) < f.resample_below_fraction * budget
        room = f.max_features - len(features)
        if (not short and not holes.any()) or room <= 0:
            return
        target = mask if short else cv2.bitwise_and(mask, holes)
        px = self.engine.detect(frame, target, room, avoid_px=features.px).astype(np.float64)
        if len(px):  # in the upkeep of the last tracked frame, self.prev
            self._add_features(px, *self.new_features.bind(frame.gray, px, features), self.prev_t_s)

    def _add_features(self, px: np.ndarray, cloth_st: np.ndarray, on_cloth: np.ndarray, t_s: float) -> None:
        """FeatureSet.add, noting where and when the features it takes were detected for the estimate."""
        assert self.features is not None
        first_new_id = self.features.next_id
        self.features.add(px, cloth_st, on_cloth)
        new = self.features.ids >= first_new_id
        ids, new_px = self.features.ids[new], self.features.px[new].astype(np.float64)
        self._detected.append(Detections(ids, np.full(len(ids), t_s), new_px))

    def _estimate(
        self,
        t_s: float,
        meas: np.ndarray,
        stats: UpdateStats,
        timing: dict[str, float],
        image: np.ndarray,
        state: StateEstimate,
    ) -> Estimate:
        assert self.features is not None and self.mesh is not None
        detected = Detections.join(self._detected)
        self._detected = []
        pred = self.estimator.feature_pixels(self.features)
        quad_seen = None
        if state.nodes_m is not None and self.colour is not None:
            n = state.nodes_m
            centres = (n[:-1, :-1] + n[:-1, 1:] + n[1:, :-1] + n[1:, 1:]) / 4.0
            seen = self.colour.is_cloth(image, self.camera_model.project(centres.reshape(-1, 3)))
            quad_seen = seen.reshape(centres.shape[:2])
        return Estimate(
            frame_t_s=t_s,
            status="tracking",
            pose=state.pose,
            pose_cov=state.pose_cov,
            nodes_m=state.nodes_m,
            outline_m=state.outline_m,
            cloth_size_m=(self.mesh.width_m, self.mesh.height_m),
            feature_id=self.features.ids.copy(),
            meas_px=meas,
            pred_px=self.features.px.astype(np.float64) if pred is None else pred,
            stats=stats,
            timing_s=timing,
            quad_seen=quad_seen,
            detected=detected.subset(np.isin(detected.ids, self.features.ids)),  # the dropped never reach one
            flatness_basis=self.flatness_basis,
            quad_height_m=self._quad_height_m,
        )
