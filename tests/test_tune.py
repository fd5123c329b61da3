"""clothd tune on a short, coarse hwsim recording of a fabric unlike the default denim (the shirting of
shirt-shear.yaml): the fitness is the model's own prediction (the node error it reports is predict mode's),
a deliberately wrong parameter set is improved, best.yaml loads as a configuration, population.csv holds
the population, a stopped tune resumes its study, workers share one, and bad input gets a reason."""

from __future__ import annotations

import contextlib
import csv
import itertools
import os
import shutil
import sqlite3
from pathlib import Path

import pytest
import yaml

from clothd.cli import main
from clothd.config import load_config, with_overrides
from clothd.taichi_runtime import start_taichi
from clothd.tools import tune, tune_space
from clothd.tools.bench_accuracy import grade
from clothd.tools.tune_fitness import ModelPredictor, measure
from clothd.tools.tune_report import SCORE_COLUMNS
from hwsim import scenario as scenarios
from hwsim.recording import record

# Small and quick: 1 s of footage, an 8 x 8 tracking mesh, 200 features.
TRACKER = {"mesh": {"nodes_x": 8, "nodes_y": 8}, "features": {"max_features": 200}}
# Wrong for any fabric that moves with its belts: the cloth barely feels them, and drags.
WRONG = {"friction_mu": 0.02, "damping_1_s": 200.0}


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("shirt")
    record(scenarios.load("shirt-shear", duration_s=1.0, supersample=1), out)
    return out


@pytest.fixture(scope="module")
def wrong_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "wrong.yaml"
    path.write_text(yaml.safe_dump({"tracker": {**TRACKER, "physics": WRONG}}))
    return path


def _tune(recording: Path, out: Path, config: Path, *extra: str) -> int:
    return main(["tune", str(recording), "--out", str(out), "--config", str(config), "--seed", "0", *extra])


def _population(out: Path) -> list[dict[str, str]]:
    with (out / "population.csv").open() as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def tuned(recording: Path, wrong_config: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("tuned")
    assert _tune(recording, out, wrong_config, "--trials", "10", "--workers", "1") == 0
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
    recording: Path, wrong_config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "tune"
    assert _tune(recording, out, wrong_config, "--trials", "3") == 0
    first = _population(out)
    assert _tune(recording, out, wrong_config, "--trials", "3") == 0
    rows = _population(out)
    assert sorted(int(r["trial"]) for r in rows) == list(range(6))
    assert sum(r["start"] == "1" for r in rows) == 1
    assert float(rows[0]["fitness_px"]) <= float(first[0]["fitness_px"])
    assert "3 trials" in capsys.readouterr().out
    with contextlib.closing(sqlite3.connect(out / "study.db")) as db:  # workers read while others write
        assert db.execute("PRAGMA journal_mode").fetchone() == ("wal",)


def test_workers_share_a_journal_study(recording: Path, wrong_config: Path, tmp_path: Path) -> None:
    journal = tmp_path / "study.log"
    args = ("--trials", "4", "--workers", "2", "--storage", str(journal))
    assert _tune(recording, tmp_path / "a", wrong_config, *args) == 0
    assert journal.stat().st_size > 0 and not (tmp_path / "a" / "study.db").exists()
    assert sorted(int(r["trial"]) for r in _population(tmp_path / "a")) == list(range(4))


def test_mesh_mode_tunes_the_whole_tracker(recording: Path, wrong_config: Path, tmp_path: Path) -> None:
    assert _tune(recording, tmp_path, wrong_config, "--trials", "2", "--model", "mesh") == 0
    rows = _population(tmp_path)
    assert len(rows) == 2 and all(float(r["node_rmse_mm"]) > 0 for r in rows)


def test_other_recordings_in_a_study_are_refused(
    recording: Path, wrong_config: Path, tuned: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _tune(recording, tuned, wrong_config, "--trials", "1", "--model", "mesh") == 2
    assert "give the same recordings and --model" in capsys.readouterr().err


def test_bad_input_gets_a_reason(
    recording: Path, wrong_config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["tune", "--out", str(tmp_path), "--trials", "1"]) == 2
    assert "no recordings" in capsys.readouterr().err
    assert _tune(tmp_path / "nowhere", tmp_path, wrong_config, "--trials", "1") == 2
    assert "no such recording" in capsys.readouterr().err
    no_commands = tmp_path / "no-commands"
    shutil.copytree(recording, no_commands, ignore=shutil.ignore_patterns("commands.csv"))
    assert _tune(no_commands, tmp_path / "a", wrong_config, "--trials", "1") == 2
    assert "the model has no input to follow" in capsys.readouterr().err
    for workers in ("0", "two"):
        with pytest.raises(SystemExit) as err:
            _tune(recording, tmp_path, wrong_config, "--workers", workers)
        assert err.value.code == 2
        assert "at least 1" in capsys.readouterr().err
