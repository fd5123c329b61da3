"""`clothd bench speed`: per-stage and whole-tick compute time of the mesh tracker at 640x480.

For each feature budget and mesh size the real tracker ticks over an hwsim recording (translate, or
`--scenario panel`, a cloth twice the side that fills a 2000-feature budget), so KLT, prediction and
correction run on real frames; the stage times are the tracker's own
(time.perf_counter around each stage). Beside it, filterpy's dense EKF does the same correction
(6 states per node, 2 measurements per feature, dense P, F, H) wherever it finishes within the budget.
Figures are medians (p50) and 99th percentiles over the ticks after a warm-up. The tracker runs with one
BLAS thread, `loop.compute_threads` OpenCV threads and a 1 ms GIL switch interval, as in the daemon's
compute process (the command sets them before numpy loads). `--plot` draws the tick against the node
count, with a previous run's figures (`--baseline`) dashed beside this run's.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from clothd.config import FeatureConfig, MeshConfig, TrackerConfig
from clothd.core.camera_model import CameraModel
from clothd.core.mesh import QuadMesh, measurement_jacobian
from clothd.tools.offline import OfflineTracking

# prepare: the frame's grey image and pyramid; estimate: bookkeeping and the estimate; resample: new
# features and their anchors (the live loop does it after the commands are out); heights: a second view's,
# on their own thread beside the tick, not part of it.
STAGES = ("prepare", "klt", "predict", "update", "estimate", "resample", "tick", "heights")
WARMUP_TICKS = 3
FILTERPY_BUDGET_S = 3.0  # one dense update slower than this is not worth repeating


@dataclass(frozen=True)
class Row:
    features: int  # the budget asked for
    mesh: str  # "12x12"
    impl: str  # "clothd" | "filterpy"
    stage: str
    p50_ms: float
    p99_ms: float
    features_tracked: int  # median features actually tracked


def _feature_config(budget: int) -> FeatureConfig:
    # A 250 x 200 mm cloth spans ~225 x 180 px; a large budget needs a denser, weaker-corner detector.
    if budget > 500:
        return FeatureConfig(max_features=budget, quality_level=0.001, min_distance_px=3.0)
    return FeatureConfig(max_features=budget)


def clothd_rows(
    recording: Path, budget: int, mesh: tuple[int, int], frames: int, cameras: int = 1
) -> list[Row]:
    cfg = TrackerConfig(
        model="mesh", mesh=MeshConfig(nodes_x=mesh[0], nodes_y=mesh[1]), features=_feature_config(budget)
    )
    timings: dict[str, list[float]] = {s: [] for s in STAGES}
    counts = []
    run = OfflineTracking(
        recording,
        cfg,
        read_ahead=False,
        progress=f"{budget} features, {mesh[0]}x{mesh[1]}",
        cameras=cameras,
    )
    for k, (_, _, est) in enumerate(run):
        if k > WARMUP_TICKS:
            counts.append(len(est.feature_id))
            for s in STAGES:
                if s in est.timing_s:
                    timings[s].append(est.timing_s[s])
        if k + 1 >= frames:
            break
    name = f"{mesh[0]}x{mesh[1]}"
    tracked = int(np.median(counts))
    return [
        Row(budget, name, "clothd", s, float(np.median(v) * 1e3), float(np.percentile(v, 99) * 1e3), tracked)
        for s, v in timings.items()
        if v
    ]


def filterpy_rows(budget: int, mesh: tuple[int, int], repeats: int = 3) -> list[Row]:
    """filterpy's dense EKF predict and update on the same problem shape, or [] when it would not
    finish within the budget."""
    from filterpy.kalman import ExtendedKalmanFilter

    nx, ny = mesh
    m, z = 6 * nx * ny, 2 * budget
    # Dense update cost ~ z³ + z² m + z m²; past ~1e10 flops a single update takes tens of seconds here.
    if z**3 + z * z * m + z * m * m > 3e10:
        return []
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    qm = QuadMesh.covering(np.array([[-0.125, -0.1], [0.125, -0.1], [0.125, 0.1], [-0.125, 0.1]]), nx, ny)
    rng = np.random.default_rng(0)
    nodes = np.column_stack([qm.rest_nodes_m().reshape(-1, 2), np.zeros(qm.n_nodes)])
    binding = qm.bind(rng.uniform([-0.12, -0.095], [0.12, 0.095], (budget, 2)))
    pred, J = measurement_jacobian(cam, nodes, binding)
    H = np.zeros((z, m))
    for i in range(budget):
        for c in range(4):
            n = binding.nodes[i, c]
            H[2 * i : 2 * i + 2, 6 * n : 6 * n + 3] = J[i, c]
    ekf = ExtendedKalmanFilter(dim_x=m, dim_z=z)
    ekf.x = np.column_stack([nodes, np.zeros_like(nodes)]).reshape(-1, 1)
    ekf.P = np.eye(m) * 1e-5
    ekf.F = np.eye(m) + np.diag(np.full(m - 3, 1 / 30), 3)
    ekf.Q = np.eye(m) * 1e-8
    ekf.R = np.eye(z) * 0.49
    meas = (pred + rng.normal(0, 0.7, pred.shape)).reshape(-1, 1)
    times: dict[str, list[float]] = {"predict": [], "update": []}
    for _ in range(repeats):
        t0 = time.perf_counter()
        ekf.predict()
        t1 = time.perf_counter()
        ekf.update(meas, lambda _x: H, lambda x: H @ x)
        t2 = time.perf_counter()
        times["predict"].append(t1 - t0)
        times["update"].append(t2 - t1)
        if t2 - t1 > FILTERPY_BUDGET_S:
            break
    name = f"{nx}x{ny}"
    return [
        Row(budget, name, "filterpy", s, float(np.median(v) * 1e3), float(np.max(v) * 1e3), budget)
        for s, v in times.items()
    ]


DEFAULT_BUDGETS = (100, 300, 1000)
DEFAULT_MESHES = ((6, 6), (9, 9), (12, 12), (16, 16), (20, 20))


def run_speed(
    recording: Path,
    budgets: tuple[int, ...] = DEFAULT_BUDGETS,
    meshes: tuple[tuple[int, int], ...] = DEFAULT_MESHES,
    frames: int = 60,
    cameras: int = 1,
) -> list[Row]:
    """cameras: the recording's first this many; filterpy's dense EKF only beside one camera's."""
    rows: list[Row] = []
    for budget in budgets:
        for mesh in meshes:
            rows += clothd_rows(recording, budget, mesh, frames, cameras)
            rows += filterpy_rows(budget, mesh) if cameras == 1 else []
    return rows


def format_rows(rows: list[Row]) -> str:
    out = [
        f"{'features':>8} {'mesh':>6} {'impl':>13} {'tracked':>7}  " + "  ".join(f"{s:>17}" for s in STAGES)
    ]
    keys = sorted(
        {(r.features, r.mesh, r.impl) for r in rows}, key=lambda k: (k[0], int(k[1].split("x")[0]), k[2])
    )
    for f, mesh, impl in keys:
        cells = []
        tracked = 0
        for s in STAGES:
            r = next((r for r in rows if (r.features, r.mesh, r.impl, r.stage) == (f, mesh, impl, s)), None)
            cells.append(f"{r.p50_ms:7.2f} /{r.p99_ms:8.2f}" if r else f"{'-':>17}")
            tracked = r.features_tracked if r else tracked
        out.append(f"{f:>8} {mesh:>6} {impl:>13} {tracked:>7}  " + "  ".join(cells))
    out.append("(each cell: p50 / p99 ms)")
    return "\n".join(out)


def rows_json(rows: list[Row]) -> list[dict[str, object]]:
    return [asdict(r) for r in rows]


def read_rows(path: Path, impl_suffix: str = "") -> list[Row]:
    """Rows from a `--json` file of this bench (an earlier run, or another tree's), their impl renamed
    with impl_suffix appended ("clothd" -> "clothd before")."""
    return [Row(**{**r, "impl": r["impl"] + impl_suffix}) for r in json.loads(path.read_text())]


def _nodes(mesh: str) -> int:
    nx, ny = (int(v) for v in mesh.split("x"))
    return nx * ny


def plot(rows: list[Row], path: Path, baseline: list[Row] | None = None) -> None:
    """The tracker's tick (p50 solid, p99 dotted) against the mesh's node count, a line per feature
    budget, with the baseline's tick p50 dashed; beside it the p50 of KLT, predict and update."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.5), dpi=110)
    budgets = sorted({r.features for r in rows if r.impl == "clothd"})

    def series(
        source: list[Row], budget: int, stage: str, pick: str = "p50_ms", impl: str = "clothd"
    ) -> tuple[list, list]:
        pts = sorted(
            (_nodes(r.mesh), getattr(r, pick))
            for r in source
            if r.impl == impl and r.features == budget and r.stage == stage
        )
        return [p[0] for p in pts], [p[1] for p in pts]

    for i, budget in enumerate(budgets):
        c = f"C{i}"
        ax.plot(*series(rows, budget, "tick"), "o-", color=c, label=f"{budget} features, p50")
        ax.plot(*series(rows, budget, "tick", "p99_ms"), ":", color=c, label=f"{budget} features, p99")
        if baseline:
            nodes, p50 = series(baseline, budget, "tick", impl="clothd before")
            if nodes:
                ax.plot(nodes, p50, "x--", color=c, alpha=0.7, label=f"{budget} features, p50 before")
        for stage, style in (("klt", "s-"), ("predict", "^-"), ("update", "v-")):
            ax2.plot(*series(rows, budget, stage), style, color=c, label=f"{stage}, {budget} features")
    for a in (ax, ax2):
        a.set_xlabel("mesh nodes")
        a.set_ylabel("ms")
        a.grid(True, alpha=0.3)
        a.set_ylim(bottom=0)
    ax.set_ylim(top=max(26.0, ax.get_ylim()[1]))
    ax.axhline(15.0, color="k", linewidth=0.8, linestyle="-.", label="bar: p50 15 ms")
    ax.axhline(25.0, color="grey", linewidth=0.8, linestyle="-.", label="bar: p99 25 ms")
    ax.set_title(f"tracker tick (1 BLAS, {cv2.getNumThreads()} OpenCV threads)")
    ax2.set_title("stages, p50")
    ax.legend(fontsize=6, ncol=2)
    ax2.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
