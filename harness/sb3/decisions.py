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

Storage: completed transitions arrive per slot at different steps, so the buffer
(:class:`~harness.sb3.replay.Replay` with ``per_decision=True``, its sampler uniform or
prioritized) stores them in one flat column (SB3's ``[buffer_size, 1]`` layout, ``n_envs=1``,
same capacity), in the order they complete, and takes SB3's ``add`` of ``n_envs`` slots through
:class:`Decisions`, whose pending transitions are pickled with the buffer (a resumed run
continues them). Nothing here knows the env: only the mask key.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from gymnasium import spaces

from harness.sb3.policies import ACTION_MASK_KEY

__all__ = ["EXPERT_KEY", "Decisions", "LabelledSamples"]


#: Info key of a slot's expert label for the decision of its step (module docstring).
EXPERT_KEY = "expert_action"


class Decisions:
    """The pending transition of each slot (module docstring): the stage in front of a
    per-decision buffer's storage.

    Args:
        slots: VecEnv slots (each with its own pending transition).
        observation_space: A ``Dict`` space with an :data:`ACTION_MASK_KEY` entry.
        action_space: A ``Discrete`` space.
        action_dim: The stored action's width.
        gamma: Discount factor of the merged rewards (the algorithm's).
        labels: Keep each decision's expert label (:data:`EXPERT_KEY`).

    Raises:
        ValueError: for an observation without an action mask.
    """

    #: The attributes a buffer pickles.
    FIELDS = ("slots", "gamma", "labels", "pending_obs", "pending_action", "pending_return")
    FIELDS += ("pending_steps", "pending_expert")

    def __init__(
        self,
        slots: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        action_dim: int,
        gamma: float,
        labels: bool,
    ) -> None:
        masked = isinstance(observation_space, spaces.Dict) and (
            ACTION_MASK_KEY in observation_space.spaces
        )
        if not masked:
            raise ValueError(
                f"a per-decision buffer reads the observation's {ACTION_MASK_KEY!r} (a Dict "
                f"observation with that key), got {observation_space}"
            )
        assert isinstance(observation_space, spaces.Dict)
        self.slots = int(slots)
        self.gamma = float(gamma)
        self.labels = bool(labels)
        # Each slot's decision's observation and action, the discounted rewards so far, the
        # steps taken (0: none pending) and its label (-1: none).
        self.pending_obs = {
            key: np.zeros((self.slots, *space.shape), dtype=space.dtype)
            for key, space in observation_space.spaces.items()
        }
        self.pending_action = np.zeros((self.slots, action_dim), dtype=action_space.dtype)
        self.pending_return = np.zeros(self.slots, dtype=np.float64)
        self.pending_steps = np.zeros(self.slots, dtype=np.int64)
        self.pending_expert = np.full(self.slots, -1, dtype=np.int64)

    def step(
        self,
        obs: dict[str, np.ndarray],
        next_obs: dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
        n_actions: int,
        store: Callable[..., None],
    ) -> None:
        """Take one step of every slot (SB3's ``add`` arguments, ``slots`` rows each) and pass
        each transition it completes to ``store`` (one row: observation, next observation,
        action, reward, done, info, then ``gamma ** tau`` and the label), in slot order."""
        steps = self.pending_steps
        new = steps == 0  # a slot without a pending transition decides at obs
        if new.any():
            for key, pending in self.pending_obs.items():
                pending[new] = np.asarray(obs[key]).reshape(pending.shape)[new]
            self.pending_action[new] = np.asarray(action).reshape(self.pending_action.shape)[new]
            self.pending_return[new] = 0.0
            if self.labels:
                for j in np.flatnonzero(new).tolist():
                    label = int(infos[j].get(EXPERT_KEY, -1))
                    # Checked here, where it enters: the margin loss then reads no device
                    # for a range check (harness.sb3.losses.margin_term).
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
            store(
                {key: pending[j : j + 1] for key, pending in self.pending_obs.items()},
                {key: np.asarray(value)[j : j + 1] for key, value in next_obs.items()},
                self.pending_action[j : j + 1],
                np.array([self.pending_return[j]], dtype=np.float32),
                np.array([bool(done[j])], dtype=np.float32),
                [infos[j]],
                self.gamma ** int(self.pending_steps[j]),
                self.pending_expert[j],
            )
        steps[complete] = 0

    def reset(self) -> None:
        """Drop the pending transitions."""
        self.pending_steps[:] = 0
        self.pending_return[:] = 0.0
        self.pending_expert[:] = -1


class LabelledSamples:
    """A batch of samples (SB3's, or the prioritized buffer's) with each one's expert label:
    every field of ``samples`` reads through, and ``experts`` is ``(batch, 1)`` int64, -1 where
    no label was given."""

    def __init__(self, samples: Any, experts: Any) -> None:
        self.samples = samples
        self.experts = experts

    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["samples"], name)
