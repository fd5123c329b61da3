"""`clothd bench tune --trial-counts N ...`: what a tune of fewer trials per search would have given, read
from the bench's single-worker tune. One worker runs a study's trials in order, and CMA-ES's proposals do
not depend on how many are asked for, so a study's first n trials are those of an n-trial tune with the
same seed. For each n: the verdict (each fold's best among its first n trials against the start, on the
recording it left out) and, against hwsim's truth, the predict-mode node RMSE of the final search's best
on the bench's held-out recordings. docs/commissioning.md, "How many trials", chose the default with it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import optuna

from clothd.config import Config
from clothd.tools import tune_space
from clothd.tools.tune import Scorer, plan, storage_of, storage_url
from clothd.tools.tune_fitness import SequenceScore, measure
from clothd.tools.tune_verdict import HeldOut, Verdict, pct_text


def trial_counts(
    recs: dict[str, Path],
    train: tuple[str, ...],
    held_out: tuple[str, ...],
    out_dir: Path,
    cfg: Config,
    counts: tuple[int, ...],
    cut_bar: float,
) -> list[dict[str, Any]]:
    """For each count: the verdict and the held-out cut of the tune in out_dir (study "tune", started from
    cfg's constants) had it run that many trials per search on one worker."""
    scorer = Scorer(cfg, "predict")
    seqs = {name: measure(recs[name], scorer.tracker) for name in (*train, *held_out)}
    start = tune_space.point_of(cfg.tracker.physics)
    starts = {name: scorer.score(seq, start) for name, seq in seqs.items()}
    storage = storage_of(storage_url(None, out_dir))
    searches = plan(len(train), "tune")
    studies = [optuna.load_study(study_name=s.study_name, storage=storage) for s in searches]
    rows = []
    for n in counts:
        bests = [_best_before(study, n) for study in studies]
        held = tuple(
            HeldOut(
                seqs[name].source,
                s.study_name,
                best.number,
                starts[name],
                scorer.score(seqs[name], best.params),
            )
            for s, best in zip(searches, bests, strict=True)
            if s.held_out is not None
            for name in (train[s.held_out],)
        )
        verdict = Verdict(held, bests[-1].number, n, (), ())
        final = bests[-1].params
        graded = {name: _cut_pct(starts[name], scorer.score(seqs[name], final)) for name in held_out}
        met = verdict.generalises and all(c <= -100 * cut_bar for c in graded.values())
        rows.append(
            {
                "trials": n,
                "verdict_change_pct": verdict.change_pct,
                "written": verdict.generalises,
                "held_out_change_pct": graded,
                "bar_met": met,
            }
        )
    return rows


def _best_before(study: optuna.Study, n: int) -> optuna.trial.FrozenTrial:
    done = [
        t
        for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
        if t.number < n
    ]
    return min(done, key=lambda t: (t.value, t.number))


def _cut_pct(start: SequenceScore, best: SequenceScore) -> float:
    assert start.node_rmse_mm is not None and best.node_rmse_mm is not None  # hwsim's recordings have truth
    return 100.0 * (best.node_rmse_mm / start.node_rmse_mm - 1.0)


def format_counts(rows: list[dict[str, Any]]) -> str:
    names = list(rows[0]["held_out_change_pct"])
    lines = [
        f"{'trials':>6} {'verdict':>10} {'best.yaml':>9} " + " ".join(f"{n:>20}" for n in names) + "  bar"
    ]
    for r in rows:
        cuts = " ".join(f"{r['held_out_change_pct'][n]:+19.1f}%" for n in names)
        written = "written" if r["written"] else "refused"
        lines.append(
            f"{r['trials']:>6} {pct_text(r['verdict_change_pct'], 9)}% {written:>9} {cuts}  "
            f"{'met' if r['bar_met'] else '-'}"
        )
    return "\n".join(lines)
