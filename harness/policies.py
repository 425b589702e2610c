"""Policies for SB3's DQN: the dueling Q-network (Wang et al., 2016,
https://arxiv.org/abs/1511.06581) and the team-map CNN policies (plain and dueling) that read the
``"teammap"`` observation's images."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import (
    BaseFeaturesExtractor,
    FlattenExtractor,
    create_mlp,
)
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.dqn.policies import DQNPolicy, QNetwork
from torch import nn

__all__ = [
    "AGGREGATORS",
    "DuelingDQNPolicy",
    "DuelingHead",
    "DuelingQNetwork",
    "DuelingTeamMapPolicy",
    "TeamMapExtractor",
    "TeamMapPolicy",
]

AGGREGATORS = ("mean", "max")

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


class DuelingQNetwork(QNetwork):
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
        # QNetwork would feed a dict net_arch to create_mlp; give it an empty one (one cheap
        # Linear layer) and replace its head right after.
        super().__init__(
            observation_space,
            action_space,
            features_extractor=features_extractor,
            features_dim=features_dim,
            net_arch=[],
            activation_fn=activation_fn,
            normalize_images=normalize_images,
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


class DuelingDQNPolicy(DQNPolicy):
    """DQN policy (online and target networks) with dueling Q-networks.

    Registered on :class:`harness.dqn.DoubleDQN` as ``"DuelingMlpPolicy"``. ``net_arch``
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


class TeamMapPolicy(DQNPolicy):
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
