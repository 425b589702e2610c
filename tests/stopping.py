"""Helpers of the tests of a training run's stops and checkpoints (``test_train.py``,
``test_checkpoints.py``): tiny runs of ``configs/smoke.yaml``, signals sent from inside a run,
and readers of what a run wrote."""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from harness.cli import main
from harness.sb3.dqn import DoubleDQN
from harness.training import train as train_module
from harness.training.checkpoints import TrainingState
from tests.test_resume import TINY as RESUME_TINY

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
# A tiny run on one thread (a tiny net's second thread only waits): checkpoints at 400 and 800,
# evaluations at 600 and 1200.
TINY = [*RESUME_TINY, "algo.threads=1"]
#: An epochs table whose training call never ends on its own (10^8 gradient steps).
ENDLESS_EPOCHS = "phases.initial.epochs=[[0.0, 100000000]]"


def sets(*overrides: str) -> list[str]:
    """``--set`` options: :data:`TINY`, with ``overrides`` in place of those of the same keys."""
    merged = {o.partition("=")[0]: o for o in [*TINY, *overrides]}
    return [a for o in merged.values() for a in ("--set", o)]


def run_args(runs: Path, *overrides: str) -> list[str]:
    return ["run", str(SMOKE), "--runs-dir", str(runs), "--no-progress", *sets(*overrides)]


def resume(run: Path) -> int:
    return main(["run", "--resume", str(run), "--no-progress"])


def episodes(run: Path) -> list[dict[str, str]]:
    with (run / "episodes.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def logged_steps(run: Path) -> list[int]:
    """The ``timesteps`` of ``episodes.csv`` so far (read while the run writes it)."""
    path = run / "episodes.csv"
    lines = path.read_text().splitlines()[1:] if path.is_file() else []
    cells = [line.split(",") for line in lines]
    return [int(c[2]) for c in cells if len(c) > 2 and c[2].isdigit()]


def contiguous(run: Path) -> bool:
    numbers = [int(row["episode"]) for row in episodes(run)]
    return numbers == list(range(len(numbers)))


def evaluation_steps(run: Path) -> list[int]:
    path = run / "evaluations.csv"
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return [int(row["timesteps"]) for row in csv.DictReader(f)]


def state_of(checkpoint: Path) -> TrainingState:
    return TrainingState.from_json((checkpoint / "state.json").read_text())


def snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


def harness_lines(err: str) -> list[str]:
    """The harness's own lines of ``err`` but its warnings (a shortened phase's schedules)."""
    return [
        line
        for line in err.splitlines()
        if line.startswith("harness:") and not line.startswith("harness: warning:")
    ]


def signal_on_call(n: int, signum: int = signal.SIGTERM) -> Callable[[], None]:
    """A function that sends ``signum`` to this process on its ``n``-th call."""
    calls = [0]

    def tick() -> None:
        calls[0] += 1
        if calls[0] == n:
            os.kill(os.getpid(), signum)

    return tick


def signal_during_evaluation(mp: pytest.MonkeyPatch, n: int = 10) -> None:
    """The in-training evaluation's policy sends SIGTERM at its ``n``-th step."""
    original = train_module.model_policy
    tick = signal_on_call(n)

    def model_policy(model: Any, *args: Any, **kwargs: Any) -> Any:
        policy = original(model, *args, **kwargs)

        def signalling(obs: Any, envs: Any) -> Any:
            tick()
            return policy(obs, envs)

        return signalling

    mp.setattr(train_module, "model_policy", model_policy)


def signal_during_training(mp: pytest.MonkeyPatch, n: int = 5) -> None:
    """The ``n``-th gradient step sends SIGTERM (before its optimizer step)."""
    original = DoubleDQN._gradient_step
    tick = signal_on_call(n)

    def gradient_step(model: DoubleDQN, replay_data: Any, *args: Any) -> Any:
        tick()
        return original(model, replay_data, *args)

    mp.setattr(DoubleDQN, "_gradient_step", gradient_step)


def stop_in_evaluation(runs: Path) -> tuple[Path, str]:
    """A tiny run in ``runs`` stopped by SIGTERM in the middle of its evaluation at step 600
    (checkpoints at 400 and 600), and what it printed."""
    err = io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stderr(err):
        signal_during_evaluation(mp)
        code = main(run_args(runs))
    assert code == 128 + signal.SIGTERM, err.getvalue()
    (run,) = runs.iterdir()
    return run, err.getvalue()
