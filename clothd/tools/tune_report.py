"""What `clothd tune` leaves in DIR: the population of designs (population.csv), the original report's
Table 2 (the best designs side by side with the search's limits), best.yaml when the tune generalises
(tune_verdict), and two plots.

A design is a completed trial: its constants in config.yaml's names and units, its fitness (mean + 2 x
worst feature pixel error, averaged over the recordings) and, where the recordings had truth, its node
RMSE. The first trial is the configuration the search started from ("start").
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import optuna
import yaml

from clothd.config import Config, PhysicsConfig
from clothd.errors import ClothdError
from clothd.tools import tune_space

BEST_YAML = "best.yaml"
POPULATION_CSV = "population.csv"
HISTORY_PNG = "history.png"
IMPORTANCE_PNG = "importance.png"
SCORE_COLUMNS = ("rank", "trial", "fitness_px", "mean_px", "worst_px", "node_rmse_mm")


@dataclass(frozen=True)
class Design:
    trial: int
    fitness_px: float
    mean_px: float
    worst_px: float
    node_rmse_mm: float | None
    physics: dict[str, float]  # tune_space.TUNED_FIELDS
    start: bool  # the configuration the search started from


def population(study: optuna.Study, base: PhysicsConfig) -> list[Design]:
    """Every completed trial, best first."""
    designs = [
        Design(
            t.number,
            float(t.value),
            float(t.user_attrs["mean_px"]),
            float(t.user_attrs["worst_px"]),
            t.user_attrs.get("node_rmse_mm"),
            tune_space.physics_fields(tune_space.physics_of(t.params, base)),
            bool(t.user_attrs.get("start", False)),
        )
        for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
        if t.value is not None
    ]
    return sorted(designs, key=lambda d: (d.fitness_px, d.trial))


def write_population(designs: list[Design], path: Path) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([*SCORE_COLUMNS, *tune_space.TUNED_FIELDS, "start"])
        for rank, d in enumerate(designs, 1):
            rmse = "" if d.node_rmse_mm is None else f"{d.node_rmse_mm:.4f}"
            scores = [rank, d.trial, f"{d.fitness_px:.5f}", f"{d.mean_px:.5f}", f"{d.worst_px:.5f}", rmse]
            w.writerow([*scores, *(f"{d.physics[k]:.6g}" for k in tune_space.TUNED_FIELDS), int(d.start)])


def write_best(design: Design, path: Path, note: str) -> None:
    """best.yaml: the design's constants as a config fragment (tracker.physics only) that `--config`
    takes as it is; everything the search did not set keeps its default."""
    fragment = {"tracker": {"physics": dict(design.physics)}}
    Config.model_validate(fragment)  # refuse to write what `clothd run --config` would refuse
    path.write_text(f"# clothd tune: {note}\n" + yaml.safe_dump(fragment, sort_keys=False))


def format_table(designs: list[Design], top: int) -> str:
    """The original's Table 2: the best `top` designs as columns, each constant as a row, with the
    limits searched; the start is added as a column when it is not among them."""
    shown = designs[:top]
    start = next((d for d in designs if d.start), None)
    if start is not None and start not in shown:
        shown = [*shown, start]
    limits = {d.name: (d.low, d.high) for d in tune_space.SPACE}
    head = ["", *(f"#{d.trial}" + (" start" if d.start else "") for d in shown), "lower", "upper"]
    rows = [head]
    for name in tune_space.TUNED_FIELDS:
        low, high = limits.get(name, (math.nan, math.nan))
        rows.append([name, *(f"{d.physics[name]:.4g}" for d in shown), _limit(low), _limit(high)])
    rows.append(["mean px", *(f"{d.mean_px:.3f}" for d in shown), "", ""])
    rows.append(["worst px", *(f"{d.worst_px:.3f}" for d in shown), "", ""])
    rows.append(["fitness (mean + 2 x worst) px", *(f"{d.fitness_px:.3f}" for d in shown), "", ""])
    if any(d.node_rmse_mm is not None for d in shown):
        rows.append(["node RMSE (truth) mm", *(_mm(d.node_rmse_mm) for d in shown), "", ""])
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    lines = [
        "  ".join(
            c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in rows
    ]
    return "\n".join(lines)


def _limit(v: float) -> str:
    return "" if math.isnan(v) else f"{v:.4g}"


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def plot_history(study: optuna.Study, path: Path) -> None:
    """Each trial's fitness and the best so far, against the trial number."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [t for t in study.get_trials(deepcopy=False) if t.value is not None and math.isfinite(t.value)]
    n = [t.number for t in done]
    v = [float(t.value) for t in done]  # type: ignore[arg-type]
    best = [min(v[: i + 1]) for i in range(len(v))]
    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    ax.scatter(n, v, s=8, alpha=0.5, label="trial")
    ax.step(n, best, where="post", color="C3", label="best so far")
    ax.set_yscale("log")
    ax.set_xlabel("trial")
    ax.set_ylabel("fitness: mean + 2 x worst, px")
    ax.set_title("clothd tune: fitness history")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_importance(study: optuna.Study, path: Path) -> dict[str, float] | None:
    """Each constant's share of the fitness's variation (Optuna's PED-ANOVA: which constants the
    recordings pin down, and which they leave free). None while the study has too few trials."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    try:
        importances = optuna.importance.get_param_importances(
            study, evaluator=optuna.importance.PedAnovaImportanceEvaluator()
        )
    except (RuntimeError, ValueError):  # fewer completed trials than the evaluator needs
        return None
    names = list(importances)[::-1]
    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    ax.barh(names, [importances[k] for k in names])
    ax.set_xlabel("importance (PED-ANOVA)")
    ax.set_title("clothd tune: what the fitness depends on")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return dict(importances)


def write_outputs(
    study: optuna.Study, base: PhysicsConfig, out_dir: Path, note: str, generalises: bool
) -> list[Design]:
    """population.csv, the plots and, when the tune generalises, best.yaml into out_dir (otherwise an
    earlier run's best.yaml goes: it would stand for a study whose best no longer passes); the population,
    best first."""
    designs = population(study, base)
    if not designs:
        raise ClothdError(f"study {study.study_name!r} has no completed trial yet")
    best = designs[0]
    header = f"trial {best.trial} of study {study.study_name!r}, fitness {best.fitness_px:.3f} px, {note}"
    if generalises:
        write_best(best, out_dir / BEST_YAML, header)
    else:
        (out_dir / BEST_YAML).unlink(missing_ok=True)
    write_population(designs, out_dir / POPULATION_CSV)
    plot_history(study, out_dir / HISTORY_PNG)
    plot_importance(study, out_dir / IMPORTANCE_PNG)
    return designs
