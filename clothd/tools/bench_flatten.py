"""`clothd bench flatten`: the closed loop flattens wrinkled cloth, judged by hwsim's truth.

`clothd run --sim` runs as a separate process (as in `bench loop`). For each seeded start
(clothd/tools/flatten_starts.py) the cloth is laid flat at a random pose (hwsim's POST /cloth) and the
tracker reset onto it; then hands push one or two ridges into it (POST /cloth/push) while the daemon
watches, as wrinkles arise in handling. Then:

With `--start laid` the ridges (5-20 mm high, on the same lines) are laid into the cloth before tracking
begins instead: the wrinkles a piece arrives with, which only a second view can see (clothd/core/stereo.py).
One second after tracking begins, the status's estimated height is read beside the truth's, and its
ridges beside the laid ones' lines.

1. `flatten` (PUT /setpoint): time to flat is the first time the true cloth is at most 1 mm high and
   covers at least 99.5 % of its rest area; a start succeeds when that comes within `flatten_s`.
2. `move` to a target 100 mm and 30° away: the final true pose error once it has held within 5 mm and
   1° for 0.5 s (or at the timeout).

Throughout, the true cloth's most stretched edge, kept apart for the flatten and the move. A start whose
ridges slide out by themselves on still belts is counted, not judged, and the next is drawn. The same
sequence of starts runs again with `control.flatten: false` and `hold` instead of `flatten`: the rigid
controller, as the baseline.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Protocol

import cv2
import httpx
import numpy as np
from tqdm import tqdm

from clothd.config import load_config, with_overrides
from clothd.tools.bench_loop import ANGLE_TOL_RAD, POS_TOL_M, DaemonProcess, free_port, pose_error
from clothd.tools.flatten_starts import draw_start, laid_ridges
from clothd.tools.lockstep import LockstepCell

FLAT_HEIGHT_M = 0.001
FLAT_AREA_RATIO = 0.995
HOLD_S = 0.5
POLL_S = 0.05
PUSH_S = 1.0
PUSH_REACH_M = 0.045  # the hands' reach either side of the line
LET_GO_WAIT_S = 1.0  # after the hands' push: they let go slowly (0.5 s in hwsim), then the cloth rests
WRINKLED_M = 0.003  # a start counts once the true cloth is this high somewhere
KEPT_S = 1.5  # ... and keeps 90 % of that height for this long on still belts
KEPT_RATIO = 0.9
MAX_DRAWS_PER_START = 4  # draws stop at this many per judged start
FOUND_WITHIN_M = 0.02  # a laid ridge is found when a reported ridge's highest point lies this near its line
FOUND_FROM_M = 0.003  # ... of the laid ridges this high
# (name, the mode a start is judged in, control.flatten): the flatness controller, then the rigid one as
# the baseline.
VARIANTS = (("flatten", "flatten", True), ("rigid", "hold", False))


def _world_push(pose: list[float], push: dict[str, Any]) -> dict[str, Any]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    px, py = push["at_cloth_m"]
    return {
        "at_m": [pose[0] + c * px - s * py, pose[1] + s * px + c * py],
        "direction_rad": math.remainder(push["direction_cloth_rad"] + pose[2], 2 * math.pi),
        "slack_m": push["slack_m"],
        "duration_s": PUSH_S,
        "reach_m": PUSH_REACH_M,
    }


class Cell(Protocol):
    """What a start asks of the cell: live (LiveCell) or in lockstep (clothd/tools/lockstep.py)."""

    def now(self) -> float: ...
    def sleep(self, seconds: float) -> None: ...
    def status(self) -> dict[str, Any]: ...
    def truth(self) -> dict[str, Any]: ...
    def setpoint_request(self, body: dict[str, Any]) -> None: ...
    def lay(self, pose: list[float], ridges: list[dict[str, Any]] | None = None) -> None: ...
    def push(self, push: dict[str, Any], then_s: float) -> None: ...


class LiveCell:
    """The daemon's API and hwsim's hooks and truth, in real time."""

    def __init__(self, d: DaemonProcess) -> None:
        self.d = d
        self.hwsim = d.truth_url.removesuffix("/truth")
        self.http = httpx.Client(timeout=10)

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    def status(self) -> dict[str, Any]:
        return dict(self.http.get(f"{self.d.base}/api/v1/status").json())

    def truth(self) -> dict[str, Any]:
        return dict(self.http.get(self.d.truth_url).json())

    def setpoint_request(self, body: dict[str, Any]) -> None:
        r = self.http.put(f"{self.d.base}/api/v1/setpoint", json=body)
        if r.status_code != 200:
            raise RuntimeError(f"setpoint {body}: {r.status_code} {r.text}")

    def wait(self, check: Any, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not check():
            if time.monotonic() > deadline:
                raise RuntimeError(f"{what}: not within {timeout_s} s")
            time.sleep(POLL_S)

    def lay(self, pose: list[float], ridges: list[dict[str, Any]] | None = None) -> None:
        self.setpoint_request({"mode": "idle"})
        self.wait(lambda: not any(self.truth()["module_speed_m_s"]), 5, "belts stopped")
        laid = {"x_m": pose[0], "y_m": pose[1], "theta_rad": pose[2], "ridges": ridges or []}
        r = self.http.post(f"{self.hwsim}/cloth", json=laid)
        r.raise_for_status()
        self.http.post(f"{self.d.base}/api/v1/reset").raise_for_status()
        time.sleep(0.5)
        self.wait(
            lambda: (s := self.status())["state"] == "tracking" and s["link"]["state"] == "connected",
            30,
            "tracking again",
        )

    def push(self, push: dict[str, Any], then_s: float) -> None:
        self.http.post(f"{self.hwsim}/cloth/push", json=push).raise_for_status()
        time.sleep(then_s)


def laid_ridges_found(
    pose: list[float], laid: list[dict[str, Any]], seen: list[dict[str, Any]]
) -> dict[str, int]:
    """How many laid ridges FOUND_FROM_M high or more a reported ridge's highest point lies within
    FOUND_WITHIN_M of: their lines (cloth frame) taken to the world by the pose they were laid at."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    found = counted = 0
    for ridge in laid:
        if ridge["height_m"] < FOUND_FROM_M:
            continue
        counted += 1
        x, y = ridge["at_m"]
        at = np.array([pose[0] + c * x - s * y, pose[1] + s * x + c * y])
        along = ridge["direction_rad"] + pose[2]
        normal = np.array([-math.sin(along), math.cos(along)])
        found += any(
            abs(float(normal @ (np.array([r["x_m"], r["y_m"]]) - at))) <= FOUND_WITHIN_M for r in seen
        )
    return {"ridges_laid": counted, "ridges_found": found}


def _wrinkle(cell: Cell, start: dict[str, Any]) -> dict[str, Any]:
    """Lay the cloth, push its ridges in, and check that the cloth keeps them while the belts stand still.
    A ridge that slides out by itself is no start to flatten: hwsim's cloth keeps one only with enough
    cloth beside it along its whole length (docs/hwsim.md, "Holding a wrinkle")."""
    laid = start.get("laid")
    cell.lay(start["pose"], laid)
    seen: dict[str, Any] = {}
    if laid:  # what tracking sees of the ridges 1 s after it began
        cell.sleep(1.0)
        flatness = cell.status()["flatness"] or {"max_height_mm": math.nan, "basis": None}
        truth_mm = cell.truth()["max_height_m"] * 1e3
        seen = {
            "basis": flatness["basis"],
            "height_at_start_mm": flatness["max_height_mm"],
            "height_error_at_start_mm": abs(flatness["max_height_mm"] - truth_mm),
            **laid_ridges_found(start["pose"], laid, flatness.get("ridges", [])),
        }
    for push in start["pushes"] if not laid else []:
        cell.push(_world_push(start["pose"], push), PUSH_S + LET_GO_WAIT_S)
    pushed_m = cell.truth()["max_height_m"]
    cell.sleep(KEPT_S)
    kept_m = cell.truth()["max_height_m"]
    return {
        **seen,
        "wrinkled": pushed_m >= WRINKLED_M and kept_m >= KEPT_RATIO * pushed_m,
        "pushed_height_mm": pushed_m * 1e3,
        "kept_height_mm": kept_m * 1e3,
    }


def _run_start(
    cell: Cell, start: dict[str, Any], mode: str, flatten_s: float, move_s: float
) -> dict[str, Any]:
    wrinkle = _wrinkle(cell, start)
    if not wrinkle["wrinkled"]:
        return wrinkle
    before = cell.truth()
    cell.setpoint_request({"mode": mode})
    t0 = cell.now()
    time_to_flat = None
    strain_flatten = 0.0
    while cell.now() - t0 < flatten_s:
        t = cell.truth()
        strain_flatten = max(strain_flatten, t["max_strain"])
        if t["max_height_m"] <= FLAT_HEIGHT_M and t["area_ratio"] >= FLAT_AREA_RATIO:
            time_to_flat = cell.now() - t0
            break
        cell.sleep(POLL_S)
    flat_truth = cell.truth()
    target = start["target"]
    # The tracker frames a cloth by its outline, so its angle may be the truth's plus pi (a rectangle's
    # symmetry): the turn is asked of the estimate, the result judged against the truth.
    estimate = cell.status()["pose"] or {"theta_rad": flat_truth["pose"][2]}  # none: tracking was lost
    turn_rad = math.remainder(target[2] - flat_truth["pose"][2], 2 * math.pi)
    cell.setpoint_request(
        {
            "mode": "move",
            "x_m": target[0],
            "y_m": target[1],
            "theta_rad": math.remainder(estimate["theta_rad"] + turn_rad, 2 * math.pi),
        }
    )
    t1 = cell.now()
    entered = None
    err = (math.inf, math.inf)
    strain_move = 0.0
    while cell.now() - t1 < move_s:
        t = cell.truth()
        strain_move = max(strain_move, t["max_strain"])
        err = pose_error(t["pose"], (target[0], target[1], target[2]))
        inside = err[0] <= POS_TOL_M and err[1] <= ANGLE_TOL_RAD
        now = cell.now() - t1
        entered = (entered if entered is not None else now) if inside else None
        if entered is not None and now - entered >= HOLD_S:
            break
        cell.sleep(POLL_S)
    end = cell.truth()
    status = cell.status()
    return {
        **wrinkle,
        "start_height_mm": before["max_height_m"] * 1e3,
        "start_area_ratio": before["area_ratio"],
        "ridges": len(start["pushes"]),
        "start_strain": before["max_strain"],
        "time_to_flat_s": time_to_flat,
        "height_after_flatten_mm": flat_truth["max_height_m"] * 1e3,
        "area_after_flatten": flat_truth["area_ratio"],
        "end_height_mm": end["max_height_m"] * 1e3,
        "max_strain_flatten": strain_flatten,
        "max_strain_move": strain_move,
        "final_err_mm": err[0] * 1e3,
        "final_err_deg": math.degrees(err[1]),
        "halt_reason": status["halt_reason"],
    }


def _summary(runs: list[dict[str, Any]], flatten_s: float) -> dict[str, Any]:
    """Over the starts that were wrinkled; the others are counted, not judged."""
    rows = [r for r in runs if r["wrinkled"]]
    times = np.array([r["time_to_flat_s"] if r["time_to_flat_s"] is not None else math.inf for r in rows])
    return {
        "starts": len(rows),
        "drawn": len(runs),
        "not_kept": len(runs) - len(rows),
        "success_pct": 100.0 * float(np.mean(times <= flatten_s)),
        # A sample, not an interpolation: a start that never went flat counts as infinitely slow.
        "time_to_flat_p50_s": float(np.percentile(times, 50, method="inverted_cdf")),
        "time_to_flat_p90_s": float(np.percentile(times, 90, method="inverted_cdf")),
        "max_strain_pct": 100.0 * max(max(r["max_strain_flatten"], r["max_strain_move"]) for r in rows),
        "max_strain_flatten_pct": 100.0 * max(r["max_strain_flatten"] for r in rows),
        "max_start_strain_pct": 100.0 * max(r["start_strain"] for r in rows),
        "final_err_mm_max": max(r["final_err_mm"] for r in rows),
        "final_err_deg_max": max(r["final_err_deg"] for r in rows),
        "final_err_mm_p50": float(np.median([r["final_err_mm"] for r in rows])),
        **_seen_at_start(rows),
        "start_height_mm_range": [
            min(r["start_height_mm"] for r in rows),
            max(r["start_height_mm"] for r in rows),
        ],
    }


def _seen_at_start(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Laid starts, 1 s after tracking began: how far the estimated height was off the truth's, and the
    share of the laid ridges found."""
    errors = [r["height_error_at_start_mm"] for r in rows if "height_error_at_start_mm" in r]
    if not errors:
        return {}
    return {
        "height_error_at_start_mm_p50": float(np.median(errors)),
        "height_error_at_start_mm_max": float(np.max(errors)),
        "measured_pct": 100.0 * float(np.mean([r["basis"] == "measured" for r in rows])),
        "ridges_found_pct": 100.0
        * sum(r["ridges_found"] for r in rows)
        / max(1, sum(r["ridges_laid"] for r in rows)),
    }


def _run_starts(
    cell: Cell,
    plan: list[dict[str, Any]],
    starts: int,
    variant: str,
    mode: str,
    flatten_s: float,
    move_s: float,
) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    with tqdm(total=starts, desc=f"flatten bench ({variant})", unit="start", disable=None) as bar:
        for start in plan:
            rows.append(_run_start(cell, start, mode, flatten_s, move_s))
            bar.update(int(rows[-1]["wrinkled"]))
            bar.set_postfix(drawn=len(rows))
            if bar.n == starts:
                break
    return rows


def run_bench(
    starts: int = 20,
    seed: int = 0,
    flatten_s: float = 10.0,
    move_s: float = 15.0,
    lockstep: bool = False,
    start: str = "pushed",
    cameras: int | None = None,
    skew_s: float | None = None,
) -> dict[str, Any]:
    """Each controller runs the same seeded sequence of starts until `starts` of them were wrinkled (or
    MAX_DRAWS_PER_START x starts were drawn). In lockstep every start runs on a cell built afresh, and
    `realtime_factor` is the simulated seconds per wall second over both controllers. start: "pushed" or
    "laid"; cameras: the cell's first this many (None: all); skew_s: lockstep only, every further camera's
    capture this long after the first's (None: as the cell sets it)."""
    plan = [draw_start(np.random.default_rng([seed, k])) for k in range(MAX_DRAWS_PER_START * starts)]
    if start == "laid":  # the same lines, laid: the pushed plan's draws stay as they are
        for k, drawn in enumerate(plan):
            drawn["laid"] = laid_ridges(drawn, np.random.default_rng([seed, k, 1]))
    result: dict[str, Any] = {"starts": plan, "skew_s": skew_s}
    if lockstep:
        t_wall = time.perf_counter()
        per_variant, simulated_s = _lockstep_rows(plan, starts, flatten_s, move_s, (cameras, skew_s))
        for (variant, _, _), variant_rows in zip(VARIANTS, per_variant, strict=True):
            result[variant] = {"summary": _summary(variant_rows, flatten_s), "runs": variant_rows}
        result["realtime_factor"] = simulated_s / (time.perf_counter() - t_wall)
        return result
    for variant, mode, flatten in VARIANTS:
        with tempfile.TemporaryDirectory(prefix="clothd-bench-flatten-") as tmp:
            config = Path(tmp) / "clothd.yaml"
            config.write_text(f"control:\n  flatten: {'true' if flatten else 'false'}\n")
            d = DaemonProcess(config, free_port(), cameras)
            try:
                d.wait_ready()
                rows = _run_starts(LiveCell(d), plan, starts, variant, mode, flatten_s, move_s)
            finally:
                d.stop()
        result[variant] = {"summary": _summary(rows, flatten_s), "runs": rows}
    return result


def _lockstep_rows(
    plan: list[dict[str, Any]], starts: int, flatten_s: float, move_s: float, views: Views
) -> tuple[list[list[dict[str, Any]]], float]:
    """Each controller's rows over the plan's first draws until `starts` were wrinkled, in lockstep, and
    the simulated seconds. Every (controller, start) runs on a cell built afresh, so they share nothing
    and a pool spreads them over the cores, the long ones beside the short."""
    n = len(VARIANTS)
    results: list[list[tuple[dict[str, Any], float]]] = []  # per draw, per controller

    def wrinkled() -> int:
        return sum(bool(per_draw[0][0]["wrinkled"]) for per_draw in results)

    ctx = multiprocessing.get_context("spawn")  # a fresh interpreter each: its own Taichi
    with (
        ProcessPoolExecutor(
            max_workers=len(os.sched_getaffinity(0)), mp_context=ctx, initializer=_one_thread_each
        ) as pool,
        tqdm(total=starts * n, desc="flatten bench (lockstep)", unit="run", disable=None) as bar,
    ):
        while len(results) < len(plan) and wrinkled() < starts:
            draws = plan[len(results) : len(results) + starts - wrinkled()]
            jobs = [
                [pool.submit(_lockstep_start, k, drawn, flatten_s, move_s, views) for k in range(n)]
                for drawn in draws
            ]
            for job in (j for per_draw in jobs for j in per_draw):
                job.add_done_callback(lambda _: bar.update())
            results += [[job.result() for job in per_draw] for per_draw in jobs]
    rows = [[per_draw[k][0] for per_draw in results] for k in range(n)]
    return rows, sum(simulated for per_draw in results for _, simulated in per_draw)


def _one_thread_each() -> None:
    """A pool worker per core: OpenCV's own threads would only contend with the other workers."""
    cv2.setNumThreads(1)


Views = tuple[int | None, float | None]  # the cell's cameras and skew, as run_bench's
_cells: dict[tuple[int, Views], LockstepCell] = {}  # a pool worker's cells, by controller and views


def _lockstep_start(
    k: int, start: dict[str, Any], flatten_s: float, move_s: float, views: Views
) -> tuple[dict[str, Any], float]:
    """One start for VARIANTS[k] in lockstep, in this process: its row and the simulated seconds."""
    _, mode, flatten = VARIANTS[k]
    twin = _cells.get((k, views))
    if twin is None:
        cfg = with_overrides(load_config(None), {"control": {"flatten": flatten}})
        twin = _cells[(k, views)] = LockstepCell(cfg, cameras=views[0], skew_s=views[1])
    else:
        twin.restart()
    begun_s = twin.simulated_s
    row = _run_start(twin, start, mode, flatten_s, move_s)
    return row, twin.simulated_s - begun_s


def format_result(result: dict[str, Any]) -> str:
    lines = [
        f"{'controller':10} {'starts':>6} {'success':>8} {'flat p50':>9} {'flat p90':>9} {'max strain':>10} "
        f"{'pose err max':>16} {'start heights':>15}"
    ]
    for variant in ("flatten", "rigid"):
        s = result[variant]["summary"]
        lo, hi = s["start_height_mm_range"]
        lines.append(
            f"{variant:10} {s['starts']:6d} {s['success_pct']:7.0f}% {s['time_to_flat_p50_s']:8.2f}s "
            f"{s['time_to_flat_p90_s']:8.2f}s {s['max_strain_pct']:9.2f}% {s['final_err_mm_max']:7.2f} mm "
            f"{s['final_err_deg_max']:4.2f}° {lo:6.1f}-{hi:4.1f} mm"
            + (f"  ({s['not_kept']} of {s['drawn']} drawn kept no ridge)" if s["not_kept"] else "")
        )
        if "height_error_at_start_mm_max" in s:
            lines.append(
                f"{'':10} 1 s after tracking began: height off by {s['height_error_at_start_mm_p50']:.2f} mm "
                f"(p50), {s['height_error_at_start_mm_max']:.2f} mm (max); laid ridges found "
                f"{s['ridges_found_pct']:.0f} %"
            )
    if result.get("skew_s"):
        lines.append(f"(every further camera captured {result['skew_s'] * 1e3:g} ms after the first)")
    return "\n".join(lines)


def write_json(result: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(result, indent=2, default=float) + "\n")
