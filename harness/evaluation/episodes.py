"""The one episode loop (:func:`run_episodes`) and the batched policies that play it.

Episode ``k`` of an evaluation with seed ``s`` is the env reset with seed ``s + k``, whatever the
number of copies stepped side by side, so results are repeatable and comparable between policies
(a trained model, the random or the frontier baseline all see the same maps and start cells).
All agents of all copies go through the policy in one batched call per step. The task
(:mod:`harness.tasks`) plays its env's copies and says what an episode reports; the coverage
env's metrics (the thesis's: coverage, useful and total coverage per agent, coverage at 33/66/100
% of the episode, Table 4.2) are :mod:`harness.tasks.coverage`'s, and are named here too.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from envs.coverage import CoverageEnv
from envs.coverage.observations import blocked_moves
from harness.tasks import headline, objective_value, selection_score, summarize, task_of
from harness.tasks.base import EpisodesStopped, TooManyFrames, mean_interval
from harness.tasks.coverage import (
    CHECKPOINT_FRACTIONS,
    COVERAGE_TARGETS,
    SLOWEST,
    EpisodeResult,
    median_steps_to,
    physical_bound,
)
from harness.tasks.pettingzoo import EpisodeView, TeamEpisodeResult

__all__ = [
    "CHECKPOINT_FRACTIONS",
    "COVERAGE_TARGETS",
    "SLOWEST",
    "BatchPolicy",
    "EpisodeResult",
    "EpisodeView",
    "EpisodesStopped",
    "TeamEpisodeResult",
    "TooManyFrames",
    "batch_len",
    "episode_draws",
    "headline",
    "mean_interval",
    "median_steps_to",
    "model_policy",
    "objective_value",
    "physical_bound",
    "run_episodes",
    "sample_categorical",
    "selection_score",
    "softmax_sample",
    "summarize",
]

#: A batched policy: ``policy(obs, envs)`` maps the observations ``(len(envs) * n_agents, ...)``
#: of every agent of every env copy in play (copy-major: copy 0's agents first; a dict of such
#: arrays for ``Dict`` observations) to actions of the same length. ``envs`` are the live
#: copies' views (the coverage env's ``CoverageEnv`` copies, for baselines that read the map;
#: a seeded :class:`EpisodeView` of another env); a learned policy ignores them.
BatchPolicy = Callable[[np.ndarray, Sequence[CoverageEnv]], np.ndarray]


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
    env: Any,
    episodes: int,
    seed: int,
    copies: int = 8,
    record_paths: bool = False,
    frames_every: int = 0,
    should_stop: Callable[[], bool] | None = None,
    progress: Callable[[int], None] | None = None,
    frame_bytes: int | None = None,
) -> list[Any]:
    """Run ``episodes`` seeded episodes with ``policy`` and return their results in order (the
    task's: :class:`EpisodeResult` for the coverage env, :class:`TeamEpisodeResult` for a
    PettingZoo env).

    This is the project's one episode loop: evaluation, ``harness tune``, the in-training
    evaluations, the baselines, path pictures and GIFs all play their episodes here, on the
    copies the env's task plays (:meth:`harness.tasks.base.Task.player`).

    Args:
        policy: The batched policy.
        env: The env section of every episode.
        episodes: Number of episodes; episode ``k`` is the env reset with ``seed + k``.
        seed: Seed of episode 0.
        copies: Env copies stepped side by side (results do not depend on it).
        record_paths: Keep each agent's positions and the map (``paths``, ``walls``: the
            coverage env's).
        frames_every: Render ``rgb_array`` frames every this many steps, plus the first and last
            (0: none).
        should_stop: Asked before every step of the copies side by side: when it returns True,
            the episodes are abandoned (training's evaluation stops so on SIGINT/SIGTERM).
        progress: Called with the number of episodes finished after each batch of copies side
            by side (``harness eval`` reports long evaluations with it).
        frame_bytes: Bounds the memory of the frames kept (each counted twice: a picture made
            of it, as a GIF's, is held too), measured from the first frame.

    Raises:
        EpisodesStopped: when ``should_stop()`` returned True.
        EnvFailed: when a PettingZoo env raised or broke the contract.
        TooManyFrames: when the frames would take more than ``frame_bytes``.
    """
    if frames_every < 0:
        raise ValueError(f"frames_every must be >= 0, got {frames_every}")
    n_copies = max(1, min(copies, episodes))
    player = task_of(env).player(n_copies, "rgb_array" if frames_every else None, record_paths)
    results: list[Any] = []
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
            obs = player.reset([seed + first + i for i in range(size)])
            frames = [[keep(player.render(i))] if frames_every else [] for i in range(size)]
            step = 0
            while player.playing:
                if should_stop is not None and should_stop():
                    raise EpisodesStopped(f"stopped at step {step} of episode {first}")
                obs = player.step(np.asarray(policy(obs, player.views())))
                step += 1
                for i, length, ended in player.stepped if frames_every else ():
                    if ended or length % frames_every == 0:
                        frames[i].append(keep(player.render(i)))
            results.extend(player.results(frames))
            if progress is not None:
                progress(len(results))
    finally:
        player.close()
    return results
