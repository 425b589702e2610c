"""One transition per decision: replay buffers that merge the steps of states with a single
allowed action into the transition of the decision before them (temporal abstraction, an option
in the sense of Sutton, Precup and Singh 1999, as SMDP Q-learning stores it).

A state whose observation's action mask (:data:`~harness.sb3.policies.ACTION_MASK_KEY`) allows
exactly one action holds no choice: the step is forced, and the value of the decision that led
there is what the forced steps earn until the next choice. For each VecEnv slot the buffer keeps
a *pending* transition: the observation and action of its last decision, the discounted sum of
the rewards since, ``R = sum_t gamma**t * r_t``, and the steps taken, ``tau``. It is stored when
the slot's next observation is a decision again (it allows two actions or more; an all-zero mask
allows every action, as :func:`~harness.sb3.dqn.allowed_actions` reads it) or its episode ends,
with that observation as the next one and the per-sample discount ``gamma**tau`` in the samples'
``discounts`` (which :class:`~harness.sb3.dqn.DoubleDQN` uses in its TD target:
``R + gamma**tau * (1 - done) * Q(s', a')``). A truncated end (``TimeLimit.truncated``) is no
terminal state, as in SB3. Without single-action states every transition is one step, and the
buffer stores what SB3's would (with ``discounts`` ``gamma``).

**Expert labels** (``labels=True``, DAgger's data: a teacher labels the states the policy
visits): the info of a decision's step may hold :data:`EXPERT_KEY`, the action a teacher would
take in the decision's state (set by whoever steps the env, before the step: the training
layer's teacher); the buffer keeps it with the decision's transition (-1: none given) and the
samples carry it as ``experts`` ``(batch, 1)``, which :class:`~harness.sb3.dqn.DoubleDQN`'s
margin term pulls the greedy action towards, on the labelled samples only.

Storage: completed transitions arrive per slot at different steps, so the buffer stores them in
one flat column (SB3's ``[buffer_size, 1]`` layout: the parent buffer is made with
``n_envs=1``, same capacity), in the order they complete, and takes SB3's ``add`` of ``n_envs``
slots. The pending transitions are plain attributes: a pickled buffer (a resumed run) continues
them. Nothing here knows the env: only the mask key.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from harness.sb3.buffers import PrioritizedDictReplayBuffer, check_n_step_returns
from harness.sb3.policies import ACTION_MASK_KEY

__all__ = [
    "EXPERT_KEY",
    "PerDecisionDictReplayBuffer",
    "PerDecisionPrioritizedDictReplayBuffer",
    "per_decision_buffer_class",
]


#: Info key of a slot's expert label for the decision of its step (module docstring).
EXPERT_KEY = "expert_action"


class _PerDecision:
    """The per-decision storage (module docstring), mixed in before an SB3 ``Dict`` buffer.

    Args:
        buffer_size: Most transitions stored (decisions, over all slots).
        observation_space: A ``Dict`` space with an :data:`ACTION_MASK_KEY` entry.
        action_space: A ``Discrete`` space.
        device: Where the samples go.
        n_envs: VecEnv slots (each with its own pending transition).
        optimize_memory_usage: Must be ``False``.
        handle_timeout_termination: As in SB3: a timeout is not a terminal state.
        gamma: Discount factor of the merged rewards (the algorithm's).
        labels: Keep each decision's expert label (:data:`EXPERT_KEY`) and sample it as
            ``experts``.
        **kwargs: The parent buffer's own arguments (the prioritized one's ``alpha``, ``beta``,
            ``eps``; its ``n_steps`` must be 1).

    Raises:
        ValueError: for an observation without an action mask, ``n_steps`` other than 1,
            ``optimize_memory_usage`` or a ``gamma`` outside ``(0, 1]``.
    """

    observations: dict[str, np.ndarray]
    pos: int
    buffer_size: int
    action_dim: int

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: Any = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        gamma: float = 0.99,
        labels: bool = False,
        **kwargs: Any,
    ) -> None:
        masked = isinstance(observation_space, spaces.Dict) and (
            ACTION_MASK_KEY in observation_space.spaces
        )
        if not masked:
            raise ValueError(
                f"a per-decision buffer reads the observation's {ACTION_MASK_KEY!r} (a Dict "
                f"observation with that key), got {observation_space}"
            )
        if optimize_memory_usage:
            raise ValueError("a per-decision buffer does not support optimize_memory_usage=True")
        if kwargs.get("n_steps", 1) != 1:
            raise ValueError(
                f"a per-decision buffer stores one transition per decision; n_steps must be 1, "
                f"got {kwargs['n_steps']!r}"
            )
        check_n_step_returns(1, gamma)
        super().__init__(  # type: ignore[call-arg]
            buffer_size,
            observation_space,
            action_space,
            device=device,
            n_envs=1,  # the flat column of completed transitions (module docstring)
            optimize_memory_usage=False,
            handle_timeout_termination=handle_timeout_termination,
            **kwargs,
        )
        self.gamma = float(gamma)
        self.slots = int(n_envs)
        #: ``gamma ** tau`` of every stored transition, in the storage's layout.
        self.step_discounts = np.zeros((self.buffer_size, 1), dtype=np.float32)
        # The pending transition of each slot: its decision's observation and action, the
        # discounted rewards so far and the steps taken (0: none pending).
        self.pending_obs = {
            key: np.zeros((self.slots, *space.shape), dtype=space.dtype)
            for key, space in observation_space.spaces.items()
        }
        self.pending_action = np.zeros((self.slots, self.action_dim), dtype=action_space.dtype)
        self.pending_return = np.zeros(self.slots, dtype=np.float64)
        self.pending_steps = np.zeros(self.slots, dtype=np.int64)
        self.labels = bool(labels)
        #: Each stored decision's expert label (-1: none), and each pending one's.
        self.expert_actions = np.full((self.buffer_size, 1), -1, dtype=np.int64)
        self.pending_expert = np.full(self.slots, -1, dtype=np.int64)

    def add(
        self,
        obs: dict[str, np.ndarray],
        next_obs: dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Take one step of every slot (SB3's arguments, ``n_envs`` rows each) and store the
        transitions it completes (module docstring), slot by slot in slot order."""
        steps = self.pending_steps
        new = steps == 0  # a slot without a pending transition decides at obs
        if new.any():
            for key, pending in self.pending_obs.items():
                pending[new] = np.asarray(obs[key]).reshape(pending.shape)[new]
            self.pending_action[new] = np.asarray(action).reshape(self.pending_action.shape)[new]
            self.pending_return[new] = 0.0
            if self.labels:
                n_actions = int(self.action_space.n)  # type: ignore[attr-defined]
                for j in np.flatnonzero(new).tolist():
                    label = int(infos[j].get(EXPERT_KEY, -1))
                    # Checked here, where it enters: the margin loss then reads no device
                    # for a range check (DoubleDQN._margin_loss).
                    if not -1 <= label < n_actions:
                        raise ValueError(
                            f"slot {j}'s {EXPERT_KEY} {label} is no action in [0, {n_actions}) "
                            "and not -1 (no label)"
                        )
                    self.pending_expert[j] = label
        self.pending_return += self.gamma**steps * np.asarray(reward, dtype=np.float64).ravel()
        steps += 1
        mask = np.asarray(next_obs[ACTION_MASK_KEY]).reshape(self.slots, -1)
        done = np.asarray(done).reshape(self.slots).astype(bool)
        complete = done | ((mask != 0).sum(axis=1) != 1)
        for j in np.flatnonzero(complete).tolist():
            self._store(j, next_obs, bool(done[j]), infos[j])
        steps[complete] = 0

    def _store(
        self, slot: int, next_obs: dict[str, np.ndarray], done: bool, info: dict[str, Any]
    ) -> None:
        """Write slot ``slot``'s pending transition, ending at its ``next_obs``, through the
        parent buffer's ``add`` (one row of the flat column; priorities and all)."""
        row = self.pos
        super().add(  # type: ignore[misc]
            {key: pending[slot : slot + 1] for key, pending in self.pending_obs.items()},
            {key: np.asarray(value)[slot : slot + 1] for key, value in next_obs.items()},
            self.pending_action[slot : slot + 1],
            np.array([self.pending_return[slot]], dtype=np.float32),
            np.array([done], dtype=np.float32),
            [info],
        )
        self.step_discounts[row, 0] = self.gamma ** int(self.pending_steps[slot])
        self.expert_actions[row, 0] = self.pending_expert[slot]

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> Any:
        """SB3's uniform samples with their ``discounts`` ``gamma ** tau``."""
        samples = super()._get_samples(batch_inds, env)  # type: ignore[misc]
        return self._with_decisions(samples, batch_inds, np.zeros_like(batch_inds))

    def _with_decisions(
        self, samples: Any, rows: np.ndarray, columns: np.ndarray, labelled: bool = True
    ) -> Any:
        """``samples`` with their ``discounts`` ``gamma ** tau`` and, with ``labels`` (and
        ``labelled``), as :class:`LabelledSamples` with their ``experts``."""
        discounts = self.to_torch(self.step_discounts[rows, columns].reshape(-1, 1))  # type: ignore[attr-defined]
        samples = samples._replace(discounts=discounts)
        return self._labelled(samples, rows, columns) if labelled else samples

    def _labelled(self, samples: Any, rows: np.ndarray, columns: np.ndarray) -> Any:
        """``samples`` as :class:`LabelledSamples` with their ``experts`` when the buffer keeps
        labels, else as they are."""
        if not self.labels:
            return samples
        experts = self.to_torch(self.expert_actions[rows, columns].reshape(-1, 1))  # type: ignore[attr-defined]
        return LabelledSamples(samples, experts)

    def reset(self) -> None:
        """Empty the buffer and drop the pending transitions."""
        super().reset()  # type: ignore[misc]
        self.pending_steps[:] = 0
        self.pending_return[:] = 0.0
        self.pending_expert[:] = -1
        self.expert_actions[:] = -1


class LabelledSamples:
    """A batch of samples (SB3's, or the prioritized buffer's) with each one's expert label:
    every field of ``samples`` reads through, and ``experts`` is ``(batch, 1)`` int64, -1 where
    no label was given."""

    def __init__(self, samples: Any, experts: Any) -> None:
        self.samples = samples
        self.experts = experts

    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["samples"], name)


class PerDecisionDictReplayBuffer(_PerDecision, DictReplayBuffer):
    """SB3's uniform ``DictReplayBuffer`` with one transition per decision (module docstring)."""


class PerDecisionPrioritizedDictReplayBuffer(_PerDecision, PrioritizedDictReplayBuffer):
    """:class:`~harness.sb3.buffers.PrioritizedDictReplayBuffer` with one transition per
    decision (module docstring): a decision's transition gets its priority when it is stored."""

    def _get_samples_at(  # type: ignore[override]
        self, batch_inds: np.ndarray, env_indices: np.ndarray, env: VecNormalize | None = None
    ) -> Any:
        """The prioritized samples at given indices, with their ``discounts`` (their labels
        are added by :meth:`sample`, once the parent has added the IS weights)."""
        samples = super()._get_samples_at(batch_inds, env_indices, env)
        return self._with_decisions(samples, batch_inds, env_indices, labelled=False)

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> Any:  # type: ignore[override]
        """The parent's prioritized batch (weights, indices, discounts), with its ``experts``
        when the buffer keeps labels (rows of the one column: the flat indices)."""
        samples = super().sample(batch_size, env)
        return self._labelled(samples, samples.indices, np.zeros_like(samples.indices))


def per_decision_buffer_class(prioritized: bool) -> type[DictReplayBuffer]:
    """The per-decision buffer: prioritized or uniform. Both keep their transitions on the host
    (the device buffer's storage has no per-decision variant; a model on an accelerator still
    samples from these, its batches copied there as SB3's own buffers' are)."""
    return PerDecisionPrioritizedDictReplayBuffer if prioritized else PerDecisionDictReplayBuffer
