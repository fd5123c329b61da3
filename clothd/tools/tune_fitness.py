"""The fitness of a set of mass–spring constants on recorded footage: the original report's cost,
mean + 2 x worst feature pixel error of the model's prediction over a sequence.

`predict` (the report's way, the model alone): a recording is measured once, whatever the constants —
the tracker without a model (`none`) finds the cloth in the first frame, lays the mesh, and follows the
features detected there with Lucas–Kanade; their material points are where they lay on the flat cloth
at the start. A trial then only runs the mass–spring model from that mesh under the recorded commands
(exactly what `predict` mode's state does: never corrected, so the features cannot move it) and
projects each feature's material point through it. Features found later are left out: without a model
nothing says which material point they are. A trial costs the physics only, no image processing.

`mesh`: the whole tracker (the EKF corrects the model) runs per trial, and the cost is taken over its
pixel residuals, as `clothd replay` reports them; slower, by the cost of tracking.

Neither needs ground truth. Where a recording has it (hwsim's truth.npz), the node error is reported
beside the fitness: RMS 3-D distance of the model's nodes from the same material points' true positions,
over every frame (as `clothd bench accuracy` grades it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clothd.config import PhysicsConfig, TrackerConfig
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import BeltField, ModuleModel
from clothd.core.estimators.mesh import MeshEstimator
from clothd.core.mesh import Binding, QuadMesh, blend
from clothd.core.messages import Estimate
from clothd.core.tracker import MIN_DT_S
from clothd.errors import InputError
from clothd.tools.grading import material_coordinates, true_positions
from clothd.tools.offline import OfflineTracking
from hwsim.truth import Truth

# Fewer features than this followed from the first frame and a sequence says nothing about the model.
MIN_FEATURES = 20


@dataclass(frozen=True)
class Sequence:
    """One recording, measured once: everything a trial needs and nothing that depends on the constants.

    t_s (F,); u: the belts under the cloth over the tick ending at each frame (None: no input known);
    mesh: the rest mesh laid over frame 0 (the tracker's); pose0 (3,); binding: the material points of the
    features detected in frame 0 (n); meas_px (F, n, 2): where LK followed them, NaN once lost;
    true_nodes_m (F, ny * nx, 3): the true positions of the mesh nodes' material points, or None."""

    source: Path
    t_s: np.ndarray
    u: list[BeltField | None]
    camera: CameraModel
    mesh: QuadMesh
    pose0: np.ndarray
    binding: Binding
    meas_px: np.ndarray
    true_nodes_m: np.ndarray | None


@dataclass(frozen=True)
class SequenceScore:
    """Over a sequence: the mean of the per-frame mean errors, the largest per-frame worst, and the node
    RMSE against the truth (None without one)."""

    mean_px: float
    worst_px: float
    node_rmse_mm: float | None

    @property
    def cost_px(self) -> float:
        """The original report's: mean + 2 x worst."""
        return self.mean_px + 2.0 * self.worst_px


def measure(recording: Path, cfg: TrackerConfig) -> Sequence:
    """Follow the features of the first frame through `recording` with the tracker's feature settings,
    up to the frame where it loses the cloth."""
    if not recording.exists():
        raise InputError(f"{recording}: no such recording")
    run = OfflineTracking(
        recording, cfg.model_copy(update={"model": "none"}), progress=f"measuring {recording}"
    )
    if run.layout is None or run.schedule is None:
        raise InputError(f"{recording}: no table.json and commands.csv: the model has no input to follow")
    modules = ModuleModel.stopped(run.layout.n_modules, cfg.modules)
    t_s: list[float] = []
    u: list[BeltField | None] = []
    meas: list[np.ndarray] = []
    ids0 = np.zeros(0, np.int64)
    features = None
    for t, _, est in run:
        tracker = run.tracker
        if features is None:  # frame 0: the cloth is found and the features of the sequence detected
            if not est.tracking or tracker.features is None or tracker.mesh is None:
                raise InputError(f"{recording}: no cloth found in the first frame")
            features, mesh, pose0 = tracker.features, tracker.mesh, est.pose
            ids0, st0 = features.ids.copy(), features.cloth_st.copy()
        elif not est.tracking or tracker.features is not features:
            break  # lost, or initialised anew: the features of frame 0 are gone
        commands = run.schedule.at(t)
        dt = t - t_s[-1] if t_s else 0.0
        speed, heading = modules.advance(commands.speed_m_s, commands.heading_rad, dt)
        u.append(BeltField(run.layout, speed, heading) if cfg.use_input else None)
        t_s.append(t)
        meas.append(_measured(est, ids0))
    if len(ids0) < MIN_FEATURES:
        raise InputError(f"{recording}: only {len(ids0)} features in the first frame (need {MIN_FEATURES})")
    if len(t_s) < 2:  # what a refused drive leaves: its recording started, then stopped at once
        raise InputError(f"{recording}: the cloth was followed in {len(t_s)} frame(s): nothing to fit to")
    rest_nodes = mesh.rest_nodes_m().reshape(-1, 2)
    true_nodes = None
    if (recording / "truth.npz").exists():
        truth = Truth.load(recording)
        true_nodes = true_positions(truth, material_coordinates(truth, rest_nodes))[: len(t_s)]
    return Sequence(
        recording, np.array(t_s), u, run.camera_model, mesh, pose0, mesh.bind(st0), np.stack(meas), true_nodes
    )


def _measured(est: Estimate, ids0: np.ndarray) -> np.ndarray:
    """(n, 2) pixels of the frame-0 features ids0 in this estimate, NaN where not measured."""
    out = np.full((len(ids0), 2), np.nan)
    idx = np.searchsorted(ids0, est.feature_id)
    known = (idx < len(ids0)) & (ids0[np.minimum(idx, len(ids0) - 1)] == est.feature_id)
    out[idx[known]] = est.meas_px[known]
    return out


class ModelPredictor:
    """The mesh model alone over measured sequences, allocated once per mesh shape (Taichi fields and
    kernel) and given each trial's constants."""

    def __init__(self, cfg: TrackerConfig) -> None:
        self.cfg = cfg
        self._models: dict[tuple[int, int], MeshEstimator] = {}

    def _model(self, seq: Sequence, physics: PhysicsConfig) -> MeshEstimator:
        shape = (seq.mesh.nx, seq.mesh.ny)
        model = self._models.get(shape)
        if model is None:
            mesh_cfg = self.cfg.mesh.model_copy(update={"nodes_x": shape[0], "nodes_y": shape[1]})
            model = MeshEstimator(seq.camera, mesh_cfg, physics, self.cfg.ekf, self.cfg.use_input, False)
            self._models[shape] = model
        model.camera_model = seq.camera
        model.sim.set_material(physics)
        model.start(seq.mesh, seq.pose0)  # lays the rest mesh, and with it the mass of these constants
        return model

    def score(self, seq: Sequence, physics: PhysicsConfig) -> SequenceScore:
        model = self._model(seq, physics)
        F = len(seq.t_s)
        nodes = np.empty((F, seq.mesh.n_nodes, 3))
        nodes[0] = model.estimate().nodes_m.reshape(-1, 3)  # type: ignore[union-attr]
        err = np.full((F, len(seq.binding)), np.nan)
        # Constants far off blow the model up within a few ticks: that design scores infinite, quietly.
        with np.errstate(invalid="ignore", over="ignore"):
            for k in range(1, F):
                model.predict(seq.u[k], max(float(seq.t_s[k] - seq.t_s[k - 1]), MIN_DT_S))
                positions = model.estimate().nodes_m.reshape(-1, 3)  # type: ignore[union-attr]
                if not np.isfinite(positions).all():
                    return _blown_up(seq.true_nodes_m)
                nodes[k] = positions
                pred_px = seq.camera.project(blend(positions, seq.binding))
                err[k] = np.linalg.norm(pred_px - seq.meas_px[k], axis=1)
            return _score(err[1:], nodes, seq.true_nodes_m)


def _score(err_px: np.ndarray, nodes_m: np.ndarray, true_nodes_m: np.ndarray | None) -> SequenceScore:
    """err_px (F, n), NaN where a feature was not measured; nodes (F, n_nodes, 3) against the truth."""
    per_frame = err_px[~np.isnan(err_px).all(axis=1)]
    if not len(per_frame):
        raise InputError("no feature was followed past the first frame")
    if not np.isfinite(per_frame[~np.isnan(per_frame)]).all():
        return _blown_up(true_nodes_m)
    mean_px = float(np.mean(np.nanmean(per_frame, axis=1)))
    worst_px = float(np.max(np.nanmax(per_frame, axis=1)))
    return SequenceScore(mean_px, worst_px, _node_rmse_mm(nodes_m, true_nodes_m))


def _blown_up(true_nodes_m: np.ndarray | None) -> SequenceScore:
    """A model that blew up scores infinite, so that a search moves away from it."""
    return SequenceScore(np.inf, np.inf, None if true_nodes_m is None else np.inf)


def _node_rmse_mm(nodes_m: np.ndarray, true_nodes_m: np.ndarray | None) -> float | None:
    """RMS 3-D distance (mm) of nodes (F, n, 3) from their true positions (F' >= F, n, 3)."""
    if true_nodes_m is None:
        return None
    d = np.linalg.norm(nodes_m - true_nodes_m[: len(nodes_m)], axis=-1)
    return float(np.sqrt(np.mean(d**2)) * 1e3)


def track_score(seq: Sequence, cfg: TrackerConfig) -> SequenceScore:
    """`mesh`: the whole tracker over the recording with cfg, cost over its residuals (measured minus
    where the corrected estimate places each feature), node error up to the first loss."""
    means: list[float] = []
    worsts: list[float] = []
    nodes: list[np.ndarray] = []
    for _, _, est in OfflineTracking(seq.source, cfg, read_ahead=False):
        if not est.tracking or est.nodes_m is None:
            break
        r = est.residual_px
        if nodes and len(r):  # frame 0 has no prediction to be wrong
            means.append(float(r.mean()))
            worsts.append(float(r.max()))
        nodes.append(est.nodes_m.reshape(-1, 3))
    if not means:
        raise InputError(f"{seq.source}: the tracker lost the cloth at once")
    if not np.isfinite(means).all():
        return _blown_up(seq.true_nodes_m)
    return SequenceScore(
        float(np.mean(means)), float(np.max(worsts)), _node_rmse_mm(np.stack(nodes), seq.true_nodes_m)
    )
