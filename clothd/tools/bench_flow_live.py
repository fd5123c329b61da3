"""`clothd bench flow --realtime`: the production flow once in real time, as a plant runs it.

hwsim serves the flow scenario (at the rate and seed asked) and `clothd run --sim` runs against it, as
separate processes with the real drivers (the stepper link on hwsim's pty, the video stream). The bench
sets mode flow over the API, lets the minutes pass on the wall clock, and reads hwsim's outfeed and the
daemon's pieces and tick counters through the API: the lockstep's figures (bench_flow.py) where the API
has them. Two differ in kind:
- `multi_piece_time_pct` is the share of status polls (every POLL_S) in which the daemon had two or more
  pieces on the table, not hwsim's truth tick by tick;
- `missed_tick_pct` counts the ticks the loop missed outright and those it sent with the last commands
  because the compute had not answered (both: a tick that carried no fresh commands), over the flow's
  ticks.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from tqdm import tqdm

from clothd.drivers.ports import RATE_WINDOW_S
from clothd.tools.bench_flow import judge, piece_line
from clothd.tools.cell_client import CellClient
from clothd.tools.lockstep_flow import flow_scenario
from clothd.tools.sim_daemon import sim_daemon

POLL_S = 0.5
DRAIN_S = 3.0  # after the minutes, for the outfeed's last judgement to reach the API


def run_flow_live(
    minutes: float, rate_per_min: float, seed: int, cameras: int | None = None
) -> dict[str, Any]:
    sc = flow_scenario(rate_per_min, seed)
    with tempfile.TemporaryDirectory(prefix="clothd-flow-") as tmp:
        work = Path(tmp)
        scenario = work / "flow.yaml"
        scenario.write_text(yaml.safe_dump(sc.model_dump(mode="json"), sort_keys=False))
        with sim_daemon(str(scenario), work, cameras) as url:
            client = CellClient(url)
            try:
                return _run(client, minutes, rate_per_min, seed)
            finally:
                client.close()


def _run(client: CellClient, minutes: float, rate_per_min: float, seed: int) -> dict[str, Any]:
    before, sim_before = client.status(), client.sim_truth()
    client.set_mode("flow")
    t0 = time.monotonic()
    polls = multi = 0
    run_s = minutes * 60.0
    pieces_by_id: dict[int, dict[str, Any]] = {}  # every piece the daemon reported, as last reported
    halted: tuple[float, str | None] | None = None  # when mode flow ended, and why
    fps_seen: list[float] = []  # the first camera's frames per second as the daemon received them, each poll
    with tqdm(
        total=round(run_s), desc=f"flow {rate_per_min:g}/min, live", unit="s", leave=False, disable=None
    ) as bar:
        while (elapsed := time.monotonic() - t0) < run_s:
            time.sleep(POLL_S)
            status = client.status()
            if status.get("mode") != "flow":  # a fault or the camera lost it: nothing moves any more
                halted = (round(time.monotonic() - t0, 1), status.get("halt_reason"))
                break
            pieces_by_id.update({p["id"]: p for p in status.get("pieces") or []})
            on_table = [p for p in status.get("pieces") or [] if p["left_t_mono_s"] is None]
            polls += 1
            multi += len(on_table) >= 2
            fps = (status.get("camera") or {}).get("fps")
            if fps is not None:
                fps_seen.append(float(fps))
            bar.n = min(round(elapsed), bar.total)
            bar.refresh()
    time.sleep(DRAIN_S)
    after, sim_after = client.status(), client.sim_truth()
    wall_s = time.monotonic() - t0
    outfeed = client.outfeed()
    pieces_by_id.update({p["id"]: p for p in after.get("pieces") or []})
    pieces = list(pieces_by_id.values())
    gone = sorted((p for p in pieces if p["left_t_mono_s"] is not None), key=lambda p: p["left_t_mono_s"])
    rejected = [p for p in pieces if p["state"] == "rejected"]
    # The daemon's pieces leave in the order hwsim judges them: matched in order when both saw as many.
    matched = len(gone) == len(outfeed)
    reasons = [p["reason"] if p["state"] == "rejected" else None for p in gone] if matched else []
    reasons += [None] * (len(outfeed) - len(reasons))
    rows, figures = judge(outfeed, reasons, minutes)
    t0_timing, t1_timing = before["timing"], after["timing"]
    due = (t1_timing["ticks"] + t1_timing["missed_ticks"]) - (t0_timing["ticks"] + t0_timing["missed_ticks"])
    missed = t1_timing["missed_ticks"] - t0_timing["missed_ticks"]
    overruns = t1_timing["compute_overruns"] - t0_timing["compute_overruns"]
    ftc = t1_timing["frame_to_command"]
    return {
        "realtime": True,
        "minutes": minutes,
        "rate_per_min": rate_per_min,
        "seed": seed,
        "cameras": len(after.get("cameras") or []) or 1,
        "pieces_in": len({p["id"] for p in pieces}),
        **figures,
        "rejects": len(rejected),
        "multi_piece_time_pct": round(100.0 * multi / max(polls, 1), 2),
        "missed_tick_pct": round(100.0 * (missed + overruns) / max(due, 1), 3),
        "ticks": due,
        "ticks_missed": missed,
        "compute_overruns": overruns,
        "frame_to_command_ms_p50": ftc["p50_ms"],
        "frame_to_command_ms_p99": ftc["p99_ms"],
        "matched_rejects": matched,
        "rejected": [{"id": p["id"], "reason": p["reason"]} for p in rejected],
        # hwsim is the cell: a world that fell behind the wall clock (no core left for it) moved the cloths
        # slower than the belts the daemon drove, and those figures are not a real cell's.
        "sim_behind_real_time_s": round(_gained(sim_before, sim_after, "behind_real_time_s"), 2),
        "sim_camera_frames_dropped": int(_gained(sim_before, sim_after, "camera_frames_dropped")),
        "camera_fps_median": round(float(np.median(fps_seen)), 2) if fps_seen else None,
        "camera_fps_min": round(min(fps_seen), 2) if fps_seen else None,
        "halted_after_s": None if halted is None else halted[0],
        "halt_reason": None if halted is None else halted[1],
        "wall_s": round(wall_s, 1),
        "pieces": rows,
    }


def _gained(before: dict[str, Any], after: dict[str, Any], counter: str) -> float:
    return float(after[counter]) - float(before[counter])


def format_live(result: dict[str, Any]) -> str:
    r = result
    lines = [
        f"clothd bench flow --realtime: {r['minutes']:g} min at {r['rate_per_min']:g} pieces/min, seed "
        f"{r['seed']}, {r['cameras']} camera(s), {r['wall_s']:.0f} s of wall time",
        f"  pieces in {r['pieces_in']}, out {r['pieces_out']}, success {r['success_pct']:.1f} %, "
        f"rejects {r['rejects']}, throughput {r['throughput_per_min']:.2f}/min",
        f"  two or more pieces on the table {r['multi_piece_time_pct']:.1f} % of the polls; time in the "
        f"cell median {r['time_in_cell_s_median']:.1f} s, p90 {r['time_in_cell_s_p90']:.1f} s",
        f"  missed ticks {r['missed_tick_pct']:.2f} % of {r['ticks']} ({r['ticks_missed']} missed, "
        f"{r['compute_overruns']} sent with the last commands); frame to command p50 "
        f"{_ms(r['frame_to_command_ms_p50'])}, p99 {_ms(r['frame_to_command_ms_p99'])}",
    ]
    if r["camera_fps_median"] is not None:
        lines.append(
            f"  the daemon's first camera: {r['camera_fps_median']:.1f} frames/s median over the polls "
            f"({RATE_WINDOW_S:g} s windows), {r['camera_fps_min']:.1f} at the lowest"
        )
    if r["sim_behind_real_time_s"] > 0.0 or r["sim_camera_frames_dropped"] > 0:
        lines.append(
            f"  hwsim dropped {r['sim_camera_frames_dropped']} camera frames to keep up with real time "
            f"and fell {r['sim_behind_real_time_s']:.1f} s behind it for good: the simulated cell was not "
            "real time"
        )
    if r["halted_after_s"] is not None:
        lines.append(f"  mode flow ended after {r['halted_after_s']:g} s: {r['halt_reason']}")
    for p in r["rejected"]:
        lines.append(f"    rejected piece {p['id']}: {p['reason']}")
    lines += [piece_line(p) for p in r["pieces"]]
    return "\n".join(lines)


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f} ms"
