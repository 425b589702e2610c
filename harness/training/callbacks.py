"""SB3 callbacks of a training phase: epochs by coverage, episode metrics, periodic work (the
evaluation and the checkpoints of ``harness.training.train`` are two) and the progress bar. Each
is small and does one thing. (The ε, β and learning-rate schedules are not callbacks:
``harness.training.train.apply_phase`` installs them on the model.)"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, ProgressBarCallback
from tqdm import TqdmExperimentalWarning
from tqdm.rich import tqdm

from harness.results.rundir import append_csv_rows
from harness.sb3.decisions import EXPERT_KEY
from harness.sb3.schedules import epochs_for
from harness.tasks.base import Task


def recent_coverages(ep_info_buffer: Any, episodes: int, n_agents: int) -> list[float]:
    """Team coverage of the last ``episodes`` finished episodes from SB3's ``ep_info_buffer``.

    VecMonitor adds one entry per slot, and all agents of a copy finish together with the same
    team coverage, so ``n_agents`` consecutive entries are one episode.
    """
    entries = list(ep_info_buffer)[-episodes * n_agents :]
    return [float(e["coverage"]) for e in entries[::n_agents] if "coverage" in e]


class EpochsByCoverageCallback(BaseCallback):
    """Set the gradient steps per training call ("epochs", Table 4.1) from recent coverage.

    Before each training call, the median team coverage of the last ``window`` finished episodes
    picks a row of ``table``; the model's ``gradient_steps`` is set to that row's epochs.
    """

    def __init__(self, table: list[tuple[float, int]], window: int, n_agents: int) -> None:
        super().__init__()
        self.table = [(float(t), int(e)) for t, e in table]
        self.window = window
        self.n_agents = n_agents

    def _update(self) -> None:
        cov = recent_coverages(self.model.ep_info_buffer, self.window, self.n_agents)
        median = float(np.median(cov)) if cov else None
        self.model.gradient_steps = epochs_for(median, self.table)
        self.logger.record("train/epochs", self.model.gradient_steps)
        if median is not None:
            self.logger.record("rollout/coverage_median", median)

    def _on_training_start(self) -> None:
        self._update()

    def _on_rollout_end(self) -> None:
        self._update()

    def _on_step(self) -> bool:
        return True


class EpisodeLogCallback(BaseCallback):
    """Write one ``episodes.csv`` row per finished episode and log rollout metrics.

    An episode is one env copy's run until its agents are all done; its row holds the episode's
    number, phase, transitions and copy, and the task's own columns
    (:meth:`harness.tasks.base.Task.training_episode`: the coverage env's team coverage, mean
    return, wall hits and new cells per agent; a PettingZoo env's team and agent returns, length
    and last infos), whose numbers go to TensorBoard (``rollout/``).

    Args:
        csv_path: The run's ``episodes.csv`` (appended to; the header is written when new).
        task: The run's task (its columns and rows).
        phase: Phase name written in each row.
        first_episode: Number of the next episode (continues across phases and resumes).
    """

    def __init__(self, csv_path: Path, task: Task, phase: str, first_episode: int = 0) -> None:
        super().__init__()
        self.csv_path = Path(csv_path)
        self.task = task
        self.columns = task.episode_columns
        self.n_agents = task.n_agents
        self.phase = phase
        self.next_episode = first_episode

    def _on_training_start(self) -> None:
        append_csv_rows(self.csv_path, self.columns, [])  # the header, when the file is new

    def _on_step(self) -> bool:
        infos = self.locals["infos"]
        labels = [info[EXPERT_KEY] for info in infos if EXPERT_KEY in info]
        if labels:  # a teacher labelled decisions of this step (algo.teacher)
            self.logger.record_mean("teacher/labels", len(labels))
            self.logger.record_mean("teacher/deviations", sum(label > 0 for label in labels))
        dones = self.locals["dones"]
        if not dones.any():
            return True
        n = self.n_agents
        rows = []
        for copy in range(len(dones) // n):
            slots = range(copy * n, copy * n + n)
            if not all(dones[k] and "episode" in infos[k] for k in slots):
                continue
            row = {
                "episode": self.next_episode,
                "phase": self.phase,
                "timesteps": self.num_timesteps,
                "copy": copy,
                **self._episode(copy, [infos[k] for k in slots]),
            }
            rows.append([row[c] for c in self.columns])
            self.next_episode += 1
        if rows:
            append_csv_rows(self.csv_path, self.columns, rows)
        return True

    def _episode(self, copy: int, infos: list[dict[str, Any]]) -> dict[str, Any]:
        """The row's own columns for an episode that ended, from its agents' last infos (SB3's
        ``VecMonitor`` put each one's ``episode`` there): the task's."""
        return self.task.training_episode(infos, self.logger.record_mean)


class PeriodicCallback(BaseCallback):
    """Call ``fn(model)`` every ``every`` transitions (0: never). Transitions arrive in blocks of
    ``n_envs``, so it fires on the first step at or past each multiple (and, with ``when``, on the
    first such step where ``when(model)`` holds).

    A subclass does its own work instead of ``fn`` by overriding :meth:`_on_period` (the
    evaluation and the checkpoints of ``harness.training.train``).
    """

    def __init__(
        self,
        every: int,
        fn: Callable[[Any], None] | None = None,
        when: Callable[[Any], bool] | None = None,
    ) -> None:
        super().__init__()
        self.every = every
        self.fn = fn
        self.when = when
        self._next: float = math.inf

    def _on_training_start(self) -> None:
        if self.every > 0:
            self._next = (self.num_timesteps // self.every + 1) * self.every

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next and (self.when is None or self.when(self.model)):
            self._next = (self.num_timesteps // self.every + 1) * self.every
            self._on_period()
        return True

    def _on_period(self) -> None:
        """What is done every ``every`` transitions: ``fn(model)``."""
        if self.fn is not None:
            self.fn(self.model)


class PhaseProgressBar(ProgressBarCallback):
    """SB3's progress bar for one phase: named after the phase, counting the phase's own
    transitions up to its length (SB3 collects whole rounds of ``n_envs`` and may pass it; the
    bar stops at the total), with the latest median coverage, ε and loss beside the name.

    Args:
        phase: The phase's name (the bar's description).
        total: Transitions of the phase still to run.
        n_agents: Agents per env copy (the coverage's episodes are ``n_agents`` entries each).
        every: Env steps between postfix updates (each reads the logger and the episodes).
    """

    def __init__(self, phase: str, total: int, n_agents: int, every: int = 50) -> None:
        super().__init__()
        self.phase, self.total, self.n_agents, self.every = phase, int(total), n_agents, every
        self._calls = 0

    def _on_training_start(self) -> None:
        with warnings.catch_warnings():  # "rich is experimental": SB3's own bar is the same
            warnings.simplefilter("ignore", TqdmExperimentalWarning)
            self.pbar = tqdm(total=self.total, desc=self.phase)

    def _on_step(self) -> bool:
        self.pbar.update(min(self.training_env.num_envs, self.total - self.pbar.n))
        self._calls += 1
        if self._calls % self.every == 0:
            # In the description: tqdm.rich's columns show no postfix.
            figures = " ".join(f"{k} {v}" for k, v in self.postfix().items())
            self.pbar.set_description(f"{self.phase}: {figures}", refresh=False)
        return True

    def postfix(self) -> dict[str, str]:
        """The latest figures: ``cov``, the median coverage of the last 20 episodes; ``ε``;
        ``loss``, the training loss."""
        out = {}
        coverages = recent_coverages(self.model.ep_info_buffer or [], 20, self.n_agents)
        if coverages:
            out["cov"] = f"{np.median(coverages):.0%}"
        out["ε"] = f"{self.model.exploration_rate:.2f}"
        loss = self.model.logger.name_to_value.get("train/loss")
        if loss is not None:
            out["loss"] = f"{loss:.3g}"
        return out
