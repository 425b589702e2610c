"""Seed groups: one run per training seed, found together.

``harness run CONFIG --seeds 0,1,2 --jobs 2`` makes a group folder ``runs/<name>-<UTC time>/``
holding ``group.json`` (the config, the seeds and each seed's run folder), ``group-config.yaml``
(the config as resolved, which a resume starts a seed from) and one ordinary run folder per
seed, ``<name>-seed<k>-<UTC time>/``, each with its own log ``<name>-seed<k>.log``.
Every run is a separate ``harness run`` process, so a group is no more than the runs it holds:
``harness eval``, ``compare``, ``render`` and ``--resume`` work on each of them as on any run.

``--jobs N`` runs N seeds at a time, each with ``cores // N`` torch threads (and the matching
``OMP_NUM_THREADS``/``MKL_NUM_THREADS``), so the jobs do not fight over the cores.

Ctrl-C or SIGTERM to the group's command is passed on to the seeds in training (each in a
process group of its own, so a terminal's Ctrl-C reaches it once), which write a checkpoint and
stop; no further seed starts, and the command ends with one line and exit code 130 or 143.
``harness run --resume GROUP`` then finishes the group: it resumes each seed that stopped, starts
those never started and leaves the finished ones alone. The group folder is locked while its
command or a resume runs (``.lock``, as a run folder is).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from harness.processes import available_cores, harness_command
from harness.results.rundir import (
    RunDir,
    RunDirError,
    against_filename,
    atomic_write_text,
    inside,
    result_filename,
    unique_folder,
)

#: The file that marks a folder as a seed group.
GROUP_FILE = "group.json"
#: The group's config as its command resolved it (the config file with the ``--set``
#: overrides): a seed that ``--resume GROUP`` starts is started from this copy inside the group,
#: never from the file ``group.json`` names (a downloaded group.json could name any file).
GROUP_CONFIG = "group-config.yaml"


def group_result_file(run_file: str) -> str:
    """The group's file of the numbers over seeds of the results each of its runs saved as
    ``run_file`` (a name of :func:`~harness.results.rundir.result_filename` or
    :func:`~harness.results.rundir.against_filename`): ``group-`` and that name, so that each
    evaluation of a group has a file of its own, as each run's has: ``eval.json`` gives
    ``group-eval.json``, ``eval-30ep.json`` (``--episodes 30``) ``group-eval-30ep.json``,
    ``against-frontier_pocket-30ep.json`` ``group-against-frontier_pocket-30ep.json``."""
    return f"group-{run_file}"


#: The numbers over seeds of ``harness eval GROUP`` (the standard evaluation of every run).
GROUP_EVAL_FILE = group_result_file(result_filename("eval", []))


def group_against_file(policy: str) -> str:
    """The file of ``harness eval GROUP --against POLICY`` (the standard evaluation): the runs'
    episode-by-episode differences from the baseline ``policy`` (their
    ``against-POLICY.json``), over seeds."""
    return group_result_file(against_filename(policy, []))


class GroupError(ValueError):
    """A seed list or group folder that cannot be used, with a one-line message."""


#: Most runs in a seed group (``--seeds N``): far more than any comparison needs.
MAX_GROUP_RUNS = 1_000

#: How a ``harness`` command's error line starts (a seed's own reason to fail, in its log).
ERROR_PREFIX = "harness: error: "
#: Bytes at the end of a failed seed's log searched for its error line.
ERROR_TAIL_BYTES = 64 * 1024


def parse_seeds(text: str, max_seed: int) -> list[int]:
    """``"0,1,2"`` → ``[0, 1, 2]``; a single number ``"3"`` means three seeds, ``0, 1, 2``.

    Raises:
        GroupError: for anything else, duplicates, or seeds outside ``[0, max_seed]``.
    """
    parts = [p.strip() for p in text.split(",")]
    try:
        numbers = [int(p) for p in parts]
    except ValueError:
        raise GroupError(f"--seeds {text!r}: expected a count (3) or a list (0,1,2)") from None
    if (numbers[0] if len(numbers) == 1 else len(numbers)) > MAX_GROUP_RUNS:
        raise GroupError(f"--seeds {text[:40]!r}: at most {MAX_GROUP_RUNS:,} runs in a group")
    seeds = list(range(numbers[0])) if len(numbers) == 1 else numbers
    if not seeds:  # a count below 1: perhaps meant as the seed itself
        raise GroupError(
            f"--seeds {text!r}: a single number is a count of seeds (--seeds 3 trains seeds 0, "
            "1, 2) and must be at least 1; to train one given seed, use --seed N"
        )
    if len(set(seeds)) != len(seeds):
        raise GroupError(f"--seeds {text!r}: a seed is given twice")
    if any(not 0 <= s <= max_seed for s in seeds):
        raise GroupError(f"--seeds {text!r}: seeds must be in [0, {max_seed}]")
    return seeds


def is_group(folder: Path) -> bool:
    """Whether ``folder`` is a seed group (holds ``group.json``)."""
    return (Path(folder) / GROUP_FILE).is_file()


def group_file(folder: Path, name: str) -> Path:
    """The group's own file ``name`` (``group.json``, ``group-eval.json``, a seed's log), asked
    for through rundir's rule: it lies inside the group folder, links resolved.

    Raises:
        LinkOutError: for one that leads out of the group, naming it and where it leads.
    """
    return inside(Path(folder) / name, folder, "the group folder")


def group_members(folder: Path) -> list[Path]:
    """Every run folder ``group.json`` names, in seed order, whether it exists or not.

    Members live inside the group folder: ``harness eval`` and ``tune`` of a group load their
    models (pickles) and write into them, so a ``group.json`` naming an absolute path, a ``..``
    path or a link leading out of the group is refused, never followed.

    Raises:
        GroupError: when ``group.json`` cannot be read or names a run outside the group.
    """
    return list(group_seeds(folder))


def group_seeds(folder: Path) -> dict[Path, Any]:
    """Every run folder ``group.json`` names (:func:`group_members`), with the seed it names for
    it (``None`` where it names none), in seed order.

    Raises:
        GroupError: when ``group.json`` cannot be read, names a run outside the group, or names
            a run folder or a seed twice (a group is one run per seed: a run counted twice, or
            a seed trained twice, would be evaluated as two seeds without a word).
    """
    folder = Path(folder)
    where = folder / GROUP_FILE
    try:
        data = json.loads(group_file(folder, GROUP_FILE).read_text(encoding="utf-8"))
        entries = [(entry["run"], entry.get("seed")) for entry in data["runs"]]
    except RunDirError:
        raise
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise GroupError(f"{where}: not a readable group file ({exc})") from None
    members: dict[Path, Any] = {}
    seeds: set[int] = set()
    for name, seed in entries:
        member = _member(folder, name)
        if member.resolve() in {m.resolve() for m in members}:
            raise GroupError(f"{where}: names run {name!r} twice (one run folder per seed)")
        if isinstance(seed, int) and not isinstance(seed, bool):
            if seed in seeds:
                raise GroupError(f"{where}: names seed {seed} twice (one run folder per seed)")
            seeds.add(seed)
        members[member] = seed
    return members


def _member(folder: Path, name: Any) -> Path:
    """``folder / name`` when that is a path inside the group folder (links resolved).

    Raises:
        GroupError: for anything else, in one line naming the group file and the entry.
    """
    where = f"{folder / GROUP_FILE}: run {name!r}"
    if not isinstance(name, str) or not Path(name).parts:
        raise GroupError(f"{where} is not the name of a run folder in the group")
    relative = Path(name)
    if relative.is_absolute() or ".." in relative.parts:
        raise GroupError(f"{where} is outside the group folder (a group's runs live inside it)")
    member = folder / relative
    try:
        inside = member.resolve().is_relative_to(folder.resolve())
    except (OSError, ValueError, RuntimeError) as exc:  # a NUL byte, a link loop
        raise GroupError(f"{where}: not a usable path ({exc})") from None
    if not inside:
        raise GroupError(f"{where} leads outside the group folder (a group's runs live inside it)")
    return member


def group_runs(folder: Path) -> list[Path]:
    """The run folders of a group that exist, in seed order.

    Raises:
        GroupError: when ``group.json`` cannot be read or names no run that exists.
    """
    folder = Path(folder)
    members = group_seeds(folder)
    for run in members:  # first: the group's own words for a file linked out of it
        _check_member_files(folder, run)
    found = [run for run in members if RunDir(run).is_run]
    if not found:
        raise GroupError(f"{folder}: the group has no run folder yet")
    for run in found:
        _check_member_seed(folder, run, members[run])
    return found


def _check_member_seed(folder: Path, run: Path, seed: Any) -> None:
    """Refuse a member whose ``config.yaml`` trains another seed than ``group.json`` says: its
    numbers would be counted as that seed's (an edited or copied group file).

    Raises:
        GroupError: naming both seeds, in one line.
    """
    from harness.config.loading import parse_yaml, read_yaml_text

    if not isinstance(seed, int) or isinstance(seed, bool):
        return  # a group file that names no seed: nothing to hold the run to
    config = RunDir(run).config
    try:
        data = parse_yaml(read_yaml_text(config, "config"), str(config))
    except ValueError:  # a config that cannot be read is the run's own error, said where read
        return
    trained = data.get("seed", 0) if isinstance(data, dict) else None
    if trained != seed:
        raise GroupError(
            f"{folder / GROUP_FILE}: names {run.name} as seed {seed}, but its config.yaml trains "
            f"seed {trained!r}: the group file does not match its runs"
        )


def _check_member_files(folder: Path, member: Path) -> None:
    """Refuse a member whose config or models (what ``eval`` and ``tune`` of a group read, and
    unpickle) lead outside the group folder: pickles are loaded only from paths named on the
    command line, and a link in a downloaded group would name another. (Each run then asks the
    same rule of its own files, against its own folder: :meth:`RunDir.inside`.)

    Raises:
        GroupError: naming the file, in one line.
    """
    for path in RunDir(member).loaded_files():
        try:
            inside(path, folder, "the group folder")
        except RunDirError as exc:  # a link out, or a link loop
            raise GroupError(f"{exc} (copy the file in instead of linking it)") from None


@dataclass
class Job:
    """One seed's training process."""

    seed: int
    run: RunDir
    process: subprocess.Popen[bytes] | None = None
    returncode: int | None = None
    cmd: list[str] | None = None
    """The command that trains it; ``None``: nothing to do (a finished seed of a resumed group)."""
    log_start: int = 0
    """Size of its log when this command started it: what its process wrote comes after (a
    resume appends to the log of the attempts before)."""

    @property
    def log(self) -> Path:
        """The seed's log, ``<run folder>.log`` beside its run folder (in the group folder)."""
        return group_file(self.run.path.parent, f"{self.run.path.name}.log")

    def error_line(self) -> str | None:
        """The last ``harness: error:`` line its process wrote to its log, without that prefix
        (the reason a failed seed gives, shown so that nobody has to open the log); ``None``
        when it wrote none (killed, or a traceback) or the log cannot be read."""
        try:
            with self.log.open("rb") as f:
                # The end is enough: an error line is the last thing a failed run writes.
                f.seek(max(self.log_start, f.seek(0, os.SEEK_END) - ERROR_TAIL_BYTES))
                tail = f.read().decode("utf-8", "replace")
        except OSError:
            return None
        errors = [
            line[len(ERROR_PREFIX) :].strip()
            for line in tail.splitlines()  # also splits at a progress bar's "\r"
            if line.startswith(ERROR_PREFIX)
        ]
        return errors[-1] if errors else None


class GroupInterrupted(Exception):
    """A seed group stopped by SIGINT or SIGTERM: the signal was passed on to the seeds in
    training, which wrote a checkpoint and stopped; the seeds after them were not started.
    ``harness run --resume GROUP`` continues it."""

    def __init__(self, signum: int, group: Path, jobs: list[Job]) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum, self.group, self.jobs = signum, group, jobs

    def summary(self) -> str:
        """``seed 0 stopped, seeds 1, 2 not started`` (the seeds done too, if any)."""
        states: dict[str, list[int]] = {"done": [], "stopped": [], "not started": []}
        for job in self.jobs:
            if job.returncode is None:
                states["not started"].append(job.seed)
            else:
                states["done" if job.returncode == 0 else "stopped"].append(job.seed)
        return ", ".join(
            f"seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))} {state}"
            for state, seeds in states.items()
            if seeds
        )


def threads_per_job(jobs: int, cores: int | None = None) -> int:
    """Torch threads for each of ``jobs`` parallel trainings: an equal share of the cores."""
    cores = cores or available_cores()
    return max(1, cores // max(1, jobs))


def run_group(
    config_path: Path,
    name: str,
    overrides: Sequence[str],
    seeds: Sequence[int],
    jobs: int,
    runs_dir: Path,
    argv: Sequence[str],
    report: Callable[[str], None] | None = None,
    every: float = 30.0,
    config_yaml: str | None = None,
    say: Callable[[str], None] | None = None,
) -> tuple[Path, list[Job]]:
    """Train one run per seed, ``jobs`` at a time, in a new group folder.

    Each seed is ``harness run CONFIG --set ... --seed k`` in its own process, writing into its
    own run folder inside the group; its output goes to ``<name>-seed<k>.log`` there.
    ``config_yaml`` (the config as resolved, :meth:`ExperimentConfig.to_yaml`) is kept as
    :data:`GROUP_CONFIG`, the config a resume starts a seed never started from. With
    ``report``, a line per running seed (:func:`seed_progress`) every ``every`` seconds when it
    changed, and one when a seed starts or ends. ``say`` receives ``group folder: PATH`` as
    soon as the folder is made, before any seed starts (a group runs for hours; its folder is
    where to look meanwhile).

    Returns:
        The group folder and the jobs with their exit codes.

    Raises:
        GroupInterrupted: on SIGINT/SIGTERM, once the seeds in training have stopped.
    """
    check_group_overrides(overrides)
    group = unique_folder(runs_dir, name)
    threads = threads_per_job(jobs)
    pending = [Job(seed, RunDir(group / f"{name}-seed{seed}")) for seed in seeds]
    data: dict[str, Any] = {
        "name": name,
        "config": str(Path(config_path).resolve()),
        "overrides": list(overrides),
        "seeds": list(seeds),
        "jobs": jobs,
        "threads_per_job": threads,
        "command": ["harness", *argv],
        "runs": [{"seed": job.seed, "run": job.run.path.name} for job in pending],
    }
    with RunDir(group).lock():  # a `--resume` of the group waits for this command to end
        if config_yaml is not None:
            atomic_write_text(group_file(group, GROUP_CONFIG), config_yaml)
        atomic_write_text(group_file(group, GROUP_FILE), json.dumps(data, indent=2) + "\n")
        if say is not None:
            say(f"group folder: {group}")
        for job in pending:
            job.cmd = _start_command(job, config_path, overrides, threads)
        return group, _run_jobs(group, pending, jobs, threads, report, every)


def _run_jobs(
    group: Path,
    jobs: list[Job],
    at_once: int,
    threads: int,
    report: Callable[[str], None] | None,
    every: float,
) -> list[Job]:
    """Run the jobs that have a command, ``at_once`` at a time; those without one count as done.

    A SIGINT or SIGTERM to this process is passed on to every seed in training (each runs in a
    process group of its own, so a terminal's Ctrl-C reaches it once, through here); no seed
    starts after it, and once the running ones have ended (each writes a checkpoint and stops,
    as ``harness run`` does), :class:`GroupInterrupted` is raised.

    Returns:
        Every job with its exit code, in the order given.
    """
    env = {
        **os.environ,
        "OMP_NUM_THREADS": str(threads),
        "MKL_NUM_THREADS": str(threads),
    }
    queue = [job for job in jobs if job.cmd is not None]
    for job in jobs:
        if job.cmd is None:
            job.returncode = 0
    running: list[Job] = []
    said: dict[int, str] = {}
    received: list[int] = []
    forwarded = 0
    next_report = time.monotonic() + every
    with _received_signals(received), _stop_on_error(running):
        while running or (queue and not received):
            while queue and not received and len(running) < at_once:
                job = queue.pop(0)
                job.process = _start(job, env)
                running.append(job)
                if report is not None:  # a word at once: the first progress line is `every` away
                    report(f"seed {job.seed}: started (log: {job.log})")
            forwarded = _forward(received, forwarded, running)
            time.sleep(0.2)
            forwarded = _forward(received, forwarded, running)
            for job in list(running):
                assert job.process is not None
                if job.process.poll() is not None:
                    job.returncode = job.process.returncode
                    running.remove(job)
                    if report is not None and not received:
                        state = "done" if job.returncode == 0 else f"failed (exit {job.returncode})"
                        report(f"{seed_progress(job)}: {state}")
            if report is not None and not received and time.monotonic() >= next_report:
                next_report = time.monotonic() + every
                for job in running:
                    line = seed_progress(job)
                    if said.get(job.seed) != line:
                        said[job.seed] = line
                        report(line)
    if received:
        raise GroupInterrupted(received[0], group, jobs)
    return jobs


@contextlib.contextmanager
def _received_signals(received: list[int]) -> Iterator[None]:
    """SIGINT and SIGTERM are noted in ``received`` (for the jobs loop to pass on) instead of
    ending this process while its seeds train."""
    if threading.current_thread() is not threading.main_thread():  # signals: main thread only
        yield
        return
    signals = (signal.SIGINT, signal.SIGTERM)
    previous = {sig: signal.signal(sig, lambda signum, frame: received.append(signum))
                for sig in signals}  # fmt: skip
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


@contextlib.contextmanager
def _stop_on_error(running: list[Job]) -> Iterator[None]:
    """On an error of this process (a log it cannot open), stop the seeds in training as a
    SIGTERM would, rather than leave them without their group command."""
    try:
        yield
    except BaseException:
        for job in running:
            assert job.process is not None
            with contextlib.suppress(ProcessLookupError):
                job.process.send_signal(signal.SIGTERM)
        for job in running:
            assert job.process is not None
            job.returncode = job.process.wait()
        raise


def _forward(received: list[int], forwarded: int, running: list[Job]) -> int:
    """Pass the signals received since the last call on to the running seeds; the count passed."""
    for signum in received[forwarded:]:
        for job in running:
            assert job.process is not None
            with contextlib.suppress(ProcessLookupError):
                job.process.send_signal(signum)
    return len(received)


def read_group(folder: Path) -> dict[str, Any]:
    """``group.json`` of a group folder, with the keys a resume needs checked.

    Raises:
        GroupError: when it cannot be read or lacks them.
    """
    path = group_file(folder, GROUP_FILE)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        ok = (
            isinstance(data["config"], str)
            and isinstance(data["overrides"], list)
            and all(isinstance(o, str) for o in data["overrides"])
            and all(isinstance(r["seed"], int) for r in data["runs"])
        )
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise GroupError(f"{path}: not a readable group file ({exc})") from None
    if not ok:
        raise GroupError(f"{path}: not a group file harness run --seeds wrote")
    return data


class SeedStanding(Protocol):
    """How a seed's run stands, as the training layer decides it
    (:func:`harness.training.state.run_state`): a group only acts on it."""

    @property
    def never_started(self) -> bool:
        """No ``config.yaml`` yet: the seed is started as the group's command would have."""

    @property
    def finished(self) -> bool:
        """Nothing left to train: the seed is left alone."""

    @property
    def words(self) -> str:
        """How it stands or stopped, for the seed's line (``stopped at step 1,200``)."""


#: Tells how a seed's run stands (the command line passes the training layer's ``run_state``).
SeedState = Callable[[RunDir], SeedStanding]


def plan_resume(folder: Path, jobs: int, state_of: SeedState) -> tuple[list[Job], list[str]]:
    """What ``harness run --resume GROUP`` does for each seed, and a line saying it per seed.

    A seed that ``state_of`` calls finished is left alone; one never started (no
    ``config.yaml``) is started as the group's command would have, from the config inside the
    group (:func:`start_config`); any other is resumed (``harness run --resume RUN``: from its
    checkpoint, or from step 0 when it stopped before the first).

    Raises:
        GroupError: for a group file that cannot be used, a seed's folder that is neither a run
            nor empty, or a seed still in training (its folder is locked by a live process).
    """
    folder = Path(folder)
    data = read_group(folder)
    members = group_members(folder)
    threads = threads_per_job(jobs)
    plan: list[Job] = []
    lines: list[str] = []
    for entry, member in zip(data["runs"], members, strict=True):
        job = Job(entry["seed"], RunDir(member))
        run, name = job.run, member.name
        standing = state_of(run)
        if standing.finished:
            lines.append(f"seed {job.seed}: {standing.words} ({name}), left alone")
        elif standing.never_started:
            config_path = start_config(folder, members, job)
            _clear_unstarted(run, job.seed)
            # The overrides are in that config already; the start sets the seed and threads.
            job.cmd = _start_command(job, config_path, [], threads)
            lines.append(f"seed {job.seed}: {standing.words}, starting it ({name})")
        else:
            _check_not_running(run, job.seed)
            job.cmd = harness_command("run", "--resume", str(run.path), "--no-progress")
            lines.append(f"seed {job.seed}: {standing.words}, resuming it ({name})")
        if job.cmd is not None:
            _ = job.log  # a log linked out of the group: refused before any seed starts
        plan.append(job)
    return plan, lines


def start_config(folder: Path, members: Sequence[Path], job: Job) -> Path:
    """The config a seed that ``--resume GROUP`` starts is started from: the group's own copy
    (:data:`GROUP_CONFIG`), or in a group made before groups kept one, a started seed's
    ``config.yaml`` (the same config but for the seed and threads, which the start sets). Both
    lie inside the group folder named on the command line; the ``config`` and ``overrides`` of
    ``group.json`` only record what the group's command was given, and are never loaded (a
    downloaded group.json could name any file, any env constructor).

    Raises:
        GroupError: when the group holds neither.
        LinkOutError: for one that leads out of the group (or out of its run).
    """
    own = group_file(folder, GROUP_CONFIG)
    if own.is_file():
        return own
    for member in members:
        run = RunDir(member)
        if run.is_run:
            return run.config
    raise GroupError(
        f"{folder / GROUP_FILE}: seed {job.seed} was never started and the group holds no config "
        f"to start it from (no {GROUP_CONFIG}, no started seed); start it with: harness run "
        f"CONFIG --set seed={job.seed} --into {job.run.path}"
    )


def resume_group(
    folder: Path,
    state_of: SeedState,
    jobs: int | None = None,
    say: Callable[[str], None] | None = None,
    report: Callable[[str], None] | None = None,
    every: float = 30.0,
) -> list[Job]:
    """``harness run --resume GROUP``: finish what a stopped group left, ``jobs`` seeds at a time
    (default: the group's own ``--jobs``), as :func:`run_group` does. ``say`` receives one line
    per seed saying what is done with it (:func:`plan_resume`, with ``state_of``) before
    anything starts.

    Returns:
        Every seed's job with its exit code (0 for those finished before).

    Raises:
        GroupInterrupted: on SIGINT/SIGTERM, once the seeds in training have stopped.
        GroupError: see :func:`plan_resume`.
        RunDirError: when another process holds the group (its command, or another resume).
    """
    folder = Path(folder)
    with RunDir(folder).lock():
        if jobs is None:
            saved = read_group(folder).get("jobs")
            jobs = saved if isinstance(saved, int) and saved >= 1 else 1
        plan, lines = plan_resume(folder, jobs, state_of)
        for line in lines:
            if say is not None:
                say(line)
        return _run_jobs(folder, plan, jobs, threads_per_job(jobs), report, every)


def _clear_unstarted(run: RunDir, seed: int) -> None:
    """Remove a seed's folder that a kill left before its ``config.yaml`` (nothing trained), so
    that the seed can start in it again.

    Raises:
        GroupError: when the folder holds anything else.
    """
    if not run.path.exists():
        return
    made = RunDir.made_names()  # what `harness run --into` makes before the config.yaml
    try:
        entries = list(run.path.iterdir())
        empty = all(
            p.name.endswith(".tmp") or (p.name in made and (not p.is_dir() or not any(p.iterdir())))
            for p in entries
        )
        if empty:
            _check_not_running(run, seed)
            shutil.rmtree(run.path)
            return
    except OSError as exc:
        raise GroupError(f"{run.path}: cannot clear it for seed {seed} ({exc.strerror})") from None
    raise GroupError(
        f"{run.path}: seed {seed}'s folder has no config.yaml but holds files; move it away to "
        "start the seed again"
    )


def _check_not_running(run: RunDir, seed: int) -> None:
    """Raises GroupError when a live process holds the seed's run folder."""
    if not run.path.is_dir():
        return
    try:
        with run.lock():
            pass
    except RunDirError as exc:
        raise GroupError(f"seed {seed}: {exc}") from None


def seed_progress(job: Job) -> str:
    """``seed k: N transitions, validation M %`` from the run's logs so far (the last finished
    episode's transition count and the last in-training validation's median coverage)."""
    parts = [f"seed {job.seed}"]
    try:
        steps = _number(_last_value(job.run.episodes_csv, "timesteps"))
    except RunDirError:  # a log linked out of its run is not read (the seed's command refuses it)
        steps = None
    parts.append(f"{int(steps):,} transitions" if steps is not None else "starting")
    value = seed_progress_value(job.run)
    if value is not None:
        parts.append(f"validation {seed_progress_metric(job.run)[1](value)}")
    return ", ".join(parts)


def seed_progress_value(run: RunDir) -> float | None:
    """The last in-training validation's median coverage of ``run`` (a PettingZoo env of one's
    own: its median team return; ``None``: none yet, or a log linked out of the run)."""
    try:
        path = run.evaluations_csv
    except RunDirError:
        return None
    value = _last_value(path, "coverage_median")
    if value is None:
        value = _last_value(path, "return_median")
    return _number(value)


def seed_progress_metric(run: RunDir) -> tuple[str, Callable[[float], str]]:
    """What :func:`seed_progress_value` of ``run`` measures, and how to write it."""
    with contextlib.suppress(RunDirError):  # a log linked out of the run is not read
        if _last_value(run.evaluations_csv, "return_median") is not None:
            return "median team return", "{:.4g}".format
    return "median coverage", "{:.1%}".format


def _number(text: str | None) -> float | None:
    """A log cell as a finite number; ``None`` for none, or one that is not (a damaged log must
    not end the seeds' training with a traceback)."""
    try:
        value = float(text) if text is not None else None
    except ValueError:
        return None
    return value if value is not None and math.isfinite(value) else None


def _last_value(path: Path, column: str) -> str | None:
    """``column`` of the last row of a CSV log, ``None`` when there is none yet (or it is being
    written: a partial last line is skipped)."""
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return None
    if len(lines) < 2:
        return None
    header = lines[0].split(",")
    if column not in header:
        return None
    for line in reversed(lines[1:]):
        cells = line.split(",")
        if len(cells) == len(header):
            return cells[header.index(column)]
    return None


#: The keys a seed group sets in each seed's command (:func:`_start_command`).
GROUP_KEYS = ("seed", "algo.threads")


def check_group_overrides(overrides: Sequence[str]) -> None:
    """Refuse a ``--set`` of a key the group sets for each seed itself (the seed's own command
    would name it twice, and every seed would fail the same way).

    Raises:
        GroupError: one line naming the key and what gives it.
    """
    for override in overrides:
        key = override.partition("=")[0].strip()
        if key in GROUP_KEYS:
            raise GroupError(
                f"--set {key}: --seeds gives each seed its seed and algo.threads (its share of "
                "the cores, by --jobs); drop it"
            )


def _start_command(
    job: Job, config_path: Path, overrides: Sequence[str], threads: int
) -> list[str]:
    """``harness run CONFIG --set ... --set seed=k --into RUN``: a seed's first start."""
    cmd = harness_command("run", str(config_path), "--no-progress")
    for override in (*overrides, *(f"{k}={v}" for k, v in zip(GROUP_KEYS, (job.seed, threads)))):
        cmd += ["--set", override]
    return [*cmd, "--into", str(job.run.path)]


def _start(job: Job, env: dict[str, str]) -> subprocess.Popen[bytes]:
    """Start a seed's command, its output appended to ``<run>.log`` beside its folder, in a
    process group of its own (a terminal's Ctrl-C is passed on by the group's command, once)."""
    assert job.cmd is not None
    path = job.log  # asks the rule first: a log linked out of the group is refused as such
    try:
        log = path.open("ab")
        job.log_start = os.fstat(log.fileno()).st_size
    except OSError as exc:
        raise RunDirError(f"{job.run.path.parent}: cannot write a log ({exc.strerror})") from None
    with log:
        return subprocess.Popen(
            job.cmd, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )
