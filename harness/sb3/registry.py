"""Named choices of a config that live in ``harness``: one registry per kind, names only.

Importing this module imports neither torch nor SB3 (a config is checked against it before any of
them loads); the objects are imported when used. The other registries: observation kinds in
``envs.coverage.observations.OBSERVATIONS``, planners and planner-backed actions in
``envs.coverage.frontier``, baselines in ``harness.evaluation.baselines.BASELINES``, optimizers
in ``torch.optim`` (resolved by ``harness.sb3.dqn.resolve_optimizer_class``).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

#: The thesis's hidden layers (3x512), the MLP policies' default head.
THESIS_NET_ARCH = (512, 512, 512)


@dataclass(frozen=True)
class PolicyEntry:
    """A policy a config can name."""

    target: str
    """``module:attribute`` of the SB3 policy class."""
    observation: str
    """The observation kind its network reads."""
    dueling: bool = False
    """Value and advantage streams (takes ``algo.dueling_aggregator``)."""
    per_agent: str = ""
    """``module:attribute`` of the same policy with one parameter set per agent
    (``algo.sharing: per_agent``; empty: none); its class name is also a ``DoubleDQN`` policy
    alias."""
    slots: bool = False
    """Its actions are candidate slots scored from a feature block of the observation (takes
    ``slots_key``): it needs an action kind whose actions are slots (the env's goal action)."""
    team_map: bool = False
    """Its features extractor is the team map's CNN (``TeamMapExtractor``): it takes
    ``algo.features_dim`` and ``algo.cnn_channels``, which size its network."""
    masked: bool = False
    """It reads a ``Dict`` of a vector observation and an action mask (PettingZoo's convention,
    ``observation`` and ``action_mask``): the network sees the observation, the mask restricts
    every choice (``DoubleDQN``'s greedy, ε-random and target actions)."""
    default_net_arch: tuple[int, ...] = THESIS_NET_ARCH
    """Its hidden layers when a config gives no ``algo.net_arch``."""

    def load(self, per_agent: bool = False) -> Any:
        """The policy class, or its per-agent version."""
        module, _, attribute = (self.per_agent if per_agent else self.target).partition(":")
        return getattr(importlib.import_module(module), attribute)

    @property
    def per_agent_name(self) -> str:
        """The per-agent class's name (``PerAgentMlpPolicy``, ...)."""
        return self.per_agent.partition(":")[2]


#: Policies by the name ``algo.policy`` takes (and ``DoubleDQN`` accepts as a string).
POLICIES: dict[str, PolicyEntry] = {
    "MlpPolicy": PolicyEntry(
        "stable_baselines3.dqn.policies:MlpPolicy",
        "thesis",
        per_agent="harness.sb3.policies:PerAgentMlpPolicy",
    ),
    "DuelingMlpPolicy": PolicyEntry(
        "harness.sb3.policies:DuelingDQNPolicy",
        "thesis",
        dueling=True,
        per_agent="harness.sb3.policies:PerAgentDuelingMlpPolicy",
    ),
    # A team-map extractor already ends in a features_dim-wide layer: its Q head has no hidden
    # layer unless asked (a 3x512 head would add ~0.66M weights to its ~0.47M).
    "TeamMapPolicy": PolicyEntry(
        "harness.sb3.policies:TeamMapPolicy",
        "teammap",
        per_agent="harness.sb3.policies:PerAgentTeamMapPolicy",
        team_map=True,
        default_net_arch=(),
    ),
    "DuelingTeamMapPolicy": PolicyEntry(
        "harness.sb3.policies:DuelingTeamMapPolicy",
        "teammap",
        dueling=True,
        per_agent="harness.sb3.policies:PerAgentDuelingTeamMapPolicy",
        team_map=True,
        default_net_arch=(),
    ),
    # A slot scorer needs a hidden layer to weigh a slot against the map.
    "SlotTeamMapPolicy": PolicyEntry(
        "harness.sb3.policies:SlotTeamMapPolicy",
        "teammap",
        slots=True,
        team_map=True,
        default_net_arch=(128,),
    ),
    # A pettingzoo env's {observation, action_mask} Dict: SB3's combined extractor on the
    # observation alone (the mask is left out of the network's input), the thesis's head.
    "MaskedMlpPolicy": PolicyEntry(
        "harness.sb3.policies:MultiInputPolicy",
        "masked",
        masked=True,
    ),
}

#: The policy of a config that names none.
DEFAULT_POLICY = "MlpPolicy"
