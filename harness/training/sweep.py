"""``harness sweep``: hyperparameter sweeps on Optuna, from one machine to many.

A *space file* maps config keys (the ``--set`` paths) to distributions::

    algo.gamma: {float: [0.9, 0.99]}
    phases.0.learning_rate: {float: [1.0e-5, 1.0e-3], log: true}
    phases.initial.batch_size: {int: [32, 128], log: true}
    algo.policy: {choice: [MlpPolicy, DuelingMlpPolicy]}
    seed: {grid: [0, 1, 2]}          # a grid (every key must then be a grid): GridSampler

Every key is checked against the config schema (both ends of a range, every choice) before any
trial starts. Each trial is an ordinary run folder, ``<sweeps-dir>/<study>/trial-<number>/``,
trained with the sampled values as ``--set`` overrides. Its in-training evaluations on the
*validation* episodes are reported to Optuna, whose pruner (median by default) may stop a weak
trial early; the trial's value is the median validation coverage of the trained model (its last
in-training evaluation when that was at the end, else one more evaluation). The test episodes
are never used. A trial whose training fails (a non-finite loss) is marked failed and does not
count.

Storage: by default a journal file inside the sweep folder (``journal.log``), so one command works
on a fresh machine; ``--storage URL`` takes any database Optuna supports (PostgreSQL for several
machines: each runs the same command with the same ``--storage`` and ``--study``, Optuna hands
out the trials, and the trial count is global). ``--jobs N`` starts N worker processes on this
machine, each with its share of the cores. ``--resume`` continues a killed sweep; trials the dead
process left running are marked failed and queued again with the same parameters (Optuna's
``RetryHeartbeatStaleTrialCallback``; with a database, a live worker does this by heartbeat). On a
grid, a failed trial (stopped by a signal, or whose training failed) does not use up its grid
point, and ``--resume`` queues every point that has no complete (or pruned) trial and none
running or queued, so a grid ends with each point trained exactly once. The
best trial is written out as ``best.yaml`` (a config that ``harness run best.yaml`` trains) and
``best.json`` (its parameters and value).

Ctrl-C or SIGTERM stops a sweep as it stops ``harness run``: a trial in training finishes its
collection round, writes a checkpoint and is marked failed; elsewhere (between trials, while a
trial is evaluated) the sweep stops at once. Either way the command ends with one line (no
Optuna traceback) and exit code 130 or 143; ``--resume`` continues it (a stopped trial of a grid
is queued again and trained from step 0 in a new trial folder). With ``--jobs N`` a SIGTERM is
passed on to the workers. No signal is lost: one that only a trial's training saw, too late to
stop it (its final save), stops the sweep before the next trial (:class:`_SignalState`). A
worker whose sweep command is killed stops by itself (``harness.processes.follow_parent``), and
until it has, a ``--resume`` is refused (the workers hold :data:`WORKERS_LOCK`). A file error in a
trial (a full disk) ends the sweep in one line naming the trial's folder (:class:`TrialFileError`).

One process works on an embedded study: the sweep holds its folder's ``.lock`` (as a run holds
its run folder), so a second sweep of it, new or ``--resume``, is refused naming the holder's pid
(a dead holder's lock is taken over). A study keeps the ``--set`` overrides it was started with
(Optuna's study user attribute ``overrides``) and refuses others. A database that stops
answering stops the sweep with one line (:class:`StorageLost`), the trial folders kept;
``--resume`` then fails and queues again at once each RUNNING trial whose run folder here no live
process holds.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import math
import os
import signal
import subprocess
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from harness.config.loading import load_config, parse_override, parse_yaml, read_yaml_text
from harness.config.schema import ConfigError
from harness.processes import harness_command
from harness.results.rundir import (
    LinkOutError,
    RunDir,
    RunDirError,
    atomic_write_text,
    inside,
)
from harness.tasks import TASKS, task_of

#: Kinds of distribution a space file may name.
KINDS = ("float", "int", "choice", "grid")
#: ``--pruner`` names (rl-zoo3's, plus Hyperband).
PRUNERS = ("median", "halving", "hyperband", "none")
#: The best trial of a study, in its folder: a config ``harness run`` trains, and its numbers.
BEST_CONFIG, BEST_RESULT = "best.yaml", "best.json"
#: Every trial of the study, one row each (Optuna's ``Study.trials_dataframe``).
TRIALS_TABLE = "trials.csv"
#: The embedded storage's file in the sweep folder (Optuna's journal).
JOURNAL = "journal.log"
#: How often a trial that died (killed worker) is queued again before it stays failed.
MAX_RETRY = 2
#: Seconds between a trial's heartbeats in a database, and without one before it counts as dead.
HEARTBEAT_S, GRACE_S = 30, 120


class SweepError(ValueError):
    """A space file, study or storage that cannot be used, with a one-line message."""


class StorageLost(SweepError):
    """The sweep's database stopped answering (a lost connection, a server that went away): the
    sweep stops with one line; ``--resume`` continues it once the database is back."""


class TrialFileError(SweepError):
    """A file of a trial could not be written or read (a full disk, a lost mount): one line
    naming the file, or the trial's run folder where the error names none (a full disk in the
    middle of a write); the trial is marked failed and ``--resume`` continues the sweep."""


def _trial_file_error(exc: OSError, trial: int, run: Path) -> TrialFileError:
    where = exc.filename if exc.filename else f"{run} (a file of the trial's run folder)"
    return TrialFileError(
        f"trial {trial}: {exc.strerror or exc}: {where}; the trial is marked failed; once that "
        "is mended, continue with the same command and --resume"
    )


class SweepInterrupted(KeyboardInterrupt):
    """A SIGTERM that reached the sweep outside a trial's training (which stops on its own:
    ``TrainingInterrupted``). A ``KeyboardInterrupt``, so that it stops the sweep wherever it
    lands, as Ctrl-C does, and Optuna marks the trial under way failed."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class _SignalState:
    """Whether the sweep is stopping on a signal already (a further SIGTERM is then ignored, so
    that it cannot break the trial's checkpoint or its FAIL state being written), and the first
    signal that reached it: read before every trial starts (:meth:`check`), so that a signal
    that only training's handler saw, too late to stop its run (during the final save, or in
    a round the pruner ended), still stops the sweep. Also the file error that failed a trial
    (:class:`TrialFileError`), which Optuna's own error on a full disk may hide."""

    def __init__(self) -> None:
        self.stopping = False
        self.signum: int | None = None
        self.file_error: TrialFileError | None = None

    def note(self, signum: int) -> None:
        """Take note of a signal (called in a signal handler: nothing else)."""
        if self.signum is None:
            self.signum = signum

    def check(self, *_: Any) -> None:
        """Stop the sweep if a signal arrived (also an Optuna callback, after every trial).

        Raises:
            SweepInterrupted: naming the signal.
        """
        if self.signum is not None:
            self.stopping = True
            raise SweepInterrupted(self.signum)


@contextlib.contextmanager
def _stop_on_sigterm(state: _SignalState) -> Iterator[None]:
    """SIGTERM stops the sweep as Ctrl-C does (:class:`SweepInterrupted`); a trial's training
    puts its own handler in place meanwhile (``harness.training.train.stop_on_signals``)."""
    if threading.current_thread() is not threading.main_thread():  # signals: main thread only
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        if state.stopping:
            return
        state.note(signum)
        state.stopping = True
        raise SweepInterrupted(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class _QuietInterrupts(logging.Filter):
    """Leaves out Optuna's "Trial N failed ... because of the following error" warning (with the
    traceback) of a trial stopped by a signal, a lost database, a file it could not write
    (:class:`TrialFileError`) or its run folder linked out of the sweep folder, and its warnings
    after it:
    the command says what happened in one line; and that warning of a trial skipped because the
    study already has its trials (:class:`StudyFull`: no failure, nothing to say)."""

    def __init__(self) -> None:
        super().__init__()
        self.quiet = False

    def filter(self, record: logging.LogRecord) -> bool:
        from harness.training.train import TrainingInterrupted

        error = record.exc_info[1] if record.exc_info else None
        if isinstance(error, StudyFull):
            return False
        if isinstance(
            error, (KeyboardInterrupt, TrainingInterrupted, TrialFileError, LinkOutError)
        ) or (error is not None and _storage_failure(error) is not None):
            self.quiet = True
        return not self.quiet


@contextlib.contextmanager
def _quiet_interrupts() -> Iterator[None]:
    logger = logging.getLogger("optuna.study._optimize")  # where Optuna logs a failed trial
    quiet = _QuietInterrupts()
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)


@dataclass(frozen=True)
class Dimension:
    """One key of the search space."""

    key: str
    kind: str
    values: tuple[Any, ...]
    """``(low, high)`` for ``float``/``int``, the options for ``choice``/``grid``."""
    log: bool = False

    def extremes(self) -> tuple[Any, ...]:
        """The values that must all be valid for the key: the ends, or every option."""
        return self.values

    def suggest(self, trial: Any) -> Any:
        if self.kind == "float":
            return trial.suggest_float(self.key, *self.values, log=self.log)
        if self.kind == "int":
            return trial.suggest_int(self.key, *self.values, log=self.log)
        return trial.suggest_categorical(self.key, list(self.values))


def load_space(path: Path) -> list[Dimension]:
    """Read and check a space file (kinds, ranges, log scales, grids).

    Raises:
        SweepError: naming the file and the key.
    """
    try:
        raw = parse_yaml(read_yaml_text(path, "space file"), str(path))
    except ConfigError as exc:  # not a regular file, too large, unreadable, not YAML
        raise SweepError(str(exc)) from None
    if not isinstance(raw, dict) or not raw:
        raise SweepError(f"{path}: expected a mapping of config keys to distributions")
    dims = [_dimension(path, str(key), spec) for key, spec in raw.items()]
    grids = [d.kind == "grid" for d in dims]
    if any(grids) and not all(grids):
        raise SweepError(f"{path}: a grid space must be all grids (Optuna's GridSampler)")
    return dims


def _dimension(path: Path, key: str, spec: Any) -> Dimension:
    where = f"{path}: {key}"
    if not isinstance(spec, dict):
        raise SweepError(f"{where}: expected {{float|int|choice|grid: ...}}, got {spec!r}")
    kinds = [k for k in spec if k in KINDS]
    extra = set(spec) - set(KINDS) - {"log"}
    if len(kinds) != 1 or extra:
        raise SweepError(f"{where}: give exactly one of {', '.join(KINDS)} (and log for ranges)")
    kind = kinds[0]
    values = spec[kind]
    log = spec.get("log", False)
    if not isinstance(log, bool):
        raise SweepError(f"{where}: log must be true or false")
    if kind in ("float", "int"):
        number = float if kind == "float" else int
        ok = (
            isinstance(values, list)
            and len(values) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
        )
        if not ok or (kind == "int" and not all(isinstance(v, int) for v in values)):
            raise SweepError(f"{where}: {kind} needs [low, high] {kind}s")
        low, high = (number(v) for v in values)
        if not (math.isfinite(low) and math.isfinite(high)) or low >= high:
            raise SweepError(f"{where}: needs finite low < high, got {values}")
        if log and low <= 0:
            raise SweepError(f"{where}: a log scale needs low > 0")
        return Dimension(key, kind, (low, high), log)
    if log:
        raise SweepError(f"{where}: log goes with float or int ranges")
    if not isinstance(values, list) or not values:
        raise SweepError(f"{where}: {kind} needs a non-empty list")
    return Dimension(key, kind, tuple(values))


def override(key: str, value: Any) -> str:
    """The ``--set`` text of one sampled value (JSON is YAML, so strings and lists survive)."""
    return f"{key}={json.dumps(value)}"


def check_space(config_path: Path, overrides: Sequence[str], dims: Sequence[Dimension]) -> None:
    """Every key of the space exists in the config schema and takes every value it can be given,
    on this machine too (``check_runtime``: a device it has, an optimizer that steps, memory
    enough), as ``harness run --set`` would take it.

    Raises:
        SweepError: naming the key and the config's own message.
    """
    from harness.training.checks import check_runtime  # torch: here

    for dim in dims:
        for value in dim.extremes():
            try:
                check_runtime(load_config(config_path, [*overrides, override(dim.key, value)]))
            except ValueError as exc:  # ConfigError too
                raise SweepError(f"space key {dim.key}={value!r}: {exc}") from None


#: The study's user attribute that keeps the ``--set`` overrides it was started with.
OVERRIDES_ATTR = "overrides"


def check_overrides(study: Any, overrides: Sequence[str]) -> None:
    """The ``--set`` overrides are part of a study's identity (every trial trains the same task):
    a new study keeps them; a study that has them refuses others. Keys of how a run uses the
    machine (``MAY_CHANGE``: ``algo.threads``, which ``--jobs`` gives its workers, ``algo.device``,
    ...) may differ. A study started before studies kept them is not checked.

    Raises:
        SweepError: naming each override that differs from the study's.
    """
    stored = study.user_attrs.get(OVERRIDES_ATTR)
    if stored is None:
        if study.get_trials(deepcopy=False):
            return  # started before studies kept their overrides: resumed as it was
        study.set_user_attr(OVERRIDES_ATTR, list(overrides))
        stored = study.user_attrs[OVERRIDES_ATTR]  # another worker's, if it was first
    differ = _override_changes(stored, overrides)
    if differ:
        started = f"--set {' '.join(stored)}" if stored else "no --set"
        raise SweepError(
            f"study {study.study_name} was started with {started}; this command differs "
            f"in {', '.join(differ)}: give the study's --set, or a new --study"
        )


def _override_changes(stored: Sequence[str], given: Sequence[str]) -> list[str]:
    """Each override that differs between the study's (``stored``) and this command's
    (``given``), as ``key=value (study: value)``; values compare as ``--set`` reads them."""
    from harness.training.checkpoints import MAY_CHANGE

    def values(texts: Sequence[str]) -> dict[str, tuple[Any, str]]:
        parsed = {}
        for text in texts:
            keys, value = parse_override(text)
            parsed[".".join(keys)] = (value, text.partition("=")[2].strip())
        return parsed

    old, new = values(stored), values(given)
    changes = []
    for key in dict.fromkeys([*old, *new]):
        if key in MAY_CHANGE or (key in old and key in new and old[key][0] == new[key][0]):
            continue
        mine = f"{key}={new[key][1]}" if key in new else f"no {key}"
        theirs = old[key][1] if key in old else "not set"
        changes.append(f"{mine} (study: {theirs})")
    return changes


def _storage(url: str | None, folder: Path) -> Any:
    import optuna
    from optuna.storages.journal import JournalFileBackend

    if url is None:
        folder.mkdir(parents=True, exist_ok=True)
        return optuna.storages.JournalStorage(JournalFileBackend(str(sweep_file(folder, JOURNAL))))
    from sqlalchemy.exc import ArgumentError

    error: Exception | None = None
    for attempt in range(5):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                # A heartbeat lets fail_stale_trials (run before each trial and by --resume) tell
                # a dead worker's running trial from a live one; the dead one is queued again.
                return _storage_class()(
                    url,
                    heartbeat_interval=HEARTBEAT_S,
                    grace_period=GRACE_S,
                    heartbeat_stale_trial_callback=_retry_callback(),
                )
        except (ArgumentError, ImportError) as exc:  # a bad URL or a missing driver: no retry
            error = exc
            break
        except Exception as exc:  # SQLAlchemy and drivers raise many kinds
            # Workers started together race to create the schema in an empty database; the
            # loser sees a duplicate type or table, and finds the schema there on a retry.
            error = exc
            time.sleep(0.5 * (attempt + 1))
    raise SweepError(
        f"--storage: cannot open {url!r} ({type(error).__name__}: {str(error).splitlines()[0]})"
    ) from None


def _storage_class() -> type:
    """Optuna's ``RDBStorage`` whose heartbeat (a thread of its own) outlives a lost database:
    Optuna's would end its thread with a traceback, and the next heartbeat after the database is
    back would never come. The trial's own next word with the storage says it is lost."""
    import optuna
    from sqlalchemy.exc import SQLAlchemyError

    class Storage(optuna.storages.RDBStorage):
        def record_heartbeat(self, trial_id: int) -> None:
            # Optuna wraps an error of the commit in its StorageInternalError.
            with contextlib.suppress(SQLAlchemyError, optuna.exceptions.StorageInternalError):
                super().record_heartbeat(trial_id)

    return Storage


def _storage_failure(exc: BaseException) -> BaseException | None:
    """The database error behind ``exc`` (SQLAlchemy's, or Optuna's ``StorageInternalError`` for
    one that has no SQLAlchemy error under it), or ``None``. Optuna raises other errors on top of
    it: its ``StorageInternalError`` from the commit's error, and, for a trial whose end cannot
    be stored, an ``UnboundLocalError`` inside ``study.optimize`` with the database's error as
    its context."""
    from optuna.exceptions import StorageInternalError
    from sqlalchemy.exc import SQLAlchemyError

    seen: set[int] = set()
    found: BaseException | None = None
    error: BaseException | None = exc
    while error is not None and id(error) not in seen:
        if isinstance(error, SQLAlchemyError):
            return error
        if isinstance(error, StorageInternalError) and found is None:
            found = error
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return found


def _lost_line(error: BaseException, run: Path | None) -> str:
    """:class:`StorageLost`'s message: the database's error, and the trial folder kept."""
    cause = getattr(error, "orig", None) or error  # the driver's words, without the SQL
    words = (str(cause).strip().splitlines() or [""])[0][:160]
    kept = f"; the trials' run folders are kept (the last one started: {run})" if run else ""
    return (
        f"--storage: lost the sweep's database ({type(error).__name__}: {words}){kept}; once the "
        "database is back, continue with the same command and --resume"
    )


def _retry_callback() -> Any:
    """Optuna's callback that queues a dead trial again (same parameters, same grid point)."""
    import optuna

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY)


def make_pruner(name: str) -> Any:
    """The Optuna pruner of a ``--pruner`` name; trials are compared at their evaluations."""
    import optuna

    if name == "median":  # the first two trials run to the end, as a baseline
        return optuna.pruners.MedianPruner(n_startup_trials=2)
    if name == "halving":
        return optuna.pruners.SuccessiveHalvingPruner()
    if name == "hyperband":
        return optuna.pruners.HyperbandPruner()
    return optuna.pruners.NopPruner()


def run_sweep(
    config_path: Path,
    overrides: Sequence[str],
    space_path: Path,
    trials: int,
    study_name: str,
    sweeps_dir: Path,
    storage_url: str | None = None,
    resume: bool = False,
    pruner: str = "median",
    jobs: int = 1,
    worker: bool = False,
    report: Callable[[str], None] | None = None,
) -> dict[str, Any] | None:
    """Run this worker's share of a sweep of ``trials`` trials in total, then write the best.

    With ``jobs > 1``, the share is run by ``jobs`` worker processes (``harness sweep ...
    --worker``), each with ``cores // jobs`` torch threads. A ``worker`` neither refuses an
    existing study nor fails running trials (its siblings' are running), nor writes the best.
    ``report`` receives one line per trial this process finishes (:func:`trial_line`).

    Returns:
        ``best.json``'s content, or ``None`` when no trial has completed yet.

    The sweep folder of an embedded study is held (``RunDir.lock``, ``.lock``) by one process,
    the sweep's (its ``--jobs`` workers are its children); a database's study is shared by every
    process given it, its trials kept apart by heartbeats and their run folders' locks.

    Raises:
        SweepError: for a bad space file, a study that exists without ``--resume`` (embedded
            storage), overrides other than the study's (:func:`check_overrides`), or a storage
            that cannot be opened; :class:`StorageLost` when the database stops answering.
        RunDirError: when a live process holds the sweep folder (embedded storage).
        ConfigError: for a bad config.
        TrainingInterrupted: on SIGINT/SIGTERM during a trial's training, after its checkpoint
            (the trial is marked failed).
        SweepInterrupted: on SIGTERM elsewhere (``KeyboardInterrupt`` on SIGINT).
    """
    state = _SignalState()
    with _stop_on_sigterm(state), _quiet_interrupts():
        spec = _Study(config_path, tuple(overrides), space_path, trials, study_name,
                      Path(sweeps_dir), storage_url, pruner)  # fmt: skip
        return _run_sweep(spec, resume, jobs, worker, report, state)


@dataclass(frozen=True)
class _Study:
    """What defines a sweep, which every process working on it shares (``run_sweep``'s
    arguments of the same names)."""

    config_path: Path
    overrides: tuple[str, ...]
    space_path: Path
    trials: int
    study_name: str
    sweeps_dir: Path
    storage_url: str | None
    pruner: str

    @property
    def folder(self) -> Path:
        """The sweep's folder (its journal, worker logs and trial runs)."""
        return self.sweeps_dir / self.study_name

    def worker_command(self, threads: int) -> list[str]:
        """The ``harness sweep ... --worker`` command of one worker with ``threads`` threads."""
        cmd = harness_command("sweep", str(self.config_path),
               "--space", str(self.space_path), "--trials", str(self.trials),
               "--study", self.study_name, "--sweeps-dir", str(self.sweeps_dir),
               "--pruner", self.pruner, "--worker")  # fmt: skip
        if self.storage_url is not None:
            cmd += ["--storage", self.storage_url]
        for item in (*self.overrides, f"algo.threads={threads}"):
            cmd += ["--set", item]
        return cmd


def sweep_file(folder: Path, name: str) -> Path:
    """The sweep folder's own file ``name`` (its journal, locks, worker logs, ``trials.csv``,
    ``best.yaml``, ``best.json``, a trial's run folder), asked for through rundir's rule: it lies
    inside the sweep folder, links resolved.

    Raises:
        LinkOutError: for one that leads out of the sweep folder, naming it and where it leads.
    """
    return inside(Path(folder) / name, folder, "the sweep folder")


def _check_sweep_files(folder: Path, jobs: int, embedded: bool) -> None:
    """Ask every file the sweep reads from or writes into ``folder`` before it starts: a link
    out found at the end (``best.yaml`` after every trial trained) would come too late, and a
    trial folder linked out would have a trial write elsewhere.

    Raises:
        LinkOutError: for the first file that leads out, in one line.
    """
    # The sweep command's lock is a RunDir's (``RunDir.lock``), named by its owner; under "/"
    # (as ``RunDir.made_names``) the name comes without asking about the file itself.
    lock = RunDir(Path(os.sep)).lock_file.name
    names = [lock, WORKERS_LOCK, TRIALS_TABLE, BEST_CONFIG, BEST_RESULT]
    names += [JOURNAL] if embedded else []
    names += [_worker_log_name(k) for k in range(jobs)] if jobs > 1 else []
    if folder.is_dir():  # trial folders of an earlier sweep of the study (--resume)
        names += sorted(p.name for p in folder.iterdir() if p.name.startswith("trial-"))
    for name in names:
        sweep_file(folder, name)


def _run_sweep(
    spec: _Study,
    resume: bool,
    jobs: int,
    worker: bool,
    report: Callable[[str], None] | None,
    state: _SignalState,
) -> dict[str, Any] | None:
    import optuna

    if jobs > 1 and any(o.partition("=")[0].strip() == "algo.threads" for o in spec.overrides):
        # Each worker's command sets it (worker_command): named twice, every worker would fail.
        raise SweepError(
            "--set algo.threads: --jobs gives each worker its share of the cores; drop it"
        )
    dims = load_space(spec.space_path)
    from harness.training.checks import checked_config

    checked_config(load_config(spec.config_path, spec.overrides), str(spec.config_path))
    check_space(spec.config_path, spec.overrides, dims)
    grid = all(d.kind == "grid" for d in dims)
    points = math.prod(len(d.values) for d in dims)
    if grid and spec.trials > points:
        raise SweepError(f"--trials {spec.trials}: the grid of {spec.space_path} has only {points}")
    embedded = spec.storage_url is None
    _check_sweep_files(spec.folder, jobs, embedded)  # before anything is read or written
    with contextlib.ExitStack() as held:
        if embedded and not worker:
            # One process owns a journal's sweep (its --jobs workers are its children): a second
            # one would fail the trials this one trains (--resume) and train them again.
            spec.folder.mkdir(parents=True, exist_ok=True)
            held.enter_context(RunDir(spec.folder).lock("a sweep of this study"))
            _check_no_workers(spec.folder)
        elif embedded:  # a --jobs worker: its sweep's --resume waits for it (_check_no_workers)
            held.enter_context(_worker_hold(spec.folder))
        storage = None
        last_run: list[Path] = []  # the run folder of the trial this process started last
        try:
            journal = sweep_file(spec.folder, JOURNAL)
            if embedded and journal.exists() and not resume and not worker:
                raise SweepError(
                    f"{spec.folder}: a sweep of this study exists; add --resume to continue it"
                )
            optuna.logging.set_verbosity(optuna.logging.WARNING)
            storage = _storage(spec.storage_url, spec.folder)  # before a database's folder is made
            spec.folder.mkdir(parents=True, exist_ok=True)
            return _run_study(spec, storage, dims, grid, resume, jobs, worker, report, state,
                              last_run.append)  # fmt: skip
        except Exception as exc:
            lost = _storage_failure(exc) if storage is not None else None
            if lost is None:
                _name_file_error(exc, spec.folder, state.file_error)
                raise
            raise StorageLost(_lost_line(lost, last_run[-1] if last_run else None)) from None


def _name_file_error(exc: Exception, folder: Path, trial_error: TrialFileError | None) -> None:
    """Turn a file error into one line that says where: the trial's (``trial_error``) when
    Optuna, failing to record that trial's end on the same full disk, raised its own error
    instead (an ``OSError``, or its ``AssertionError`` for a trial left running); else one that
    names no file is the sweep folder's (its journal).

    Raises:
        SweepError: for such an error (nothing for any other: the caller raises it).
    """
    if trial_error is not None:  # the sweep was ending on it: what came after is its doing
        raise trial_error from None
    if isinstance(exc, OSError) and not exc.filename:
        raise SweepError(
            f"{exc.strerror or exc}: {folder} (the sweep's folder); once that is mended, "
            "continue with the same command and --resume"
        ) from None


def _run_study(
    spec: _Study,
    storage: Any,
    dims: Sequence[Dimension],
    grid: bool,
    resume: bool,
    jobs: int,
    worker: bool,
    report: Callable[[str], None] | None,
    state: _SignalState,
    started: Callable[[Path], None],
) -> dict[str, Any] | None:
    """The sweep on its opened ``storage`` (:func:`run_sweep`); ``started`` receives the run
    folder of each trial this process starts."""
    import optuna

    folder = spec.folder
    sampler = _grid_sampler(dims) if grid else optuna.samplers.TPESampler(seed=None)
    study = optuna.create_study(
        study_name=spec.study_name,
        storage=storage,
        direction="maximize",
        sampler=sampler,
        pruner=make_pruner(spec.pruner),
        load_if_exists=True,
    )
    check_overrides(study, spec.overrides)
    if resume and not worker:
        _fail_dead_trials(study, folder, embedded=spec.storage_url is None)
        if grid:
            _requeue_grid(study, sampler, spec.trials)
    if jobs > 1:
        _run_workers(spec, jobs)
    else:
        from harness.training.train import TrainingFailed, TrainingInterrupted

        # The lock of the trial in training, from before the trial names its run folder until
        # Optuna has recorded how it ended (released as the next trial starts, or the sweep
        # ends): a folder of a RUNNING trial that no live process holds is a dead trial.
        trial_lock = contextlib.ExitStack()

        def objective(trial: Any) -> float:
            trial_lock.close()
            try:
                return _objective(trial, spec.config_path, spec.overrides, dims, folder,
                                  spec.trials, trial_lock, started, state.note)  # fmt: skip
            except TrainingInterrupted:
                state.stopping = True  # its checkpoint is written; now the trial is marked failed
                raise
            except TrialFileError as exc:
                state.file_error = exc  # recording the trial's end may fail on the same disk
                raise

        counted = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)
        left = spec.trials - len(study.get_trials(deepcopy=False, states=counted))
        if left > 0:
            with trial_lock:
                study.optimize(
                    objective,
                    n_trials=left,
                    callbacks=[
                        optuna.study.MaxTrialsCallback(spec.trials, states=counted),
                        *([_Reporter(report, spec.trials)] if report is not None else []),
                        state.check,  # before the next trial starts: a signal ends the sweep
                    ],
                    catch=(StudyFull, TrainingFailed),
                )
    return None if worker else write_best(study, spec.config_path, spec.overrides, folder)


def _run_workers(spec: _Study, jobs: int) -> None:
    """``jobs`` worker processes on the study, each on its share of the cores; their output goes
    to ``worker-<k>.log`` in the sweep folder.

    Raises:
        SweepError: when a worker failed (naming its log).
    """
    from harness.results.groups import threads_per_job

    threads = threads_per_job(jobs)
    cmd = spec.worker_command(threads)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    processes: list[subprocess.Popen[bytes]] = []
    try:
        for k in range(jobs):
            with sweep_file(spec.folder, _worker_log_name(k)).open("wb") as log:
                processes.append(
                    subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
                )
        codes = [p.wait() for p in processes]
    except KeyboardInterrupt as exc:  # Ctrl-C reached the workers too: let them end their trials
        if isinstance(exc, SweepInterrupted):  # a SIGTERM reached this process alone
            for p in processes:
                p.send_signal(exc.signum)
        for p in processes:
            p.wait()
        raise
    failed = [k for k, code in enumerate(codes) if code != 0]
    if failed:
        log = spec.folder / _worker_log_name(failed[0])
        raise SweepError(f"sweep worker {failed[0]} failed; see {log}")


def _worker_log_name(k: int) -> str:
    """The name of worker ``k``'s log in the sweep folder."""
    return f"worker-{k}.log"


#: The file of a sweep folder that its ``--jobs`` workers hold (a shared ``flock``) as long as
#: they live: the sweep folder's ``.lock`` is the sweep command's, gone with it when it is killed.
WORKERS_LOCK = ".workers.lock"


@contextlib.contextmanager
def _worker_hold(folder: Path) -> Iterator[None]:
    """Hold ``folder``'s :data:`WORKERS_LOCK` (shared with the sweep's other workers) for the
    life of this worker; the kernel lets go of it when the process ends, however it ends."""
    fd = os.open(sweep_file(folder, WORKERS_LOCK), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH)
        yield
    finally:
        os.close(fd)


def _check_no_workers(folder: Path) -> None:
    """Refuse to go on while workers of an earlier sweep of ``folder`` live: their command was
    killed (its ``.lock`` is free) but they still train, and a ``--resume`` would mark their
    running trials failed and train them again. They stop by themselves once their parent is
    gone (``harness.processes.follow_parent``).

    Raises:
        SweepError: naming the folder.
    """
    path = sweep_file(folder, WORKERS_LOCK)
    try:
        fd = os.open(path, os.O_RDWR)
    except FileNotFoundError:  # no sweep of this folder had --jobs
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise SweepError(
            f"{folder}: workers of an earlier sweep of this study are still running (its "
            "command ended without them); they stop by themselves: try again once they have"
        ) from None
    finally:
        os.close(fd)


def _fail_dead_trials(study: Any, folder: Path, embedded: bool) -> None:
    """Mark the trials a killed worker left RUNNING as failed and queue each again with the same
    parameters (its run folder stays; the count of finished trials does not include it)."""
    import optuna

    running = (optuna.trial.TrialState.RUNNING,)
    if embedded:  # one machine, one journal: this process holds the sweep, the rest are gone
        dead = study.get_trials(deepcopy=False, states=running)
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            optuna.storages.fail_stale_trials(study)  # by heartbeat: live workers keep theirs
        # At once, without waiting for the heartbeat's grace period: the trials whose run folder
        # in this sweep folder no live process holds (their process lost the database, or was
        # killed). A trial of another machine has no folder here and is left to the heartbeat.
        dead = [
            t
            for t in study.get_trials(deepcopy=False, states=running)
            if _abandoned(t.user_attrs.get("run"), folder)
        ]
    retry = _retry_callback()
    for trial in dead:
        try:
            study._storage.set_trial_state_values(trial._trial_id, optuna.trial.TrialState.FAIL)
        except optuna.exceptions.UpdateFinishedTrialError:
            continue  # another worker failed it (and queued it) first
        retry(study, study._storage.get_trial(trial._trial_id))


def _abandoned(run: str | None, folder: Path) -> bool:
    """Whether ``run`` (a trial's run folder) is a folder of this sweep that no live process
    holds: a trial holds its folder's lock from before it names the folder until its end is
    recorded."""
    if run is None or Path(run).parent.resolve() != folder.resolve() or not Path(run).is_dir():
        return False
    try:
        with RunDir(Path(run)).lock():
            return True
    except RunDirError:  # held by a live trial (or not lockable: left alone)
        return False


#: The trials that settle a grid point: trained to the end, or stopped by the pruner.
_DONE = ("COMPLETE", "PRUNED")
#: The trials that hold a grid point for now: in training, or queued.
_HELD = ("RUNNING", "WAITING")


def _grid_sampler(dims: Sequence[Dimension]) -> Any:
    """Optuna's ``GridSampler`` of an all-grid space, with one fixed shuffle on every worker:
    trial k takes grid point k, so workers sharing a study never draw the same point (Optuna's
    advice for distributed grids).

    Unlike Optuna's own, a *failed* trial does not use up its grid point (Optuna counts every
    finished trial, a failed one too): a trial stopped by Ctrl-C or SIGTERM, or whose training
    failed, leaves its point to be trained again, and a queued (``WAITING``) trial holds its
    point as a running one does. Otherwise a sweep interrupted in a trial would never train that
    point, and take another one twice instead.
    """
    import optuna

    class GridSampler(optuna.samplers.GridSampler):
        def before_trial(self, study: Any, trial: Any) -> None:
            number, attrs = trial.number, trial.system_attrs
            if number < len(self._all_grids) and not {"grid_id", "fixed_params"} & set(attrs):
                # Trial k takes point k, unless a queued trial of a resume took that one.
                states = _grid_states(study, self).get(number, set())
                free = self._get_unvisited_grid_ids(study)
                if states & {*_DONE, *_HELD} and free:
                    grid_id = int(self._rng.rng.choice(free))
                    study._storage.set_trial_system_attr(
                        trial._trial_id, "search_space", self._search_space
                    )
                    study._storage.set_trial_system_attr(trial._trial_id, "grid_id", grid_id)
                    return
            super().before_trial(study, trial)

        def _get_unvisited_grid_ids(self, study: Any) -> list[int]:
            states = _grid_states(study, self)
            done = {g for g, names in states.items() if names & set(_DONE)}
            held = {g for g, names in states.items() if names & set(_HELD)}
            unvisited = set(range(len(self._all_grids))) - done
            # Every point started already: those not settled (as Optuna's does).
            return sorted(unvisited - held or unvisited)

    return GridSampler({d.key: list(d.values) for d in dims}, seed=0)


def _grid_states(study: Any, sampler: Any) -> dict[int, set[str]]:
    """The states (names) of the trials on each grid point of ``sampler``'s grid."""
    states: dict[int, set[str]] = {}
    for trial in study._storage.get_all_trials(study._study_id, deepcopy=False):
        attrs = trial.system_attrs
        if "grid_id" in attrs and sampler._same_search_space(attrs.get("search_space", {})):
            states.setdefault(attrs["grid_id"], set()).add(trial.state.name)
    return states


def _requeue_grid(study: Any, sampler: Any, trials: int) -> list[int]:
    """On ``--resume`` of a grid sweep, queue every grid point that has no complete (or pruned)
    trial and none running or queued, in grid order, as many as the sweep still needs: a trial
    that a signal stopped (marked failed) is trained again, and never a point that has its
    trial already. Returns the queued grid points.
    """
    import optuna

    states = _grid_states(study, sampler)
    done = {g for g, names in states.items() if names & set(_DONE)}
    held = {g for g, names in states.items() if names & set(_HELD)} - done
    counted = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)
    room = trials - len(study.get_trials(deepcopy=False, states=counted)) - len(held)
    missing = [g for g in range(len(sampler._all_grids)) if g not in done | held][: max(0, room)]
    for grid_id in missing:
        params = dict(zip(sampler._param_names, sampler._all_grids[grid_id], strict=True))
        study.add_trial(
            optuna.trial.create_trial(
                state=optuna.trial.TrialState.WAITING,
                system_attrs={
                    "grid_id": grid_id,
                    "search_space": sampler._search_space,
                    "fixed_params": params,
                },
            )
        )
    return missing


class StudyFull(Exception):
    """Another worker's trials already make up the sweep's total (the trial is marked failed,
    with the user attribute ``skipped``, and this worker stops)."""


def _claim(trial: Any, total: int) -> None:
    """Keep the total exact with several workers: a trial counts only if fewer than ``total``
    trials numbered before it are complete, pruned or running. Optuna numbers trials atomically
    in the storage, so two workers never both claim the last place (``MaxTrialsCallback`` alone
    checks after a trial, and two workers starting at once would overshoot).

    Raises:
        StudyFull: when the study has its trials already.
    """
    import optuna

    alive = (
        optuna.trial.TrialState.COMPLETE,
        optuna.trial.TrialState.PRUNED,
        optuna.trial.TrialState.RUNNING,
    )
    before = trial.study.get_trials(deepcopy=False, states=alive)
    if sum(1 for t in before if t.number < trial.number) >= total:
        trial.set_user_attr("skipped", f"the study already had its {total} trials")
        trial.study.stop()
        raise StudyFull(trial.number)


def _objective(
    trial: Any,
    config_path: Path,
    overrides: Sequence[str],
    dims: Sequence[Dimension],
    folder: Path,
    total: int,
    lock: contextlib.ExitStack,
    started: Callable[[Path], None] = lambda run: None,
    on_signal: Callable[[int], None] | None = None,
) -> float:
    """Train one trial into its own run folder; its value is the median validation coverage
    (a PettingZoo env of one's own: the median team return, or the ``env.pettingzoo.select``
    group's, :func:`objective_value`).
    The folder's lock goes onto ``lock`` (the caller releases it once Optuna has recorded the
    trial's end); ``started`` receives the folder; ``on_signal`` hears of a signal that
    reaches the trial's training (``train``'s).

    Raises:
        optuna.TrialPruned: when the pruner stops it (the run folder keeps what it logged).
        TrainingFailed: on a non-finite loss (the trial is marked failed).
    """
    import optuna

    from harness.evaluation.episodes import model_policy, objective_value, run_episodes, summarize
    from harness.training.train import train

    _claim(trial, total)
    params = {d.key: d.suggest(trial) for d in dims}
    config = load_config(config_path, [*overrides, *(override(k, v) for k, v in params.items())])
    run = RunDir.create_at(sweep_file(folder, f"trial-{trial.number:04d}"))
    lock.enter_context(run.lock())  # before the trial names it: a --resume leaves it alone
    started(run.path)
    trial.set_user_attr("run", str(run.path))
    last: dict[str, Any] = {}

    def report(timesteps: int, summary: dict[str, Any]) -> None:
        last.update(timesteps=timesteps, value=objective_value(summary))
        trial.report(last["value"], timesteps)
        if trial.should_prune():
            raise optuna.TrialPruned(f"pruned at {timesteps} transitions")

    if config.prior is not None:  # a map prior's trial: its last validation log-loss, negated
        from harness.training.prior import train_prior

        def report_prior(step: int, summary: dict[str, Any]) -> None:
            last.update(timesteps=step, value=-summary["unseen_logloss"])
            trial.report(last["value"], step)
            if trial.should_prune():
                raise optuna.TrialPruned(f"pruned at {step} gradient steps")

        try:
            train_prior(
                config, run, progress_bar=False, command=["sweep", str(trial.number)],
                on_evaluation=report_prior, on_signal=on_signal,
            )  # fmt: skip
        except OSError as exc:
            raise _trial_file_error(exc, trial.number, run.path) from None
        return last["value"]
    try:
        model = train(
            config, run, progress_bar=False, command=["sweep", str(trial.number)],
            on_evaluation=report, on_signal=on_signal,
        )  # fmt: skip
        if last.get("timesteps") == model.num_timesteps:  # the last evaluation saw the model
            return last["value"]
        ev = config.eval
        results = run_episodes(
            model_policy(model, ev.temperature, ev.shield),
            config.env,
            ev.episodes,
            ev.validation_seed,
        )
    except OSError as exc:  # a full disk: one line that names where, not Optuna's traceback
        raise _trial_file_error(exc, trial.number, run.path) from None
    return objective_value(summarize(results))


#: What a trial's value is (``best.json``'s ``objective``): :func:`objective_value` of the
#: validation episodes of the trained model (its task's objective,
#: :meth:`harness.tasks.base.Task.objective`, "median coverage of the config's validation
#: episodes" for the coverage env); for a map prior (``prior:``): higher is better, as for the
#: others.
PRIOR_OBJECTIVE = "minus the mean log-loss per unseen cell of the validation episodes' maps"


def trial_line(study: Any, trial: Any, total: int) -> str:
    """One finished trial: its number of ``total``, parameters, value, state and the best so far,
    e.g. ``trial 3/40 complete: algo.gamma=0.97 -> 0.812 (best 0.840, trial 1)``."""
    params = " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                      for k, v in trial.params.items())  # fmt: skip
    state = trial.state.name.lower()
    value = f" -> {trial.value:.3f}" if trial.value is not None else ""
    try:
        best = study.best_trial
        best_text = f" (best {best.value:.3f}, trial {best.number})"
    except ValueError:  # no trial completed yet
        best_text = ""
    return f"trial {trial.number + 1}/{total} {state}: {params}{value}{best_text}"


class _Reporter:
    """Optuna callback: :func:`trial_line` of every trial this process finishes."""

    def __init__(self, report: Callable[[str], None], total: int) -> None:
        self.report, self.total = report, total

    def __call__(self, study: Any, trial: Any) -> None:
        if "skipped" not in trial.user_attrs:  # not run: the study had its trials (StudyFull)
            self.report(trial_line(study, trial, self.total))


def write_best(
    study: Any, config_path: Path, overrides: Sequence[str], folder: Path
) -> dict[str, Any] | None:
    """``best.yaml`` (a ready config) and ``best.json`` (parameters, value, trial) of a study,
    and ``trials.csv``, every trial: number, state, value, parameters, times, run folder."""
    import optuna

    table = study.trials_dataframe(
        attrs=("number", "state", "value", "params", "user_attrs", "duration")
    )
    atomic_write_text(sweep_file(folder, TRIALS_TABLE), table.to_csv(index=False))

    complete = study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
    if not complete:
        return None
    best = max(complete, key=lambda t: t.value)
    config = load_config(
        config_path, [*overrides, *(override(k, v) for k, v in best.params.items())]
    )
    atomic_write_text(sweep_file(folder, BEST_CONFIG), config.to_yaml())
    task = task_of(config.env)
    result = {
        "study": study.study_name,
        "trial": best.number,
        "value": best.value,
        "objective": PRIOR_OBJECTIVE if config.prior is not None else task.objective(task.select),
        "params": best.params,
        "run": best.user_attrs.get("run"),
        "trials": {
            state.name.lower(): len(study.get_trials(deepcopy=False, states=(state,)))
            for state in optuna.trial.TrialState
        },
    }
    if task.select is not None:  # (format_best's words: the group's return, not the team's)
        result["select"] = task.select
    atomic_write_text(sweep_file(folder, BEST_RESULT), json.dumps(result, indent=2) + "\n")
    return result


def format_best(result: dict[str, Any] | None) -> str:
    if result is None:
        return "no trial has completed yet"
    params = ", ".join(f"{k}={v!r}" for k, v in result["params"].items())
    select = result.get("select")
    task = next((t for t in TASKS if t.objective(select) == result.get("objective")), TASKS[0])
    if result.get("objective") == PRIOR_OBJECTIVE:
        value = f"validation unseen_logloss {-result['value']:.4f}"
    else:
        value = f"validation {task.selection_metric(select)} {task.format_value(result['value'])}"
    return (
        f"best trial {result['trial']}: {value} ({params}); "
        f"trials {yaml.safe_dump(result['trials'], default_flow_style=True).strip()}"
    )
