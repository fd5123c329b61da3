"""`clothd bench tune`: `clothd tune` on hwsim footage of a fabric unlike the default denim, graded on
footage it never saw, on the bars of issue 12.

- Fabric: hwsim's shirting (hwsim/scenarios/shirt-*.yaml): light, soft, and slides on the belts; the
  tracker's default constants are hand-set for denim.
- Training: shirt-shear and shirt-squeeze. Held out: shirt-twist, shirt-drag and shirt-stretch-offset,
  with drives the tune never saw (the issue asks for two; shirt-stretch-offset, a tug of war between the
  cloth's halves, is the hardest for the model). Graded beside them, not in the bar (`BEYOND` says why):
  shirt-stretch, the same tug of war with the cloth centred, whose winner is a coin flip decided by
  hwsim's seeded belt vibration (docs/commissioning.md, "Tune"), and shirt-random, left out for an error
  in the model's input, not in the fabric (its modules accelerate at their limit all the time; the input
  ran a frame early until hwsim's recordings stamped commands when they act, 2026-11-26).
- The tune runs twice, from scratch, side by side in this one run, as the command a user runs (`clothd
  tune`, a process of its own): `--workers 1` and `--workers 2`, the same trials and seed; the speed-up
  is the ratio of their wall times (starting, measuring the recordings and starting the workers
  included), and of their search times (first trial's start to last trial's end); beside them the CPU
  time the tune and its workers used. Run inside this
  process instead, after it had started Taichi and recorded with hwsim, two workers took 1.5-2x as long
  per trial and gained nothing (not understood; `clothd tune` itself never starts Taichi).
- Graded as `clothd bench accuracy` grades (node RMSE against hwsim's truth), with the default constants
  and with the `--workers 1` tune's best.yaml, in predict mode (the model alone, as the report tuned it)
  and in mesh mode (the EKF). Bars: in predict mode the tuned constants cut every held-out recording's
  node RMSE by at least 40 %; in mesh mode they make none worse.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import optuna

from clothd.config import load_config, with_overrides
from clothd.errors import ClothdError
from clothd.taichi_runtime import start_taichi
from clothd.tools.bench_accuracy import grade
from clothd.tools.recordings import scenario_recording
from clothd.tools.tune import storage_of, storage_url
from clothd.tools.tune_report import BEST_YAML, population
from hwsim import scenario as scenarios
from hwsim.scenario import ClothSpec

TRAIN = ("shirt-shear", "shirt-squeeze")
HELD_OUT = ("shirt-twist", "shirt-drag", "shirt-stretch-offset")
# Graded and printed, not in the bar, each with the reason.
BEYOND = {
    "shirt-stretch": "a coin flip: the halves pull evenly and hwsim's seeded belt vibration picks the "
    "winner (the centre ends 25 mm to -y or +y by seed), which no model alone can predict",
    "shirt-random": "left out before it was graded: its error was in the model's input (a frame early "
    "until 2026-11-26, docs/commissioning.md), not in the fabric",
}
PREDICT_CUT_BAR = 0.40  # predict mode: held-out node RMSE at most 60 % of the defaults'
WORKERS = (1, 2)


def _fabric() -> dict[str, Any]:
    """hwsim's shirting beside its default denim."""
    shirting = scenarios.load(TRAIN[0]).cloth.model_dump()
    denim = ClothSpec().model_dump()
    keys = ("areal_density_kg_m2", "stretch_stiffness_n_m", "shear_stiffness_n_m", "bending_stiffness_n_m")
    return {
        "shirting": {k: shirting[k] for k in keys} | {"mu": shirting["friction"]["mu"]},
        "denim": {k: denim[k] for k in keys} | {"mu": denim["friction"]["mu"]},
    }


def run_bench(cache: Path, out: Path, trials: int, seed: int) -> dict[str, Any]:
    defaults = load_config(None)
    start_taichi(defaults.taichi.arch)  # before hwsim records, so that the tracker's settings hold
    recs = {name: scenario_recording(cache, name) for name in (*TRAIN, *HELD_OUT, *BEYOND)}
    runs: dict[str, dict[str, Any]] = {}
    for workers in WORKERS:
        out_w = out / f"workers-{workers}"
        shutil.rmtree(out_w, ignore_errors=True)  # from scratch: a resumed study would time less
        command = [sys.executable, "-m", "clothd.cli", "tune", *(str(recs[n]) for n in TRAIN)]
        command += ["--trials", str(trials), "--workers", str(workers), "--seed", str(seed)]
        command += ["--out", str(out_w)]
        start, cpu0 = time.perf_counter(), _children_cpu_s()
        done = subprocess.run(command, capture_output=True, text=True)
        wall_s, cpu_s = time.perf_counter() - start, _children_cpu_s() - cpu0
        if done.returncode != 0:
            raise ClothdError(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
        study = optuna.load_study(study_name="tune", storage=storage_of(storage_url(None, out_w)))
        designs = population(study, defaults.tracker.physics)
        runs[str(workers)] = {
            "trials": len(designs),
            "wall_s": wall_s,
            "search_s": _search_s(study),
            "cpu_s": cpu_s,
            "table": _table(done.stdout),
            "best_trial": designs[0].trial,
            "best_fitness_px": designs[0].fitness_px,
            "start_fitness_px": next(d.fitness_px for d in designs if d.start),
            "best_yaml": str(out_w / BEST_YAML),
        }
    tuned = load_config(out / f"workers-{WORKERS[0]}" / BEST_YAML)
    rows = []
    for name, rec in recs.items():
        role = "train" if name in TRAIN else "held-out" if name in HELD_OUT else "not in the bar"
        for mode in ("predict", "mesh"):
            row: dict[str, Any] = {"recording": name, "role": role, "mode": mode}
            for label, cfg in (("default", defaults), ("tuned", tuned)):
                mode_cfg = with_overrides(cfg, {"tracker": {"model": mode}}).tracker
                graded = grade(rec, name, f"{mode} {label}", mode_cfg).row
                row[f"{label}_rmse_mm"] = graded.node_rmse_mm
                row[f"{label}_cost_px"] = graded.cost_px
            row["change_pct"] = 100.0 * (row["tuned_rmse_mm"] / row["default_rmse_mm"] - 1.0)
            rows.append(row)
    held = [r for r in rows if r["role"] == "held-out"]
    passes = {
        "predict_cut": all(r["change_pct"] <= -100 * PREDICT_CUT_BAR for r in held if r["mode"] == "predict"),
        "mesh_not_worse": all(r["change_pct"] <= 0.0 for r in held if r["mode"] == "mesh"),
    }
    one, two = runs["1"], runs["2"]
    return {
        "fabric": _fabric(),
        "train": list(TRAIN),
        "held_out": list(HELD_OUT),
        "not_in_the_bar": dict(BEYOND),
        "cores": os.cpu_count(),
        "tune": runs,
        "speedup_workers_2": one["wall_s"] / two["wall_s"],
        "search_speedup_workers_2": one["search_s"] / two["search_s"],
        "graded": rows,
        "pass": passes,
    }


def _children_cpu_s() -> float:
    """CPU time of this process's finished children and theirs (the tune and its workers): beside the
    wall time it tells a slow run from one that waited for cores other processes held."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _table(stdout: str) -> str:
    """The printed Table 2 of `clothd tune`'s output (the workers' Taichi banners left out)."""
    lines = [line for line in stdout.splitlines() if not line.startswith("[Taichi]")]
    return "\n".join(lines).strip().split("\n\n")[0]


def _search_s(study: optuna.Study) -> float:
    """From the first trial's start to the last one's end: the wall time less measuring the recordings
    and starting the workers (Taichi, its kernels)."""
    starts = [t.datetime_start for t in study.get_trials(deepcopy=False) if t.datetime_start is not None]
    ends = [t.datetime_complete for t in study.get_trials(deepcopy=False) if t.datetime_complete is not None]
    return (max(ends) - min(starts)).total_seconds()


def format_result(result: dict[str, Any]) -> str:
    fab = result["fabric"]
    lines = [
        f"fabric: hwsim shirting {fab['shirting']}",
        f"        (denim: {fab['denim']})",
        f"train {', '.join(result['train'])}; held out {', '.join(result['held_out'])}",
        "",
        "clothd tune --workers 1 (the best designs, and the start):",
        result["tune"]["1"]["table"],
        "",
        f"{'workers':>7} {'trials':>6} {'wall':>8} {'search':>8} {'cpu':>8} {'trials/s':>8} {'start':>9} "
        f"{'best':>9}",
    ]
    for w, r in result["tune"].items():
        lines.append(
            f"{w:>7} {r['trials']:>6} {r['wall_s']:7.1f}s {r['search_s']:7.1f}s {r['cpu_s']:7.1f}s "
            f"{r['trials'] / r['wall_s']:8.2f} {r['start_fitness_px']:7.2f}px {r['best_fitness_px']:7.2f}px"
        )
    lines.append(
        f"speed-up from --workers 2 on {result['cores']} cores: {result['speedup_workers_2']:.2f}x wall, "
        f"{result['search_speedup_workers_2']:.2f}x search (the trials alone)"
    )
    lines += ["", f"{'recording':<20} {'role':<15} {'mode':<8} {'default':>10} {'tuned':>10} {'change':>8}"]
    for r in result["graded"]:
        lines.append(
            f"{r['recording']:<20} {r['role']:<15} {r['mode']:<8} {r['default_rmse_mm']:7.2f} mm "
            f"{r['tuned_rmse_mm']:7.2f} mm {r['change_pct']:+7.1f}%"
        )
    for name, why in result["not_in_the_bar"].items():
        lines.append(f"{name} is not in the bar ({why})")
    p = result["pass"]
    lines.append("")
    lines.append(
        f"held-out predict node RMSE cut >= {100 * PREDICT_CUT_BAR:.0f} %: {_verdict(p['predict_cut'])}"
    )
    lines.append(f"held-out mesh node RMSE not worse:      {_verdict(p['mesh_not_worse'])}")
    return "\n".join(lines)


def _verdict(ok: bool) -> str:
    return "pass" if ok else "FAIL"


def write_json(result: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(result, indent=2) + "\n")
