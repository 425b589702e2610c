"""Training an experiment, top to bottom: config → VecEnv → model → phases → run directory.

``train(config, run)`` is what ``harness run`` calls:

1. seed everything and set torch's thread count;
2. build the VecEnv (``harness.adapters``) and the ``DoubleDQN`` (``build_model``);
3. for each phase in order, on the same model and replay buffer: apply the phase's settings
   (learning rate, batch size, train_freq, PER alpha) and call ``model.learn`` with the phase's
   callbacks (ε and β schedules, epochs by coverage, episode log, evaluation, checkpoints);
4. save ``model.zip``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import configure
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import set_random_seed
from stable_baselines3.common.vec_env import VecEnv

from harness.adapters import make_vec_env
from harness.buffers import PrioritizedReplayBuffer
from harness.callbacks import (
    EpisodeLogCallback,
    EpochsByCoverageCallback,
    LinearScheduleCallback,
    PeriodicCallback,
)
from harness.config import ExperimentConfig, PhaseConfig
from harness.dqn import DoubleDQN
from harness.evaluation import model_policy, run_episodes, summarize
from harness.rundir import RunDir, atomic_write, atomic_write_text
from harness.schedules import PhaseLinearSchedule

log = logging.getLogger(__name__)


def configure_torch(threads: int | None) -> None:
    """Set torch's CPU thread count (on a 2-core machine 1 thread is usually fastest)."""
    if threads is not None:
        torch.set_num_threads(threads)


def build_model(config: ExperimentConfig, venv: VecEnv) -> DoubleDQN:
    """Make the ``DoubleDQN`` of ``config.algo`` with the first phase's settings."""
    algo, first = config.algo, config.phases[0]
    policy_kwargs: dict[str, Any] = {
        "net_arch": list(algo.net_arch),
        "optimizer_class": getattr(torch.optim, algo.optimizer),
        "optimizer_kwargs": dict(algo.optimizer_kwargs),
    }
    if algo.policy == "DuelingMlpPolicy":
        policy_kwargs["aggregator"] = algo.dueling_aggregator
    buffer_kwargs: dict[str, Any] | None = None
    if algo.prioritized:
        buffer_kwargs = {"alpha": first.alpha, "beta": first.beta.start, "eps": algo.per_eps}
    return DoubleDQN(
        algo.policy,
        venv,
        learning_rate=_lr_start(first),
        buffer_size=algo.buffer_size,
        learning_starts=algo.learning_starts,
        batch_size=first.batch_size,
        gamma=algo.gamma,
        train_freq=(first.train_freq, "step"),
        gradient_steps=first.epochs[0][1],
        replay_buffer_class=PrioritizedReplayBuffer if algo.prioritized else None,
        replay_buffer_kwargs=buffer_kwargs,
        target_update_interval=algo.target_update_interval,
        exploration_initial_eps=first.exploration.start,
        exploration_final_eps=first.exploration.end,
        max_grad_norm=algo.max_grad_norm,
        double_q=algo.double_q,
        # Enough finished episodes for the epochs table's median (one entry per slot).
        stats_window_size=max(
            100, max(p.epochs_window for p in config.phases) * config.env.n_agents
        ),
        policy_kwargs=policy_kwargs,
        device=algo.device,
        seed=None,  # SuperSuit's VecEnv has no seed(); train() seeds torch/numpy and the env copies
        verbose=0,
    )


def _lr_start(phase: PhaseConfig) -> float:
    lr = phase.learning_rate
    return lr[0] if isinstance(lr, tuple) else lr


def apply_phase(model: DoubleDQN, phase: PhaseConfig) -> None:
    """Set what changes between phases on the live model (SPEC §4)."""
    lr = phase.learning_rate
    start, end = lr if isinstance(lr, tuple) else (lr, lr)
    # SB3 reads lr_schedule(progress_remaining) at each training call; progress runs 1 → 0
    # over each learn() call, i.e. over the phase.
    model.learning_rate = start
    model.lr_schedule = PhaseLinearSchedule(start, end, phase.timesteps, phase.timesteps)
    model.batch_size = phase.batch_size
    model.train_freq = TrainFreq(phase.train_freq, TrainFrequencyUnit.STEP)
    if isinstance(model.replay_buffer, PrioritizedReplayBuffer):
        model.replay_buffer.alpha = phase.alpha


def phase_callbacks(
    config: ExperimentConfig,
    phase: PhaseConfig,
    run: RunDir,
    evaluator: Evaluator,
    first_episode: int,
) -> tuple[list[BaseCallback], EpisodeLogCallback]:
    """The callbacks of one phase, in the order they run."""
    n_agents = config.env.n_agents
    episode_log = EpisodeLogCallback(run.episodes_csv, n_agents, phase.name, first_episode)
    callbacks: list[BaseCallback] = [
        LinearScheduleCallback(
            "exploration_schedule",
            phase.exploration.start,
            phase.exploration.end,
            phase.exploration.steps,
            phase.timesteps,
        ),
        LinearScheduleCallback(
            "beta_schedule", phase.beta.start, phase.beta.end, phase.beta.steps, phase.timesteps
        ),
        EpochsByCoverageCallback(phase.epochs, phase.epochs_window, n_agents),
        episode_log,
        PeriodicCallback(config.eval.every, evaluator),
        PeriodicCallback(config.checkpoint.every, lambda m: save_checkpoint(m, run)),
    ]
    return callbacks, episode_log


class Evaluator:
    """Greedy evaluation on the eval seed's fresh maps during training; keeps the best model.

    The same maps and start cells are used at every evaluation, so the curve is comparable over
    training. "Best" is the highest median coverage, wall hits breaking ties.
    """

    def __init__(self, config: ExperimentConfig, run: RunDir) -> None:
        self.config, self.run = config, run
        self.best = -np.inf

    def __call__(self, model: DoubleDQN) -> None:
        cfg = self.config.eval
        summary = summarize(
            run_episodes(model_policy(model), self.config.env, cfg.episodes, cfg.seed)
        )
        model.logger.record("eval/coverage_median", summary["coverage_median"])
        model.logger.record("eval/coverage_mean", summary["coverage_mean"])
        model.logger.record("eval/wall_hits_mean", summary["wall_hits_mean"])
        model.logger.dump(model.num_timesteps)
        score = summary["coverage_median"] - 1e-3 * summary["wall_hits_mean"]
        if score > self.best:
            self.best = score
            save_model(model, self.run.best_model)


def save_model(model: DoubleDQN, path: Path) -> None:
    """Atomically save an SB3 model zip."""

    def write(tmp: Path) -> None:
        with tmp.open("wb") as f:
            model.save(f)

    atomic_write(path, write)


def save_checkpoint(model: DoubleDQN, run: RunDir, state: dict[str, Any] | None = None) -> None:
    """Atomically write the latest checkpoint: model, replay buffer and training state.

    Each file is replaced only once its new version is complete, so the last good checkpoint
    survives a crash at any point.
    """
    save_model(model, run.checkpoints / "model.zip")

    def write_buffer(tmp: Path) -> None:
        with tmp.open("wb") as f:
            model.save_replay_buffer(f)

    atomic_write(run.checkpoints / "replay_buffer.pkl", write_buffer)
    info = {"num_timesteps": int(model.num_timesteps), **(state or {})}
    atomic_write_text(run.checkpoints / "state.json", json.dumps(info, indent=2))


def train(config: ExperimentConfig, run: RunDir, progress_bar: bool = True) -> DoubleDQN:
    """Train ``config`` into ``run`` (a freshly created run directory)."""
    configure_torch(config.algo.threads)
    set_random_seed(config.seed)
    atomic_write_text(run.config, config.to_yaml())

    venv = make_vec_env(config.env, config.vec.copies, config.vec.num_cpus, seed=config.seed)
    try:
        model = build_model(config, venv)
        model.action_space.seed(config.seed)
        model.set_logger(configure(str(run.tb), ["tensorboard", "csv"]))
        evaluator = Evaluator(config, run)
        next_episode = 0
        for index, phase in enumerate(config.phases):
            apply_phase(model, phase)
            callbacks, episode_log = phase_callbacks(config, phase, run, evaluator, next_episode)
            model.learn(
                total_timesteps=phase.timesteps,
                callback=CallbackList(callbacks),
                log_interval=config.n_slots,  # dump logs once per round of finished episodes
                reset_num_timesteps=False,
                progress_bar=progress_bar,
            )
            next_episode = episode_log.next_episode
            save_checkpoint(
                model, run, {"phase": index, "phase_done": True, "next_episode": next_episode}
            )
        save_model(model, run.model)
        return model
    finally:
        venv.close()
