"""The task interface: what the harness asks of an env family (BenchMARL's ``TaskClass``,
``benchmarl/environments/common.py``, is the model). A :class:`Task` builds the env and its
episode player, knows its agents and spaces, the metrics an episode reports and their summary,
the headline and selection score (what ``best_model.zip`` is chosen by), the baselines it offers,
its logs' columns and what TensorBoard gets; the commands, the episode loop
(:func:`harness.evaluation.episodes.run_episodes`), compare, tune, sweeps and the training ask
it instead of asking which env it is. :mod:`harness.tasks` holds the registry.

What only a summary is known of (an ``eval.json``, a tune row, a log's header) is answered by
the task's class: its class attributes and class methods read nothing of a config.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import numpy as np

from harness.factory import make_env

#: ``record(key, value)``: where a task's numbers go in TensorBoard (SB3's logger's
#: ``record_mean`` for training episodes, ``record`` for an evaluation).
Record = Callable[[str, float], None]


#: Bootstrap resamples of the interval of the mean coverage, and the generator's seed (fixed:
#: the same episodes give the same interval).
BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED = 2000, 0


def mean_interval(values: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """The ``level`` percentile-bootstrap interval of the mean of ``values`` (over episodes),
    SciPy's ``bootstrap``; a single value is its own interval."""
    if len(values) < 2 or np.ptp(values) == 0:
        return float(values[0]), float(values[0])
    from scipy.stats import bootstrap

    res = bootstrap(
        (values,),
        np.mean,
        n_resamples=BOOTSTRAP_RESAMPLES,
        confidence_level=level,
        method="percentile",
        rng=np.random.default_rng(BOOTSTRAP_SEED),
    )
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def sampling_note(temperature: float | None) -> str:
    """How a test policy picks actions: ``"Boltzmann, temperature T"`` (``""`` when greedy)."""
    return f"Boltzmann, temperature {temperature:g}" if temperature else ""


class EpisodesStopped(Exception):
    """The episode loop gave up on its episodes because ``should_stop()`` said so."""


class TooManyFrames(Exception):
    """An episode's frames would take more memory than the caller allows (``frame_bytes``)."""


class EpisodePlayer(ABC):
    """Copies of a task's env played side by side by the one episode loop
    (:func:`harness.evaluation.episodes.run_episodes`): reset a batch of copies, hand the
    policy the observations of every agent of the copies still playing (copy-major), step them
    with its actions, and give each finished episode's result."""

    @abstractmethod
    def reset(self, seeds: Sequence[int]) -> Any:
        """Reset copy ``i`` with ``seeds[i]`` (``len(seeds)`` copies play); the observations of
        :attr:`playing`'s copies, stacked."""

    @property
    @abstractmethod
    def playing(self) -> list[int]:
        """The copies still in their episode."""

    @abstractmethod
    def views(self) -> Sequence[Any]:
        """What the policy is handed beside the observations, one per playing copy (the
        coverage env's copies, which baselines read the map of; a seeded view otherwise)."""

    @abstractmethod
    def step(self, actions: np.ndarray) -> Any:
        """Step the playing copies with ``actions`` (one per agent, copy-major); the next
        observations of the copies still playing."""

    @property
    @abstractmethod
    def stepped(self) -> list[tuple[int, int, bool]]:
        """``(copy, length, ended)`` of each copy the last :meth:`step` stepped."""

    @abstractmethod
    def render(self, copy: int) -> np.ndarray:
        """Copy ``copy``'s ``rgb_array`` frame."""

    @abstractmethod
    def results(self, frames: list[list[np.ndarray]]) -> list[Any]:
        """The results of the episodes the last :meth:`reset` started (each copy's ``frames``
        handed to it)."""

    def close(self) -> None:  # noqa: B027 (most players have nothing to close)
        """Close the copies."""


class Task(ABC):
    """An env family as the harness trains and evaluates it, for one ``env`` section."""

    name: ClassVar[str]
    """The task's name (a PettingZoo env's summaries say it as ``source``)."""
    metric: ClassVar[str]
    """The headline's words (``"coverage"``, ``"team return"``)."""
    prefix: ClassVar[str]
    """The headline's summary keys: ``{prefix}_median``, ``_mean``, ``_q1``, ``_q3``, ``_iqr``."""
    percent: ClassVar[bool]
    """Whether the headline is a fraction shown in percent (else a plain number)."""
    penalty: ClassVar[str | None] = None
    """A summary key compared beside the headline, lower better (``wall_hits_mean``)."""
    paths: ClassVar[bool] = False
    """Whether its episodes record the agents' paths on a grid map (``harness render``'s path
    picture; else the env's own frames)."""
    compare_keys: ClassVar[tuple[str, ...]]
    """The numbers ``harness compare`` reads of an evaluation (each checked to be finite)."""
    tune_keys: ClassVar[tuple[str, ...]]
    """The numbers a ``harness tune`` row keeps."""
    group_keys: ClassVar[tuple[str, ...]]
    """The numbers ``group-eval.json`` keeps of each seed's run."""
    episode_columns: ClassVar[tuple[str, ...]]
    """``episodes.csv``'s columns (the training episodes)."""
    evaluation_columns: ClassVar[tuple[str, ...]]
    """``evaluations.csv``'s columns (the in-training evaluations)."""
    episode_metric: ClassVar[str]
    """An episode's headline number: the ``episodes.csv`` column compare draws, and the
    per-episode list of an evaluation that ``harness eval --against`` compares."""
    monitor_keys: ClassVar[tuple[str, ...]] = ()
    """The info keys SB3's ``VecMonitor`` keeps at an episode's end."""
    batched_core: ClassVar[bool] = False
    """Whether its env has the batched core (``vec.backend: core``); else SuperSuit steps it."""
    leaving_agents: ClassVar[bool] = False
    """Whether agents may leave mid-episode and episodes end on the env's own time limit
    (SuperSuit's VecEnv then gets the harness's wrappers: ``harness.training.adapters``)."""
    render_every: ClassVar[int | None] = None
    """``harness render``'s frame interval when none is given (``None``: the task's own rule)."""

    def __init__(self, env: Any) -> None:
        self.env = env

    @classmethod
    @abstractmethod
    def takes(cls, env: Any) -> bool:
        """Whether ``env`` (an ``env`` section) is this task's."""

    @classmethod
    def owns_summary(cls, summary: dict[str, Any]) -> bool:
        """Whether ``summary`` (an evaluation's, a tune row) is this task's."""
        return summary.get("source") == cls.name

    # ---------------------------------------------------------------- the env
    @property
    def n_agents(self) -> int:
        """Agents of the team."""
        return int(self.env.n_agents)

    @property
    def agents(self) -> tuple[str, ...]:
        """The agents' names, in the order of the policy's batch."""
        return tuple(f"agent_{k}" for k in range(self.n_agents))

    def make_env(self, render_mode: str | None = None) -> Any:
        """One PettingZoo ``ParallelEnv`` of the task (:func:`harness.factory.make_env`)."""
        return make_env(self.env, render_mode)

    @abstractmethod
    def start(self, config: Any) -> tuple[Any, Any]:
        """What a run does before its folder is made: build the env once (a user's constructor
        runs here, not while a config is validated) and check that ``config`` can train on it;
        returns one VecEnv slot's observation and action spaces, as the model sees them.

        Raises:
            ConfigError: one line naming the key.
        """

    @abstractmethod
    def player(self, copies: int, render_mode: str | None, record_paths: bool) -> EpisodePlayer:
        """The copies the episode loop plays (at most ``copies`` side by side)."""

    def check_baseline(  # noqa: B027 (most tasks take every baseline)
        self, name: str, plays_any_env: bool, offered: Sequence[str]
    ) -> None:
        """``ValueError`` (one line) unless the baseline ``name`` plays this task
        (``plays_any_env``: it reads nothing of the coverage env; ``offered``: those that
        do)."""

    def check_renders(self) -> None:  # noqa: B027 (the coverage env renders)
        """``ValueError`` (one line) unless the env renders ``rgb_array`` frames."""

    # ---------------------------------------------------------------- metrics
    @classmethod
    @abstractmethod
    def summarize(cls, results: list[Any]) -> dict[str, Any]:
        """An evaluation's numbers over its episodes' results."""

    @classmethod
    def headline(cls, summary: dict[str, Any], stat: str = "median") -> float:
        """The summary's headline ``stat`` (``median``, ``mean``, ``q1``, ``q3``, ``iqr``)."""
        return float(summary[f"{cls.prefix}_{stat}"])

    @classmethod
    @abstractmethod
    def selection_score(cls, summary: dict[str, Any]) -> float:
        """The one number a policy is picked by (``best_model.zip``, ``harness tune``);
        higher is better."""

    @classmethod
    @abstractmethod
    def per_episode(cls, results: list[Any]) -> dict[str, list[Any]]:
        """The per-episode numbers an evaluation file keeps."""

    @classmethod
    def objective(cls, select: str | None = None) -> str:
        """What a sweep's trial value is (``select``: the group it maximises, :attr:`select`)."""
        return f"median {cls.selection_metric(select)} of the config's validation episodes"

    @classmethod
    def objective_value(cls, summary: dict[str, Any]) -> float:
        """A sweep's trial value (:meth:`objective`): the headline's median."""
        return cls.headline(summary)

    @classmethod
    def selection_metric(cls, select: str | None = None) -> str:
        """What the choices on validation episodes maximise, in words (tune's table, a sweep's
        objective): the headline's metric (``select``: a task's group, :attr:`select`)."""
        return cls.metric

    @property
    def select(self) -> str | None:
        """The group of agents whose return the choices on validation episodes maximise
        (``None``: the task's own rule, :meth:`selection_score`)."""
        return None

    @classmethod
    def format_value(cls, value: float) -> str:
        """A headline number as a line shows it."""
        return f"{value:.1%}" if cls.percent else f"{value:.4g}"

    @classmethod
    @abstractmethod
    def format_summary(cls, summary: dict[str, Any]) -> str:
        """A readable table of an evaluation's summary."""

    @classmethod
    @abstractmethod
    def format_tune(cls, result: dict[str, Any]) -> list[str]:
        """The table lines of ``harness tune``'s rows, the chosen one marked."""

    @classmethod
    @abstractmethod
    def compare_header(cls) -> str:
        """The headline columns' header of ``harness compare``'s table."""

    @classmethod
    @abstractmethod
    def compare_row(cls, summary: dict[str, Any]) -> str:
        """The headline columns of one evaluation in ``harness compare``'s table."""

    # ---------------------------------------------------------------- training's logs
    @abstractmethod
    def training_episode(self, infos: list[dict[str, Any]], record: Record) -> dict[str, Any]:
        """An ``episodes.csv`` row's own columns for a finished training episode, from its
        agents' last infos (``VecMonitor``'s ``episode`` among them); its numbers recorded
        (TensorBoard's ``rollout/``)."""

    @classmethod
    @abstractmethod
    def record_evaluation(cls, summary: dict[str, Any], record: Record) -> None:
        """An in-training evaluation's numbers for TensorBoard (``eval/``)."""
