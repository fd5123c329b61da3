"""`clothd bench drift`: does the live tracker drift over a shift? Judged by hwsim's truth.

`clothd run --sim` runs as a separate process (as in `bench loop`). After a reset onto the cloth at rest:

1. rest, every module stopped, for `rest_s`: the estimate's pose error against hwsim's true pose and the
   residual (mean and worst, px), sampled every `sample_s`. Growth is the mean of the last three samples
   less that of the first three (the first taken `SETTLE_S` after the reset). Bars: pose error growth
   <= 0.2 mm, residual growth <= 0.1 px.
2. a random drive for `drive_s`: seeded `move`s, each to a pose within `DRIVE_BOX` of the table's centre,
   held briefly, then the next. Node RMSE: the estimate's mesh nodes against the true position of the
   material point each node lay on after the reset (found through hwsim's nodes, as `clothd bench
   accuracy` grades: clothd/tools/grading.py). Bar: <= 2 mm at the end.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from tqdm import tqdm

from clothd.tools.bench_loop import DaemonProcess, free_port
from hwsim import scenario as scenarios
from hwsim.truth import surface_points, surface_weights

SETTLE_S = 5.0
EDGE_SAMPLES = 3  # growth: the mean of the last three samples less that of the first three
DRIVE_BOX = (0.06, 0.04, 0.4)  # x_m, y_m, theta_rad either side of the table's centre
MOVE_HOLD_S = (2.0, 6.0)  # each drive move is held this long (seeded), then the next is given
POSE_GROWTH_BAR_MM = 0.2
RESIDUAL_GROWTH_BAR_PX = 0.1
NODE_RMSE_BAR_MM = 2.0


class _Cell:
    def __init__(self, d: DaemonProcess) -> None:
        self.d = d
        self.http = httpx.Client(timeout=10)
        self.size_m = scenarios.load("cell").cloth.size_m

    def status(self) -> dict[str, Any]:
        return dict(self.http.get(f"{self.d.base}/api/v1/status").json())

    def truth(self, nodes: bool = False) -> dict[str, Any]:
        return dict(self.http.get(self.d.truth_url + ("?nodes=1" if nodes else "")).json())

    def setpoint(self, body: dict[str, Any]) -> None:
        r = self.http.put(f"{self.d.base}/api/v1/setpoint", json=body)
        if r.status_code != 200:
            raise RuntimeError(f"setpoint {body}: {r.status_code} {r.text}")

    def reset_onto_cloth(self) -> None:
        self.setpoint({"mode": "idle"})
        self.http.post(f"{self.d.base}/api/v1/reset").raise_for_status()
        deadline = time.monotonic() + 60
        time.sleep(0.5)
        while (s := self.status())["state"] != "tracking" or s["mesh"] is None:
            if time.monotonic() > deadline:
                raise RuntimeError("not tracking again within 60 s of the reset")
            time.sleep(0.2)


class _NodeGrader:
    """The estimate's nodes as material points (where they lay when made), graded against hwsim's nodes."""

    def __init__(self, cell: _Cell) -> None:
        truth = np.asarray(cell.truth(nodes=True)["nodes_m"])
        est = _mesh_nodes(cell.status())
        ny, nx = truth.shape[:2]
        w, h = cell.size_m
        self.spacing = (w / (nx - 1), h / (ny - 1))
        s, t = np.meshgrid(np.arange(nx) * self.spacing[0], np.arange(ny) * self.spacing[1])
        st = np.stack([s, t], axis=-1).reshape(-1, 2)
        a = np.column_stack([truth[..., :2].reshape(-1, 2), np.ones(nx * ny)])
        coef, *_ = np.linalg.lstsq(a, st, rcond=None)
        material = np.column_stack([est[:, :2], np.ones(len(est))]) @ coef
        self.idx, self.w = surface_weights(np.clip(material, 0.0, [w, h]), self.spacing, (ny, nx))

    def rmse_mm(self, cell: _Cell) -> float:
        truth = np.asarray(cell.truth(nodes=True)["nodes_m"])
        est = _mesh_nodes(cell.status())
        true_pts = surface_points(truth, self.idx, self.w)
        return float(np.sqrt(np.mean(np.sum((est - true_pts) ** 2, axis=1))) * 1e3)


def _mesh_nodes(status: dict[str, Any]) -> np.ndarray:
    mesh = status["mesh"]
    if mesh is None:
        raise RuntimeError("the tracker lost the cloth")
    return np.asarray(mesh["nodes_m"], float)


def _sample(cell: _Cell, t_s: float) -> dict[str, Any]:
    s, truth = cell.status(), cell.truth()
    pose, true_pose = s["pose"], truth["pose"]
    if pose is None or pose["x_m"] is None:
        raise RuntimeError("the tracker lost the cloth")
    # A rectangle turned by pi lies as it did: the tracker frames the cloth by its outline.
    angle = abs(math.remainder(pose["theta_rad"] - true_pose[2], math.pi))
    return {
        "t_s": t_s,
        "pose_err_mm": 1e3 * math.hypot(pose["x_m"] - true_pose[0], pose["y_m"] - true_pose[1]),
        "angle_err_deg": math.degrees(angle),
        "residual_mean_px": s["residual"]["mean_px"],
        "residual_worst_px": s["residual"]["worst_px"],
        "features": s["features"],
    }


def _growth(samples: list[dict[str, Any]], key: str) -> float:
    first = np.mean([r[key] for r in samples[:EDGE_SAMPLES]])
    last = np.mean([r[key] for r in samples[-EDGE_SAMPLES:]])
    return float(last - first)


def _rest(cell: _Cell, rest_s: float, sample_s: float) -> list[dict[str, Any]]:
    samples = []
    t0 = time.monotonic()
    with tqdm(total=round(rest_s), desc="drift bench (rest)", unit="s", disable=None) as bar:
        while (t := time.monotonic() - t0) <= rest_s:
            samples.append(_sample(cell, t))
            bar.update(round(t) - bar.n)
            time.sleep(max(0.0, t0 + len(samples) * sample_s - time.monotonic()))
    return samples


def _drive(cell: _Cell, grader: _NodeGrader, drive_s: float, seed: int) -> list[dict[str, Any]]:
    rng = np.random.default_rng(seed)
    samples = []
    t0 = time.monotonic()
    with tqdm(total=round(drive_s), desc="drift bench (drive)", unit="s", disable=None) as bar:
        while (t := time.monotonic() - t0) < drive_s:
            est = cell.status()["pose"]
            turn = rng.uniform(-DRIVE_BOX[2], DRIVE_BOX[2])
            # The turn is asked of the estimate's angle, kept near the table's axes (pi apart look alike).
            theta = est["theta_rad"] - math.remainder(est["theta_rad"], math.pi) + turn
            cell.setpoint(
                {
                    "mode": "move",
                    "x_m": rng.uniform(-DRIVE_BOX[0], DRIVE_BOX[0]),
                    "y_m": rng.uniform(-DRIVE_BOX[1], DRIVE_BOX[1]),
                    "theta_rad": theta,
                }
            )
            time.sleep(rng.uniform(*MOVE_HOLD_S))
            t = time.monotonic() - t0
            samples.append(_sample(cell, t) | {"node_rmse_mm": grader.rmse_mm(cell)})
            bar.update(min(round(t), round(drive_s)) - bar.n)
    cell.setpoint({"mode": "hold"})
    time.sleep(MOVE_HOLD_S[1])
    samples.append(_sample(cell, time.monotonic() - t0) | {"node_rmse_mm": grader.rmse_mm(cell)})
    return samples


def run_bench(
    config: Path | None, rest_s: float = 600.0, drive_s: float = 600.0, sample_s: float = 5.0, seed: int = 0
) -> dict[str, Any]:
    d = DaemonProcess(config, free_port())
    try:
        d.wait_ready()
        cell = _Cell(d)
        cell.reset_onto_cloth()
        grader = _NodeGrader(cell)
        time.sleep(SETTLE_S)
        rest = _rest(cell, rest_s, sample_s)
        rest_rmse = grader.rmse_mm(cell)
        drive = _drive(cell, grader, drive_s, seed) if drive_s > 0 else []
    finally:
        d.stop()
    summary: dict[str, Any] = {
        "rest_s": rest_s,
        "pose_err_growth_mm": _growth(rest, "pose_err_mm"),
        "residual_mean_growth_px": _growth(rest, "residual_mean_px"),
        "residual_worst_growth_px": _growth(rest, "residual_worst_px"),
        "pose_err_start_mm": rest[0]["pose_err_mm"],
        "pose_err_end_mm": rest[-1]["pose_err_mm"],
        "features_start": rest[0]["features"],
        "features_end": rest[-1]["features"],
        "residual_mean_end_px": rest[-1]["residual_mean_px"],
        "residual_worst_end_px": rest[-1]["residual_worst_px"],
        "node_rmse_after_rest_mm": rest_rmse,
        "drive_s": drive_s,
    }
    if drive:
        summary |= {
            "node_rmse_end_mm": drive[-1]["node_rmse_mm"],
            "node_rmse_max_mm": max(r["node_rmse_mm"] for r in drive),
            "moves": len(drive) - 1,
        }
    return {"summary": summary, "rest": rest, "drive": drive}


def _verdict(value: float, bar: float) -> str:
    return "met" if value <= bar else "MISSED"


def format_result(result: dict[str, Any]) -> str:
    s = result["summary"]
    pose_growth, res_growth = s["pose_err_growth_mm"], s["residual_mean_growth_px"]
    lines = [
        f"clothd bench drift: {s['rest_s']:.0f} s at rest, then {s['drive_s']:.0f} s of random moves",
        f"  at rest: pose error {s['pose_err_start_mm']:.3f} -> {s['pose_err_end_mm']:.3f} mm, growth "
        f"{pose_growth:+.3f} mm (bar {POSE_GROWTH_BAR_MM} mm: {_verdict(pose_growth, POSE_GROWTH_BAR_MM)})",
        f"  at rest: residual growth mean {res_growth:+.3f} px "
        f"(bar {RESIDUAL_GROWTH_BAR_PX} px: {_verdict(res_growth, RESIDUAL_GROWTH_BAR_PX)}), "
        f"worst {s['residual_worst_growth_px']:+.3f} px",
        f"  at the end of the rest: residual {s['residual_mean_end_px']:.3f} / "
        f"{s['residual_worst_end_px']:.3f} px, features measured {s['features_start']} -> "
        f"{s['features_end']}, node RMSE {s['node_rmse_after_rest_mm']:.2f} mm",
    ]
    if "node_rmse_end_mm" in s:
        rmse = s["node_rmse_end_mm"]
        lines.append(
            f"  after {s['moves']} moves: node RMSE {rmse:.2f} mm (bar {NODE_RMSE_BAR_MM} mm: "
            f"{_verdict(rmse, NODE_RMSE_BAR_MM)}), at most {s['node_rmse_max_mm']:.2f} mm along the way"
        )
    return "\n".join(lines)


def write_json(result: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(result, indent=2) + "\n")
