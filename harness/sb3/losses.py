"""The parts of :class:`~harness.sb3.dqn.DoubleDQN`'s loss, composed by its ``train``: the TD
target (double-Q or max, with per-sample ``discounts``, over the actions the next observation
allows), the per-sample Huber loss, DQfD's margin towards an expert's action or the samples' own
labels, and the IS-weighted (per agent set) mean. Each is a function of the networks and the
batch; the model's hooks (``_td_target``, ``_loss_terms``, ``_weighted_loss``) call them.

Also what the update keeps of each step (:class:`StepStats`, read once per training call) and
the action masks' reading (:func:`allowed_actions`), which exploration shares.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.type_aliases import PyTorchObs
from torch.nn import functional as F

from harness.sb3.policies import ACTION_MASK_KEY
from harness.sb3.targets import double_q_target, large_margin_loss, max_q_target

__all__ = [
    "LossOptions",
    "NonFiniteLossError",
    "StepStats",
    "allowed_actions",
    "check_finite",
    "margin_term",
    "masked",
    "per_agent_loss",
    "td_loss",
    "td_target",
    "weighted_loss",
]


@dataclass(frozen=True)
class LossOptions:
    """What :class:`~harness.sb3.dqn.DoubleDQN` adds to SB3's loss.

    Attributes:
        double_q: Bootstrap with ``Q_target(s', argmax_a Q_online(s', a))`` (else SB3's
            ``max_a Q_target(s', a)``).
        expert_action: The action DQfD's large-margin loss favours; ``None``: no such loss
            (unless the samples carry their own ``experts`` labels).
        margin: The lead over every other action's value the margin loss asks of the expert's.
        margin_weight: The margin loss's weight beside the TD loss (DQfD's lambda_2).
    """

    double_q: bool = True
    expert_action: int | None = None
    margin: float = 0.8
    margin_weight: float = 1.0

    def check(self, action_space: Any) -> LossOptions:
        """These options, checked against a ``Discrete`` ``action_space``."""
        if self.expert_action is not None and not 0 <= self.expert_action < action_space.n:
            raise ValueError(
                f"expert_action {self.expert_action} is not an action of {action_space}"
            )
        if self.margin < 0 or self.margin_weight < 0:
            raise ValueError(
                f"margin and margin_weight must be >= 0, got {self.margin} and {self.margin_weight}"
            )
        return replace(self, margin=float(self.margin), margin_weight=float(self.margin_weight))


class NonFiniteLossError(FloatingPointError):
    """The training loss became NaN or infinite; the weights are no longer trustworthy."""


def check_finite(what: str, values: np.ndarray, num_timesteps: int, first_update: int) -> None:
    """Raise :class:`NonFiniteLossError` naming the first entry of ``values`` (one per update,
    from ``first_update``; or a step's TD errors, at ``first_update``) that is not finite."""
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        update = first_update + (int(bad[0]) if what == "loss" else 0)
        raise NonFiniteLossError(
            f"the {what} became {float(values[bad[0]])} at step {num_timesteps} (update {update})"
        )


def allowed_actions(
    obs: PyTorchObs | np.ndarray | dict[str, np.ndarray], n_actions: int
) -> th.Tensor | np.ndarray | None:
    """The actions the observations' :data:`ACTION_MASK_KEY` entry allows, ``(batch, n_actions)``
    bool (a torch tensor for tensors, a numpy array for arrays), or ``None`` when the
    observations carry no mask.

    Any nonzero entry counts as allowed. A row that allows nothing allows every action instead:
    the terminal observation of a PettingZoo env often has an all-zero mask, and a choice among
    no actions has no value (its bootstrap would be ``-inf``, and ``0 * -inf`` a NaN target).
    """
    if not isinstance(obs, dict) or ACTION_MASK_KEY not in obs:
        return None
    mask = obs[ACTION_MASK_KEY]
    if isinstance(mask, th.Tensor):
        allowed = mask.reshape(-1, n_actions) != 0
        return allowed | ~allowed.any(dim=1, keepdim=True)
    allowed = np.asarray(mask).reshape(-1, n_actions) != 0
    return allowed | ~allowed.any(axis=1, keepdims=True)


def masked(q: th.Tensor, allowed: th.Tensor | None) -> th.Tensor:
    """``q`` with the actions ``allowed`` leaves out at ``-inf``, so that argmax skips them."""
    return q if allowed is None else q.masked_fill(~allowed, float("-inf"))


def _to_host(tensor: th.Tensor) -> np.ndarray:
    """``tensor``'s values as a numpy array: the one way the update reads the device (a host
    synchronisation on an accelerator), so that the reads can be counted."""
    return tensor.detach().cpu().numpy()


class StepStats:
    """Scalars of each gradient step of a training call (the loss, the mean TD error, ...),
    kept on the device where they were computed until :meth:`read` brings all of them to the
    host in one transfer: a read per step would make the host wait for every step's kernels."""

    def __init__(self) -> None:
        self._values: dict[str, list[th.Tensor]] = {}

    def add(self, name: str, value: th.Tensor) -> None:
        """Record one step's ``value`` (a one-element tensor) under ``name``; reads nothing."""
        self._values.setdefault(name, []).append(value.detach().reshape(()))

    def extend(self, values: dict[str, th.Tensor]) -> None:
        """:meth:`add` each of ``values`` (one step's, by name)."""
        for name, value in values.items():
            self.add(name, value)

    def latest(self) -> dict[str, th.Tensor]:
        """Every name's last value, in the order the names were first added."""
        return {name: values[-1] for name, values in self._values.items()}

    def read(self) -> dict[str, np.ndarray]:
        """Every name's values in the order added, float64, in one transfer; then forgets them.

        Empty (and no transfer) when nothing was added.
        """
        if not self._values:
            return {}
        names = list(self._values)
        # One concatenation (promoted to a common dtype) and one copy to the host.
        host = _to_host(th.cat([th.stack(self._values[name]) for name in names]))
        out: dict[str, np.ndarray] = {}
        start = 0
        for name in names:
            n = len(self._values[name])
            out[name] = host[start : start + n].astype(np.float64)
            start += n
        self._values.clear()
        return out


def td_target(
    q_net: th.nn.Module,
    q_net_target: th.nn.Module,
    replay_data: Any,
    gamma: float,
    double_q: bool,
    n_actions: int,
) -> th.Tensor:
    """The TD target of each sample, ``(batch, 1)``, without gradient: Double-Q's
    (:func:`~harness.sb3.targets.double_q_target`) or the plain max
    (:func:`~harness.sb3.targets.max_q_target`), over the actions the next observation allows,
    with the samples' own ``discounts`` (n-step or per-decision ``gamma**k``) when they carry
    them, else ``gamma``."""
    discounts = getattr(replay_data, "discounts", None)
    if discounts is None:
        discounts = gamma
    next_obs = replay_data.next_observations
    with th.no_grad():
        next_q_target = q_net_target(next_obs)
        allowed = allowed_actions(next_obs, n_actions)
        blocked = None if allowed is None else ~allowed
        rewards, dones = replay_data.rewards, replay_data.dones
        if double_q:
            next_q_online = q_net(next_obs)
            return double_q_target(rewards, dones, discounts, next_q_online, next_q_target, blocked)
        return max_q_target(rewards, dones, discounts, next_q_target, blocked)


def td_loss(current_q: th.Tensor, target_q: th.Tensor) -> th.Tensor:
    """The Huber loss of each sample's TD error, ``(batch, 1)``: per sample, so that the IS
    weights can scale each term."""
    return F.smooth_l1_loss(current_q, target_q, reduction="none")


def margin_term(
    replay_data: Any,
    q_values: th.Tensor,
    options: LossOptions,
    n_actions: int,
    stats: StepStats | None = None,
) -> th.Tensor:
    """DQfD's large-margin term towards the expert's action, times ``margin_weight``,
    ``(batch, 1)`` (:func:`~harness.sb3.targets.large_margin_loss`): towards each sample's own
    label when the samples carry ``experts`` (a teacher's labels, :mod:`harness.sb3.decisions`;
    0 on the samples labelled -1, none), else towards ``options.expert_action``. Records the
    unweighted margin loss and the expert agreement of the greedy actions (over the labelled
    samples) as ``margin_loss`` and ``expert_agreement``."""
    experts = getattr(replay_data, "experts", None)
    if experts is not None:
        labelled = experts >= 0
        expert: th.Tensor | int = th.where(labelled, experts, th.zeros_like(experts))
        # The labels' range was checked as they entered the buffer: no device read here.
        margin_loss = large_margin_loss(q_values, expert, options.margin, check_range=False)
        margin_loss = margin_loss * labelled
    else:
        assert options.expert_action is not None
        labelled, expert = None, options.expert_action
        margin_loss = large_margin_loss(q_values, expert, options.margin)
    term = options.margin_weight * margin_loss
    if stats is not None:
        # The agreement of the action the policy would take: the greedy one among the allowed
        # actions when the observations carry a mask.
        allowed_now = allowed_actions(replay_data.observations, n_actions)
        greedy = masked(q_values, allowed_now).argmax(dim=1, keepdim=True)  # type: ignore[arg-type]
        agree = (greedy == expert).float()
        if labelled is None:
            stats.add("margin_loss", margin_loss.mean())
            stats.add("expert_agreement", agree.mean())
        else:  # over the labelled samples (none labelled: 0)
            count = labelled.sum().clamp(min=1)
            stats.add("margin_loss", margin_loss.sum() / count)
            stats.add("expert_agreement", (agree * labelled).sum() / count)
    return term


def per_agent_loss(
    per_sample_loss: th.Tensor,
    agent: th.Tensor,
    n_agents: int,
    weights: th.Tensor | None = None,
) -> th.Tensor:
    """The loss of N independent learners in one batch: the sum over agents of each agent's
    (IS-weighted) mean loss over its own samples.

    Why weighting rather than stratified sampling: the replay buffer (and PER's sum tree) stays
    one, unchanged, over all slots. Conditional on being agent ``i``'s, a prioritized sample is
    drawn with probability ``p_j / sum_i(p)``, exactly what agent ``i``'s own prioritized buffer
    would draw; only the number of agent ``i``'s samples in a batch varies (``N * batch_size``
    are drawn: ``batch_size`` per agent in expectation with uniform replay, as every slot holds
    as many transitions; under PER in proportion to each agent's share of the priorities).
    Dividing each agent's terms by its own count gives each set the gradient of a batch mean
    over its own transitions, as a separate learner with its own batch would get; a plain mean
    over the whole batch would instead scale each set's step by its share of the batch.
    Gradients reach a set only from its own samples (:class:`PerAgentQNetwork` routes them), and
    the IS weights are normalised by each agent's own largest weight in the batch (a separate
    buffer's normalisation), so no agent's transitions change another's step.

    Args:
        per_sample_loss: ``(batch, 1)`` or ``(batch,)`` losses.
        agent: ``(batch,)`` agent index of each sample.
        n_agents: Number of agents (parameter sets).
        weights: IS weights ``(batch, 1)`` from a prioritized buffer, or ``None``.

    Returns:
        The scalar loss to minimise.
    """
    losses = per_sample_loss.reshape(-1)
    if weights is not None:
        w = weights.reshape(-1).to(losses.dtype)
        largest = th.zeros(n_agents, dtype=w.dtype, device=w.device).scatter_reduce(
            0, agent, w, reduce="amax", include_self=False
        )
        losses = losses * (w / largest[agent])
    # Counted by a scatter, not th.bincount: on CUDA bincount reads the indices' range back
    # to the host (a synchronisation per gradient step). The counts are the same integers.
    ones = th.ones_like(losses)
    counts = th.zeros(n_agents, dtype=losses.dtype, device=losses.device)
    counts = counts.index_add(0, agent, ones).clamp(min=1)
    return (losses / counts[agent]).sum()


def weighted_loss(
    per_sample_loss: th.Tensor, replay_data: Any, q_net: Any, agent_sets: int
) -> th.Tensor:
    """The scalar loss to minimise from the per-sample losses: the mean, each sample scaled by
    its IS weight when the batch carries ``weights`` (prioritized replay); with per-agent sets
    (``agent_sets`` > 1, ``q_net`` a per-agent network) the sum of each set's mean over its own
    samples (:func:`per_agent_loss`)."""
    weights = getattr(replay_data, "weights", None)
    if agent_sets > 1:
        agent = q_net.agents_of(replay_data.observations)
        return per_agent_loss(per_sample_loss, agent, agent_sets, weights)
    weighted = per_sample_loss if weights is None else weights * per_sample_loss
    return weighted.mean()
