"""`clothd bench flow`: the production flow in lockstep on hwsim's flow scenario, judged by its outfeed.

hwsim's infeed lays a piece every 60/R seconds (one or two ridges of 5-15 mm each, drawn from the seed);
clothd finds each, flattens it, places it and drives it out; hwsim's outfeed judges each piece from its
truth as it reaches the +x edge. A piece succeeds when it is not a flap, was not rejected by the cell, and
left flat (true max height <= 1 mm) within 5 mm and 1 degree of the placement (across the direction of
travel: along it the crossing itself fixes where it is).

The interface (docs/benchmarks.md, "Production flow"): `--minutes M --rate R --seed S --json F`, whose
JSON has pieces_in, pieces_out, success_pct, rejects, throughput_per_min, multi_piece_time_pct and
missed_tick_pct. A missed tick is a tick whose commands came later than one tick after it began on this
machine (the lockstep itself has no deadline): its frame's tracking and control, after whatever work the
last tick left for after its commands (a frame's upkeep, a piece's start) ran past the tick.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from clothd.config import load_config
from clothd.core.pieces import Piece
from clothd.tools.lockstep_flow import LockstepFlow, flow_scenario

FLAT_MM = 1.0
PLACED_MM = 5.0
PLACED_DEG = 1.0
MATCH_S = 5.0  # the cell lets a piece go (its centre over the edge) this soon after hwsim judged it


def judged_ok(record: dict[str, Any]) -> bool:
    return (
        record["max_height_mm"] <= FLAT_MM
        and record["pose_error_mm"] <= PLACED_MM
        and record["pose_error_deg"] <= PLACED_DEG
    )


def _matched_rejects(outfeed: list[dict[str, Any]], gone: list[Piece]) -> list[str | None]:
    """For each judged piece in order, the reason the cell rejected it (None: not rejected). The cell's
    pieces leave in the order hwsim judges them; each is matched to the first let go after it."""
    reasons: list[str | None] = []
    k = 0
    for record in outfeed:
        while k < len(gone) and (gone[k].left_s or 0.0) < record["left_s"]:
            k += 1
        if k < len(gone) and (gone[k].left_s or 0.0) - record["left_s"] <= MATCH_S:
            reasons.append(gone[k].reason)
            k += 1
        else:
            reasons.append(None)
    return reasons


def judge(
    outfeed: list[dict[str, Any]], reasons: list[str | None], minutes: float
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Each piece hwsim's outfeed judged, with the reason the cell rejected it (None: not) and whether it
    succeeded; and the figures over them: pieces out, success among those that are not flaps,
    throughput, time in the cell."""
    rows = [
        {**r, "rejected": reason, "ok": reason is None and judged_ok(r)}
        for r, reason in zip(outfeed, reasons, strict=True)
    ]
    good = [r for r in rows if not r["flap"]]
    successes = sum(r["ok"] for r in good)
    times = np.array([r["t_s"] for r in rows] or [np.nan])
    return rows, {
        "pieces_out": len(rows),
        "success_pct": round(100.0 * successes / len(good), 2) if good else 0.0,
        "throughput_per_min": round(successes / minutes, 3),
        "time_in_cell_s_median": round(float(np.median(times)), 2),
        "time_in_cell_s_p90": round(float(np.percentile(times, 90)), 2),
    }


def piece_line(p: dict[str, Any]) -> str:
    """One judged piece, as the benches print it."""
    verdict = "ok" if p["ok"] else "FAIL" + (f" ({p['rejected']})" if p["rejected"] else "")
    flap = "  flap" if p["flap"] else ""
    return (
        f"    piece {p['id']:3d} {p.get('fabric', ''):8s} {p['t_s']:6.1f} s"
        f"  height {p['max_height_mm']:5.2f} mm"
        f"  y {p['pose_error_mm']:5.2f} mm  {p['pose_error_deg']:5.2f} deg{flap}  {verdict}"
    )


def run_flow(minutes: float, rate_per_min: float, seed: int, cameras: int | None = None) -> dict[str, Any]:
    sc = flow_scenario(rate_per_min, seed)
    cell = LockstepFlow(load_config(None), sc, cameras=cameras)
    t_wall = time.perf_counter()
    steps = max(1, round(minutes * 60.0))
    for _ in tqdm(range(steps), desc=f"flow {rate_per_min:g}/min", unit="sim s", leave=False, disable=None):
        cell.run(1.0)
    wall_s = time.perf_counter() - t_wall
    outfeed = list(cell.world.outfeed)
    rows, figures = judge(outfeed, _matched_rejects(outfeed, list(cell.cell.tracking.gone)), minutes)
    seen = cell.summary()
    assert cell.world.infeed is not None
    return {
        "minutes": minutes,
        "rate_per_min": rate_per_min,
        "seed": seed,
        "cameras": len(cell.sensors),
        "pieces_in": 1 + cell.world.infeed.laid_count,
        # The infeed waits while the last piece is still in its way: the rate laid is the cell's pace.
        "laid_per_min": round(cell.world.infeed.laid_count / minutes, 3),
        "waiting_at_end": cell.world.infeed.waiting(cell.world.t_s),
        **figures,
        "rejects": len(seen["rejected"]),
        "multi_piece_time_pct": seen["multi_piece_time_pct"],
        "missed_tick_pct": seen["missed_tick_pct"],
        "frame_ms_p50": seen["frame_ms_p50"],
        "frame_ms_p99": seen["frame_ms_p99"],
        "realtime_factor": round(minutes * 60.0 / wall_s, 3),
        "rejected": seen["rejected"],
        "pieces": rows,
    }


def run_bench(minutes: float, rates: list[float], seed: int, cameras: int | None = None) -> dict[str, Any]:
    """The flow at each rate; the first rate's figures at the top level (the interface), every rate's
    under `rates`, and the highest rate that kept 98 % success with the infeed keeping up (at most one
    piece waiting at the end: a rate the cell cannot take is not one it kept)."""
    runs = [run_flow(minutes, rate, seed, cameras) for rate in rates]
    kept = [r["rate_per_min"] for r in runs if r["success_pct"] >= 98.0 and r["waiting_at_end"] <= 1]
    result = dict(runs[0])
    if len(runs) > 1:
        result["rates"] = [{k: v for k, v in r.items() if k != "pieces"} for r in runs]
        result["highest_rate_98pct"] = max(kept) if kept else None
    return result


def format_result(result: dict[str, Any]) -> str:
    r = result
    lines = [
        f"clothd bench flow: {r['minutes']:g} min at {r['rate_per_min']:g} pieces/min, seed {r['seed']}, "
        f"{r['cameras']} camera(s), {r['realtime_factor']:.2f}x real time",
        f"  pieces in {r['pieces_in']} (laid {r['laid_per_min']:.2f}/min, "
        f"{r['waiting_at_end']} waiting at the end), out {r['pieces_out']}, "
        f"success {r['success_pct']:.1f} %, "
        f"rejects {r['rejects']}, throughput {r['throughput_per_min']:.2f}/min",
        f"  two or more pieces on the table {r['multi_piece_time_pct']:.1f} % of the time; time in the "
        f"cell median {r['time_in_cell_s_median']:.1f} s, p90 {r['time_in_cell_s_p90']:.1f} s",
        f"  missed ticks {r['missed_tick_pct']:.2f} % (frame p50 {r['frame_ms_p50']:.1f} ms, "
        f"p99 {r['frame_ms_p99']:.1f} ms)",
    ]
    lines += [piece_line(p) for p in r["pieces"]]
    for rate in r.get("rates", []):
        lines.append(
            f"  rate {rate['rate_per_min']:g}/min: laid {rate['laid_per_min']:.2f}/min"
            f" ({rate['waiting_at_end']} waiting at the end), success {rate['success_pct']:.1f} %,"
            f" out {rate['pieces_out']}"
        )
    if "highest_rate_98pct" in r:
        lines.append(f"  highest rate with >= 98 % success: {r['highest_rate_98pct']}")
    return "\n".join(lines)


def write_json(result: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(result, indent=2) + "\n")


def plot_rates(result: dict[str, Any], path: Path) -> None:
    """Success and throughput against the rate pieces are laid at, with the 98 % bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = result.get("rates") or [result]
    rates = [r["rate_per_min"] for r in runs]
    fig, ax = plt.subplots(figsize=(6.5, 3.8), dpi=110)
    right = ax.twinx()
    ax.plot(rates, [r["success_pct"] for r in runs], "o-", color="C0", label="success (%)")
    right.plot(rates, [r["throughput_per_min"] for r in runs], "s--", color="C1", label="throughput (/min)")
    right.plot(rates, [r["laid_per_min"] for r in runs], "^:", color="C2", label="laid (/min)")
    ax.axhline(98.0, color="k", linewidth=0.8, linestyle="-.", label="bar: 98 %")
    ax.set_xlabel("pieces due per minute (the rate asked)")
    ax.set_ylabel("pieces flat and placed, %")
    right.set_ylabel("pieces per minute")
    ax.set_ylim(0, 105)
    right.set_ylim(0, 1.1 * max(rates))
    ax.grid(True, alpha=0.3)
    left_h, left_l = ax.get_legend_handles_labels()
    right_h, right_l = right.get_legend_handles_labels()
    ax.legend(left_h + right_h, left_l + right_l, fontsize=7, loc="lower left")
    ax.set_title(
        f"Production flow: {result['minutes']:g} min a rate, seed {result['seed']}, "
        f"{result['cameras']} camera(s)"
    )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
