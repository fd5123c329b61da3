"""Whether a tune generalises: each search's best design and the start (the configuration's constants)
scored on the recording that search never saw, and the spread of the good designs of the search whose best
is written (the original report's Table 2 read for what the footage leaves free).

best.yaml is written only when the best designs beat the start on the held-out footage: the geometric
mean over the folds of each one's held-out fitness relative to the start's is below 1, so that every
recording's relative change counts alike, whatever its scale in pixels. The folds together decide, not
each: a recording that shows what the others do not (the cloth sheared, where the others push or turn it)
defeats the one search that never saw it, while the search on all of them, the design written, has it;
the report names such a fold. Otherwise the verdict says by how much the best lost, and why it may have:
designs equally good on the training footage that differ widely in a constant say the footage does not
pin that constant down (an ill-posed fit), and a best found among the last trials says the search had not
finished.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import optuna

from clothd.config import PhysicsConfig
from clothd.errors import ClothdError
from clothd.tools import tune_space
from clothd.tools.tune_fitness import Sequence, SequenceScore
from clothd.tools.tune_report import population

VERDICT_JSON = "verdict.json"
# The good designs whose spread is reported: the best few, as the printed Table 2 shows them.
GOOD_DESIGNS = 5
# A constant that differs more than this (max / min) among the good designs is not pinned down.
FREE_RATIO = 10.0
# A best found in the last fifth of a study's trials: the search was still improving.
LATE_SHARE = 0.8

Scoring = Callable[[Sequence, dict[str, float]], SequenceScore]


@dataclass(frozen=True)
class Search:
    """One study of a tune: the recordings it searches on, and the one it never sees, which judges its best
    design (None: the search on every recording, judged by the folds of a cross-validation)."""

    study_name: str
    train: tuple[int, ...]  # indices into the recordings as given
    held_out: int | None


@dataclass(frozen=True)
class HeldOut:
    """One search's best design and the start on the recording that search never saw."""

    recording: Path
    study_name: str
    best_trial: int
    start: SequenceScore
    best: SequenceScore

    @property
    def change_pct(self) -> float:
        """The best design's held-out fitness against the start's, percent (negative: better)."""
        return 100.0 * (self.best.cost_px / self.start.cost_px - 1.0)

    @property
    def beats_start(self) -> bool:
        return self.best.cost_px < self.start.cost_px


@dataclass(frozen=True)
class Spread:
    """A constant's range among the good designs."""

    name: str
    low: float
    high: float

    @property
    def ratio(self) -> float:
        return self.high / self.low if self.low > 0 else math.inf


@dataclass(frozen=True)
class Verdict:
    held_out: tuple[HeldOut, ...]
    best_trial: int  # of the study whose best is written
    trials: int  # completed in that study
    good_fitness_px: tuple[float, ...]  # its GOOD_DESIGNS best fitness values, best first
    spread: tuple[Spread, ...]  # each constant's range among those designs

    @property
    def ratio(self) -> float:
        """The best designs' held-out fitness relative to the start's, geometric mean over the folds."""
        return math.prod(h.best.cost_px / h.start.cost_px for h in self.held_out) ** (
            1.0 / len(self.held_out)
        )

    @property
    def change_pct(self) -> float:
        return 100.0 * (self.ratio - 1.0)

    @property
    def generalises(self) -> bool:
        return self.ratio < 1.0

    @property
    def free(self) -> tuple[Spread, ...]:
        """The constants the training footage leaves free, widest first."""
        return tuple(sorted((s for s in self.spread if s.ratio > FREE_RATIO), key=lambda s: -s.ratio))

    @property
    def found_late(self) -> bool:
        return self.best_trial >= LATE_SHARE * self.trials


def judge(
    searches: tuple[Search, ...],
    studies: tuple[optuna.Study, ...],
    sequences: tuple[Sequence, ...],
    score: Scoring,
    start: dict[str, float],
    base: PhysicsConfig,
) -> Verdict:
    """Score every search's best design and `start` (a search-space point) on the recording it kept out;
    the spread is the last study's, whose best is written."""
    held = tuple(
        _held_out(search, study, sequences[search.held_out], score, start)
        for search, study in zip(searches, studies, strict=True)
        if search.held_out is not None
    )
    designs = population(studies[-1], base)
    if not designs:
        raise ClothdError(f"study {studies[-1].study_name!r} has no completed trial yet")
    good = designs[:GOOD_DESIGNS]
    spread = tuple(
        Spread(name, min(d.physics[name] for d in good), max(d.physics[name] for d in good))
        for name in tune_space.TUNED_FIELDS
    )
    return Verdict(held, designs[0].trial, len(designs), tuple(d.fitness_px for d in good), spread)


def _held_out(
    search: Search, study: optuna.Study, seq: Sequence, score: Scoring, start: dict[str, float]
) -> HeldOut:
    try:
        best = study.best_trial
    except ValueError:  # no completed trial
        raise ClothdError(f"study {study.study_name!r} has no completed trial yet") from None
    return HeldOut(seq.source, search.study_name, best.number, score(seq, start), score(seq, best.params))


def format_verdict(verdict: Verdict) -> str:
    """The held-out table, the good designs' spread, and what the verdict is, with the reason."""
    lines = ["held out: the fitness (mean + 2 x worst px) on footage the search never saw"]
    head = f"{'recording':<24} {'study':<18} {'start':>9} {'best':>9} {'change':>8}"
    truth = any(h.start.node_rmse_mm is not None for h in verdict.held_out)
    lines.append(head + ("  node RMSE (truth) start → best" if truth else ""))
    for h in verdict.held_out:
        row = (
            f"{h.recording.name:<24} {h.study_name:<18} {_num(h.start.cost_px, 7)}px "
            f"{_num(h.best.cost_px, 7)}px {pct_text(h.change_pct, 7)}%"
        )
        if h.start.node_rmse_mm is not None and h.best.node_rmse_mm is not None:
            row += f"  {_num(h.start.node_rmse_mm)} → {_num(h.best.node_rmse_mm)} mm"
        lines.append(row)
    lines += ["", *_format_spread(verdict), "", *_conclusion(verdict)]
    return "\n".join(lines)


def _format_spread(verdict: Verdict) -> list[str]:
    best, last = verdict.good_fitness_px[0], verdict.good_fitness_px[-1]
    lines = [
        f"the {len(verdict.good_fitness_px)} best designs of {verdict.trials} (fitness {_num(best)} … "
        f"{_num(last)} px, {pct_text(100 * (last / best - 1))} %): each constant's range among them"
    ]
    for s in verdict.spread:
        ratio = "" if math.isinf(s.ratio) else f"{s.ratio:8.1f}x"
        flag = "  free: the footage does not pin it down" if s.ratio > FREE_RATIO else ""
        lines.append(f"  {s.name:<22} {s.low:10.4g} … {s.high:<10.4g} {ratio}{flag}")
    return lines


def _conclusion(verdict: Verdict) -> list[str]:
    folds = len(verdict.held_out)
    mean = f"{pct_text(verdict.change_pct)} %" + (
        f" (geometric mean over {folds} folds)" if folds > 1 else ""
    )
    lost = [h for h in verdict.held_out if not h.beats_start]
    if verdict.generalises:
        lines = [f"the best designs beat the start on the held-out footage: {mean}"]
        if lost:
            lines.append(
                "  but lost where a recording shows what the others do not (the design written saw it):"
            )
        return lines + [_lost(h) for h in lost]
    lines = [
        f"best.yaml not written: the best designs do not beat the start on footage their searches never saw: "
        f"{mean}",
        *(_lost(h) for h in lost),
    ]
    if verdict.free:
        names = ", ".join(f"{s.name} ({s.ratio:.0f}x)" for s in verdict.free)
        lines.append(
            f"  designs about as good as the best differ widely in {names}: the training footage does not "
            "pin these down (an ill-posed fit); record drives that move the cloth differently"
        )
    if verdict.found_late:
        lines.append(
            f"  the best was found at trial {verdict.best_trial} of {verdict.trials}: the search was still "
            "improving; run the same command again for more trials"
        )
    return lines


def _lost(h: HeldOut) -> str:
    if h.best.cost_px == h.start.cost_px:
        return f"  {h.recording.name}: the search {h.study_name!r} found nothing better than the start"
    return (
        f"  {h.recording.name}: {_num(h.best.cost_px)} px (trial {h.best_trial} of {h.study_name!r}) against "
        f"the start's {_num(h.start.cost_px)} px ({pct_text(h.change_pct)} %)"
    )


def _num(value: float, width: int = 0, sign: str = "", decimals: int = 2) -> str:
    """Fixed decimals, or a power of ten for a model that ran away on footage it was not fitted to."""
    return f"{value:{sign}{width}.{decimals}f}" if abs(value) < 1e5 else f"{value:{sign}{width}.1e}"


def pct_text(value: float, width: int = 0) -> str:
    """A change in percent, signed, one decimal (a power of ten past 1e5)."""
    return _num(value, width, "+", 1)


def verdict_json(verdict: Verdict, written: bool) -> dict[str, Any]:
    return {
        "generalises": verdict.generalises,
        "best_yaml_written": written,
        "change_pct": verdict.change_pct,
        "best_trial": verdict.best_trial,
        "trials": verdict.trials,
        "held_out": [
            {
                "recording": str(h.recording),
                "study": h.study_name,
                "best_trial": h.best_trial,
                "start_fitness_px": h.start.cost_px,
                "best_fitness_px": h.best.cost_px,
                "change_pct": h.change_pct,
                "start_node_rmse_mm": h.start.node_rmse_mm,
                "best_node_rmse_mm": h.best.node_rmse_mm,
            }
            for h in verdict.held_out
        ],
        "good_fitness_px": list(verdict.good_fitness_px),
        "spread": {s.name: [s.low, s.high] for s in verdict.spread},
    }


def write_verdict(verdict: Verdict, written: bool, path: Path) -> None:
    path.write_text(json.dumps(verdict_json(verdict, written), indent=2) + "\n")
