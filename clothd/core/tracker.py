"""One tracker tick: frame -> features -> predict -> gate and correct -> estimate.

Modes (the original report's six variants):
- `none`: raw features, no model; a feature is placed where Lucas–Kanade measured it.
- `predict`: the mesh model driven by the conveyor input, never corrected.
- `rigid`: the rigid plate EKF; `mesh`: the mesh EKF. Both with the conveyor input, or without it.

Features keep their identity (an id each) from detection until they are dropped: by the forward–
backward check, by the filter's Mahalanobis gate, or by leaving the cloth. When fewer than a fraction
of `max_features` remain, or a part of the cloth has none, new ones are detected inside the current
cloth outline and bound to cloth space through the current estimate.

The core is pure: a `clock` is injected only to time the stages.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

from clothd.config import TrackerConfig
from clothd.core import rigid
from clothd.core.binding import cloth_coordinates
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout, ModuleModel, rigid_velocity_fit
from clothd.core.ekf import UpdateStats, gate, predict, update_information
from clothd.core.features import FeatureEngine, GrayFrame, coverage_holes
from clothd.core.folds import fold_heights_m
from clothd.core.mesh import Binding, QuadMesh, blend, measurement_jacobian
from clothd.core.mesh_ekf import NodeBelief
from clothd.core.messages import Estimate, ModuleCommands
from clothd.core.physics import CONTACT_HEIGHT_M, MassSpring, stick_time_s
from clothd.core.segmentation import ClothRegion, cloth_mask_from_outline, find_cloth, full_frame_region

Clock = Callable[[], float]
Belts = tuple[np.ndarray, np.ndarray]  # each module's signed belt speed (m/s) and heading (rad)


class Tracker:
    def __init__(
        self,
        cfg: TrackerConfig,
        camera: CameraModel,
        conveyor: ConveyorLayout | None,
        roi: str = "auto",
        clock: Clock | None = None,
    ) -> None:
        self.cfg = cfg
        self.camera = camera
        self.conveyor = conveyor
        self.roi = roi
        self.clock = clock or (lambda: 0.0)
        self.engine = FeatureEngine(cfg.features)
        # The modules keep moving whatever the tracker believes, so their model survives a reset.
        self.modules = (
            None
            if conveyor is None
            else ModuleModel(
                conveyor.n_modules, cfg.modules.accel_limit_m_s2, cfg.modules.steer_rate_limit_rad_s
            )
        )
        self._modules_t_s: float | None = None
        self._reset_state()

    def _reset_state(self) -> None:
        self.initialised = False
        self.prev: GrayFrame | None = None
        self.prev_t_s = 0.0
        self.next_id = 0
        self.ids = np.zeros(0, np.int64)
        self.px = np.zeros((0, 2), np.float32)
        self.cloth_xy = np.zeros((0, 2))  # cloth-space (s, t) of each feature
        self.mesh: QuadMesh | None = None
        self.binding: Binding | None = None
        self.sim: MassSpring | None = None
        self.belief: NodeBelief | None = None
        self.x = np.zeros(rigid.N_STATES)
        self.P = rigid.initial_covariance(self.cfg.ekf)
        self.pose0 = np.zeros(3)

    def reset(self) -> None:
        """Forget everything; the next frame initialises again."""
        self._reset_state()

    @property
    def mesh_shape(self) -> tuple[int, int] | None:
        """(ny, nx) of the tracking mesh once initialised."""
        return None if self.mesh is None else (self.mesh.ny, self.mesh.nx)

    # -- the tick --------------------------------------------------------------------------------

    def step(self, image: np.ndarray, t_s: float, commands: ModuleCommands | None) -> Estimate:
        timing: dict[str, float] = {}
        t0 = self.clock()
        frame = self.engine.prepare(image)
        belts = self._advance_modules(t_s, commands)
        if not self.initialised or self.prev is None:
            return self._initialise(frame, image, t_s, timing, t0)
        dt = max(t_s - self.prev_t_s, 1e-3)
        t1 = self.clock()
        guess = self._predict(dt, belts)
        t2 = self.clock()
        result = self.engine.track(self.prev, frame, self.px, guess_px=guess)
        t3 = self.clock()
        keep = result.ok
        meas = result.px
        stats = UpdateStats(int(keep.sum()), 0, 0.0)
        if self.cfg.model in ("rigid", "mesh") and keep.any():
            stats, accepted = self._correct(meas, keep)
            keep = keep & accepted
        t4 = self.clock()
        meas_all = np.where(keep[:, None], meas, np.nan)
        self._drop(keep)
        self.px = meas[keep].astype(np.float32)
        estimate = self._estimate(t_s, meas_all[keep], stats, timing)
        if self._diverged(stats):
            self.reset()
            estimate = self._lost(t_s, timing)
        else:
            self._resample(frame, image.shape[:2])
        self.prev, self.prev_t_s = frame, t_s
        t5 = self.clock()
        timing.update(
            prepare=t1 - t0, predict=t2 - t1, klt=t3 - t2, update=t4 - t3, resample=t5 - t4, tick=t5 - t0
        )
        return estimate

    # -- initialisation --------------------------------------------------------------------------

    def _initialise(
        self, frame: GrayFrame, image: np.ndarray, t_s: float, timing: dict[str, float], t0: float
    ) -> Estimate:
        h, w = image.shape[:2]
        region: ClothRegion | None = full_frame_region(w, h) if self.roi == "full" else find_cloth(image)
        if region is None:
            return self._lost(t_s, timing)
        corners_world = self.camera.backproject_to_plane(region.corners_px.astype(np.float64))[:, :2]
        self.mesh = QuadMesh.covering(corners_world, self.cfg.mesh.nodes_x, self.cfg.mesh.nodes_y)
        self.pose0 = np.array([*corners_world.mean(axis=0), self.mesh.theta_rad])
        self.x = np.concatenate([self.pose0, np.zeros(3)])
        self.P = rigid.initial_covariance(self.cfg.ekf)
        rest = self.mesh.rest_nodes_m().reshape(-1, 2)
        nodes = np.column_stack([rest, np.zeros(len(rest))])
        if self.cfg.model in ("mesh", "predict"):
            self.sim = MassSpring(self.cfg.physics, self.mesh.rest_nodes_m())
            e = self.cfg.ekf
            P0 = np.diag([e.initial_pos_sigma_m**2] * 3 + [e.initial_vel_sigma_m_s**2] * 3)
            self.belief = NodeBelief(
                np.column_stack([nodes, np.zeros_like(nodes)]),
                np.tile(P0, (len(nodes), 1, 1)),
                self.mesh.quad_nodes(),
            )
        self.initialised = True
        self.prev, self.prev_t_s = frame, t_s
        mask = cloth_mask_from_outline(region.corners_px, w, h, int(self.cfg.features.edge_margin_px))
        self._add_features(self.engine.detect(frame, mask, self.cfg.features.max_features))
        timing["tick"] = self.clock() - t0
        return self._estimate(t_s, self.px.astype(np.float64), UpdateStats(len(self.ids), 0, 0.0), timing)

    # -- model -----------------------------------------------------------------------------------

    def _belt_input(self, points_m: np.ndarray, belts: Belts | None) -> tuple[np.ndarray, np.ndarray]:
        """Belt velocity (n, 2) under points, and whether a belt is there, for the modules' state."""
        if self.conveyor is None or belts is None:
            return np.zeros((len(points_m), 2)), np.zeros(len(points_m), bool)
        speed_m_s, heading_rad = belts
        if not self.cfg.use_input:
            # Without the input (u = 0) the model takes the modules as stopped: the cloth rests on still
            # belts, and friction holds the mesh where the features last put it.
            speed_m_s = np.zeros_like(speed_m_s)
        return self.conveyor.belt_velocity(points_m, speed_m_s, heading_rad)

    def _advance_modules(self, t_s: float, commands: ModuleCommands | None) -> Belts | None:
        """The modules' (signed speed, heading) over the tick ending at t_s, from their commands."""
        if self.modules is None or commands is None:
            return None
        dt = max(t_s - self._modules_t_s, 0.0) if self._modules_t_s is not None else 0.0
        self._modules_t_s = t_s
        return self.modules.advance(commands.speed_m_s, commands.heading_rad, dt)

    def _predict(self, dt: float, belts: Belts | None) -> np.ndarray | None:
        """Advance the model to this tick and return the predicted pixels of the features (LK's first
        guess), or None in the model-free mode."""
        cfg = self.cfg
        if cfg.model == "none":
            return None
        if cfg.model == "rigid":
            tau = None
            twist = None
            if self.conveyor is not None and belts is not None and cfg.use_input:
                # The plate follows the belts as a node does: friction's stick time plus the damping's.
                tau = stick_time_s(cfg.physics) + 1.0 / cfg.physics.damping_1_s
                probe = rigid.world_points(self.x, self._cloth_probe_body())
                vel, on = self._belt_input(probe, belts)
                twist = rigid_velocity_fit(probe[on], vel[on], self.x[:2]) if on.any() else np.zeros(3)
            x_pred = rigid.predict_mean(self.x, dt, tau, twist)
            self.x, self.P = predict(
                self.x, self.P, x_pred, rigid.transition(dt, tau), rigid.process_noise(cfg.ekf, dt)
            )
            return rigid.measure(self.camera, self.x, self._body())[0].astype(np.float32)
        assert self.sim is not None and self.belief is not None
        pos, vel = self.belief.x[:, :3], self.belief.x[:, 3:]
        belt_v, on_belt = self._belt_input(pos, belts)
        self.sim.set_state(pos, vel)
        self.sim.step(dt, belt_v, on_belt)
        x_new, v_new = self.sim.state()
        in_contact = on_belt & (x_new[:, 2] <= CONTACT_HEIGHT_M)
        F = self.sim.transition_blocks(dt, in_contact)
        e = cfg.ekf
        Q = np.diag([e.process_pos_sigma_m**2] * 3 + [e.process_vel_sigma_m_s**2] * 3)
        self.belief.predict(np.column_stack([x_new, v_new]), F, np.tile(Q, (len(x_new), 1, 1)))
        return self._feature_pixels().astype(np.float32)

    def _correct(self, meas: np.ndarray, ok: np.ndarray) -> tuple[UpdateStats, np.ndarray]:
        """Gate and correct with the features LK kept; returns stats and the gate's verdict (n,)."""
        e = self.cfg.ekf
        R_px2 = e.meas_sigma_px**2
        accepted = np.ones(len(ok), bool)
        idx = np.flatnonzero(ok)
        if self.cfg.model == "rigid":
            pred, H = rigid.measure(self.camera, self.x, self._body()[idx])
            nu = meas[idx] - pred
            S = np.einsum("nij,jk,nlk->nil", H, self.P, H) + R_px2 * np.eye(2)
            inside, d2 = gate(nu, S, e.gate_chi2)
            accepted[idx[~inside]] = False
            sel = idx[inside]
            if len(sel):
                Hs = H[inside].reshape(-1, rigid.N_STATES)
                self.x, self.P = update_information(self.x, self.P, nu[inside].ravel(), Hs, R_px2)
            return UpdateStats(len(sel), int((~inside).sum()), float(d2[inside].sum())), accepted
        assert self.belief is not None and self.binding is not None
        sub = self.binding.subset(idx)
        pred, J = measurement_jacobian(self.camera, self.belief.positions_m, sub)
        # The camera corrects the nodes on the table plane only. From above, height barely moves a pixel,
        # and a filter free to use it explained in-plane model error with it: nodes floated 15-20 mm up
        # on flat cloth. Height comes from inextensibility instead (_lift_folds).
        J[..., 2] = 0.0
        stats, inside = self.belief.correct(
            sub.quad, sub.nodes, J, meas[idx] - pred, R_px2, e.gate_chi2, e.smoothness_sigma_m
        )
        accepted[idx[~inside]] = False
        self._lift_folds()
        return stats, accepted

    def _lift_folds(self) -> None:
        """Set the node heights from how much shorter the cloth is on the table than at rest."""
        assert self.belief is not None and self.mesh is not None
        z = fold_heights_m(
            self.belief.positions_m[:, :2].reshape(self.mesh.ny, self.mesh.nx, 2),
            self.mesh.rest_nodes_m(),
            self.cfg.mesh.fold_tolerance_strain,
        )
        e = self.cfg.ekf
        self.belief.set_heights(z.ravel(), e.initial_pos_sigma_m, e.initial_vel_sigma_m_s)

    def _diverged(self, stats: UpdateStats) -> bool:
        """Lost: too few features survive, or the innovations are far beyond what the filter expects."""
        too_few = len(self.ids) < max(6, self.cfg.features.max_features // 50)
        return too_few or stats.nis_per_measurement > self.cfg.ekf.divergence_nis

    # -- features --------------------------------------------------------------------------------

    def _body(self) -> np.ndarray:
        return rigid.body_coordinates(self.cloth_xy, self.pose0)

    def _cloth_probe_body(self) -> np.ndarray:
        """Body coordinates of a coarse grid over the cloth, to read the belts under it."""
        assert self.mesh is not None
        return rigid.body_coordinates(self.mesh.rest_nodes_m().reshape(-1, 2), self.pose0)

    def _feature_pixels(self) -> np.ndarray:
        """Where the current estimate places every feature, (n, 2)."""
        if self.cfg.model == "none":
            return self.px.astype(np.float64)
        if self.cfg.model == "rigid":
            return rigid.measure(self.camera, self.x, self._body())[0]
        assert self.belief is not None and self.binding is not None
        return self.camera.project(blend(self.belief.positions_m, self.binding))

    def _node_pixels(self) -> np.ndarray:
        assert self.belief is not None
        return self.camera.project(self.belief.positions_m)

    def _add_features(self, px: np.ndarray) -> None:
        if len(px) == 0:
            return
        px = px.astype(np.float64)
        if self.belief is not None and self.initialised and len(self.ids) > 0:
            assert self.mesh is not None
            st, on = cloth_coordinates(self.mesh, self._node_pixels(), px)
        elif self.cfg.model == "rigid" and len(self.ids) > 0:
            world = self.camera.backproject_to_plane(px)[:, :2]
            st = (
                rigid.body_coordinates(world, self.x[:3]) @ rigid.rotation(float(self.pose0[2])).T
                + self.pose0[:2]
            )
            on = np.ones(len(px), bool)
        else:
            st = self.camera.backproject_to_plane(px)[:, :2]
            on = np.ones(len(px), bool)
        if self.mesh is not None:
            b = self.mesh.bind(np.nan_to_num(st))
            on &= b.inside
        px, st = px[on], st[on]
        self.ids = np.concatenate([self.ids, self.next_id + np.arange(len(px))])
        self.next_id += len(px)
        self.px = np.concatenate([self.px, px.astype(np.float32)])
        self.cloth_xy = np.concatenate([self.cloth_xy, st])
        if self.mesh is not None:
            self.binding = self.mesh.bind(self.cloth_xy)

    def _drop(self, keep: np.ndarray) -> None:
        self.ids, self.cloth_xy = self.ids[keep], self.cloth_xy[keep]
        if self.binding is not None:
            self.binding = self.binding.subset(np.flatnonzero(keep))

    def outline_m(self) -> np.ndarray | None:
        """The cloth's current outline on the table, world (k, 2) metres; None before initialisation or
        in the model-free mode."""
        if self.mesh is None or self.cfg.model == "none":
            return None
        if self.belief is not None:
            g = self.belief.positions_m[:, :2].reshape(self.mesh.ny, self.mesh.nx, 2)
            return _boundary(g)
        w, h = self.mesh.width_m / 2, self.mesh.height_m / 2
        return rigid.world_points(self.x, np.array([[-w, -h], [w, -h], [w, h], [-w, h]]))[:, :2]

    def _outline_px(self) -> np.ndarray:
        """The cloth's current outline in the image, (k, 2)."""
        assert self.mesh is not None
        if self.belief is not None:
            return _boundary(self._node_pixels().reshape(self.mesh.ny, self.mesh.nx, 2))
        outline = self.outline_m()
        if outline is not None:
            return self.camera.project(np.column_stack([outline, np.zeros(len(outline))]))
        return cv2.convexHull(self.px.astype(np.float32)).reshape(-1, 2).astype(np.float64)

    def _resample(self, frame: GrayFrame, shape: tuple[int, int]) -> None:
        f = self.cfg.features
        h, w = shape
        if len(self.ids) < 3:
            return
        mask = cloth_mask_from_outline(self._outline_px(), w, h, int(f.edge_margin_px))
        holes = coverage_holes(mask, self.px, f.resample_cell_px)
        short = len(self.ids) < f.resample_below_fraction * f.max_features
        if not short and not holes.any():
            return
        target = mask if short else cv2.bitwise_and(mask, holes)
        room = f.max_features - len(self.ids)
        if room > 0:
            self._add_features(self.engine.detect(frame, target, room, avoid_px=self.px))

    # -- output ----------------------------------------------------------------------------------

    def _pose(self) -> tuple[np.ndarray, np.ndarray]:
        if self.cfg.model == "rigid":
            return self.x[:3].copy(), self.P[:3, :3].copy()
        if self.belief is not None:
            b = self.belief
            return _best_fit_pose(self.mesh, b.positions_m), _best_fit_pose_cov(b.positions_m, b.P)
        return self.pose0.copy(), np.full((3, 3), np.nan)

    def _estimate(
        self, t_s: float, meas: np.ndarray, stats: UpdateStats, timing: dict[str, float]
    ) -> Estimate:
        pose, cov = self._pose()
        nodes = None
        if self.belief is not None and self.mesh is not None:
            nodes = self.belief.positions_m.reshape(self.mesh.ny, self.mesh.nx, 3).copy()
        return Estimate(
            t_s, "tracking", pose, cov, nodes, self.ids.copy(), meas, self._feature_pixels(), stats, timing
        )

    def _lost(self, t_s: float, timing: dict[str, float]) -> Estimate:
        empty = np.zeros((0, 2))
        nan3 = np.full(3, np.nan)
        return Estimate(
            t_s,
            "lost",
            nan3,
            np.full((3, 3), np.nan),
            None,
            np.zeros(0, np.int64),
            empty,
            empty,
            UpdateStats(0, 0, 0.0),
            timing,
        )


def _best_fit_pose_cov(nodes_m: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Covariance (3, 3) of the best-fit pose under the filter's independent node blocks P (n, 6, 6):
    the centre is the mean of the nodes, and a small rotation moves node i by θ ẑ × r_i, so to first
    order θ = Σ (r_i × Δp_i) / Σ |r_i|²."""
    r = nodes_m[:, :2] - nodes_m[:, :2].mean(axis=0)
    n = len(r)
    J = np.zeros((n, 3, 2))  # d pose / d p_i,xy
    J[:, 0, 0] = J[:, 1, 1] = 1.0 / n
    J[:, 2, :] = np.stack([-r[:, 1], r[:, 0]], axis=1) / float((r**2).sum())
    return np.asarray(np.einsum("nij,njk,nlk->il", J, P[:, :2, :2], J))


def _boundary(grid: np.ndarray) -> np.ndarray:
    """The outer ring of a (ny, nx, d) grid, in order around it, (k, d)."""
    return np.concatenate([grid[0, :], grid[1:, -1], grid[-1, -2::-1], grid[-2:0:-1, 0]])


def _best_fit_pose(mesh: QuadMesh | None, nodes_m: np.ndarray) -> np.ndarray:
    """The rigid pose [X, Y, θ] that best maps the rest mesh onto the nodes' x, y (Kabsch in 2-D)."""
    assert mesh is not None
    rest = mesh.rest_nodes_m().reshape(-1, 2)
    cur = nodes_m[:, :2]
    rc, cc = rest.mean(axis=0), cur.mean(axis=0)
    M = (rest - rc).T @ (cur - cc)
    rot = math.atan2(M[0, 1] - M[1, 0], M[0, 0] + M[1, 1])
    return np.array([cc[0], cc[1], math.remainder(mesh.theta_rad + rot, 2 * math.pi)])
