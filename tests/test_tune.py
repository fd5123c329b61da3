"""clothd tune on short, coarse hwsim recordings of a fabric unlike the default denim (the shirting of
shirt-*.yaml): the fitness is the model's own prediction (the node error it reports is predict mode's),
a deliberately wrong parameter set is improved, the result is judged on a recording the search never saw
(three or more are cross-validated) and best.yaml is written only when it beats the start there, with the
reason when it does not; best.yaml loads as a configuration, population.csv holds the population, a
stopped tune resumes its study, workers share one, and bad input gets a reason."""

from __future__ import annotations

import contextlib
import csv
import itertools
import json
import math
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import optuna
import pytest
import yaml
from live_cell import wait
from postgres_server import postgres_server

from clothd.cli import main
from clothd.config import load_config, with_overrides
from clothd.taichi_runtime import start_taichi
from clothd.tools import tune, tune_space
from clothd.tools.bench_accuracy import grade
from clothd.tools.bench_tune_trials import trial_counts
from clothd.tools.tune_fitness import ModelPredictor, SequenceScore, measure
from clothd.tools.tune_report import SCORE_COLUMNS
from clothd.tools.tune_verdict import HeldOut, Spread, Verdict, format_verdict
from hwsim import scenario as scenarios
from hwsim.recording import record

# On one worker: its module's recordings and tune are made once, not once per worker.
pytestmark = [pytest.mark.clock_free, pytest.mark.xdist_group("tune")]

# Small and quick: 1 s of footage, an 8 x 8 tracking mesh, 200 features.
TRACKER = {"mesh": {"nodes_x": 8, "nodes_y": 8}, "features": {"max_features": 200}}
# Wrong for any fabric that moves with its belts: the cloth barely feels them, and drags.
WRONG = {"friction_mu": 0.02, "damping_1_s": 200.0}


def _record(tmp_path_factory: pytest.TempPathFactory, scenario: str) -> Path:
    out = tmp_path_factory.mktemp(scenario)
    record(scenarios.load(scenario, duration_s=1.0, supersample=1), out)
    return out


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _record(tmp_path_factory, "shirt-shear")


@pytest.fixture(scope="module")
def held_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A drive the search on `recording` never sees: the cloth's halves turned against each other."""
    return _record(tmp_path_factory, "shirt-twist")


@pytest.fixture(scope="module")
def wrong_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "wrong.yaml"
    path.write_text(yaml.safe_dump({"tracker": {**TRACKER, "physics": WRONG}}))
    return path


def _tune(recordings: list[Path], out: Path, config: Path, *extra: str) -> int:
    return main(
        ["tune", *map(str, recordings), "--out", str(out), "--config", str(config), "--seed", "0", *extra]
    )


def _verdict(out: Path) -> dict:
    return json.loads((out / "verdict.json").read_text())


def _population(out: Path) -> list[dict[str, str]]:
    with (out / "population.csv").open() as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def tuned(
    recording: Path, held_out: Path, wrong_config: Path, tmp_path_factory: pytest.TempPathFactory
) -> Path:
    out = tmp_path_factory.mktemp("tuned")
    assert _tune([recording, held_out], out, wrong_config, "--trials", "10", "--workers", "1") == 0
    return out


def test_fitness_runs_the_model_as_predict_mode_does(recording: Path) -> None:
    """The trial's model is predict mode's: the node error it reports is what bench accuracy grades."""
    start_taichi("cpu")
    cfg = with_overrides(load_config(None), {"tracker": {**TRACKER, "model": "predict"}}).tracker
    seq = measure(recording, cfg)
    assert seq.meas_px.shape[0] == 31 and seq.meas_px.shape[1] >= 20
    physics = tune_space.physics_of(tune_space.point_of(cfg.physics), cfg.physics)
    assert physics == cfg.physics  # the search space's point of a configuration is that configuration
    score = ModelPredictor(cfg).score(seq, physics)
    graded = grade(recording, "shirt-shear", "predict", cfg)
    assert score.node_rmse_mm == pytest.approx(graded.row.node_rmse_mm, rel=1e-9)
    assert 0 < score.mean_px < score.worst_px


def test_every_corner_of_the_search_box_is_a_valid_configuration() -> None:
    """CMA-ES clips its proposals onto the box's edges: none of them may be refused (areal density is
    declared gt=0.01, open)."""
    base = load_config(None).tracker.physics
    names = [d.name for d in tune_space.SPACE]
    for corner in itertools.product(*((d.low, d.high) for d in tune_space.SPACE)):
        tune_space.physics_of(dict(zip(names, corner, strict=True)), base)


def test_workers_are_spawned_with_one_blas_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    for var in tune.BLAS_THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    with tune._blas_threads():
        assert all(os.environ[var] == "1" for var in tune.BLAS_THREAD_VARS)
    assert not any(var in os.environ for var in tune.BLAS_THREAD_VARS)  # the parent's own is untouched
    monkeypatch.setenv("OMP_NUM_THREADS", "3")  # the user's choice stands
    with tune._blas_threads():
        assert os.environ["OMP_NUM_THREADS"] == "3" and "OPENBLAS_NUM_THREADS" not in os.environ
    assert os.environ["OMP_NUM_THREADS"] == "3"


def test_tune_improves_a_wrong_parameter_set(tuned: Path) -> None:
    rows = _population(tuned)
    start = next(r for r in rows if r["start"] == "1")
    best = rows[0]
    assert start["trial"] == "0"
    assert best["rank"] == "1" and best["start"] == "0"
    assert float(best["fitness_px"]) < 0.7 * float(start["fitness_px"])
    assert float(best["node_rmse_mm"]) < float(start["node_rmse_mm"])
    assert float(start["friction_mu"]) == WRONG["friction_mu"]
    assert (tuned / "history.png").stat().st_size > 0


def test_the_best_is_judged_on_the_recording_kept_out(tuned: Path, recording: Path, held_out: Path) -> None:
    """Two recordings: the search runs on the first; the second judges its best against the start."""
    verdict = _verdict(tuned)
    assert verdict["generalises"] and verdict["best_yaml_written"]
    [judged] = verdict["held_out"]
    assert judged["recording"] == str(held_out) and judged["study"] == "tune"
    assert judged["best_trial"] == int(_population(tuned)[0]["trial"])
    assert judged["best_fitness_px"] < judged["start_fitness_px"]
    assert judged["best_node_rmse_mm"] < judged["start_node_rmse_mm"]  # the truth agrees
    assert judged["change_pct"] == pytest.approx(
        100 * (judged["best_fitness_px"] / judged["start_fitness_px"] - 1)
    )
    with contextlib.closing(sqlite3.connect(tuned / "study.db")) as db:  # the kept-out one was never run
        assert db.execute("SELECT study_name FROM studies").fetchall() == [("tune",)]
    study = optuna.load_study(study_name="tune", storage=f"sqlite:///{tuned / 'study.db'}")
    assert study.user_attrs["recordings"] == [str(recording.resolve())]


def test_a_best_no_better_than_the_start_is_not_written(
    recording: Path, held_out: Path, wrong_config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One trial is the start itself: nothing beats it on the held-out footage, so best.yaml is refused
    (exit status 1), an earlier one removed, and the output says why."""
    (tmp_path / "best.yaml").write_text("tracker: {physics: {friction_mu: 0.5}}\n")
    assert _tune([recording, held_out], tmp_path, wrong_config, "--trials", "1") == 1
    out = capsys.readouterr().out
    assert not (tmp_path / "best.yaml").exists()
    assert "best.yaml not written" in out and "found nothing better than the start" in out
    verdict = _verdict(tmp_path)
    assert not verdict["generalises"] and not verdict["best_yaml_written"]
    assert verdict["held_out"][0]["change_pct"] == 0.0
    assert (tmp_path / "population.csv").exists()  # the population is still there to read


def test_the_refusal_names_the_loss_the_free_constants_and_a_late_best() -> None:
    """The reason, as the report's Table 2 reads it: by how much the best lost on which recording, which
    constants equally good designs leave free (an ill-posed fit), and a search still improving."""
    lost = HeldOut(
        Path("rec/lining-c"), "tune", 38, SequenceScore(5.0, 10.0, 5.48), SequenceScore(8.0, 16.0, 9.55)
    )
    spread = (
        Spread("stretch_k_n_m", 2.0, 100.0),
        Spread("friction_mu", 0.3, 0.4),
        Spread("slack_strain", 0, 0.01),
    )
    verdict = Verdict((lost,), best_trial=38, trials=40, good_fitness_px=(30.0, 31.0, 32.0), spread=spread)
    assert not verdict.generalises
    assert [s.name for s in verdict.free] == ["slack_strain", "stretch_k_n_m"]
    text = format_verdict(verdict)
    assert "lining-c: 40.00 px (trial 38 of 'tune') against the start's 25.00 px (+60.0 %)" in text
    assert "5.48 → 9.55 mm" in text
    assert "the 3 best designs of 40 (fitness 30.00 … 32.00 px, +6.7 %)" in text
    assert "stretch_k_n_m (50x)" in text and "ill-posed" in text
    assert "friction_mu (" not in text.split("best.yaml not written")[1]
    assert "still improving" in text
    assert math.isinf(spread[2].ratio)


def test_a_model_that_ran_away_on_held_out_footage_reads_as_a_power_of_ten() -> None:
    """A design fitted elsewhere can run away on footage it never saw without going NaN (20 shirting
    trials did: 6.2e18 px); the report stays readable."""
    ran_away = HeldOut(
        Path("rec/shear"),
        "tune without 1",
        14,
        SequenceScore(15.0, 16.0, 9.2),
        SequenceScore(6.2e18, 0.0, 1e17),
    )
    text = format_verdict(Verdict((ran_away,), best_trial=14, trials=20, good_fitness_px=(20.0,), spread=()))
    assert (
        "shear: 6.2e+18 px (trial 14 of 'tune without 1') against the start's 47.00 px (+1.3e+19 %)" in text
    )
    assert "9.20 → 1.0e+17 mm" in text


def test_a_fold_may_lose_where_its_recording_shows_what_the_others_do_not() -> None:
    """Cross-validated, the verdict is the geometric mean of the folds' held-out fitness relative to the
    start's: one fold that never saw the only shear lost there, the other won by more; the design written
    was searched on all of them. The report names the fold that lost."""
    folds = (
        HeldOut(
            Path("rec/shear"),
            "tune without 1",
            150,
            SequenceScore(20.0, 40.0, 10.1),
            SequenceScore(5.0, 5.0, 2.6),
        ),
        HeldOut(
            Path("rec/squeeze"),
            "tune without 2",
            185,
            SequenceScore(30.0, 35.0, 30.5),
            SequenceScore(40.0, 53.0, 47.2),
        ),
    )
    verdict = Verdict(folds, best_trial=120, trials=200, good_fitness_px=(20.0,), spread=())
    assert verdict.generalises and verdict.ratio == pytest.approx(math.sqrt(0.15 * 1.46))
    text = format_verdict(verdict)
    assert "held-out footage: -53.2 % (geometric mean over 2 folds)" in text
    assert (
        "squeeze: 146.00 px (trial 185 of 'tune without 2') against the start's 100.00 px (+46.0 %)" in text
    )
    assert "shear:" not in text.split("beat the start")[1]


def test_three_recordings_are_cross_validated(
    recording: Path, held_out: Path, wrong_config: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """Each recording is kept out of one search (a fold), and the design written comes from the search on
    all of them, once every fold's best beat the start on its held-out recording."""
    third = _record(tmp_path_factory, "shirt-squeeze")
    out = tmp_path_factory.mktemp("cv")
    recordings = [recording, held_out, third]
    status = _tune(recordings, out, wrong_config, "--trials", "2")
    verdict = _verdict(out)
    assert status == (0 if verdict["generalises"] else 1)
    assert [h["recording"] for h in verdict["held_out"]] == [str(r) for r in recordings]
    storage = f"sqlite:///{out / 'study.db'}"
    names = {s.study_name for s in optuna.get_all_study_summaries(storage)}
    assert names == {"tune", "tune without 1", "tune without 2", "tune without 3"}
    for k, rec in enumerate(recordings):
        fold = optuna.load_study(study_name=f"tune without {k + 1}", storage=storage)
        assert fold.user_attrs["recordings"] == [str(r.resolve()) for r in recordings if r != rec]
        assert len(fold.trials) == 2
    final = optuna.load_study(study_name="tune", storage=storage)
    assert final.user_attrs["recordings"] == [str(r.resolve()) for r in recordings]
    assert len(_population(out)) == 2  # the population is the final search's
    # bench tune --trial-counts reads fewer trials from the same studies; all of them are this tune
    cfg = load_config(wrong_config)
    recs = dict(zip(("shear", "twist", "squeeze"), recordings, strict=True))
    [one, two] = trial_counts(recs, ("shear", "twist", "squeeze"), ("twist",), out, cfg, (1, 2), 0.4)
    assert two["verdict_change_pct"] == pytest.approx(verdict["change_pct"])
    assert one["verdict_change_pct"] == 0.0 and not one["written"]  # one trial: the start itself
    assert one["held_out_change_pct"] == {"twist": 0.0}


def test_best_yaml_loads_as_a_configuration(tuned: Path, wrong_config: Path) -> None:
    best = _population(tuned)[0]
    cfg = load_config(tuned / "best.yaml")  # as `clothd run --config` and `clothd replay --config` load it
    for name in tune_space.TUNED_FIELDS:
        assert getattr(cfg.tracker.physics, name) == pytest.approx(float(best[name]), rel=1e-5)
    assert cfg.tracker.mesh == load_config(None).tracker.mesh  # a fragment: only the physics is set
    assert main(["check-config", str(tuned / "best.yaml")]) == 0


def test_population_csv_has_the_columns(tuned: Path) -> None:
    rows = _population(tuned)
    with (tuned / "population.csv").open() as f:
        header = next(csv.reader(f))
    assert header == [*SCORE_COLUMNS, *tune_space.TUNED_FIELDS, "start"]
    assert len(rows) == 10
    fitness = [float(r["fitness_px"]) for r in rows]
    assert fitness == sorted(fitness)
    assert sorted(int(r["trial"]) for r in rows) == list(range(10))


def test_a_second_run_continues_the_study(
    recording: Path, held_out: Path, wrong_config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "tune"
    assert _tune([recording, held_out], out, wrong_config, "--trials", "3") in (0, 1)
    first = _population(out)
    assert _tune([recording, held_out], out, wrong_config, "--trials", "3") in (0, 1)
    rows = _population(out)
    assert sorted(int(r["trial"]) for r in rows) == list(range(6))
    assert sum(r["start"] == "1" for r in rows) == 1
    assert float(rows[0]["fitness_px"]) <= float(first[0]["fitness_px"])
    assert "3 trials" in capsys.readouterr().out
    with contextlib.closing(sqlite3.connect(out / "study.db")) as db:  # workers read while others write
        assert db.execute("PRAGMA journal_mode").fetchone() == ("wal",)


def test_workers_share_a_journal_study(
    recording: Path, held_out: Path, wrong_config: Path, tmp_path: Path
) -> None:
    journal = tmp_path / "study.log"
    args = ("--trials", "4", "--workers", "2", "--storage", str(journal))
    assert _tune([recording, held_out], tmp_path / "a", wrong_config, *args) in (0, 1)
    assert journal.stat().st_size > 0 and not (tmp_path / "a" / "study.db").exists()
    assert sorted(int(r["trial"]) for r in _population(tmp_path / "a")) == list(range(4))


def _tune_command(
    recordings: list[Path], out: Path, config: Path, seed: int, storage: str, trials: int
) -> list[str]:
    """`clothd tune` as a process of its own, as each machine sharing a study runs it."""
    args = ["--storage", storage, "--trials", str(trials), "--seed", str(seed), "--config", str(config)]
    return [sys.executable, "-m", "clothd.cli", "tune", *map(str, recordings), *args, "--out", str(out)]


def test_two_tunes_share_a_study_on_postgresql(
    recording: Path, held_out: Path, wrong_config: Path, tmp_path: Path
) -> None:
    """docs/commissioning.md's many machines on one study: two `clothd tune` processes started at once on
    one PostgreSQL server (a real one, started for the test), each with its own seed and --out. The study
    gets both processes' trials and one start, and the last to finish sees them all."""
    trials = 3
    with postgres_server() as url:
        tunes = [
            subprocess.Popen(
                _tune_command(
                    [recording, held_out], tmp_path / f"machine-{seed}", wrong_config, seed, url, trials
                ),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            for seed in (0, 1)
        ]
        outputs = [t.communicate(timeout=600)[0] for t in tunes]
        assert [t.returncode for t in tunes] in ([0, 0], [1, 1]), outputs  # one study, one verdict
        study = optuna.load_study(study_name="tune", storage=url)
        done = study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))
    assert len(done) == 2 * trials
    assert sum(bool(t.user_attrs.get("start")) for t in done) == 1
    assert max(len(_population(tmp_path / f"machine-{seed}")) for seed in (0, 1)) == 2 * trials
    assert not (tmp_path / "machine-0" / "study.db").exists()


# Imports, says it is ready, waits for the go, then opens the storage: the six open it at the same moment.
_OPEN_AT_ONCE = """
import sys, time, pathlib
from clothd.tools.tune import storage_of
url, ready, go = sys.argv[1], pathlib.Path(sys.argv[2]), pathlib.Path(sys.argv[3])
ready.touch()
while not go.exists():
    time.sleep(0.002)
storage_of(url)
"""


def test_machines_opening_a_new_postgresql_study_at_once_all_get_it(tmp_path: Path) -> None:
    """Optuna creates its tables on first use, and processes doing so at once on one new database race
    (plain RDBStorage: 2-4 of 6 failed on a duplicate key, in each of 3 tries); the storage retries."""
    go = tmp_path / "go"
    with postgres_server() as url:
        opening = [
            subprocess.Popen(
                [sys.executable, "-c", _OPEN_AT_ONCE, url, str(tmp_path / f"ready-{k}"), str(go)],
                stderr=subprocess.PIPE,
                text=True,
            )
            for k in range(6)
        ]
        wait(lambda: len(list(tmp_path.glob("ready-*"))) == 6, 120, "six processes ready")
        go.touch()
        errors = [p.communicate(timeout=120)[1] for p in opening]
    assert [p.returncode for p in opening] == [0] * 6, errors


def test_mesh_mode_tunes_the_whole_tracker(
    recording: Path, held_out: Path, wrong_config: Path, tmp_path: Path
) -> None:
    assert _tune([recording, held_out], tmp_path, wrong_config, "--trials", "2", "--model", "mesh") in (0, 1)
    rows = _population(tmp_path)
    assert len(rows) == 2 and all(float(r["node_rmse_mm"]) > 0 for r in rows)
    [judged] = _verdict(tmp_path)["held_out"]  # judged by the whole tracker too
    assert judged["start_node_rmse_mm"] < 5.0  # the EKF follows the cloth whatever the model


def test_other_recordings_in_a_study_are_refused(
    recording: Path, held_out: Path, wrong_config: Path, tuned: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _tune([recording, held_out], tuned, wrong_config, "--trials", "1", "--model", "mesh") == 2
    assert "give the same recordings and --model" in capsys.readouterr().err


def test_bad_input_gets_a_reason(
    recording: Path, held_out: Path, wrong_config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["tune", "--out", str(tmp_path), "--trials", "1"]) == 2
    assert "no recordings" in capsys.readouterr().err
    assert _tune([recording], tmp_path, wrong_config, "--trials", "1") == 2
    assert "1 recording given, 2 needed: a tune keeps one out of its search" in capsys.readouterr().err
    assert _tune([tmp_path / "nowhere", held_out], tmp_path, wrong_config, "--trials", "1") == 2
    assert "no such recording" in capsys.readouterr().err
    no_commands = tmp_path / "no-commands"
    shutil.copytree(recording, no_commands, ignore=shutil.ignore_patterns("commands.csv"))
    assert _tune([no_commands, held_out], tmp_path / "a", wrong_config, "--trials", "1") == 2
    assert "the model has no input to follow" in capsys.readouterr().err
    # What a refused drive leaves: its recording of one frame. Named, and no study is stored on it.
    one_frame = tmp_path / "one-frame"
    later_frames = lambda _dir, names: [n for n in names if n.endswith(".png") and n != "000000.png"]  # noqa: E731
    shutil.copytree(recording, one_frame, ignore=later_frames)
    assert len(list((one_frame / "frames").iterdir())) == 1
    assert _tune([one_frame, held_out], tmp_path / "b", wrong_config, "--trials", "1") == 2
    assert f"{one_frame}: the cloth was followed in 1 frame(s)" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()
    for workers in ("0", "two"):
        with pytest.raises(SystemExit) as err:
            _tune([recording, held_out], tmp_path, wrong_config, "--workers", workers)
        assert err.value.code == 2
        assert "at least 1" in capsys.readouterr().err
