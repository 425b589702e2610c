"""How :class:`~harness.sb3.dqn.DoubleDQN` acts: ε-greedy with a coin per observation (per VecEnv
slot, not SB3's one coin per batch), and the greedy and random choices among the actions an
observation's mask allows (:func:`~harness.sb3.losses.allowed_actions`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

from harness.sb3.losses import allowed_actions, masked
from harness.sb3.policies import ACTION_MASK_KEY

__all__ = [
    "check_action_mask_space",
    "epsilon_greedy",
    "masked_argmax",
    "masked_greedy",
    "masked_random",
]


def epsilon_greedy(
    action: np.ndarray, rate: float, n_actions: int, allowed: np.ndarray | None
) -> np.ndarray:
    """The greedy ``action`` (any shape) with each entry replaced, with probability ``rate`` on
    its own, by a uniformly random action: among all ``n_actions``, or among the ``allowed``
    ones (``(batch, n_actions)`` bool) when given.

    The global ``np.random`` draws (what SB3 seeds in ``set_random_seed`` and uses itself), so
    runs stay reproducible with ``seed=``: first one coin per entry, then the random actions.
    Random actions are in ``[0, n)`` like the greedy argmax (SB3's Q-network ignores
    ``Discrete.start``).
    """
    greedy = np.asarray(action)
    flat = greedy.reshape(-1)
    explore = np.random.random_sample(flat.shape[0]) < rate  # noqa: NPY002
    if allowed is None:
        random_actions = np.random.randint(n_actions, size=flat.shape[0])  # noqa: NPY002
    else:  # uniform over the allowed actions: the largest of iid keys, the others below all
        keys = np.random.random_sample((flat.shape[0], n_actions))  # noqa: NPY002
        random_actions = np.where(allowed, keys, -1.0).argmax(axis=1)
    mixed = np.where(explore, random_actions, flat).astype(flat.dtype, copy=False)
    return mixed.reshape(greedy.shape)


def masked_greedy(
    policy: Any, q_net: Any, observation: dict[str, np.ndarray], n_actions: int
) -> tuple[np.ndarray, np.ndarray]:
    """The greedy action among the actions the observation's mask allows, shaped as SB3's
    ``policy.predict`` shapes it, and the ``(batch, n_actions)`` allowed mask."""
    policy.set_training_mode(False)
    obs, vectorized = policy.obs_to_tensor(observation)
    with th.no_grad():
        allowed = allowed_actions(obs, n_actions)
        assert isinstance(allowed, th.Tensor)
        action = masked_argmax(q_net, obs, allowed).cpu().numpy()
    action = action if vectorized else action.squeeze(axis=0)
    return action, allowed.cpu().numpy()


def masked_argmax(q_net: Any, obs: dict[str, th.Tensor], allowed: th.Tensor) -> th.Tensor:
    """The best allowed action of each row, the network run on the rows with a choice only: a
    row whose mask allows one action (a forced step: a held goal) takes it without a pass of
    the network (the same action: the masked argmax of a row with one allowed action is that
    action)."""
    deciding = allowed.sum(dim=1) > 1
    n_deciding = int(deciding.sum())  # one read of the device for both cases below
    if n_deciding == deciding.numel():
        return masked(q_net(obs), allowed).argmax(dim=1)
    action = allowed.to(th.int8).argmax(dim=1)  # a forced row's one action
    if n_deciding > 0:
        rows = {key: value[deciding] for key, value in obs.items()}
        action[deciding] = masked(q_net(rows), allowed[deciding]).argmax(dim=1)
    return action


def masked_random(action_space: spaces.Discrete, allowed: np.ndarray) -> np.ndarray:
    """A uniformly random allowed action per row of ``allowed``, from the action space's own
    generator (as SB3's random actions before ``learning_starts``)."""
    return np.array([action_space.sample(mask=row.astype(np.int8)) for row in allowed])


def check_action_mask_space(observation_space: spaces.Space, action_space: Any) -> None:
    """Refuse an :data:`ACTION_MASK_KEY` entry of a ``Dict`` observation space that is not a
    ``MultiBinary(n)`` or a ``Box`` of shape ``(n,)`` for ``n`` actions; nothing without one."""
    if not isinstance(observation_space, spaces.Dict):
        return
    mask_space = observation_space.spaces.get(ACTION_MASK_KEY)
    if mask_space is None:
        return
    n_actions = int(action_space.n)
    shape_ok = mask_space.shape == (n_actions,)
    if not (isinstance(mask_space, (spaces.MultiBinary, spaces.Box)) and shape_ok):
        raise ValueError(
            f"the {ACTION_MASK_KEY!r} observation must be a MultiBinary({n_actions}) or a Box "
            f"of shape ({n_actions},), one entry per action, got {mask_space}"
        )
