"""Double DQN on SB3's DQN, at its hooks, composed of the modules beside it: the loss's parts
(``losses``), exploration, replay, the recorded gradient step (``graphs``) and ``saving``."""

from __future__ import annotations

import io
from dataclasses import astuple
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from stable_baselines3.common.utils import ConstantSchedule
from stable_baselines3.dqn import DQN
from stable_baselines3.dqn.policies import DQNPolicy

from harness.sb3 import losses
from harness.sb3.exploration import (
    check_action_mask_space,
    epsilon_greedy,
    masked_greedy,
    masked_random,
)
from harness.sb3.graphs import GraphedStep, record_step, side_stream
from harness.sb3.losses import (
    LossOptions,
    NonFiniteLossError,
    StepStats,
    allowed_actions,
    per_agent_loss,
)
from harness.sb3.policies import (
    ACTION_MASK_KEY,
    PerAgentQNetwork,
    harness_policy_aliases,
    resolve_optimizer_class,
)
from harness.sb3.replay import graphable, priorities_on_device, prioritized
from harness.sb3.saving import (
    FORMAT_KEY,
    MODEL_FORMAT,
    OldModelError,
    check_model_format,
    saved_model_format,
    target_as_online,
)

__all__ = [
    "ACTION_MASK_KEY",
    "MODEL_FORMAT",
    "DoubleDQN",
    "LossOptions",
    "NonFiniteLossError",
    "OldModelError",
    "StepStats",
    "allowed_actions",
    "per_agent_loss",
    "resolve_optimizer_class",
    "saved_model_format",
    "target_as_online",
]


class DoubleDQN(DQN):
    """SB3 DQN with Double-Q targets, prioritized replay and per-slot epsilon-greedy.

    Every argument but ``loss`` and ``cuda_graph`` is SB3's ``DQN``'s (``**kwargs``). Beside it:
    the loss's parts (:meth:`train`, :mod:`harness.sb3.losses`): double-Q target, the samples'
    own ``discounts``, IS weights, DQfD's margin, per agent set; invalid-action masking with a
    ``Dict`` observation's :data:`ACTION_MASK_KEY` entry (greedy, ε-random and pre-learning
    actions and the target's max over the allowed actions); one exploration coin per VecEnv
    slot (:meth:`predict`); RMSprop by default (``policy_kwargs["optimizer_class"]`` may name a
    ``torch.optim`` class); the harness's policy names (:data:`harness.sb3.registry.POLICIES`);
    ``beta_schedule`` written to a prioritized buffer's ``beta`` at every env step (both
    schedules rebuilt by ``_setup_model``, not saved); phases (:meth:`start_phase`).

    Args:
        policy: Policy class or alias (``"MlpPolicy"``, ``"DuelingMlpPolicy"``, ...).
        env: Environment (a VecEnv with several slots is fine).
        loss: What the loss adds to SB3's (default: the double-Q target, no margin).
        cuda_graph: On CUDA with a buffer that samples there, record a gradient step once as a
            CUDA graph and launch it for every later step (:mod:`harness.sb3.graphs`): the same
            results, faster; one that cannot be recorded warns once and trains without.
        **kwargs: SB3 ``DQN``'s arguments (``_init_setup_model``: ``load``'s).
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = harness_policy_aliases(DQN)
    #: Gradient steps taken without a graph before one is recorded, in each process (the first
    #: steps set up the optimizer's state and cuBLAS's work spaces, not to be done in a recording).
    GRAPH_WARMUP_STEPS: ClassVar[int] = 3
    beta_schedule: Schedule
    #: The current phase's first transition and length (``None``: SB3's progress, no phases).
    phase_start: int = 0
    phase_timesteps: int | None = None

    def __init__(
        self,
        policy: str | type[DQNPolicy],
        env: GymEnv | str,
        loss: LossOptions | None = None,
        cuda_graph: bool = True,
        _init_setup_model: bool = True,
        **kwargs: Any,
    ) -> None:
        # A copy (the caller's stays), with the resolved class (what gets saved).
        policy_kwargs = dict(kwargs.pop("policy_kwargs", None) or {})
        policy_kwargs["optimizer_class"] = resolve_optimizer_class(
            policy_kwargs.get("optimizer_class", th.optim.RMSprop)
        )
        kwargs.update(policy_kwargs=policy_kwargs, _init_setup_model=False)
        super().__init__(policy, env, **kwargs)
        # Saved one by one (the data keys of every saved model): double_q, expert_action, ...
        loss = (loss or LossOptions()).check(getattr(self, "action_space", None))
        self.double_q, self.expert_action, self.margin, self.margin_weight = astuple(loss)
        self.cuda_graph = bool(cuda_graph)
        # The recorded step, a failed recording and the steps taken in this process (not saved).
        self._graph: GraphedStep | None = None
        self._graph_failed = False
        self._steps_here = 0
        setattr(self, FORMAT_KEY, MODEL_FORMAT)
        if _init_setup_model:
            self._setup_model()

    @property
    def loss_options(self) -> LossOptions:
        """The loss's options (as taken, or as the saved model held them)."""
        return LossOptions(self.double_q, self.expert_action, self.margin, self.margin_weight)

    @property
    def prioritized(self) -> bool:
        """Whether the replay buffer samples by priority (and has ``beta`` and ``alpha``)."""
        return prioritized(self.replay_buffer)

    @property
    def masked(self) -> bool:
        """Whether the observations carry an action mask (:data:`ACTION_MASK_KEY`)."""
        space = self.observation_space
        return isinstance(space, spaces.Dict) and ACTION_MASK_KEY in space.spaces

    @property
    def agent_sets(self) -> int:
        """Parameter sets of the Q-network: ``n_agents`` for a per-agent policy, else 1."""
        return self.q_net.n_agents if isinstance(self.q_net, PerAgentQNetwork) else 1

    @property
    def _n_actions(self) -> int:
        return int(self.action_space.n)  # type: ignore[attr-defined]

    def _setup_model(self) -> None:
        check_action_mask_space(self.observation_space, self.action_space)
        super()._setup_model()
        initial_beta = self.replay_buffer.beta if self.prioritized else 0.0  # type: ignore[union-attr]
        self.beta_schedule = ConstantSchedule(initial_beta)

    def start_phase(self, timesteps: int, start: int | None = None) -> None:
        """Make ``progress_remaining`` run from 1 to 0 over a phase of ``timesteps`` transitions
        that started at ``num_timesteps`` ``start`` (default now; a resumed run: the original)."""
        if timesteps <= 0:
            raise ValueError(f"a phase needs timesteps > 0, got {timesteps}")
        self.phase_timesteps = int(timesteps)
        self.phase_start = int(self.num_timesteps if start is None else start)
        self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)

    def at_round_boundary(self) -> bool:
        """Whether the phase so far is whole rounds of ``train_freq`` env steps (a checkpoint there
        resumes on the uninterrupted run's rounds: the same training calls)."""
        steps = (self.num_timesteps - self.phase_start) // self.n_envs
        return steps % self.train_freq.frequency == 0

    def _update_current_progress_remaining(self, num_timesteps: int, total_timesteps: int) -> None:
        if self.phase_timesteps is None:
            super()._update_current_progress_remaining(num_timesteps, total_timesteps)
            return
        done = num_timesteps - self.phase_start
        self._current_progress_remaining = 1.0 - done / self.phase_timesteps

    def _on_step(self) -> None:
        super()._on_step()
        if self.prioritized:
            self.replay_buffer.beta = self.beta_schedule(self._current_progress_remaining)  # type: ignore[union-attr]

    @classmethod
    def load(cls, path: str | Path | io.BufferedIOBase, *args: Any, **kwargs: Any) -> DoubleDQN:  # type: ignore[override]
        """SB3's ``load``, of a model in today's :data:`MODEL_FORMAT` only (else
        :class:`OldModelError`, one line)."""
        check_model_format(path)
        return super().load(path, *args, **kwargs)  # type: ignore[return-value]

    def _excluded_save_params(self) -> list[str]:
        # The schedules are rebuilt on load (saved, they would pickle a callback's closure).
        excluded = ["exploration_schedule", "beta_schedule", "_graph", "_graph_failed"]
        return [*super()._excluded_save_params(), *excluded, "_steps_here"]

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """SB3's DQN update, the loss from the hooks :meth:`_td_target`, :meth:`_loss_terms` and
        :meth:`_weighted_loss`; statistics read once per call (:class:`StepStats`), then checked
        (:class:`NonFiniteLossError` names the first bad update). With N agent sets a step
        samples ``N * batch_size`` transitions (:func:`per_agent_loss`)."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        batch = batch_size * self.agent_sets
        stats = StepStats()
        graphs = self._graphs_wanted()
        graph = self._graphed_step(batch) if graphs else None  # one look per call
        for step in range(gradient_steps):
            if graph is not None:  # the sample, the loss, the gradients, the priorities
                stats.extend(graph.replay())
                self.policy.optimizer.step()
                continue
            with side_stream(graphs):  # the steps before a recording, as torch asks
                replay_data = self.replay_buffer.sample(batch, env=self._vec_normalize_env)  # type: ignore[union-attr]
                loss, abs_td = self._gradient_step(replay_data, stats)
                self._record_step(replay_data, loss, abs_td, stats)
            self._update_host_priorities(replay_data, abs_td, stats, step)

        values = stats.read()  # the call's one read of the device
        self._check_finite(values)
        self._n_updates += gradient_steps
        self._steps_here += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", np.mean(self._reported_losses(values)))
        self.logger.record("train/mean_td_error", np.mean(values.get("td_error", [])))
        if "margin_loss" in values:
            self.logger.record("train/margin_loss", np.mean(values["margin_loss"]))
            self.logger.record("train/expert_agreement", np.mean(values["expert_agreement"]))
        if self.prioritized:
            self.logger.record("train/beta", self.replay_buffer.beta)  # type: ignore[union-attr]
            self.logger.record("train/alpha", self.replay_buffer.alpha)  # type: ignore[union-attr]

    def _record_step(self, replay_data: Any, loss: Any, abs_td: Any, stats: StepStats) -> None:
        """Record a step's loss and mean TD error; priorities on the device are written there
        (reading nothing: a non-finite one makes the loss so, which the call's read reports)."""
        stats.add("loss", loss)
        stats.add("td_error", abs_td.mean())
        if priorities_on_device(self.replay_buffer):
            self.replay_buffer.update_priorities(replay_data.indices, abs_td)  # type: ignore[union-attr]

    def _update_host_priorities(
        self, replay_data: Any, abs_td: th.Tensor, stats: StepStats, step: int
    ) -> None:
        """A host prioritized buffer's new priorities (a transfer a step); stops at a bad one."""
        if not self.prioritized or priorities_on_device(self.replay_buffer):
            return
        priorities = losses._to_host(abs_td)
        if not np.isfinite(priorities).all():
            self._check_finite(stats.read())
            losses.check_finite("TD error", priorities, self.num_timesteps, self._n_updates + step)
        self.replay_buffer.update_priorities(replay_data.indices, priorities)  # type: ignore[union-attr]

    def _reported_losses(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """Each step's logged loss: the mean over the agent sets (the minimised one is the sum)."""
        return values.get("loss", np.empty(0)) / self.agent_sets

    def _check_finite(self, values: dict[str, np.ndarray]) -> None:
        """Raise :class:`NonFiniteLossError` naming the first update whose loss is not finite."""
        reported = self._reported_losses(values)
        losses.check_finite("loss", reported, self.num_timesteps, self._n_updates)

    def _gradient_step(
        self, replay_data: Any, stats: StepStats | None = None
    ) -> tuple[th.Tensor, th.Tensor]:
        """One optimizer step on a batch: the minimised loss and the samples' ``|TD error|``."""
        loss, abs_td = self._backward(replay_data, stats)
        self.policy.optimizer.step()
        return loss, abs_td

    def _backward(
        self, replay_data: Any, stats: StepStats | None = None
    ) -> tuple[th.Tensor, th.Tensor]:
        """The loss from the hooks and its clipped gradients (what a CUDA graph records)."""
        target_q = self._td_target(replay_data)
        q_values = self.q_net(replay_data.observations)
        current_q = th.gather(q_values, dim=1, index=replay_data.actions.long())
        terms = self._loss_terms(replay_data, q_values, current_q, target_q, stats)
        per_sample_loss = terms[0]
        for term in terms[1:]:
            per_sample_loss = per_sample_loss + term
        loss = self._weighted_loss(per_sample_loss, replay_data)
        self.policy.optimizer.zero_grad()
        loss.backward()
        if isinstance(self.q_net, PerAgentQNetwork):
            self.q_net.clip_grad_norm_(self.max_grad_norm)
        else:
            th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
        return loss.detach(), (current_q.detach() - target_q).abs().reshape(-1)

    def _td_target(self, replay_data: Any) -> th.Tensor:
        """The TD target of each sample, ``(batch, 1)``, without gradient
        (:func:`~harness.sb3.losses.td_target`)."""
        return losses.td_target(
            self.q_net, self.q_net_target, replay_data, self.gamma, self.double_q, self._n_actions
        )

    def _loss_terms(
        self,
        replay_data: Any,
        q_values: th.Tensor,
        current_q: th.Tensor,
        target_q: th.Tensor,
        stats: StepStats | None = None,
    ) -> list[th.Tensor]:
        """The per-sample loss terms, ``(batch, 1)`` each, summed in this order: the TD loss, then
        DQfD's margin with ``expert_action`` or the samples' ``experts``. A new term: one more."""
        terms = [self._td_loss(current_q, target_q)]
        if self.expert_action is not None or getattr(replay_data, "experts", None) is not None:
            terms.append(self._margin_loss(replay_data, q_values, stats))
        return terms

    def _td_loss(self, current_q: th.Tensor, target_q: th.Tensor) -> th.Tensor:
        """The Huber loss of each sample's TD error (:func:`~harness.sb3.losses.td_loss`)."""
        return losses.td_loss(current_q, target_q)

    def _margin_loss(
        self, replay_data: Any, q_values: th.Tensor, stats: StepStats | None = None
    ) -> th.Tensor:
        """DQfD's weighted margin term (:func:`~harness.sb3.losses.margin_term`)."""
        return losses.margin_term(replay_data, q_values, self.loss_options, self._n_actions, stats)

    def _weighted_loss(self, per_sample_loss: th.Tensor, replay_data: Any) -> th.Tensor:
        """The scalar loss (:func:`~harness.sb3.losses.weighted_loss`)."""
        return losses.weighted_loss(per_sample_loss, replay_data, self.q_net, self.agent_sets)

    def _graphs_wanted(self) -> bool:
        """Whether this call's steps go through a recorded graph (CUDA, a graphable buffer)."""
        return (
            self.cuda_graph
            and not self._graph_failed
            and graphable(self.replay_buffer)
            and self.device.type == "cuda"
        )

    def _graph_key(self, batch: int) -> tuple[Any, ...]:
        """What a recorded step of ``batch`` samples holds fixed (another key: record again)."""
        weights = tuple(p.data_ptr() for p in self.policy.parameters())
        buffer_key = self.replay_buffer.graph_key()  # type: ignore[union-attr]
        loss = astuple(self.loss_options)
        return (batch, buffer_key, self.gamma, *loss, self.max_grad_norm, weights)

    def _graphed_step(self, batch: int) -> GraphedStep | None:
        """The recorded step for ``batch`` samples (recorded now if stale); ``None`` while
        warming up (in each process) or after a failed recording."""
        if self._steps_here < self.GRAPH_WARMUP_STEPS:
            return None
        key = self._graph_key(batch)
        if self._graph is not None and self._graph.key == key:
            return self._graph
        buffer = self.replay_buffer
        self._graph = None  # free the stale graph's memory first

        def step(draws: th.Tensor) -> dict[str, th.Tensor]:
            recorded = StepStats()
            replay_data = buffer.sample_at(draws)  # type: ignore[union-attr]
            loss, abs_td = self._backward(replay_data, recorded)
            self._record_step(replay_data, loss, abs_td, recorded)
            return recorded.latest()

        parameters = list(self.policy.parameters())
        self._graph = record_step(key, step, batch, buffer.draw, parameters, self.device)  # type: ignore[union-attr]
        if self._graph is None:
            self._graph_failed = True
            self.policy.optimizer.zero_grad()
        return self._graph

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """ε-greedy with a coin per observation (:func:`~harness.sb3.exploration.epsilon_greedy`),
        the greedy and random actions among the allowed ones with a mask; returns as SB3's."""
        allowed = None
        if self.masked:
            action, allowed = masked_greedy(self.policy, self.q_net, observation, self._n_actions)  # type: ignore[arg-type]
        else:
            action, state = self.policy.predict(observation, state, episode_start, deterministic)
        if deterministic or self.exploration_rate <= 0.0:
            return action, state
        return epsilon_greedy(action, self.exploration_rate, self._n_actions, allowed), state

    def _sample_action(
        self,
        learning_starts: int,
        action_noise: ActionNoise | None = None,
        n_envs: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """SB3's choice; before ``learning_starts`` among the allowed actions with a mask."""
        allowed = None
        if self.masked and self.num_timesteps < learning_starts:
            assert self._last_obs is not None, "self._last_obs was not set"
            allowed = allowed_actions(self._last_obs, self._n_actions)
        if allowed is None:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        action = masked_random(self.action_space, allowed)  # type: ignore[arg-type]
        return action, action
