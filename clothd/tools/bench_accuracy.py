"""`clothd bench accuracy`: every tracker mode on every shipped scenario, graded against hwsim's truth.

- Feature error (px): a feature is the cloth patch it was detected on. Its material point is found
  from the truth at its first frame (the truth surface point seen at its detection pixel; in a frame
  smeared over an exposure, where the cloth was in the exposure's middle); its true
  pixel in every later frame is that point's projection. Error = |where the estimate places the
  feature − its true pixel|, over the features alive in a frame; per frame the mean and the worst.
  Over the sequence: the mean of the per-frame means and the largest per-frame worst; the original
  report's cost is mean + 2 x worst.
- Node error (mm): a mesh node is the material point under it at initialisation; error = 3-D distance
  to that point's true position (the rigid model's nodes are its rest mesh moved rigidly).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from clothd.config import TrackerConfig
from clothd.core.messages import Estimate, feature_detections
from clothd.formats import read_camera
from clothd.tools.grading import FeatureTruth, material_coordinates, true_positions
from clothd.tools.offline import OfflineTracking
from clothd.tools.oracle import track_with_oracle
from clothd.tools.recordings import recorded_exposure_s
from hwsim.truth import Truth

MODES: tuple[tuple[str, str, bool], ...] = (
    ("none", "none", True),
    ("predict", "predict", True),
    ("rigid", "rigid", True),
    ("rigid --no-input", "rigid", False),
    ("mesh", "mesh", True),
    ("mesh --no-input", "mesh", False),
)
SCENARIOS = ("translate", "rotate", "compress", "occlude", "random")


@dataclass(frozen=True)
class AccuracyRow:
    scenario: str
    mode: str
    feat_mean_px: float
    feat_worst_px: float
    cost_px: float  # mean + 2 x worst
    node_rmse_mm: float | None
    node_max_mm: float | None
    lost_frames: int
    realtime_factor: float


@dataclass(frozen=True)
class Graded:
    row: AccuracyRow
    per_frame_mean_px: np.ndarray  # (F,)
    per_frame_worst_px: np.ndarray  # (F,)


Births = dict[int, tuple[int, np.ndarray]]  # feature id -> (frame, detection pixel (2,))


def track_with_births(run: OfflineTracking) -> tuple[list[Estimate], Births]:
    """Every frame's estimate, and where each feature was detected: the frame and pixel of its detection,
    as the estimates say (estimates.npz's detect_frame and detect_px). A feature found in a frame's upkeep
    is first measured by LK in the next frame; that measurement may already have slipped (along a periodic
    weave's stripes, by whole pixels), so it is not its birth."""
    ests = [est for _, _, est in run]
    return ests, feature_detections(ests)


def _node_errors_mm(truth: Truth, ests: list[Estimate]) -> np.ndarray | None:
    """(F', n) node errors over the frames the tracker was tracking, or None without a model. A node is
    the material point under it when the tracker (re)initialised: the first tracked frame of a run."""
    errs = []
    truth_pts = None
    was_tracking = False
    for k, e in enumerate(ests):
        if not e.tracking or e.nodes_m is None:
            was_tracking = False
            continue
        nodes = e.nodes_m.reshape(-1, 3)
        if not was_tracking:
            truth_pts = true_positions(truth, material_coordinates(truth, nodes[:, :2], frame=k))
            was_tracking = True
        assert truth_pts is not None
        errs.append(np.linalg.norm(nodes - truth_pts[k], axis=1) * 1e3)
    return np.asarray(errs) if errs else None


def grade(
    recording: Path,
    scenario: str,
    mode: str,
    cfg: TrackerConfig,
    camera_json: Path | None = None,
    cameras: int = 1,
    oracle: bool = False,
) -> Graded:
    """One mode on one recording. camera_json: the camera the tracker is given instead of the
    recording's (a calibrated one); the grading itself always goes through the recording's true camera.
    cameras: the recording's first this many, to the tracker. oracle: every feature LK keeps is measured
    at its true pixel (clothd/tools/oracle.py)."""
    truth = Truth.load(recording)
    run = OfflineTracking(
        recording, cfg, camera_json, read_ahead=False, progress=f"{scenario}: {mode}", cameras=cameras
    )
    camera = read_camera(recording / "camera.json")
    feature_truth = FeatureTruth(truth, camera, recorded_exposure_s(recording))
    start = time.perf_counter()
    if oracle:  # it learns each feature's truth as an estimate reports its detection
        ests = track_with_oracle(run, feature_truth)
        wall = time.perf_counter() - start
    else:
        ests, births = track_with_births(run)
        wall = time.perf_counter() - start
        feature_truth.learn_births(births)
    true_px = feature_truth.pixels
    means, worsts = np.full(len(ests), np.nan), np.full(len(ests), np.nan)
    for k, e in enumerate(ests):
        errs = [
            np.linalg.norm(p - true_px[f][k])
            for f, p in zip(e.feature_id.tolist(), e.pred_px, strict=True)
            if f in true_px
        ]
        if errs:
            means[k], worsts[k] = float(np.mean(errs)), float(np.max(errs))
    nodes = _node_errors_mm(truth, ests)
    feat_mean, feat_worst = float(np.nanmean(means)), float(np.nanmax(worsts))
    row = AccuracyRow(
        scenario,
        mode,
        feat_mean,
        feat_worst,
        feat_mean + 2 * feat_worst,
        None if nodes is None else float(np.sqrt(np.mean(nodes**2))),
        None if nodes is None else float(nodes.max()),
        sum(not e.tracking for e in ests),
        (len(ests) / float(1.0 / (truth.t_s[1] - truth.t_s[0]))) / wall,
    )
    return Graded(row, means, worsts)


def format_table(rows: list[AccuracyRow]) -> str:
    out = []
    for sc in dict.fromkeys(r.scenario for r in rows):
        out.append(f"\n{sc}")
        out.append(
            f"  {'mode':<22} {'feat mean':>9} {'worst':>7} {'mean+2w':>8} {'node rmse':>9} {'max':>7} "
            f"{'lost':>5} {'x rt':>5}"
        )
        for r in (r for r in rows if r.scenario == sc):
            rmse = f"{r.node_rmse_mm:6.2f} mm" if r.node_rmse_mm is not None else f"{'-':>9}"
            nmax = f"{r.node_max_mm:7.2f}" if r.node_max_mm is not None else f"{'-':>7}"
            out.append(
                f"  {r.mode:<22} {r.feat_mean_px:6.3f} px {r.feat_worst_px:7.2f} {r.cost_px:8.2f} {rmse} "
                f"{nmax} {r.lost_frames:>5} {r.realtime_factor:5.1f}"
            )
    return "\n".join(out)


def plot(scenario: str, graded: dict[str, Graded], fps: float, path: Path) -> None:
    """Per-frame mean (solid) and worst (dashed) feature error of each mode, as the original's Figures
    6/9/12 plot residuals against frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=110)
    for i, (mode, g) in enumerate(graded.items()):
        colour = f"C{i}"
        frames = np.arange(len(g.per_frame_mean_px))
        ax.plot(frames, g.per_frame_mean_px, color=colour, label=f"{mode} mean")
        ax.plot(frames, g.per_frame_worst_px, color=colour, linestyle="--", linewidth=0.8)
    ax.set_yscale("log")
    ax.set_ylim(bottom=0.01)  # frame 0 is exact by construction; below 0.01 px is noise
    ax.set_xlabel(f"frame ({fps:.0f} fps)")
    ax.set_ylabel("feature error vs truth, px (dashed: worst)")
    ax.set_title(f"{scenario}: feature error by mode")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def rows_json(rows: list[AccuracyRow]) -> list[dict[str, object]]:
    return [asdict(r) for r in rows]
