"""Seed groups: one run per training seed, found together.

``harness run CONFIG --seeds 0,1,2 --jobs 2`` makes a group folder ``runs/<name>-<UTC time>/``
holding ``group.json`` (the config, the seeds and each seed's run folder) and one ordinary run
folder per seed, ``<name>-seed<k>-<UTC time>/``, each with its own log ``<name>-seed<k>.log``.
Every run is a separate ``harness run`` process, so a group is no more than the runs it holds:
``harness eval``, ``compare``, ``render`` and ``--resume`` work on each of them as on any run.

``--jobs N`` runs N seeds at a time, each with ``cores // N`` torch threads (and the matching
``OMP_NUM_THREADS``/``MKL_NUM_THREADS``), so the jobs do not fight over the cores.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness.results.rundir import RunDir, RunDirError, atomic_write_text, unique_folder

#: The file that marks a folder as a seed group.
GROUP_FILE = "group.json"
#: The numbers over seeds of ``harness eval GROUP`` (the standard evaluation of every run).
GROUP_EVAL_FILE = "group-eval.json"


class GroupError(ValueError):
    """A seed list or group folder that cannot be used, with a one-line message."""


#: Most runs in a seed group (``--seeds N``): far more than any comparison needs.
MAX_GROUP_RUNS = 1_000


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
    if not seeds:
        raise GroupError(f"--seeds {text!r}: needs at least one seed")
    if len(set(seeds)) != len(seeds):
        raise GroupError(f"--seeds {text!r}: a seed is given twice")
    if any(not 0 <= s <= max_seed for s in seeds):
        raise GroupError(f"--seeds {text!r}: seeds must be in [0, {max_seed}]")
    return seeds


def is_group(folder: Path) -> bool:
    """Whether ``folder`` is a seed group (holds ``group.json``)."""
    return (Path(folder) / GROUP_FILE).is_file()


def group_members(folder: Path) -> list[Path]:
    """Every run folder ``group.json`` names, in seed order, whether it exists or not.

    Members live inside the group folder: ``harness eval`` and ``tune`` of a group load their
    models (pickles) and write into them, so a ``group.json`` naming an absolute path, a ``..``
    path or a link leading out of the group is refused, never followed.

    Raises:
        GroupError: when ``group.json`` cannot be read or names a run outside the group.
    """
    folder = Path(folder)
    try:
        data = json.loads((folder / GROUP_FILE).read_text(encoding="utf-8"))
        names = [entry["run"] for entry in data["runs"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise GroupError(f"{folder / GROUP_FILE}: not a readable group file ({exc})") from None
    return [_member(folder, name) for name in names]


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
    found = [run for run in group_members(folder) if RunDir(run).config.is_file()]
    if not found:
        raise GroupError(f"{folder}: the group has no run folder yet")
    return found


@dataclass
class Job:
    """One seed's training process."""

    seed: int
    run: RunDir
    process: subprocess.Popen[bytes] | None = None
    returncode: int | None = None


def available_cores() -> int:
    """The cores this process may run on: its CPU affinity (``taskset``, Slurm, containers
    restrict it), else the machine's count."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0)) or 1
    return os.cpu_count() or 1


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
) -> tuple[Path, list[Job]]:
    """Train one run per seed, ``jobs`` at a time, in a new group folder.

    Each seed is ``harness run CONFIG --set ... --seed k`` in its own process, writing into its
    own run folder inside the group; its output goes to ``<name>-seed<k>.log`` there. With
    ``report``, a line per running seed (:func:`seed_progress`) every ``every`` seconds when it
    changed, and one when a seed ends.

    Returns:
        The group folder and the jobs with their exit codes.
    """
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
    atomic_write_text(group / GROUP_FILE, json.dumps(data, indent=2) + "\n")
    env = {
        **os.environ,
        "OMP_NUM_THREADS": str(threads),
        "MKL_NUM_THREADS": str(threads),
    }
    running: list[Job] = []
    done: list[Job] = []
    queue = list(pending)
    said: dict[int, str] = {}
    next_report = time.monotonic() + every
    try:
        while queue or running:
            while queue and len(running) < jobs:
                job = queue.pop(0)
                job.process = _start(job, config_path, overrides, threads, env)
                running.append(job)
            time.sleep(0.2)
            for job in list(running):
                assert job.process is not None
                if job.process.poll() is not None:
                    job.returncode = job.process.returncode
                    running.remove(job)
                    done.append(job)
                    if report is not None:
                        state = "done" if job.returncode == 0 else f"failed (exit {job.returncode})"
                        report(f"{seed_progress(job)}: {state}")
            if report is not None and time.monotonic() >= next_report:
                next_report = time.monotonic() + every
                for job in running:
                    line = seed_progress(job)
                    if said.get(job.seed) != line:
                        said[job.seed] = line
                        report(line)
    except KeyboardInterrupt:  # pass Ctrl-C on: each child checkpoints and stops cleanly
        for job in running:
            assert job.process is not None
            job.process.wait()
            job.returncode = job.process.returncode
            done.append(job)
        raise
    return group, sorted(done, key=lambda j: seeds.index(j.seed))


def seed_progress(job: Job) -> str:
    """``seed k: N transitions, validation M %`` from the run's logs so far (the last finished
    episode's transition count and the last in-training validation's median coverage)."""
    parts = [f"seed {job.seed}"]
    steps = _number(_last_value(job.run.episodes_csv, "timesteps"))
    parts.append(f"{int(steps):,} transitions" if steps is not None else "starting")
    coverage = seed_progress_value(job.run)
    if coverage is not None:
        parts.append(f"validation {coverage:.1%}")
    return ", ".join(parts)


def seed_progress_value(run: RunDir) -> float | None:
    """The last in-training validation's median coverage of ``run`` (``None``: none yet)."""
    return _number(_last_value(run.evaluations_csv, "coverage_median"))


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


def _start(
    job: Job, config_path: Path, overrides: Sequence[str], threads: int, env: dict[str, str]
) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", "harness.cli", "run", str(config_path), "--no-progress"]
    for override in (*overrides, f"seed={job.seed}", f"algo.threads={threads}"):
        cmd += ["--set", override]
    cmd += ["--into", str(job.run.path)]
    try:
        log = (job.run.path.parent / f"{job.run.path.name}.log").open("wb")
    except OSError as exc:
        raise RunDirError(f"{job.run.path.parent}: cannot write a log ({exc.strerror})") from None
    with log:
        return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
