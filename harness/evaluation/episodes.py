"""Evaluation on fresh, seeded episodes (the thesis's metrics: coverage, useful and total
coverage per agent, coverage at 33/66/100 % of the episode, Table 4.2).

Episode ``k`` of an evaluation with seed ``s`` is the env reset with seed ``s + k``, whatever the
number of copies stepped side by side, so results are repeatable and comparable between policies
(a trained model, the random or the frontier baseline all see the same maps and start cells).
All agents of all copies go through the policy in one batched call per step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from envs.coverage import CoverageEnv
from envs.coverage.core import CoverageCore
from envs.coverage.observations import blocked_moves
from harness.config.schema import EnvConfig, PettingZooEnvConfig
from harness.factory import make_core_spec

#: A batched policy: ``policy(obs, envs)`` maps the observations ``(len(envs) * n_agents, ...)``
#: of every agent of every env copy in play (copy-major: copy 0's agents first; a dict of such
#: arrays for ``Dict`` observations) to actions of the same length. ``envs`` are the live
#: ``CoverageEnv`` copies, for baselines that read the map; a learned policy ignores them.
BatchPolicy = Callable[[np.ndarray, Sequence[CoverageEnv]], np.ndarray]

#: Fractions of the episode at which coverage is recorded (Table 4.2).
CHECKPOINT_FRACTIONS = (0.33, 0.66, 1.0)
#: Team coverages whose first step is recorded: policies that both reach full coverage are then
#: compared on speed (the frontier planner's strength).
COVERAGE_TARGETS = (0.90, 0.99)


class EpisodesStopped(Exception):
    """:func:`run_episodes` gave up on its episodes because ``should_stop()`` said so."""


@dataclass
class EpisodeResult:
    """Metrics of one finished episode."""

    coverage: float
    """Team coverage at the end (visited free cells / free cells)."""
    coverage_at: list[float]
    """Team coverage at 33 %, 66 % and 100 % of the episode."""
    wall_hits: list[int]
    """Per agent."""
    new_cells: list[int]
    """Per agent: cells credited to it."""
    steps: int
    free_cells: int
    paths: list[np.ndarray] = field(default_factory=list)
    """Per agent ``(steps + 1, 2)`` positions, when recorded."""
    steps_to: dict[str, int | None] = field(default_factory=dict)
    """Steps the team took to reach each of :data:`COVERAGE_TARGETS` (``None``: not reached)."""
    walls: np.ndarray | None = None
    """``bool (H, W)`` map of the episode (True = wall), when paths are recorded."""
    frames: list[np.ndarray] = field(default_factory=list)
    """``rgb_array`` frames (``uint8 (H*k, W*k, 3)``) at step 0, every ``frames_every`` steps
    and the last step, when asked for."""


def model_policy(model: Any, temperature: float = 0.0, shield: bool = False) -> BatchPolicy:
    """A batched policy from an SB3 model: greedy (ε = 0) when ``temperature`` is 0, else
    Boltzmann, each agent sampling its action from ``softmax(Q / temperature)``.

    With ``shield`` the moves that the agent's own observation shows to be blocked (a wall or
    the grid's edge next to it, :func:`envs.coverage.observations.blocked_moves`) are left out
    before the choice: a safety shield on the learned policy (Alshiekh et al. 2018, "Safe
    Reinforcement Learning via Shielding"), so the test policy never hits a wall, and an agent
    whose best Q-value is a blocked move takes its best free one instead of pushing forever.

    A memoryless greedy policy on a partial observation repeats itself once its surroundings are
    visited (a loop it cannot leave); sampling near-tied actions breaks such loops, while actions
    far below the best (a wall: -10) keep a vanishing probability. The noise of each env copy is
    drawn from that copy's ``np_random`` (seeded by its reset), so an episode's actions depend on
    its seed alone, not on how many copies run side by side.
    """
    if temperature < 0:
        raise ValueError(f"temperature must be >= 0, got {temperature}")

    def q_values(obs: np.ndarray) -> np.ndarray:
        import torch as th

        with th.no_grad():
            q = model.q_net(model.policy.obs_to_tensor(obs)[0]).cpu().numpy().astype(np.float64)
        if shield:
            # stay is never blocked: a row keeps a finite value
            q[blocked_moves(obs, q.shape[1])] = -np.inf
        from harness.sb3.dqn import allowed_actions

        allowed = allowed_actions(obs, q.shape[1])
        if allowed is not None:  # the goal action's empty slots: as the greedy choice masks them
            q[~allowed] = -np.inf
        return q

    def greedy(obs: np.ndarray, envs: Sequence[CoverageEnv]) -> np.ndarray:
        if shield:
            return q_values(obs).argmax(axis=1)
        # The model's own greedy choice: DoubleDQN's masks the goal action's empty slots.
        actions, _ = model.predict(obs, deterministic=True)
        return np.asarray(actions)

    def boltzmann(obs: np.ndarray, envs: Sequence[CoverageEnv]) -> np.ndarray:
        q = q_values(obs)
        return softmax_sample(q, temperature, episode_draws(envs, batch_len(obs) // len(envs)))

    return greedy if temperature == 0 else boltzmann


def batch_len(obs: np.ndarray | dict[str, np.ndarray]) -> int:
    """Observations in a batch (a ``Dict`` observation's batch is a dict of stacked arrays)."""
    if isinstance(obs, dict):
        return len(next(iter(obs.values())))
    return len(obs)


def softmax_sample(q: np.ndarray, temperature: float, uniform: np.ndarray) -> np.ndarray:
    """Sample one action per row of ``q`` from ``softmax(q / temperature)`` by inverse CDF.

    Args:
        q: ``(batch, n_actions)`` action values.
        temperature: Softmax temperature, > 0.
        uniform: ``(batch,)`` draws from U[0, 1), one per row.
    """
    z = (q - q.max(axis=1, keepdims=True)) / temperature  # shift: exp never overflows
    return sample_categorical(np.exp(z), uniform)


def sample_categorical(weights: np.ndarray, uniform: np.ndarray) -> np.ndarray:
    """Sample one column index per row, with probability proportional to ``weights``, by inverse
    CDF.

    Args:
        weights: ``(batch, n)`` non-negative weights, each row with a positive sum.
        uniform: ``(batch,)`` draws from U[0, 1), one per row.
    """
    cdf = np.cumsum(weights / weights.sum(axis=1, keepdims=True), axis=1)
    # The first index whose cumulative probability passes the draw (clip guards rounding at 1).
    return np.minimum((cdf <= uniform[:, None]).sum(axis=1), weights.shape[1] - 1)


def episode_draws(envs: Sequence[CoverageEnv], per_copy: int) -> np.ndarray:
    """``per_copy`` draws from U[0, 1) from each env copy's ``np_random`` (seeded by its reset),
    copy-major like a batch of observations: a stochastic test policy then repeats an episode
    from its seed alone, whatever the number of copies side by side."""
    return np.concatenate([env.np_random.random(per_copy) for env in envs])


def run_episodes(
    policy: BatchPolicy,
    env: EnvConfig | PettingZooEnvConfig,
    episodes: int,
    seed: int,
    copies: int = 8,
    record_paths: bool = False,
    frames_every: int = 0,
    should_stop: Callable[[], bool] | None = None,
    progress: Callable[[int], None] | None = None,
) -> list[EpisodeResult]:
    """Run ``episodes`` seeded episodes with ``policy`` and return their metrics in order.

    This is the project's one episode loop: evaluation, ``harness tune``, the in-training
    evaluations, the baselines, path pictures and GIFs all play their episodes here. A
    ``pettingzoo`` env section plays its episodes in
    :func:`harness.evaluation.foreign.run_foreign_episodes` (its results are
    ``ForeignEpisodeResult`` s).

    Args:
        policy: The batched policy.
        env: The env of every episode.
        episodes: Number of episodes; episode ``k`` is the env reset with ``seed + k``.
        seed: Seed of episode 0.
        copies: Env copies stepped side by side (results do not depend on it).
        record_paths: Keep each agent's positions and the map (``paths``, ``walls``).
        frames_every: Render ``rgb_array`` frames every this many steps, plus the first and last
            (0: none).
        should_stop: Asked before every step of the copies side by side: when it returns True,
            the episodes are abandoned (training's evaluation stops so on SIGINT/SIGTERM).
        progress: Called with the number of episodes finished after each batch of copies side
            by side (``harness eval`` reports long evaluations with it).

    Raises:
        EpisodesStopped: when ``should_stop()`` returned True.
    """
    if frames_every < 0:
        raise ValueError(f"frames_every must be >= 0, got {frames_every}")
    if not isinstance(env, EnvConfig):  # a PettingZoo env of one's own: its own loop
        if record_paths:
            raise ValueError("paths are the coverage env's: a pettingzoo env has none")
        from harness.evaluation.foreign import run_foreign_episodes

        return run_foreign_episodes(  # type: ignore[return-value]
            policy, env, episodes, seed, copies, frames_every, should_stop, progress
        )
    render_mode = "rgb_array" if frames_every else None
    n_copies = max(1, min(copies, episodes))
    spec = make_core_spec(env)
    # One batched core per batch size (the last batch may be smaller), each copy handed to the
    # policy as an env view (baselines read the map from it); all copies step in one call.
    batches: dict[int, tuple[CoverageCore, list[CoverageEnv]]] = {}
    n_agents, max_steps = env.n_agents, env.max_steps
    marks = [max(1, round(f * max_steps)) for f in CHECKPOINT_FRACTIONS]
    targets = [(f, _target_key(f)) for f in COVERAGE_TARGETS]
    results: list[EpisodeResult] = []
    for first in range(0, episodes, n_copies):
        size = min(n_copies, episodes - first)
        if size not in batches:
            core = CoverageCore(spec, size)
            batches[size] = (core, [CoverageEnv.copy_of(core, b, render_mode) for b in range(size)])
        core, batch = batches[size]
        for i, e in enumerate(batch):
            e.reset(seed=seed + first + i)
        obs = core.observe()
        paths = [[e.positions] for e in batch] if record_paths else None
        frames: list[list[np.ndarray]] = [[e.render()] if frames_every else [] for e in batch]
        at: list[list[float]] = [[] for _ in batch]
        reached: list[dict[str, int | None]] = [
            {_target_key(f): None for f in COVERAGE_TARGETS} for _ in batch
        ]
        for t in range(1, max_steps + 1):
            if should_stop is not None and should_stop():
                raise EpisodesStopped(f"stopped at step {t - 1} of episode {first}")
            actions = np.asarray(policy(CoverageCore.flat(obs), batch)).reshape(size, n_agents)
            core.step(actions)
            obs = core.observe()
            coverage = (core.n_visited / core.n_free).tolist()
            for i, e in enumerate(batch):
                if paths is not None:
                    paths[i].append(e.positions)
                if frames_every and (t % frames_every == 0 or t == max_steps):
                    frames[i].append(e.render())
                if t in marks:  # a short episode can hit one step for two marks
                    at[i].extend([coverage[i]] * marks.count(t))
                for f, key in targets:
                    if reached[i][key] is None and coverage[i] >= f:
                        reached[i][key] = t
        for i, e in enumerate(batch):
            results.append(
                EpisodeResult(
                    coverage=e.coverage,
                    coverage_at=at[i],
                    wall_hits=core.wall_hits[i].tolist(),
                    new_cells=core.new_cells[i].tolist(),
                    steps=max_steps,
                    free_cells=e.free_cells,
                    paths=list(np.stack(paths[i], axis=1)) if paths is not None else [],
                    steps_to=reached[i],
                    walls=np.array(e.walls) if record_paths else None,
                    frames=frames[i],
                )
            )
        if progress is not None:
            progress(len(results))
    return results


def _target_key(fraction: float) -> str:
    return f"steps_to_{round(fraction * 100)}"


def median_steps_to(results: list[EpisodeResult], key: str) -> float | None:
    """Median over episodes of the steps to reach a coverage (an episode that never reached it
    counts as infinitely slow); ``None`` when the median episode did not reach it."""
    values = [r.steps_to.get(key) for r in results]
    finite = np.array([np.inf if v is None else v for v in values], dtype=float)
    median = float(np.median(finite))
    return None if not np.isfinite(median) else median


def headline(summary: dict[str, Any], stat: str = "median") -> float:
    """An evaluation's headline number: the team coverage's ``stat`` (``median``, ``mean``,
    ``q1``, ``q3``, ``iqr``) for the coverage env, the team return's for a PettingZoo env of
    one's own (``summary["source"] == "pettingzoo"``). Sweeps, ``harness tune``, ``compare``
    and seed groups read their number here."""
    from harness.evaluation.foreign import SOURCE

    prefix = "return" if summary.get("source") == SOURCE else "coverage"
    return float(summary[f"{prefix}_{stat}"])


#: The steps :func:`selection_score` counts for a median episode that never reaches 99 %.
SLOWEST = 1e5


def selection_score(summary: dict[str, Any]) -> float:
    """The project's one rule for picking a policy: fewest wall hits first, then the highest
    median coverage (the thesis's tests show zero wall hits), then the fewest median steps to
    99 % (teams that cover the whole map, 4 agents on 50x50, tie on coverage; speed is then
    the measure). Higher is better.

    ``best_model.zip`` (the best in-training evaluation) and ``harness tune`` (the test
    temperature) both choose by it. One more wall hit over the evaluation episodes costs
    ``1000 / episodes`` and a median never exceeds 1; a median step costs ``1e-12`` (a median
    that never reaches 99 % counts as :data:`SLOWEST` steps, at most ``1e-7``), less than the
    smallest difference of two median coverages on maps of up to 500,000 free cells. So the
    order is lexicographic for fewer than 1000 episodes. A single float, because a
    checkpoint's training state keeps it.

    A PettingZoo env of one's own (``summary["source"] == "pettingzoo"``) is scored by its mean
    team return.
    """
    from harness.evaluation.foreign import SOURCE

    if summary.get("source") == SOURCE:  # a PettingZoo env of one's own: the team return
        return float(summary["return_mean"])
    steps = summary.get("steps_to_99")
    speed = -1e-12 * (SLOWEST if steps is None else float(steps))
    return float(summary["coverage_median"]) - 1000.0 * float(summary["wall_hits_mean"]) + speed


def physical_bound(n_agents: int, steps: int, free_cells: int) -> float:
    """The most of a map a team can have covered: ``min(1, N * (T + 1) / F)`` for ``N`` agents,
    ``T`` steps and ``F`` free cells (each agent's start cell, then one new cell per move)."""
    return min(1.0, n_agents * (steps + 1) / free_cells)


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


def summarize(results: list[EpisodeResult]) -> dict[str, Any]:
    """The thesis's numbers over a list of episodes (all fractions in [0, 1]), and the physical
    limit beside them: ``bound`` (the mean over episodes of :func:`physical_bound`) and
    ``efficiency``, ``coverage_mean / bound``. Episodes of a PettingZoo env of one's own are
    summarized by :func:`harness.evaluation.foreign.summarize_foreign`."""
    if results and not isinstance(results[0], EpisodeResult):
        from harness.evaluation.foreign import summarize_foreign

        return summarize_foreign(results)  # type: ignore[arg-type]
    cov = np.array([r.coverage for r in results])
    q1, q3 = np.percentile(cov, [25, 75])
    n_agents = len(results[0].new_cells)
    per_agent = []
    for k in range(n_agents):
        credited = np.array([r.new_cells[k] for r in results], dtype=float)
        per_agent.append(
            {
                "agent": f"agent_{k}",
                "useful_coverage": float(np.mean(credited / [r.steps for r in results])),
                "total_coverage": float(np.mean(credited / [r.free_cells for r in results])),
            }
        )
    at = np.array([r.coverage_at for r in results])
    bound = float(np.mean([physical_bound(n_agents, r.steps, r.free_cells) for r in results]))
    low, high = mean_interval(cov)
    return {
        "episodes": len(results),
        "coverage_median": float(np.median(cov)),
        "coverage_mean": float(cov.mean()),
        "coverage_mean_ci": [low, high],
        "bound": bound,
        "efficiency": float(cov.mean()) / bound,
        "coverage_iqr": float(q3 - q1),
        "coverage_q1": float(q1),
        "coverage_q3": float(q3),
        "coverage_min": float(cov.min()),
        "coverage_max": float(cov.max()),
        "coverage_at_median": {
            f"{round(f * 100)}%": float(v)
            for f, v in zip(CHECKPOINT_FRACTIONS, np.median(at, axis=0))
        },
        **{_target_key(f): median_steps_to(results, _target_key(f)) for f in COVERAGE_TARGETS},
        "wall_hits_mean": float(np.mean([sum(r.wall_hits) for r in results])),
        "wall_hits_episodes": int(sum(1 for r in results if sum(r.wall_hits) > 0)),
        "per_agent": per_agent,
    }
