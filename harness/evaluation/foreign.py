"""Evaluation episodes of a PettingZoo env of one's own (``env: {pettingzoo: ...}``): the loop,
its results and their summary. :func:`harness.evaluation.episodes.run_episodes` and
``summarize`` hand such an env here; the coverage env's metrics never apply to it.

Episode ``k`` of an evaluation with seed ``s`` is the env reset with seed ``s + k`` (as for the
coverage env), whatever the number of copies stepped side by side; a copy's agents go through
the batched policy together with every other copy's, copy-major. Metrics: the team's return (the
sum of its agents' returns) and each agent's, the episode's length, and the numeric per-agent
infos the env reports at an episode's last step (``coverage`` among them, if it reports one).
"""

from __future__ import annotations

import numbers
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from harness.config.pettingzoo import blank_observation, stack_observations
from harness.config.schema import PettingZooEnvConfig
from harness.factory import make_env

#: ``summary["source"]`` of a summary made here (the coverage env's summaries have none).
SOURCE = "pettingzoo"

#: Seconds between two lines saying where a long episode is (an evaluation's episodes of an env
#: that ends them late, or never: the env's guard stops it at ``env.pettingzoo.step_limit``).
LONG_EPISODE_EVERY_S = 30.0


class TooManyFrames(Exception):
    """An episode's frames would take more memory than the caller allows (``frame_bytes``)."""


@dataclass
class ForeignEpisodeResult:
    """Metrics of one finished episode of a PettingZoo env of one's own."""

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

    @property
    def team_return(self) -> float:
        """The team's return: the sum of its agents' returns."""
        return float(sum(self.returns))


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


def run_foreign_episodes(
    policy: Callable[[np.ndarray, Any], np.ndarray],
    env: PettingZooEnvConfig,
    episodes: int,
    seed: int,
    copies: int = 8,
    frames_every: int = 0,
    should_stop: Callable[[], bool] | None = None,
    progress: Callable[[int], None] | None = None,
    frame_bytes: int | None = None,
) -> list[ForeignEpisodeResult]:
    """Run ``episodes`` seeded episodes with the batched ``policy`` (episode ``k``: the env reset
    with ``seed + k``) and return their metrics in order. See
    :func:`harness.evaluation.episodes.run_episodes` for the arguments; ``frame_bytes`` bounds
    the memory of the frames kept (each counted twice: a picture made of it, as a GIF's, is
    held too), measured from the first frame.

    An agent that has left the episode (``env.agents`` no longer holds it) is given zeros as its
    observation in the batch and its action is dropped; its return counts the steps it was in,
    and its infos are those of its last step. An episode that runs long says so on
    stderr every :data:`LONG_EPISODE_EVERY_S` seconds; the env's guard ends the work at
    ``env.pettingzoo.step_limit`` steps (:class:`harness.config.pettingzoo.EnvFailed`).

    Raises:
        EpisodesStopped: when ``should_stop()`` returned True.
        EnvFailed: when the env raised or broke the contract.
        TooManyFrames: when the frames would take more than ``frame_bytes``.
    """
    from harness.evaluation.episodes import EpisodesStopped

    spaces = env.spaces  # (the observation with the agent's one-hot index where it has one)
    agents, n_agents = spaces.agents, spaces.n_agents
    n_actions = int(spaces.action_space.n)
    zeros = blank_observation(spaces.observation_space)
    render_mode = "rgb_array" if frames_every else None
    n_copies = max(1, min(copies, episodes))
    envs = [make_env(env, render_mode) for _ in range(n_copies)]
    results: list[ForeignEpisodeResult] = []
    limit = env.pettingzoo.step_limit
    kept = 0  # frames, for frame_bytes

    def keep(frame: np.ndarray) -> np.ndarray:
        nonlocal kept
        kept += 1
        if frame_bytes is not None and kept * 2 * frame.nbytes > frame_bytes:
            height, width = frame.shape[:2]
            raise TooManyFrames(
                f"the env's frames are {height}x{width} pixels ({2 * frame.nbytes:,} bytes each "
                f"with the picture made of it): {kept - 1:,} of them fit in {frame_bytes:,}"
            )
        return frame

    try:
        for first in range(0, episodes, n_copies):
            size = min(n_copies, episodes - first)
            batch = envs[:size]
            obs = [e.reset(seed=seed + first + i)[0] for i, e in enumerate(batch)]
            views = [
                EpisodeView(np.random.default_rng(seed + first + i), n_actions) for i in range(size)
            ]
            returns = np.zeros((size, n_agents))
            lengths = [0] * size
            last: list[dict[str, Any]] = [{} for _ in range(size)]
            frames = [[keep(e.render())] if frames_every else [] for e in batch]
            live = [bool(e.live_agents()) for e in batch]
            started = reported = time.monotonic()
            while any(live):
                if should_stop is not None and should_stop():
                    raise EpisodesStopped(f"stopped in episode {first}")
                if time.monotonic() - reported >= LONG_EPISODE_EVERY_S:
                    reported = time.monotonic()
                    print(
                        f"  episode {first + lengths.index(max(lengths))}: step {max(lengths):,} "
                        f"of at most {limit:,} (env.pettingzoo.step_limit), "
                        f"{(reported - started) / 60:.1f} min",
                        file=sys.stderr,
                        flush=True,
                    )
                playing = [i for i in range(size) if live[i]]
                stacked = stack_observations(
                    [obs[i].get(a, zeros) for i in playing for a in agents]
                )
                actions = np.asarray(policy(stacked, [views[i] for i in playing]))
                actions = actions.reshape(len(playing), n_agents)
                for row, i in enumerate(playing):
                    e = batch[i]
                    alive = e.live_agents()
                    act = {a: int(actions[row, k]) for k, a in enumerate(agents) if a in alive}
                    obs[i], rewards, terms, truncs, infos = e.step(act)
                    lengths[i] += 1
                    for k, a in enumerate(agents):
                        if a in act:  # (an agent that has left earns nothing)
                            returns[i, k] += float(rewards.get(a, 0.0))
                            if a in infos:
                                last[i][a] = infos[a]
                    ended = not e.live_agents() or all(
                        terms.get(a, False) or truncs.get(a, False) for a in act
                    )
                    if frames_every and (ended or lengths[i] % frames_every == 0):
                        frames[i].append(keep(e.render()))
                    if ended:
                        live[i] = False
            for i in range(size):
                per_agent = [numeric_infos(last[i].get(a, {})) for a in agents]
                keys = sorted({key for info in per_agent for key in info})
                results.append(
                    ForeignEpisodeResult(
                        agents=agents,
                        returns=returns[i].tolist(),
                        length=lengths[i],
                        infos={key: [info.get(key, np.nan) for info in per_agent] for key in keys},
                        frames=frames[i],
                    )
                )
            if progress is not None:
                progress(len(results))
    finally:
        for e in envs:
            e.close()
    return results


def summarize_foreign(results: list[ForeignEpisodeResult]) -> dict[str, Any]:
    """The numbers of a list of episodes: the team's return (median, mean with its bootstrap
    interval, quartiles, range), the mean length, each agent's mean return and the means of its
    numeric infos, and each info key's mean over episodes of the team's mean. ``coverage_mean``
    and ``coverage_median`` (the team's mean ``coverage`` info) only where the env reports a
    ``coverage`` info."""
    from harness.evaluation.episodes import mean_interval

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
        "source": SOURCE,
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
    if "coverage" in keys:
        coverage = info_values("coverage")
        summary["coverage_mean"] = _nanmean(coverage)
        finite = coverage[~np.isnan(coverage)]  # (nanmedian warns when all are NaN)
        summary["coverage_median"] = float(np.median(finite)) if len(finite) else None
    return summary


def _nanmean(values: np.ndarray) -> float | None:
    """The mean of the values that are not nan; ``None`` when all are (JSON has no nan)."""
    finite = values[~np.isnan(values)]
    return float(finite.mean()) if len(finite) else None
