"""`clothd tune`: identify the cloth model's constants from recorded footage, as the original report's
Table 2 did (docs/commissioning.md, "Tune").

Every tune keeps footage out of its search, to judge the result on (tune_verdict): with two recordings
it searches on the first and keeps the second out; with three or more it cross-validates, one search on
all but each recording in turn (the folds), then the search on all of them, whose best design is the one
written. Why: a search on a few recordings can fit them with constants that follow other footage worse
than the start did, and only footage it never saw shows it.

The recordings are measured once (tune_fitness.measure); then `workers` processes share each search's
Optuna study in turn, each asking the study's CMA-ES for constants and scoring them (tune_fitness), until
`trials` more trials are done or its share of `timeout_s` has passed. The studies live in their storage (a
SQLite file in DIR by default), so a tune stopped for any reason goes on where it was when run again, and
`--storage` lets machines elsewhere join them. The constants the search starts from (the configuration's)
are each study's first trial, so the population always holds the design it set out to improve on.

Workers are spawned, not forked: Taichi's runtime does not survive a fork, and each worker starts its own
(taichi_runtime.start_taichi) with the configuration's arch.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import sqlalchemy
from optuna.storages.journal import JournalFileBackend
from tqdm import tqdm

from clothd.config import Config, TrackerConfig
from clothd.errors import ClothdError, ConfigError, InputError
from clothd.taichi_runtime import start_taichi
from clothd.tools import tune_space
from clothd.tools.tune_fitness import ModelPredictor, Sequence, SequenceScore, measure, track_score
from clothd.tools.tune_verdict import Search, Verdict, judge

MODELS = ("predict", "mesh")
_POLL_S = 0.5  # how often the progress bar reads the studies
BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_RDB_TRIES = 3  # creating an RDB storage's tables, against a machine creating them at the same moment
_RDB_RETRY_S = 0.5


def plan(n_recordings: int, study_name: str) -> tuple[Search, ...]:
    """Two recordings: search on the first, keep the second out. Three or more: leave-one-out folds, then
    the search on all of them (more footage fits better; the folds say whether such a fit generalises)."""
    if n_recordings < 2:
        raise InputError(
            f"{n_recordings} recording given, 2 needed: a tune keeps one out of its search to check the "
            "result on (3 or more are cross-validated; docs/commissioning.md, 'Tune')"
        )
    if n_recordings == 2:
        return (Search(study_name, (0,), 1),)
    every = tuple(range(n_recordings))
    folds = tuple(
        Search(f"{study_name} without {k + 1}", tuple(i for i in every if i != k), k) for k in every
    )
    return (*folds, Search(study_name, every, None))


@dataclass(frozen=True)
class TuneJob:
    """What every worker needs: the searches, the measured recordings and the configuration they start
    from."""

    storage: str  # storage_url's
    model: str
    searches: tuple[Search, ...]
    sequences: tuple[Sequence, ...]  # every recording's, as given
    cfg: Config
    seed: int


@dataclass(frozen=True)
class TuneRun:
    searches: tuple[Search, ...]
    studies: tuple[optuna.Study, ...]  # the searches'; the last one's best is the design written
    verdict: Verdict
    trials_run: int  # by this run, over every search; the studies may hold more from earlier ones
    wall_s: float

    @property
    def study(self) -> optuna.Study:
        return self.studies[-1]


def storage_url(storage: str | None, out_dir: Path) -> str:
    """--storage as every worker can open it: an RDB URL as given (sqlite:///..., postgresql://...), a
    journal file's path made absolute; default, a SQLite file in DIR."""
    if storage is None:
        return f"sqlite:///{(out_dir / 'study.db').resolve()}"
    return storage if "://" in storage else str(Path(storage).resolve())


def storage_of(url: str) -> optuna.storages.BaseStorage:
    """The Optuna storage at url: an RDB, or a journal file (machines sharing a file system)."""
    if "://" not in url:
        return optuna.storages.JournalStorage(JournalFileBackend(url))
    sqlite = url.startswith("sqlite")
    # SQLite serialises writers: workers wait their turn rather than fail on a locked database.
    connect = {"timeout": 60} if sqlite else {}
    try:
        storage = _rdb_storage(url, connect)
    except Exception as err:  # SQLAlchemy's many errors (bad URL, missing driver, unreachable server)
        raise ConfigError(f"--storage {url}: {err}") from None
    if sqlite:
        sqlalchemy.event.listen(storage.engine, "connect", _sqlite_wal)
        storage.engine.dispose()  # the connections made before the listener
    return storage


def _rdb_storage(url: str, connect: dict[str, Any]) -> optuna.storages.RDBStorage:
    """Optuna's RDB storage, which creates its tables on first use. Machines starting at once on a new
    database race to create them (PostgreSQL: a duplicate key in alembic_version, or a table that exists
    by the time it is created); the one that lost finds them made when it tries again."""
    engine = {"connect_args": connect}
    for _ in range(_RDB_TRIES - 1):
        try:
            return optuna.storages.RDBStorage(url, engine_kwargs=engine)
        except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError):
            time.sleep(_RDB_RETRY_S)
    return optuna.storages.RDBStorage(url, engine_kwargs=engine)  # the last try's error is the caller's


def _sqlite_wal(connection: Any, _record: Any) -> None:
    """Write-ahead logging: a worker reading the study no longer waits for the other's write (SQLite's
    busy wait sleeps in steps of up to 100 ms), and a commit syncs the log, not the database."""
    cursor = connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


def open_study(
    storage: optuna.storages.BaseStorage, name: str, recordings: list[Path], model: str, start: Config
) -> optuna.Study:
    """The study, created on first use with the configured constants as its first trial; a study begun on
    other recordings or another model is refused, since its fitness values would not compare.

    Of processes starting on one study at once (machines sharing --storage), the storage lets exactly one
    create it, and that one enqueues the start; the others take it as it is, unchecked while its creator
    has not yet recorded what it runs on."""
    names = [str(r.resolve()) for r in recordings]
    try:
        study = optuna.create_study(study_name=name, storage=storage, direction="minimize")
    except optuna.exceptions.DuplicatedStudyError:
        study = optuna.load_study(study_name=name, storage=storage)
    else:
        study.set_user_attr("recordings", names)
        study.set_user_attr("model", model)
        study.enqueue_trial(tune_space.point_of(start.tracker.physics), user_attrs={"start": True})
        return study
    attrs = study.user_attrs
    if "recordings" in attrs and (attrs["recordings"] != names or attrs.get("model") != model):
        raise InputError(
            f"study {name!r} was run on {study.user_attrs.get('recordings')} with model "
            f"{study.user_attrs.get('model')}: give the same recordings and --model, or another --study-name"
        )
    return study


def _sampler(job: TuneJob, worker: int) -> optuna.samplers.CmaEsSampler:
    """CMA-ES from the configured constants, seeded per worker (one seed for all would have every worker
    propose the same points)."""
    with warnings.catch_warnings():
        # x0 is deprecated in Optuna 5 (to go in 6, pinned out in pyproject): it is the one way to start
        # the search from the engineer's constants rather than the middle of the box.
        warnings.simplefilter("ignore", FutureWarning)
        return optuna.samplers.CmaEsSampler(
            x0=tune_space.point_of(job.cfg.tracker.physics),
            seed=job.seed + worker,
            warn_independent_sampling=False,
        )


class Scorer:
    """A search-space point scored on one recording, by the model alone or the whole tracker."""

    def __init__(self, cfg: Config, model: str) -> None:
        self.tracker: TrackerConfig = cfg.tracker.model_copy(update={"model": model})
        self.predictor = ModelPredictor(self.tracker) if model == "predict" else None

    def score(self, seq: Sequence, params: dict[str, float]) -> SequenceScore:
        physics = tune_space.physics_of(params, self.tracker.physics)
        if self.predictor is not None:
            return self.predictor.score(seq, physics)
        return track_score(seq, self.tracker.model_copy(update={"physics": physics}))


class Objective:
    """One trial: the constants CMA-ES proposes, scored on every recording of the search; the fitness is
    the mean of the recordings' mean + 2 x worst. Per-recording figures go into the trial's user
    attributes."""

    def __init__(self, scorer: Scorer, sequences: tuple[Sequence, ...]) -> None:
        self.scorer = scorer
        self.sequences = sequences

    def __call__(self, trial: optuna.Trial) -> float:
        params = tune_space.suggest(trial)
        scores = [self.scorer.score(seq, params) for seq in self.sequences]
        trial.set_user_attr("mean_px", float(np.mean([s.mean_px for s in scores])))
        trial.set_user_attr("worst_px", float(np.mean([s.worst_px for s in scores])))
        rmse = [s.node_rmse_mm for s in scores if s.node_rmse_mm is not None]
        if rmse:
            trial.set_user_attr("node_rmse_mm", float(np.mean(rmse)))
        trial.set_user_attr("cost_px_each", [s.cost_px for s in scores])
        return float(np.mean([s.cost_px for s in scores]))


def _work(job: TuneJob, worker: int, trials: int, deadline: float | None) -> None:
    """A worker process: its share of each search's trials in turn, each search within an even share of
    the time left before the deadline (time.time()), so that a timeout leaves none of them empty."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    start_taichi(job.cfg.taichi.arch)
    storage = storage_of(job.storage)
    scorer = Scorer(job.cfg, job.model)
    for k, search in enumerate(job.searches):
        sampler = _sampler(job, worker)
        study = optuna.load_study(study_name=search.study_name, storage=storage, sampler=sampler)
        timeout = None if deadline is None else max((deadline - time.time()) / (len(job.searches) - k), 0.0)
        objective = Objective(scorer, tuple(job.sequences[i] for i in search.train))
        study.optimize(objective, n_trials=trials, timeout=timeout)


def _shares(trials: int, workers: int) -> list[int]:
    """trials split over the workers, the remainder to the first ones."""
    return [trials // workers + (w < trials % workers) for w in range(workers)]


def tune(
    recordings: list[Path],
    out_dir: Path,
    cfg: Config,
    trials: int,
    workers: int = 1,
    storage: str | None = None,
    model: str = "predict",
    timeout_s: float | None = None,
    seed: int = 0,
    study_name: str = "tune",
) -> TuneRun:
    """Run `trials` more trials of each search's study (fewer if timeout_s runs out first) on `workers`
    processes, then judge the result on the footage each search kept out."""
    if not recordings:
        raise InputError("no recordings to tune on")
    searches = plan(len(recordings), study_name)
    if workers < 1 or trials < 1:
        raise InputError(f"--workers ({workers}) and --trials ({trials}) must be at least 1")
    if model not in MODELS:
        raise InputError(f"--model {model}: one of {', '.join(MODELS)}")
    missing = [str(r) for r in recordings if not r.is_dir()]
    if missing:
        raise InputError(f"no such recording: {', '.join(missing)}")
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # the bar and the table say what matters
    start = time.perf_counter()
    deadline = None if timeout_s is None else time.time() + timeout_s
    # Every recording is read before a study is stored: one that cannot be tuned on is named now, and
    # leaves no study behind that the next run, without it, would not match.
    sequences = tuple(measure(r, cfg.tracker) for r in recordings)
    out_dir.mkdir(parents=True, exist_ok=True)
    url = storage_url(storage, out_dir)
    studies = tuple(
        open_study(storage_of(url), s.study_name, [recordings[i] for i in s.train], model, cfg)
        for s in searches
    )
    job = TuneJob(url, model, searches, sequences, cfg, seed)
    before = _finished(studies)
    ctx = multiprocessing.get_context("spawn")
    procs: list[BaseProcess] = [
        ctx.Process(target=_work, args=(job, w, n, deadline), name=f"tune-{w}")
        for w, n in enumerate(_shares(trials, workers))
        if n > 0
    ]
    with _blas_threads():
        for p in procs:
            p.start()
    try:
        _follow(studies, before, trials * len(searches), procs)
    finally:
        for p in procs:
            p.join()
    failed = [p.name for p in procs if p.exitcode != 0]
    if failed:
        raise ClothdError(f"tune workers failed ({', '.join(failed)}): see their messages above")
    start_taichi(cfg.taichi.arch)  # only now: the workers are done, and the judge runs the model here
    physics = cfg.tracker.physics
    score = Scorer(cfg, model).score
    verdict = judge(searches, studies, job.sequences, score, tune_space.point_of(physics), physics)
    return TuneRun(searches, studies, verdict, _finished(studies) - before, time.perf_counter() - start)


@contextlib.contextmanager
def _blas_threads() -> Iterator[None]:
    """One BLAS thread per worker, in the environment the workers are spawned with (read as they import
    numpy), unless the user has set one. A pool of every core per worker only spins over matrices this
    small: one worker alone kept both of 2 cores busy (87 s of CPU in 50 s) for no gain, and two workers
    each ran a trial about twice as slowly as one alone."""
    if any(os.environ.get(var) is not None for var in BLAS_THREAD_VARS):
        yield
        return
    os.environ.update(dict.fromkeys(BLAS_THREAD_VARS, "1"))
    try:
        yield
    finally:
        for var in BLAS_THREAD_VARS:
            os.environ.pop(var, None)


def _finished(studies: tuple[optuna.Study, ...]) -> int:
    return sum(len(s.get_trials(deepcopy=False, states=_FINISHED)) for s in studies)


def _follow(studies: tuple[optuna.Study, ...], before: int, trials: int, procs: list[BaseProcess]) -> None:
    """A progress bar over this run's trials of every search (on a terminal only)."""
    with tqdm(total=trials, desc="tune", unit="trial", disable=None) as bar:
        while any(p.is_alive() for p in procs):
            time.sleep(_POLL_S)
            bar.update(max(_finished(studies) - before - bar.n, 0))


_FINISHED = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.FAIL, optuna.trial.TrialState.PRUNED)
