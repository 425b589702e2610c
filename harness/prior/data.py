"""Partial maps: the team's map at steps of episodes a written planner plays, with the truth.

A partial map is coded cell by cell as :data:`SEEN_FREE`, :data:`SEEN_WALL` or :data:`UNSEEN`
(what the team has seen: :attr:`envs.coverage.CoverageEnv.known`); its target is the true map.
The episodes are played by the harness's one episode loop
(:func:`harness.evaluation.episodes.run_episodes`) with a planner baseline wrapped in
:class:`_Recorder`, which keeps ``snapshots`` team maps of each episode at steps drawn uniformly
from the episode (a team map with nothing unseen left is skipped: it has no target).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from harness.config.schema import EnvConfig
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import BatchPolicy, run_episodes
from harness.prior.coding import SEEN_FREE, SEEN_WALL, UNSEEN, code_team_map

#: The codes are :mod:`harness.prior.coding`'s, re-exported here beside the recorder.
__all__ = ["SEEN_FREE", "SEEN_WALL", "UNSEEN", "PartialMaps", "code_team_map", "record"]


@dataclass
class PartialMaps:
    """Partial maps of one size with their true maps.

    Attributes:
        states: ``uint8 (N, H, W)`` codes (:data:`SEEN_FREE`, :data:`SEEN_WALL`,
            :data:`UNSEEN`).
        walls: ``bool (N, H, W)``: the true maps.
        episodes: ``int (N,)``: the episode (offset from the seed) each was taken in.
    """

    states: np.ndarray
    walls: np.ndarray
    episodes: np.ndarray

    def __len__(self) -> int:
        return int(self.states.shape[0])

    @property
    def unseen(self) -> np.ndarray:
        """``bool (N, H, W)``: the cells to predict."""
        return self.states == UNSEEN


class _Recorder:
    """A batched policy that plays ``inner`` and keeps each copy's team map at ``snapshots``
    steps of its episode, drawn from ``rng`` when the episode starts (copies in order, so the
    same seed keeps the same maps whatever the copies side by side)."""

    def __init__(self, inner: BatchPolicy, snapshots: int, rng: np.random.Generator) -> None:
        self.inner, self.snapshots, self.rng = inner, snapshots, rng
        self._when: dict[int, tuple[int, set[int]]] = {}  # id(env) -> (episode, steps)
        self._episodes = 0
        self.kept: dict[tuple[int, int], list[tuple[np.ndarray, np.ndarray, int]]] = {}

    def __call__(self, obs: Any, envs: Sequence[Any]) -> np.ndarray:
        for env in envs:
            if env.steps == 0:  # a new episode on this copy
                steps = self.rng.choice(env.max_steps, size=self.snapshots, replace=False)
                self._when[id(env)] = (self._episodes, set(steps.tolist()))
                self._episodes += 1
            episode, steps = self._when[id(env)]
            if env.steps in steps:
                seen = env.known
                if not seen.all():
                    walls = np.array(env.walls, dtype=bool)
                    self.kept.setdefault(walls.shape, []).append(
                        (code_team_map(seen, walls), walls, episode)
                    )
        return self.inner(obs, envs)

    def maps(self) -> list[PartialMaps]:
        """What was kept, one :class:`PartialMaps` per map size."""
        return [
            PartialMaps(
                np.stack([s for s, _, _ in rows]),
                np.stack([w for _, w, _ in rows]),
                np.array([e for _, _, e in rows], dtype=np.int64),
            )
            for rows in self.kept.values()
        ]


def record(
    env: EnvConfig, planner: str, episodes: int, seed: int, snapshots: int, copies: int = 8
) -> list[PartialMaps]:
    """Partial maps of ``episodes`` episodes (seeds ``seed``, ``seed + 1``, ...) played by the
    planner baseline ``planner`` (a ``--policy`` name, e.g. ``frontier_pocket``), ``snapshots``
    an episode: one :class:`PartialMaps` per map size."""
    recorder = _Recorder(make_baseline(planner, seed), snapshots, np.random.default_rng(seed))
    run_episodes(recorder, env, episodes, seed, copies=copies)
    return recorder.maps()
