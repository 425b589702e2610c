"""Policies for SB3's DQN: the dueling Q-network (Wang et al., 2016,
https://arxiv.org/abs/1511.06581), the team-map CNN policies (plain and dueling) that read the
``"teammap"`` observation's images, and per-agent versions of every policy (one parameter set
per agent in one batched module, ``algo.sharing: per_agent``).

Every policy here builds its features extractor on the observation space less the
:data:`ACTION_MASK_KEY` entry: an invalid-action mask is for choosing among the Q-values
(:class:`harness.sb3.dqn.DoubleDQN`), not an input of the network that computes them.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    FlattenExtractor,
    create_mlp,
)
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.dqn.policies import DQNPolicy, QNetwork
from stable_baselines3.dqn.policies import MultiInputPolicy as SB3MultiInputPolicy
from torch import nn

__all__ = [
    "ACTION_MASK_KEY",
    "AGENT_KEY",
    "AGGREGATORS",
    "SLOTS_KEY",
    "DuelingDQNPolicy",
    "DuelingHead",
    "DuelingQNetwork",
    "DuelingTeamMapPolicy",
    "MultiInputPolicy",
    "PerAgentDuelingMlpPolicy",
    "PerAgentDuelingTeamMapPolicy",
    "PerAgentMlpPolicy",
    "PerAgentQNetwork",
    "PerAgentTeamMapPolicy",
    "SlotQNetwork",
    "SlotTeamMapPolicy",
    "TeamMapExtractor",
    "TeamMapPolicy",
    "harness_policy_aliases",
    "resolve_optimizer_class",
    "without_action_mask",
]

AGGREGATORS = ("mean", "max")

#: The key of a ``Dict`` observation's invalid-action mask (PettingZoo's convention): a
#: ``MultiBinary(n)`` or a ``Box`` of shape ``(n,)``, 1 where an action is allowed, 0 where not.
ACTION_MASK_KEY = "action_mask"

#: Default key of the agent's one-hot index in a ``Dict`` observation, read by the per-agent
#: policies (``agent_key``): the key under which the coverage env adds its agent indication
#: (``envs.coverage.observations.AGENT_ID_KEY``).
AGENT_KEY = "agent_id"

#: ``net_arch`` is one list for both streams or ``{"value": [...], "advantage": [...]}``.
DuelingNetArch = list[int] | dict[str, list[int]]


def _check_aggregator(aggregator: str) -> str:
    if aggregator not in AGGREGATORS:
        raise ValueError(f"aggregator must be one of {AGGREGATORS}, got {aggregator!r}")
    return aggregator


def split_net_arch(net_arch: DuelingNetArch) -> tuple[list[int], list[int]]:
    """Hidden layer sizes of the (value, advantage) streams.

    Args:
        net_arch: One list applied to both streams, or a dict with exactly the keys
            ``"value"`` and ``"advantage"``.

    Returns:
        The value-stream and advantage-stream layer sizes.
    """
    if isinstance(net_arch, dict):
        if set(net_arch) != {"value", "advantage"}:
            raise ValueError(
                f"dueling net_arch dict needs exactly the keys 'value' and 'advantage', "
                f"got {sorted(net_arch)}"
            )
        return list(net_arch["value"]), list(net_arch["advantage"])
    return list(net_arch), list(net_arch)


def without_action_mask(space: spaces.Space) -> spaces.Space:
    """``space`` less its :data:`ACTION_MASK_KEY` entry (any other space as it is)."""
    if isinstance(space, spaces.Dict) and ACTION_MASK_KEY in space.spaces:
        return spaces.Dict({k: v for k, v in space.spaces.items() if k != ACTION_MASK_KEY})
    return space


class _IgnoresActionMask:
    """Mixin for a DQN policy whose features extractor does not read the action mask.

    SB3's ``CombinedExtractor`` and :class:`TeamMapExtractor` build one branch per key of the
    space they are given and read only those keys in ``forward``, so an extractor built on the
    space less the mask ignores the mask in every batch. The Q-network itself keeps the full
    space: SB3's ``preprocess_obs`` converts every key of a batch by the space's entry for it,
    and the batches (from the env and the replay buffer) carry the mask.
    """

    observation_space: spaces.Space
    features_extractor_class: type[BaseFeaturesExtractor]
    features_extractor_kwargs: dict[str, Any]

    def make_features_extractor(self) -> BaseFeaturesExtractor:
        space = without_action_mask(self.observation_space)
        return self.features_extractor_class(space, **self.features_extractor_kwargs)


class DuelingHead(nn.Module):
    """Value and advantage streams on shared features, combined into Q-values.

    ``Q = V + A - mean_a(A)`` (``"mean"``) or ``Q = V + A - max_a(A)`` (``"max"``). Subtracting
    an aggregate of ``A`` makes the split identifiable: with ``"mean"`` the mean of Q over
    actions is V, with ``"max"`` the max of Q is V.

    Args:
        features_dim: Size of the shared features.
        n_actions: Number of discrete actions.
        net_arch: Hidden layers, see :func:`split_net_arch`.
        activation_fn: Activation between hidden layers.
        aggregator: ``"mean"`` or ``"max"``.
    """

    def __init__(
        self,
        features_dim: int,
        n_actions: int,
        net_arch: DuelingNetArch,
        activation_fn: type[nn.Module] = nn.ReLU,
        aggregator: str = "mean",
    ) -> None:
        super().__init__()
        self.aggregator = _check_aggregator(aggregator)
        value_arch, advantage_arch = split_net_arch(net_arch)
        self.value_net = nn.Sequential(*create_mlp(features_dim, 1, value_arch, activation_fn))
        self.advantage_net = nn.Sequential(
            *create_mlp(features_dim, n_actions, advantage_arch, activation_fn)
        )

    def forward(self, features: th.Tensor) -> th.Tensor:
        """Q-values ``(batch, n_actions)`` from features ``(batch, features_dim)``."""
        value = self.value_net(features)
        advantage = self.advantage_net(features)
        if self.aggregator == "mean":
            baseline = advantage.mean(dim=1, keepdim=True)
        else:
            baseline = advantage.max(dim=1, keepdim=True).values
        return value + advantage - baseline


class _HeadlessQNetwork(QNetwork):
    """SB3's ``QNetwork`` for subclasses that replace its head (``q_net``) in their
    ``__init__``: ``QNetwork`` feeds its ``net_arch`` to ``create_mlp``, so it is built with
    none (one cheap ``Linear``, replaced right after); feature extraction, ``forward`` (when
    the subclass keeps it) and greedy ``_predict`` stay SB3's."""

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        activation_fn: type[nn.Module],
        normalize_images: bool,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            features_extractor=features_extractor,
            features_dim=features_dim,
            net_arch=[],
            activation_fn=activation_fn,
            normalize_images=normalize_images,
        )


class DuelingQNetwork(_HeadlessQNetwork):
    """SB3 ``QNetwork`` whose head is a :class:`DuelingHead`.

    ``QNetwork.forward`` computes ``self.q_net(features)``, so only ``q_net`` is swapped for the
    dueling head; feature extraction, greedy ``_predict`` and everything else are SB3's.

    Args:
        observation_space: Observation space.
        action_space: Action space.
        features_extractor: Shared features extractor (Flatten for the MLP policy).
        features_dim: Output size of the features extractor.
        net_arch: Hidden layers of the streams, see :func:`split_net_arch`; default ``[64, 64]``.
        activation_fn: Activation function.
        normalize_images: Whether to divide image observations by 255.
        aggregator: ``"mean"`` or ``"max"``.
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        net_arch: DuelingNetArch | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        aggregator: str = "mean",
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            features_extractor,
            features_dim,
            activation_fn,
            normalize_images,
        )
        self.net_arch = [64, 64] if net_arch is None else net_arch  # type: ignore[assignment]
        self.aggregator = _check_aggregator(aggregator)
        self.q_net = DuelingHead(  # type: ignore[assignment]
            features_dim,
            int(self.action_space.n),
            self.net_arch,
            activation_fn,
            aggregator,
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(aggregator=self.aggregator)
        return data


class DuelingDQNPolicy(_IgnoresActionMask, DQNPolicy):
    """DQN policy (online and target networks) with dueling Q-networks.

    Registered on :class:`harness.sb3.dqn.DoubleDQN` as ``"DuelingMlpPolicy"``. ``net_arch``
    applies to both streams (a list) or per stream (``{"value": [...], "advantage": [...]}``);
    the thesis setup is ``[512, 512, 512]``. ``aggregator`` is part of the constructor
    parameters, so it survives ``policy.save``/``load`` and ``DoubleDQN.save``/``load``.

    Args:
        observation_space: Observation space.
        action_space: Action space.
        lr_schedule: Learning rate schedule.
        net_arch: Hidden layers of the streams; default ``[64, 64]``.
        activation_fn: Activation function.
        features_extractor_class: Shared features extractor class (Flatten by default).
        features_extractor_kwargs: Keyword arguments for the features extractor.
        normalize_images: Whether to divide image observations by 255.
        optimizer_class: Optimizer class (``DoubleDQN`` defaults it to RMSprop).
        optimizer_kwargs: Optimizer keyword arguments, excluding the learning rate.
        aggregator: ``"mean"`` (default) or ``"max"``.
    """

    q_net: DuelingQNetwork
    q_net_target: DuelingQNetwork

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        net_arch: DuelingNetArch | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = FlattenExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        aggregator: str = "mean",
    ) -> None:
        # DQNPolicy.__init__ builds the networks (make_q_net), which needs the aggregator, so
        # it is set first; a plain str attribute is safe before nn.Module.__init__.
        self.aggregator = _check_aggregator(aggregator)
        if isinstance(net_arch, dict):
            split_net_arch(net_arch)  # fail early on bad keys
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=net_arch,  # type: ignore[arg-type]
            activation_fn=activation_fn,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
        )

    def make_q_net(self) -> DuelingQNetwork:
        # Separate features extractor per network, as SB3 does.
        net_args = self._update_features_extractor(self.net_args, features_extractor=None)
        return DuelingQNetwork(**net_args, aggregator=self.aggregator).to(self.device)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(aggregator=self.aggregator)
        return data


class TeamMapExtractor(BaseFeaturesExtractor):
    """Features of the ``"teammap"`` observation: a small conv stack per image, then one layer.

    Each image (``"local"`` crop, ``"global"`` pooled map; any side) goes through a 3x3 conv
    (``channels[0]`` filters, same size) and a 3x3 conv with stride 2 (``channels[1]``), ReLU
    after each, then is flattened; the flat images and the ``"vector"`` are concatenated and
    mapped to ``features_dim`` with a ReLU. SB3's ``NatureCNN`` needs images of 36x36 or more,
    hence this one. SB3 has already divided the uint8 images by 255.

    Args:
        observation_space: The ``Dict`` space (``local``, ``global``, ``vector``; any image keys
            work: every 3-D ``Box`` is an image, every 1-D one a vector).
        features_dim: Output size.
        channels: Filters of the two conv layers of each image branch.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        features_dim: int = 256,
        channels: tuple[int, int] | list[int] = (8, 16),
    ) -> None:
        super().__init__(observation_space, features_dim)
        first, second = (int(c) for c in channels)
        branches: dict[str, nn.Module] = {}
        flat = 0
        for key, space in observation_space.spaces.items():
            shape = space.shape
            assert shape is not None
            if len(shape) == 3:
                branch: nn.Module = nn.Sequential(
                    nn.Conv2d(shape[0], first, kernel_size=3, padding=1),
                    nn.ReLU(),
                    nn.Conv2d(first, second, kernel_size=3, stride=2, padding=1),
                    nn.ReLU(),
                    nn.Flatten(),
                )
                with th.no_grad():  # the flat size, as SB3's NatureCNN computes it
                    flat += int(branch(th.zeros(1, *shape)).shape[1])
            else:
                branch = nn.Flatten()
                flat += int(np.prod(shape))
            branches[key] = branch
        self.branches = nn.ModuleDict(branches)
        self.linear = nn.Sequential(nn.Linear(flat, features_dim), nn.ReLU())

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        parts = [branch(observations[key]) for key, branch in self.branches.items()]
        return self.linear(th.cat(parts, dim=1))


class TeamMapPolicy(_IgnoresActionMask, DQNPolicy):
    """DQN policy on the ``"teammap"`` observation: :class:`TeamMapExtractor`, then SB3's Q head
    (``net_arch`` hidden layers, default none). Registered as ``"TeamMapPolicy"``."""

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = TeamMapExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=[] if net_arch is None else net_arch,
            activation_fn=activation_fn,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
        )


class DuelingTeamMapPolicy(DuelingDQNPolicy):
    """Dueling DQN policy on the ``"teammap"`` observation: :class:`TeamMapExtractor`, then
    value and advantage streams (``net_arch``, default none: one linear layer each).
    Registered as ``"DuelingTeamMapPolicy"``."""

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        lr_schedule: Schedule,
        net_arch: DuelingNetArch | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = TeamMapExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
        aggregator: str = "mean",
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            lr_schedule,
            net_arch=[] if net_arch is None else net_arch,
            activation_fn=activation_fn,
            features_extractor_class=features_extractor_class,
            features_extractor_kwargs=features_extractor_kwargs,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            aggregator=aggregator,
        )


#: Default key of the per-slot feature block that :class:`SlotQNetwork` scores: the key under
#: which the coverage env puts its goal candidates (``envs.coverage.goals.GOALS_KEY``).
SLOTS_KEY = "goals"


class SlotQNetwork(_HeadlessQNetwork):
    """A Q-network whose actions are *slots*, each described by a row of features: one shared
    scorer (an MLP) maps ``[slot features, observation features]`` to the slot's value, so the
    values follow the slots when they are reordered (permutation-equivariant), and any number of
    slots shares the same weights (a pointer-network style head, as in learned frontier
    selection). The observation's other keys go through the features extractor as usual.

    Args:
        observation_space, action_space, features_extractor, features_dim, activation_fn,
        normalize_images: As SB3's ``QNetwork``; ``features_extractor`` reads neither the slots
            nor the action mask.
        net_arch: Hidden layers of the scorer (default ``[128]``).
        slots_key: The ``(n_actions, F)`` float ``Box`` of slot features in the observation.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Discrete,
        features_extractor: BaseFeaturesExtractor,
        features_dim: int,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        normalize_images: bool = True,
        slots_key: str = SLOTS_KEY,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            features_extractor,
            features_dim,
            activation_fn,
            normalize_images,
        )
        slots = observation_space.spaces.get(slots_key)
        n = int(action_space.n)
        if slots is None or slots.shape is None or len(slots.shape) != 2 or slots.shape[0] != n:
            raise ValueError(
                f"a slot Q-network needs a {slots_key!r} Box of shape ({n}, features) in the "
                f"observation, one row per action; got {slots}"
            )
        self.slots_key = slots_key
        self.net_arch = [128] if net_arch is None else list(net_arch)
        layers = create_mlp(features_dim + int(slots.shape[1]), 1, self.net_arch, activation_fn)
        self.q_net = nn.Sequential(*layers)

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        features = self.extract_features(obs, self.features_extractor)  # (batch, features_dim)
        slots = obs[self.slots_key].float()  # type: ignore[index]  (batch, slots, F)
        shared = features.unsqueeze(1).expand(-1, slots.shape[1], -1)
        return self.q_net(th.cat([slots, shared], dim=-1)).squeeze(-1)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(slots_key=self.slots_key)
        return data


class SlotTeamMapPolicy(TeamMapPolicy):
    """DQN policy that scores candidate slots (:class:`SlotQNetwork`) with the team map's
    features (:class:`TeamMapExtractor` on every key but the slots and the action mask).
    Registered as ``"SlotTeamMapPolicy"``; the coverage env's goal action
    (``frontier: {action: {goal: {k: K}}}``) is what it is for.

    Args:
        net_arch: Hidden layers of the shared scorer (default ``[128]``).
        slots_key: The slot features' key (default :data:`SLOTS_KEY`).
        Others: as :class:`TeamMapPolicy`.
    """

    def __init__(
        self,
        *args: Any,
        net_arch: list[int] | None = None,
        slots_key: str = SLOTS_KEY,
        **kwargs: Any,
    ) -> None:
        self.slots_key = slots_key  # read by make_features_extractor during SB3's _build
        super().__init__(*args, net_arch=[128] if net_arch is None else net_arch, **kwargs)

    def make_features_extractor(self) -> BaseFeaturesExtractor:
        space = without_action_mask(self.observation_space)
        assert isinstance(space, spaces.Dict)
        rest = spaces.Dict({k: v for k, v in space.spaces.items() if k != self.slots_key})
        return self.features_extractor_class(rest, **self.features_extractor_kwargs)

    def make_q_net(self) -> SlotQNetwork:
        net_args = self._update_features_extractor(self.net_args, features_extractor=None)
        return SlotQNetwork(**net_args, slots_key=self.slots_key).to(self.device)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(slots_key=self.slots_key)
        return data


class MultiInputPolicy(_IgnoresActionMask, SB3MultiInputPolicy):
    """SB3's DQN ``MultiInputPolicy`` (``CombinedExtractor`` on a ``Dict`` observation) whose
    extractor leaves out the action mask. ``DoubleDQN``'s ``"MultiInputPolicy"``."""


# ---------------------------------------------------------------------- per-agent networks
def split_agent_id(
    obs: PyTorchObs, n_agents: int, agent_key: str = AGENT_KEY
) -> tuple[PyTorchObs, th.Tensor]:
    """The observation without the agent's one-hot index, and the index ``(batch,)``.

    The two layouts of agent indication (Terry et al. 2020): the last ``n_agents`` entries of a
    vector, or the ``agent_key`` entry of a dict.
    """
    if isinstance(obs, dict):
        inner = {key: value for key, value in obs.items() if key != agent_key}
        return inner, obs[agent_key].argmax(dim=1)
    return obs[:, :-n_agents], obs[:, -n_agents:].argmax(dim=1)


def without_agent_id(
    space: spaces.Space, n_agents: int, agent_key: str = AGENT_KEY
) -> spaces.Space:
    """The observation space of one agent's network: ``space`` less the one-hot index (the
    ``agent_key`` entry of a ``Dict``, the last ``n_agents`` entries of a vector)."""
    if isinstance(space, spaces.Dict):
        if agent_key not in space.spaces:
            raise ValueError(
                f"a per-agent policy needs the agent's one-hot index under {agent_key!r} "
                f"(agent_key), got the keys {sorted(space.spaces)}"
            )
        return spaces.Dict({k: v for k, v in space.spaces.items() if k != agent_key})
    assert isinstance(space, spaces.Box) and space.shape is not None
    if space.shape != (space.shape[0],) or space.shape[0] <= n_agents:
        raise ValueError(
            f"a per-agent policy for {n_agents} agents needs observations that end in their "
            f"one-hot index (env agent_id=True), got {space}"
        )
    return spaces.Box(space.low[:-n_agents], space.high[:-n_agents], dtype=space.dtype)  # type: ignore[arg-type]


class PerAgentQNetwork(BasePolicy):
    """N Q-networks of one architecture as one module: each sample goes to its agent's set.

    The N networks' weights are stacked (``torch.func.stack_module_state``): every parameter
    of agent ``i``'s network is ``params[name][i]``. A batch is routed by the agent index that
    comes with each observation (:func:`split_agent_id`, one-hot stripped before the network):
    the samples are scattered into an ``(N, m, ...)`` block (``m``: the largest count of one
    agent, the rest zero padding), the N networks run at once with ``torch.func.vmap`` (batched
    matmuls, grouped convolutions) and each sample's Q-values are gathered back in batch order.
    So ``predict`` on VecEnv slots and ``train`` on replay samples use the same path, in any
    order; a padding row feeds nothing back, and agent ``i``'s weights get gradients from agent
    ``i``'s samples only. Any SB3 ``QNetwork`` works as the template (MLP, dueling, team map).

    Args:
        observation_space: The observation space with the agent's one-hot index.
        action_space: Action space.
        nets: The N networks (built on the space without the index), one per agent, in
            agent order; their weights become the initial sets.
        agent_key: The key of the one-hot index in a ``Dict`` observation (unused for a vector).
    """

    action_space: spaces.Discrete

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Discrete,
        nets: list[nn.Module],
        agent_key: str = AGENT_KEY,
    ) -> None:
        super().__init__(observation_space, action_space)
        self.n_agents = len(nets)
        self.agent_key = agent_key
        params, buffers = th.func.stack_module_state(nets)  # type: ignore[arg-type]
        linear_weights = {
            f"{name}.weight" if name else "weight"
            for name, module in nets[0].named_modules()
            if isinstance(module, nn.Linear)
        }
        # ParameterDict keys may not contain ".": one parameter per template parameter.
        self.params = nn.ParameterDict(
            {
                _key(k): nn.Parameter(_input_major(v) if k in linear_weights else v)
                for k, v in params.items()
            }
        )
        for name, value in buffers.items():
            self.register_buffer("stacked_" + _key(name), value)
        self._buffer_names = list(buffers)
        # A weightless copy to call with each set (kept out of the module tree: it holds no state
        # of its own, and must not be moved, saved or counted).
        self._template = [copy.deepcopy(nets[0]).to("meta")]

    def forward(self, obs: PyTorchObs) -> th.Tensor:
        """Q-values ``(batch, n_actions)``, each row from its agent's network."""
        inner, agent = split_agent_id(obs, self.n_agents, self.agent_key)
        return self.route(inner, agent)

    def agents_of(self, obs: PyTorchObs) -> th.Tensor:
        """The agent index ``(batch,)`` of each observation."""
        return split_agent_id(obs, self.n_agents, self.agent_key)[1]

    def route(self, inner: PyTorchObs, agent: th.Tensor) -> th.Tensor:
        """Q-values of observations without the index, row ``j`` by agent ``agent[j]``'s set."""
        n = self.n_agents
        onehot = nn.functional.one_hot(agent, n)
        rank = (onehot.cumsum(0) * onehot).sum(1) - 1  # position of each sample in its group
        width = self._block_width(onehot)

        def grouped(x: th.Tensor) -> th.Tensor:
            block = x.new_zeros((n, width, *x.shape[1:]))
            block[agent, rank] = x
            return block

        block_obs = (
            {k: grouped(v) for k, v in inner.items()} if isinstance(inner, dict) else grouped(inner)
        )
        params = {name: self.params[_key(name)] for name in self._param_names}
        buffers = {name: getattr(self, "stacked_" + _key(name)) for name in self._buffer_names}
        template = self._template[0]

        def one(p: dict[str, th.Tensor], b: dict[str, th.Tensor], x: PyTorchObs) -> th.Tensor:
            return th.func.functional_call(template, (p, b), (x,))

        q = th.func.vmap(one)(params, buffers, block_obs)  # (n, width, n_actions)
        return q[agent, rank]

    @staticmethod
    def _block_width(onehot: th.Tensor) -> int:
        """Rows of each agent's block for a batch routed by ``onehot`` ``(batch, n)``: on the CPU
        the largest group's size; on an accelerator the whole batch, an upper bound read from
        no tensor (reading the group sizes would wait for the device once per forward pass, and
        keep a training step from being recorded as a CUDA graph). Any width at least the
        largest group gives the same Q-values: the extra rows are zero padding no sample reads
        (``tests/test_sharing.py``)."""
        if onehot.device.type != "cpu":
            return onehot.shape[0]
        return int(onehot.sum(0).max()) if onehot.numel() else 0

    @property
    def _param_names(self) -> list[str]:
        return [name for name, _ in self._template[0].named_parameters()]

    def _predict(self, observation: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        return self(observation).argmax(dim=1).reshape(-1)

    def agent_parameters(self, agent: int) -> dict[str, th.Tensor]:
        """Agent ``agent``'s weights by the template's parameter names (views)."""
        return {name: self.params[_key(name)][agent] for name in self._param_names}

    def clip_grad_norm_(self, max_norm: float) -> None:
        """Clip each agent's gradient to ``max_norm`` on its own (what N separate learners, each
        with its own ``clip_grad_norm_``, would do); a joint norm would let one agent's large
        gradient shrink the others' steps."""
        grads = [p.grad for p in self.params.values() if p.grad is not None]
        if not grads:
            return
        # Per-agent norms without a squared copy of each gradient: these tensors are N times a
        # network's size, and passes over them are what a per-agent step spends its time on.
        # (Reduced over the trailing dimensions, not reshaped: the linear weights' gradients are
        # not contiguous, see _input_major, and a reshape would copy them.)
        norms = th.stack([th.linalg.vector_norm(g, dim=tuple(range(1, g.dim()))) for g in grads])
        scale = (max_norm / (th.linalg.vector_norm(norms, dim=0) + 1e-6)).clamp(max=1.0)
        # Most steps clip nothing: on the CPU, skip a pass over every gradient then. On an
        # accelerator asking would wait for the device, and a scale of 1 leaves a gradient as it
        # is, so every step scales.
        if scale.device.type != "cpu" or bool((scale < 1.0).any()):
            for g in grads:
                g.mul_(scale.reshape(-1, *([1] * (g.dim() - 1))))


def _key(name: str) -> str:
    return name.replace(".", "__")


def _input_major(weight: th.Tensor) -> th.Tensor:
    """The stacked linear weights ``(N, out, in)`` with the memory layout of ``(N, in, out)``.

    Under ``vmap`` a linear layer computes ``x @ W^T`` and its weight gradient comes out as the
    transpose of a contiguous ``(N, in, out)`` product. Autograd hands a leaf a gradient without
    a copy only when the strides match the parameter's, so a parameter stored this way gets its
    gradient as computed, where a contiguous one got a transposed copy of it every step (the
    largest single cost of a per-agent step on a CPU). The optimizer's state takes the same
    layout (``zeros_like`` preserves strides), and shape, values and state dict are unchanged.
    """
    return weight.transpose(-1, -2).contiguous().transpose(-1, -2)


class _PerAgent(_IgnoresActionMask):
    """Mixin that gives a DQN policy one parameter set per agent (``algo.sharing: per_agent``).

    The online and target networks are :class:`PerAgentQNetwork` s of ``n_agents`` networks of
    the base policy's kind (MLP, dueling, team map), each built on the observation space less
    the agent's one-hot index. ``n_agents`` and ``agent_key`` (the key of the one-hot index in a
    ``Dict`` observation; default :data:`AGENT_KEY`, the coverage env's) are constructor
    parameters, saved with the model, and so is ``groups``: where a set plays for a group of
    agents, each set's group name and agent names, in set order (``None``: not recorded, as in
    a model saved before it was; a loader compares it with the env it is to play). Everything
    else (optimizer, target updates, double-Q, PER) is the base policy's.
    """

    n_agents: int
    agent_key: str
    groups: dict[str, tuple[str, ...]] | None
    net_args: dict[str, Any]

    def __init__(
        self,
        *args: Any,
        n_agents: int = 1,
        agent_key: str = AGENT_KEY,
        groups: Mapping[str, Sequence[str]] | None = None,
        **kwargs: Any,
    ) -> None:
        if isinstance(n_agents, bool) or not isinstance(n_agents, int) or n_agents < 1:
            raise ValueError(f"n_agents must be an integer >= 1, got {n_agents!r}")
        if groups is not None and len(groups) != n_agents:
            raise ValueError(f"groups: {len(groups)} groups for n_agents={n_agents} parameter sets")
        # make_q_net runs inside the base __init__ and needs them; plain values are safe to set
        # before nn.Module.__init__.
        self.n_agents = n_agents
        self.agent_key = str(agent_key)
        self.groups = (
            None
            if groups is None
            else {str(name): tuple(map(str, members)) for name, members in groups.items()}
        )
        super().__init__(*args, **kwargs)

    def make_q_net(self) -> PerAgentQNetwork:
        full = self.observation_space
        inner = without_agent_id(full, self.n_agents, self.agent_key)
        make_one = super().make_q_net  # type: ignore[misc]
        # The base policy builds a network (features extractor included) for the space it was
        # given: show it the space without the index while it builds the N of them.
        self.observation_space = inner
        self.net_args = {**self.net_args, "observation_space": inner}
        try:
            nets = [make_one() for _ in range(self.n_agents)]
        finally:
            self.observation_space = full
            self.net_args = {**self.net_args, "observation_space": full}
        q_net = PerAgentQNetwork(full, self.action_space, nets, self.agent_key)  # type: ignore[attr-defined]
        return q_net.to(self.device)  # type: ignore[attr-defined]

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()  # type: ignore[misc]
        data.update(n_agents=self.n_agents, agent_key=self.agent_key)
        if self.groups is not None:
            data["groups"] = {name: list(members) for name, members in self.groups.items()}
        return data


class PerAgentMlpPolicy(_PerAgent, DQNPolicy):
    """``MlpPolicy`` with one parameter set per agent (``n_agents``)."""


class PerAgentDuelingMlpPolicy(_PerAgent, DuelingDQNPolicy):
    """``DuelingMlpPolicy`` with one parameter set per agent (``n_agents``)."""


class PerAgentTeamMapPolicy(_PerAgent, TeamMapPolicy):
    """``TeamMapPolicy`` with one parameter set per agent (``n_agents``)."""


class PerAgentDuelingTeamMapPolicy(_PerAgent, DuelingTeamMapPolicy):
    """``DuelingTeamMapPolicy`` with one parameter set per agent (``n_agents``)."""


def resolve_optimizer_class(optimizer: str | type[th.optim.Optimizer]) -> type[th.optim.Optimizer]:
    """The ``torch.optim`` class named ``optimizer`` (``"RMSprop"``, ``"Adam"``, ...); classes
    pass through unchanged, so config files can use names and code can use classes."""
    if isinstance(optimizer, str):
        candidate = getattr(th.optim, optimizer, None)
        if not (isinstance(candidate, type) and issubclass(candidate, th.optim.Optimizer)):
            raise ValueError(f"unknown torch optimizer {optimizer!r}: not a class in torch.optim")
        return candidate
    if isinstance(optimizer, type) and issubclass(optimizer, th.optim.Optimizer):
        return optimizer
    raise ValueError(f"optimizer_class must be a torch.optim.Optimizer subclass, got {optimizer!r}")


def harness_policy_aliases(algorithm: Any) -> dict[str, type[BasePolicy]]:
    """``algorithm``'s policy aliases (SB3's ``MlpPolicy``, ...) and every name of the harness's
    policy registry (:data:`harness.sb3.registry.POLICIES`, their per-agent names too), with
    ``"MultiInputPolicy"`` the one that leaves the action mask out of the network's input."""
    from harness.sb3.registry import POLICIES

    return {
        **algorithm.policy_aliases,
        **{name: entry.load() for name, entry in POLICIES.items()},
        **{
            entry.per_agent_name: entry.load(per_agent=True)
            for entry in POLICIES.values()
            if entry.per_agent
        },
        "MultiInputPolicy": MultiInputPolicy,
    }
