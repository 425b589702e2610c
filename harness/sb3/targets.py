"""TD targets for Q-learning, and the imitation margin beside them, as small pure torch functions.

Both functions follow SB3's conventions: ``rewards`` and ``dones`` are ``(batch, 1)`` float
tensors (``(batch,)`` is accepted and reshaped), the next-state Q-values are
``(batch, n_actions)`` and ``discounts`` is either a float ``gamma`` or a ``(batch, 1)`` tensor
(SB3's ``NStepReplayBuffer`` returns per-sample ``gamma ** k``). The result is ``(batch, 1)``.

They carry no autograd state of their own: call them under ``torch.no_grad()`` as the
training loop does.

Both take an optional ``blocked`` mask, ``(batch, n_actions)`` bool: actions the next
observation does not allow (the negation of its invalid-action mask), left out of the max (or the
online argmax). A row that blocks every action falls back to all of them: the terminal
observation of a PettingZoo env often allows nothing, and its bootstrap, multiplied by
``1 - done = 0``, would otherwise be ``0 * -inf``, a NaN target.
"""

from __future__ import annotations

import torch as th

__all__ = ["double_q_target", "large_margin_loss", "max_q_target"]


def _as_column(x: th.Tensor, name: str, batch_size: int) -> th.Tensor:
    """Reshape ``x`` to ``(batch, 1)``.

    A ``(batch,)`` tensor broadcast against a ``(batch, 1)`` one silently becomes
    ``(batch, batch)``, so shapes are normalised and checked here rather than trusted.
    """
    if x.numel() != batch_size:
        raise ValueError(f"{name} has {x.numel()} elements, expected {batch_size} (one per sample)")
    return x.reshape(-1, 1)


def _prepare(
    rewards: th.Tensor,
    dones: th.Tensor,
    discounts: th.Tensor | float,
    next_q: th.Tensor,
) -> tuple[th.Tensor, th.Tensor, th.Tensor | float]:
    if next_q.dim() != 2:
        raise ValueError(
            f"next-state Q-values must be (batch, n_actions), got {tuple(next_q.shape)}"
        )
    batch_size = next_q.shape[0]
    rewards = _as_column(rewards, "rewards", batch_size)
    dones = _as_column(dones, "dones", batch_size)
    if isinstance(discounts, th.Tensor):
        discounts = _as_column(discounts, "discounts", batch_size)
    return rewards, dones, discounts


def _allowed(q: th.Tensor, blocked: th.Tensor | None) -> th.Tensor:
    """``q`` with the blocked actions at ``-inf``, so that max and argmax skip them; a row that
    blocks every action keeps all of them (see the module's docstring)."""
    if blocked is None:
        return q
    if blocked.shape != q.shape:
        raise ValueError(f"blocked must be {tuple(q.shape)}, got {tuple(blocked.shape)}")
    blocked = blocked.bool()
    blocked = blocked & ~blocked.all(dim=1, keepdim=True)
    return q.masked_fill(blocked, float("-inf"))


def max_q_target(
    rewards: th.Tensor,
    dones: th.Tensor,
    discounts: th.Tensor | float,
    next_q_target: th.Tensor,
    blocked: th.Tensor | None = None,
) -> th.Tensor:
    """Plain DQN target, as in SB3: ``r + discount * (1 - done) * max_a Q_target(s', a)``.

    Args:
        rewards: Rewards, ``(batch, 1)``.
        dones: Termination flags (timeouts already removed), ``(batch, 1)``.
        discounts: ``gamma`` or per-sample discounts ``(batch, 1)``.
        next_q_target: Target-network Q-values of the next observations, ``(batch, n_actions)``.
        blocked: Actions the max leaves out, ``(batch, n_actions)`` bool, or ``None``; a row
            that blocks every action leaves out none.

    Returns:
        The TD target, ``(batch, 1)``.
    """
    rewards, dones, discounts = _prepare(rewards, dones, discounts, next_q_target)
    next_q = _allowed(next_q_target, blocked).max(dim=1, keepdim=True).values
    return rewards + discounts * (1.0 - dones) * next_q


def double_q_target(
    rewards: th.Tensor,
    dones: th.Tensor,
    discounts: th.Tensor | float,
    next_q_online: th.Tensor,
    next_q_target: th.Tensor,
    blocked: th.Tensor | None = None,
) -> th.Tensor:
    """Double-DQN target (van Hasselt et al., 2016).

    ``r + discount * (1 - done) * Q_target(s', argmax_a Q_online(s', a))``: the online network
    selects the action and the target network evaluates it, which removes the maximisation
    bias of :func:`max_q_target`.

    Args:
        rewards: Rewards, ``(batch, 1)``.
        dones: Termination flags (timeouts already removed), ``(batch, 1)``.
        discounts: ``gamma`` or per-sample discounts ``(batch, 1)``.
        next_q_online: Online-network Q-values of the next observations, ``(batch, n_actions)``.
        next_q_target: Target-network Q-values of the next observations, ``(batch, n_actions)``.
        blocked: Actions the online argmax leaves out, ``(batch, n_actions)`` bool, or ``None``;
            a row that blocks every action leaves out none.

    Returns:
        The TD target, ``(batch, 1)``.
    """
    if next_q_online.shape != next_q_target.shape:
        raise ValueError(
            "online and target Q-values must have the same shape, got "
            f"{tuple(next_q_online.shape)} and {tuple(next_q_target.shape)}"
        )
    rewards, dones, discounts = _prepare(rewards, dones, discounts, next_q_target)
    greedy_actions = _allowed(next_q_online, blocked).argmax(dim=1, keepdim=True)
    next_q = th.gather(next_q_target, dim=1, index=greedy_actions)
    return rewards + discounts * (1.0 - dones) * next_q


def large_margin_loss(
    q: th.Tensor,
    expert_actions: th.Tensor | int,
    margin: float,
    expert_set: th.Tensor | None = None,
    check_range: bool = True,
) -> th.Tensor:
    """DQfD's supervised large-margin loss (Hester et al., 2018, eq. 2), per sample.

    ``max_a [Q(s, a) + l(a_E, a)] - Q(s, a_E)`` with ``l(a_E, a) = margin`` for ``a != a_E``
    and 0 for the expert's action ``a_E``. It is 0 once the expert's action leads every other
    action by at least ``margin``, and otherwise pulls the expert's value up and the best rival's
    down: the greedy policy then copies the expert unless the TD loss holds another action's
    value higher (how strongly depends on the loss's weight, see docs/training.md).

    With ``expert_set`` (actions that do what the expert's action does), ``l`` is 0 on the whole
    set and the expert's value is the set's best: ``max_a [Q(s, a) + margin * (a not in E)] -
    max_{a in E} Q(s, a)``, so the margin separates different behaviour only.

    Args:
        q: Online Q-values of the observations, ``(batch, n_actions)``.
        expert_actions: The expert's action per sample, ``(batch,)`` or ``(batch, 1)`` integers,
            or one action index for every sample.
        margin: ``l``, the lead asked of the expert's action (>= 0).
        expert_set: ``(batch, n_actions)`` bool, True for the actions equivalent to the expert's
            (the expert's own action is always counted), or ``None``.
        check_range: Refuse a tensor of expert actions outside ``[0, n_actions)``; the check
            reads the tensor's device (a host round trip on a GPU), so a caller whose actions
            were checked where they were made passes ``False``.

    Returns:
        The loss per sample, ``(batch, 1)``, >= 0.
    """
    if q.dim() != 2:
        raise ValueError(f"Q-values must be (batch, n_actions), got {tuple(q.shape)}")
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    batch_size, n_actions = q.shape
    out_of_range = f"expert actions must lie in [0, {n_actions})"
    if isinstance(expert_actions, int):
        # Checked on the host: the training loop's one expert action costs no read of the device.
        if not 0 <= expert_actions < n_actions:
            raise ValueError(out_of_range)
        expert = th.full((batch_size, 1), expert_actions, dtype=th.long, device=q.device)
    else:
        expert = _as_column(expert_actions, "expert_actions", batch_size).long()
        if check_range and bool(((expert < 0) | (expert >= n_actions)).any()):
            raise ValueError(out_of_range)
    in_set = th.zeros_like(q, dtype=th.bool).scatter(1, expert, True)
    if expert_set is not None:
        if expert_set.shape != q.shape:
            raise ValueError(f"expert_set must be {tuple(q.shape)}, got {tuple(expert_set.shape)}")
        in_set = in_set | expert_set.bool()
    bonus = (~in_set).to(q.dtype) * float(margin)
    best_expert = q.masked_fill(~in_set, float("-inf")).max(dim=1, keepdim=True).values
    return (q + bonus).max(dim=1, keepdim=True).values - best_expert
