"""SB3 callbacks of a training phase: epochs by coverage, episode metrics, periodic evaluation
and checkpoints. Each is small and does one thing. (The ε, β and learning-rate schedules are not
callbacks: ``harness.training.train.apply_phase`` installs them on the model.)"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from harness.results.rundir import EPISODE_COLUMNS, append_csv_rows
from harness.sb3.schedules import epochs_for


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

    An episode is one env copy's run of ``max_steps``; its row holds the team's coverage, the mean
    of the agents' returns, the team's wall hits and the new cells of each agent (``a;b;c``).

    Args:
        csv_path: The run's ``episodes.csv`` (appended to; the header is written when new).
        n_agents: Agents per copy.
        phase: Phase name written in each row.
        first_episode: Number of the next episode (continues across phases and resumes).
    """

    def __init__(self, csv_path: Path, n_agents: int, phase: str, first_episode: int = 0) -> None:
        super().__init__()
        self.csv_path = Path(csv_path)
        self.n_agents = n_agents
        self.phase = phase
        self.next_episode = first_episode

    def _on_training_start(self) -> None:
        append_csv_rows(self.csv_path, EPISODE_COLUMNS, [])  # the header, when the file is new

    def _on_step(self) -> bool:
        dones = self.locals["dones"]
        if not dones.any():
            return True
        infos = self.locals["infos"]
        n = self.n_agents
        rows = []
        for copy in range(len(dones) // n):
            slots = range(copy * n, copy * n + n)
            if not all(dones[k] and "episode" in infos[k] for k in slots):
                continue
            eps = [infos[k]["episode"] for k in slots]
            row = {
                "episode": self.next_episode,
                "phase": self.phase,
                "timesteps": self.num_timesteps,
                "copy": copy,
                "coverage": float(eps[0]["coverage"]),
                "reward_mean": float(np.mean([e["r"] for e in eps])),
                "wall_hits": int(sum(e["wall_hits"] for e in eps)),
                "new_cells": ";".join(str(int(e["new_cells"])) for e in eps),
                "length": int(eps[0]["l"]),
            }
            rows.append([row[c] for c in EPISODE_COLUMNS])
            self.next_episode += 1
            self.logger.record_mean("rollout/coverage", row["coverage"])
            self.logger.record_mean("rollout/wall_hits", row["wall_hits"])
            self.logger.record_mean("rollout/team_reward_mean", row["reward_mean"])
        if rows:
            append_csv_rows(self.csv_path, EPISODE_COLUMNS, rows)
        return True


class PeriodicCallback(BaseCallback):
    """Call ``fn(model)`` every ``every`` transitions (0: never). Transitions arrive in blocks of
    ``n_envs``, so it fires on the first step at or past each multiple (and, with ``when``, on the
    first such step where ``when(model)`` holds)."""

    def __init__(
        self,
        every: int,
        fn: Callable[[Any], None],
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
            self.fn(self.model)
        return True
