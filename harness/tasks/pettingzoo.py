"""The task of any PettingZoo env (``env: {pettingzoo: {make, kwargs}}``,
:class:`PettingZooTask`): the user's constructor behind the contract's guard
(:mod:`harness.config.pettingzoo`), its episodes played one copy at a time, and their metrics: the
team's return (the sum of its agents' returns) and each agent's, the episode's length, and the
numeric per-agent infos the env reports at an episode's last step (``coverage`` among them, if it
reports one).

Episode ``k`` of an evaluation with seed ``s`` is the env reset with seed ``s + k`` (as for the
coverage env), whatever the number of copies stepped side by side; a copy's agents go through
the batched policy together with every other copy's, copy-major.
"""

from __future__ import annotations

import json
import math
import numbers
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from harness.config.pettingzoo import blank_observation, stack_observations
from harness.config.schema import ConfigError, PettingZooEnvConfig
from harness.factory import make_env
from harness.tasks.base import (
    EpisodePlayer,
    Record,
    Task,
    mean_interval,
    sampling_note,
)

#: Seconds between two lines saying where a long episode is (an evaluation's episodes of an env
#: that ends them late, or never: the env's guard stops it at ``env.pettingzoo.step_limit``).
LONG_EPISODE_EVERY_S = 30.0
#: The info key of an episode cut by a time limit (SB3's: the replay buffer then bootstraps).
TIME_LIMIT_KEY = "TimeLimit.truncated"
#: Info keys that the harness's VecEnvs add (not the env's own infos): the time limit's flag.
VEC_INFO_KEYS = (TIME_LIMIT_KEY,)


@dataclass
class TeamEpisodeResult:
    """Metrics of one finished episode of a PettingZoo env."""

    task: ClassVar[type[Task]]
    """The task whose episode it is (:func:`harness.tasks.summarize` asks it)."""

    agents: tuple[str, ...]
    """The env's ``possible_agents``."""
    returns: list[float]
    """Per agent (``agents`` order): the sum of its rewards."""
    length: int
    """Steps of the episode."""
    infos: dict[str, list[float]] = field(default_factory=dict)
    """Numeric infos at the episode's last step (an agent that left: at its own last step), per
    key, per agent (``nan`` where an agent did not report it)."""
    frames: list[np.ndarray] = field(default_factory=list)
    """``rgb_array`` frames at step 0, every ``frames_every`` steps and the last step."""
    groups: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """The agents' groups (:func:`harness.config.pettingzoo.agent_groups`; empty: one)."""
    select: str | None = None
    """The group whose return choices maximise (``env.pettingzoo.select``; ``None``: the team)."""

    @property
    def team_return(self) -> float:
        """The team's return: the sum of its agents' returns."""
        return float(sum(self.returns))

    def group_return(self, group: str) -> float:
        """A group's return: the sum of its agents' returns."""
        members = self.groups[group]
        return float(sum(r for a, r in zip(self.agents, self.returns, strict=True) if a in members))


@dataclass
class EpisodeView:
    """One env copy as a batched policy sees it: ``np_random``, seeded by the episode's seed (a
    Boltzmann policy draws its noise from it), and the number of actions (the random
    baseline's)."""

    np_random: np.random.Generator
    n_actions: int


def numeric_infos(info: Any) -> dict[str, float]:
    """The numeric scalars (numbers and booleans, numpy's included) of one agent's info dict."""
    if not isinstance(info, dict):
        return {}
    out = {}
    for key, value in info.items():
        if isinstance(value, np.ndarray) and value.shape == ():
            value = value.item()
        if isinstance(value, (numbers.Real, np.bool_)):
            out[str(key)] = float(value)
    return out


def summarize(results: list[TeamEpisodeResult]) -> dict[str, Any]:
    """The numbers of a list of episodes: the team's return (median, mean with its bootstrap
    interval, quartiles, range), the mean length, each agent's mean return and the means of its
    numeric infos, and each info key's mean over episodes of the team's mean. ``coverage_mean``
    and ``coverage_median`` (the team's mean ``coverage`` info) only where the env reports a
    ``coverage`` info; ``select``, the group the choices maximise
    (:meth:`PettingZooTask.selection_score`), only where the config names one."""
    agents = results[0].agents
    team = np.array([r.team_return for r in results])
    q1, q3 = np.percentile(team, [25, 75])
    low, high = mean_interval(team)
    keys = sorted({key for r in results for key in r.infos})

    def info_values(key: str, k: int | None = None) -> np.ndarray:
        # Per episode: agent k's value, or the team's mean (nan where none reported it).
        out = []
        for r in results:
            values = np.array(r.infos.get(key, [np.nan] * len(agents)), dtype=float)
            chosen = values[k] if k is not None else values
            out.append(np.nan if np.all(np.isnan(chosen)) else float(np.nanmean(chosen)))
        return np.array(out)

    per_agent = []
    for k, agent in enumerate(agents):
        row: dict[str, Any] = {
            "agent": agent,
            "return_mean": float(np.mean([r.returns[k] for r in results])),
        }
        for key in keys:
            row[f"{key}_mean"] = _nanmean(info_values(key, k))
        per_agent.append(row)
    summary: dict[str, Any] = {
        "source": PettingZooTask.name,
        "episodes": len(results),
        "return_median": float(np.median(team)),
        "return_mean": float(team.mean()),
        "return_mean_ci": [low, high],
        "return_iqr": float(q3 - q1),
        "return_q1": float(q1),
        "return_q3": float(q3),
        "return_min": float(team.min()),
        "return_max": float(team.max()),
        "length_mean": float(np.mean([r.length for r in results])),
        "infos": {key: _nanmean(info_values(key)) for key in keys},
        "per_agent": per_agent,
    }
    groups = results[0].groups
    if len(groups) > 1:  # each side of a competitive env apart (the team's return adds them)
        summary["groups"] = {}
        for name, members in groups.items():
            values = np.array([r.group_return(name) for r in results])
            g1, g3 = np.percentile(values, [25, 75])
            summary["groups"][name] = {
                "agents": list(members),
                "return_median": float(np.median(values)),
                "return_mean": float(values.mean()),
                "return_q1": float(g1),
                "return_q3": float(g3),
            }
    if results[0].select is not None:  # (the summary carries the rule to every choice)
        summary["select"] = results[0].select
    if "coverage" in keys:
        coverage = info_values("coverage")
        summary["coverage_mean"] = _nanmean(coverage)
        finite = coverage[~np.isnan(coverage)]  # (nanmedian warns when all are NaN)
        summary["coverage_median"] = float(np.median(finite)) if len(finite) else None
    return summary


def _finite(value: float | None) -> float | None:
    """``value``, or ``None`` (JSON's null) where it is none or not finite: JSON has no NaN."""
    return float(value) if value is not None and math.isfinite(value) else None


def _nanmean(values: np.ndarray) -> float | None:
    """The mean of the values that are not nan; ``None`` when all are (JSON has no nan)."""
    finite = values[~np.isnan(values)]
    return float(finite.mean()) if len(finite) else None


class PettingZooPlayer(EpisodePlayer):
    """Copies of the env stepped one after the other, each until its episode ends (its agents
    all gone, or all terminated or truncated). An agent that has left the episode (``env.agents``
    no longer holds it) is given its blank observation (zeros; every action allowed where the
    observations carry a mask) in the batch and its action is dropped; its return counts the
    steps it was in, and its infos are those of its last step. An episode that runs long says
    so on stderr every :data:`LONG_EPISODE_EVERY_S` seconds; the env's guard ends the work at
    ``env.pettingzoo.step_limit`` steps (:class:`harness.config.pettingzoo.EnvFailed`)."""

    def __init__(
        self, env: PettingZooEnvConfig, copies: int, render_mode: str | None, record_paths: bool
    ) -> None:
        if record_paths:
            raise ValueError("paths are the coverage env's: a pettingzoo env has none")
        spaces = env.spaces  # (the observation with the agent's one-hot index where it has one)
        self.agents, self.n_agents = spaces.agents, spaces.n_agents
        self.n_actions = int(spaces.action_space.n)
        self.zeros = blank_observation(spaces.observation_space)
        self.limit = env.pettingzoo.step_limit
        self.groups = env.groups
        self.select = env.select
        self.envs = [make_env(env, render_mode) for _ in range(copies)]

    def reset(self, seeds: Sequence[int]) -> Any:
        self.first = seeds[0] if seeds else 0
        self.batch = self.envs[: len(seeds)]
        self.obs = [e.reset(seed=seed)[0] for e, seed in zip(self.batch, seeds, strict=True)]
        self._views = [EpisodeView(np.random.default_rng(seed), self.n_actions) for seed in seeds]
        self.returns = np.zeros((len(seeds), self.n_agents))
        self.lengths = [0] * len(seeds)
        self.last: list[dict[str, Any]] = [{} for _ in seeds]
        self.live = [bool(e.live_agents()) for e in self.batch]
        self._stepped: list[tuple[int, int, bool]] = []
        self.started = self.reported = time.monotonic()
        return self._observations()

    def _observations(self) -> Any:
        return stack_observations(
            [self.obs[i].get(a, self.zeros) for i in self.playing for a in self.agents]
        )

    @property
    def playing(self) -> list[int]:
        return [i for i, live in enumerate(self.live) if live]

    def views(self) -> Sequence[Any]:
        return [self._views[i] for i in self.playing]

    def step(self, actions: np.ndarray) -> Any:
        if time.monotonic() - self.reported >= LONG_EPISODE_EVERY_S:
            self.reported = time.monotonic()
            longest = max(self.lengths)
            print(
                f"  episode {self.first + self.lengths.index(longest)}: step {longest:,} "
                f"of at most {self.limit:,} (env.pettingzoo.step_limit), "
                f"{(self.reported - self.started) / 60:.1f} min",
                file=sys.stderr,
                flush=True,
            )
        playing = self.playing
        actions = np.asarray(actions).reshape(len(playing), self.n_agents)
        self._stepped = []
        for row, i in enumerate(playing):
            e = self.batch[i]
            alive = e.live_agents()
            act = {a: int(actions[row, k]) for k, a in enumerate(self.agents) if a in alive}
            self.obs[i], rewards, terms, truncs, infos = e.step(act)
            self.lengths[i] += 1
            for k, a in enumerate(self.agents):
                if a in act:  # (an agent that has left earns nothing)
                    self.returns[i, k] += float(rewards.get(a, 0.0))
                    if a in infos:
                        self.last[i][a] = infos[a]
            ended = not e.live_agents() or all(
                terms.get(a, False) or truncs.get(a, False) for a in act
            )
            self._stepped.append((i, self.lengths[i], ended))
            if ended:
                self.live[i] = False
        return self._observations() if any(self.live) else None

    @property
    def stepped(self) -> list[tuple[int, int, bool]]:
        return self._stepped

    def render(self, copy: int) -> np.ndarray:
        return self.batch[copy].render()

    def results(self, frames: list[list[np.ndarray]]) -> list[Any]:
        out = []
        for i in range(len(self.batch)):
            per_agent = [numeric_infos(self.last[i].get(a, {})) for a in self.agents]
            keys = sorted({key for info in per_agent for key in info})
            out.append(
                TeamEpisodeResult(
                    agents=self.agents,
                    returns=self.returns[i].tolist(),
                    length=self.lengths[i],
                    infos={key: [info.get(key, np.nan) for info in per_agent] for key in keys},
                    frames=frames[i],
                    groups=self.groups,
                    select=self.select,
                )
            )
        return out

    def close(self) -> None:
        for e in self.envs:
            e.close()


class PettingZooTask(Task):
    """Any PettingZoo env (``env: {pettingzoo: {make, kwargs}}``): its constructor imported by
    name and run behind the contract's guard."""

    name = "pettingzoo"
    metric = "team return"
    prefix = "return"
    percent = False
    compare_keys = ("return_median", "return_iqr", "return_mean")
    #: (``groups`` and ``select`` where the summary has them: a selected group's rows.)
    tune_keys = (
        "source",
        "return_median",
        "return_q1",
        "return_q3",
        "return_mean",
        "groups",
        "select",
    )
    group_keys = ("seed", "return_mean", "return_median")
    #: The team's return (the sum of its agents'), each agent's (``a;b;c``), the length, and
    #: the numeric per-agent infos of the episode's last step as JSON (``{"key": [a, b, c]}``).
    episode_columns = (
        "episode",
        "phase",
        "timesteps",
        "copy",
        "team_return",
        "returns",
        "length",
        "infos",
    )
    evaluation_columns = (
        "timesteps",
        "episodes",
        "temperature",
        "return_median",
        "return_q1",
        "return_q3",
        "return_mean",
        "length_mean",
    )
    episode_metric = "team_return"
    render_every = 1
    leaving_agents = True
    env: PettingZooEnvConfig

    @classmethod
    def takes(cls, env: Any) -> bool:
        return isinstance(env, PettingZooEnvConfig)

    @property
    def n_agents(self) -> int:
        return self.env.spaces.n_agents

    @property
    def agents(self) -> tuple[str, ...]:
        return self.env.spaces.agents

    @property
    def groups(self) -> dict[str, tuple[str, ...]]:
        """The agents' groups: ``env.pettingzoo.groups``, else by name prefix
        (:func:`harness.config.pettingzoo.agent_groups`)."""
        return self.env.groups

    @property
    def select(self) -> str | None:
        """``env.pettingzoo.select`` (checked against the groups where the run started)."""
        return self.env.pettingzoo.select

    def start(self, config: Any) -> tuple[Any, Any]:
        try:
            self.env.pettingzoo.probe()  # the constructor: once, here
            config.check_env_fits()
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        spaces = self.env.spaces
        return spaces.observation_space, spaces.action_space

    def player(self, copies: int, render_mode: str | None, record_paths: bool) -> EpisodePlayer:
        try:  # the constructor, where nothing built the env yet (an evaluation's start)
            self.env.pettingzoo.probe()
            _ = self.env.select  # (a --set one against the env's groups)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        return PettingZooPlayer(self.env, copies, render_mode, record_paths)

    def check_baseline(self, name: str, plays_any_env: bool, offered: Sequence[str]) -> None:
        if not plays_any_env:
            raise ValueError(
                f"plays the coverage env only; a pettingzoo env takes {', '.join(offered)}"
            )

    def check_renders(self) -> None:
        probe = self.make_env()
        modes = (getattr(probe, "metadata", None) or {}).get("render_modes", [])
        declared = getattr(probe.unwrapped, "own_metadata", True)
        probe.close()
        if "rgb_array" not in modes:
            why = (
                f"its metadata['render_modes'] is {list(modes)}"
                if declared
                else "it has no metadata"
            )
            raise ValueError(
                f"{self.env.pettingzoo.make} does not render rgb_array frames ({why}: an env "
                "that draws lists 'rgb_array' there, takes render_mode and returns the frame "
                "from render())"
            )

    @classmethod
    def summarize(cls, results: list[Any]) -> dict[str, Any]:
        return summarize(results)

    @classmethod
    def selection_score(cls, summary: dict[str, Any]) -> float:
        """The mean return of the summary's ``select`` group, else the team's."""
        return cls._selected(summary, "mean")

    @classmethod
    def objective_value(cls, summary: dict[str, Any]) -> float:
        """The median return of the summary's ``select`` group, else the team's."""
        return cls._selected(summary, "median")

    @classmethod
    def _selected(cls, summary: dict[str, Any], stat: str) -> float:
        # The one rule of every choice on validation episodes: a competitive env's sides cancel
        # in the team's return (a zero-sum env's is always 0), so a config may name a side.
        select = summary.get("select")
        numbers = summary if select is None else summary["groups"][select]
        return float(numbers[f"return_{stat}"])

    @classmethod
    def selection_metric(cls, select: str | None = None) -> str:
        return cls.metric if select is None else f"return of group {select}"

    @classmethod
    def per_episode(cls, results: list[Any]) -> dict[str, list[Any]]:
        return {
            "team_return": [r.team_return for r in results],
            "length": [r.length for r in results],
        }

    @classmethod
    def format_summary(cls, summary: dict[str, Any]) -> str:
        how = sampling_note(summary.get("temperature"))
        low, high = summary["return_mean_ci"]
        lines = [
            f"policy    {summary['policy']}{f' ({how})' if how else ''}",
            f"episodes  {summary['episodes']} (seed {summary['seed']}), "
            f"{summary['env']['pettingzoo']['make']}",
            f"team return  median {summary['return_median']:.4g}   mean "
            f"{summary['return_mean']:.4g} [95 % CI {low:.4g}, {high:.4g}]   IQR "
            f"{summary['return_iqr']:.4g} ({summary['return_q1']:.4g} .. "
            f"{summary['return_q3']:.4g})",
            f"length       mean {summary['length_mean']:.4g} steps",
        ]
        for group, g in summary.get("groups", {}).items():
            lines.append(
                f"group {group} ({len(g['agents'])} agents): return median "
                f"{g['return_median']:.4g}   mean {g['return_mean']:.4g}   "
                f"({g['return_q1']:.4g} .. {g['return_q3']:.4g})"
            )
        for key, value in summary["infos"].items():
            lines.append(f"info {key:<8}team mean {'-' if value is None else f'{value:.4g}'}")
        keys = [key for key in summary["per_agent"][0] if key != "agent"]
        lines += ["", f"{'agent':<12}" + "".join(f"{key:>16}" for key in keys)]
        for a in summary["per_agent"]:
            cells = ("-" if a[key] is None else f"{a[key]:.4g}" for key in keys)
            lines.append(f"{a['agent']:<12}" + "".join(f"{cell:>16}" for cell in cells))
        return "\n".join(lines)

    @classmethod
    def format_tune(cls, result: dict[str, Any]) -> list[str]:
        select = result["rows"][0].get("select")
        what = cls.selection_metric(select)
        lines = [f"{'T':>6}{'median':>10}{'q1':>10}{'q3':>10}{'mean':>10}   ({what})"]
        for r in result["rows"]:
            mark = "  <- chosen" if r["temperature"] == result["chosen"] else ""
            row = r if select is None else r["groups"][select]  # (the numbers chosen by)
            numbers = (row[f"return_{k}"] for k in ("median", "q1", "q3", "mean"))
            lines.append(f"{r['temperature']:>6g}" + "".join(f"{v:>10.4g}" for v in numbers) + mark)
        return lines

    @classmethod
    def compare_header(cls) -> str:
        return f"{'median return':>14}{'return IQR':>12}"

    @classmethod
    def compare_row(cls, summary: dict[str, Any]) -> str:
        return f"{summary['return_median']:>14.4g}{summary['return_iqr']:>12.4g}"

    def training_episode(self, infos: list[dict[str, Any]], record: Record) -> dict[str, Any]:
        """The team's return, each agent's, the length and the numeric infos each agent
        reported at the episode's last step (JSON); TensorBoard gets their means
        (``rollout/team_return``, ``rollout/<agent>/return``, ``rollout/<agent>/<key>``,
        ``rollout/info/<key>``, the team's mean)."""
        returns = [float(info["episode"]["r"]) for info in infos]
        # (less the VecEnv's own: the time limit's flag)
        per_agent = [
            {k: v for k, v in numeric_infos(info).items() if k not in VEC_INFO_KEYS}
            for info in infos
        ]
        keys = sorted({key for info in per_agent for key in info})
        table = {key: [info.get(key) for info in per_agent] for key in keys}
        record("rollout/team_return", sum(returns))
        groups = self.groups
        if len(groups) > 1:
            for group, members in groups.items():
                mine = [r for a, r in zip(self.agents, returns, strict=True) if a in members]
                record(f"rollout/group/{group}/return", sum(mine))
        for agent, value, info in zip(self.agents, returns, per_agent, strict=True):
            record(f"rollout/{agent}/return", value)
            for key, number in info.items():
                record(f"rollout/{agent}/{key}", number)
        for key, values in table.items():
            given = [v for v in values if v is not None]
            record(f"rollout/info/{key}", float(np.mean(given)))
        return {
            "team_return": sum(returns),
            "returns": ";".join(f"{r:g}" for r in returns),
            "length": int(infos[0]["episode"]["l"]),
            "infos": json.dumps(
                {key: [_finite(v) for v in values] for key, values in table.items()},
                separators=(",", ":"),
            ),
        }

    @classmethod
    def record_evaluation(cls, summary: dict[str, Any], record: Record) -> None:
        for key in ("return_median", "return_mean", "length_mean"):
            record(f"eval/{key}", summary[key])
        for key, value in summary["infos"].items():
            if value is not None:
                record(f"eval/info/{key}", value)
        for group, values in summary.get("groups", {}).items():
            for key in ("return_median", "return_mean"):
                record(f"eval/group/{group}/{key}", values[key])


TeamEpisodeResult.task = PettingZooTask
