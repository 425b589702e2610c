"""Shared fixtures and helpers: small hand-built grids and envs made for them, the check of a
one-line error, the overrides of a tiny goal-action run, and the processes a test starts
(:func:`spawn`), ended with the test whatever its outcome."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from envs import coverage_v0


def pytest_configure(config: pytest.Config) -> None:
    # A suite started in the background by a non-interactive shell (``pytest &``, nohup, some CI
    # runners) inherits SIGINT ignored, and the harness rightly keeps an ignored SIGINT (as
    # Python does). The Ctrl-C tests are about a user's terminal: give the suite, and the
    # commands it starts, the terminal's disposition wherever it runs.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


#: The processes the running test started (:func:`spawn`), and whether each leads a process
#: group of its own; each ends with the test.
_SPAWNED: list[tuple[subprocess.Popen, bool]] = []


def spawn(cmd: Sequence[str], **kwargs: Any) -> subprocess.Popen:
    """``subprocess.Popen(cmd, **kwargs)`` in a process group of its own (a new session, unless
    ``start_new_session`` says otherwise), killed whole when the test ends, however it ends
    (:func:`_end_spawned`): the processes it started (env workers, seed runs, sweep workers) go
    with it. A test that fails or times out is one failed test, not a hung suite with processes
    left behind."""
    kwargs.setdefault("start_new_session", True)
    proc = subprocess.Popen(cmd, **kwargs)
    _SPAWNED.append((proc, bool(kwargs["start_new_session"])))
    return proc


def group_left(proc: subprocess.Popen, seconds: float = 10.0) -> bool:
    """Whether a process of ``proc``'s group (its own session: :func:`spawn`) still exists after
    at most ``seconds`` (an ended process that nobody reaped yet counts until it is reaped)."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            return False
        if time.monotonic() > deadline:
            return True
        time.sleep(0.1)


def end_group(proc: subprocess.Popen, own_group: bool = True) -> None:
    """Kill ``proc`` and, with ``own_group`` (it leads a process group: :func:`spawn`), every
    process left in that group, also once ``proc`` itself has ended; reap it, close its pipes.
    (A group's id is not given to a new process while a member of the group lives.)"""
    if own_group:
        with contextlib.suppress(ProcessLookupError):  # nothing left in it
            os.killpg(proc.pid, signal.SIGKILL)
    if proc.poll() is None:
        proc.kill()
    proc.wait()
    for pipe in (proc.stdin, proc.stdout, proc.stderr):
        if pipe is not None:
            pipe.close()


@pytest.fixture(autouse=True)
def _end_spawned() -> Iterator[None]:
    """End what the test started with :func:`spawn`, after it, passed, failed or timed out."""
    yield
    while _SPAWNED:
        end_group(*_SPAWNED.pop())


def root_first_env(**extra: str) -> dict[str, str]:
    """This process's environment for a child that imports this checkout: the repository first
    on ``PYTHONPATH``, what was there kept (where the packages come from a ``PYTHONPATH``)."""
    import os

    root = str(Path(__file__).resolve().parents[1])
    path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path, **extra}


def grid_from(text: str) -> np.ndarray:
    """Grid from the text map format (``#`` wall, ``.`` free), ignoring surrounding whitespace."""
    rows = [line.strip() for line in text.strip().splitlines()]
    return np.array([[ch == "#" for ch in row] for row in rows], dtype=bool)


@pytest.fixture
def make_env():
    """Factory: an env reset on the given text grid with fixed start cells."""

    def _make(text: str, starts: list[tuple[int, int]], **kwargs):
        grid = grid_from(text)
        env = coverage_v0.parallel_env(
            height=grid.shape[0], width=grid.shape[1], n_agents=len(starts), **kwargs
        )
        obs, infos = env.reset(seed=0, options={"grid": grid, "starts": starts})
        return env, obs

    return _make


def one_error_line(err: str) -> str:
    """The only line of ``err``, checked to be a harness error."""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("harness: error: ") and "Traceback" not in err
    return lines[0]


def refused_run(config: Path, overrides: list[str], runs: Path, capsys) -> str:
    """The one error line of ``harness run config --set ...`` into ``runs``, checked to exit
    with 2 and to leave no run folder behind."""
    from harness.cli import main

    args = ["run", str(config), "--runs-dir", str(runs)]
    for override in overrides:
        args += ["--set", override]
    assert main(args) == 2
    line = one_error_line(capsys.readouterr().err)
    assert list(runs.iterdir()) == []
    return line


#: ``--set`` overrides that make a goal-action config (``configs/goals_*.yaml``) a run of a few
#: seconds: 12x12 random maps of 40 steps, 4 slots, a 16-wide network, 600 transitions.
TINY_GOAL_RUN = {
    "env.map": "random",
    "env.height": "12",
    "env.width": "12",
    "env.max_steps": "40",
    "env.test_maps": "[]",
    "env.observation": "{teammap: {crop: 7, global_size: 6}}",
    "env.frontier.action.goal.k": "4",
    "vec.copies": "2",
    "algo.buffer_size": "2000",
    "algo.learning_starts": "200",
    "algo.features_dim": "16",
    "algo.net_arch": "[16]",
    "phases.0.timesteps": "600",
    "phases.0.exploration.steps": "400",
    "eval.every": "600",
    "eval.episodes": "2",
    "checkpoint.every": "600",
}


def tiny_goal_run(config: Path, runs: Path, **changes: str) -> list[str]:
    """``harness run`` arguments of ``config`` with :data:`TINY_GOAL_RUN` (updated by
    ``changes``, keys with ``__`` for ``.``) into ``runs``, without a progress bar."""
    args = ["run", str(config), "--runs-dir", str(runs), "--no-progress"]
    overrides = {**TINY_GOAL_RUN, **{k.replace("__", "."): v for k, v in changes.items()}}
    for key, value in overrides.items():
        args += ["--set", f"{key}={value}"]
    return args


# ---------------------------------------------------------------- a run stopped in an evaluation
@pytest.fixture(scope="session")
def stopped_in_evaluation(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A tiny run stopped by SIGTERM in the middle of its evaluation at step 600 (checkpoints
    at 400 and 600), and what it printed (``tests/stopping.py``); made once, read only."""
    from tests.stopping import stop_in_evaluation

    return stop_in_evaluation(tmp_path_factory.mktemp("stopped"))


@pytest.fixture
def run_copy(stopped_in_evaluation: tuple[Path, str], tmp_path: Path) -> Path:
    """A copy of the stopped run to resume or damage."""
    import shutil

    run, _ = stopped_in_evaluation
    copy = tmp_path / run.name
    shutil.copytree(run, copy)
    return copy


# ------------------------------------------------------------------ a Ctrl-C from inside training
@contextlib.contextmanager
def interrupted_past(steps: int) -> Iterator[list[int]]:
    """Training under it gets one SIGINT (Ctrl-C) to this process, sent at the end of its first
    gradient update past ``steps`` transitions; yields the list that then holds that step."""
    from harness.sb3.dqn import DoubleDQN

    original, fired = DoubleDQN.train, []

    def train_then_interrupt(model: Any, gradient_steps: int, batch_size: int = 100) -> None:
        original(model, gradient_steps, batch_size)
        if model.num_timesteps >= steps and not fired:
            fired.append(model.num_timesteps)
            os.kill(os.getpid(), signal.SIGINT)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(DoubleDQN, "train", train_then_interrupt)
        yield fired
