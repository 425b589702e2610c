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
    ``slots_key``; the env's goal action)."""

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
    "TeamMapPolicy": PolicyEntry(
        "harness.sb3.policies:TeamMapPolicy",
        "teammap",
        per_agent="harness.sb3.policies:PerAgentTeamMapPolicy",
    ),
    "DuelingTeamMapPolicy": PolicyEntry(
        "harness.sb3.policies:DuelingTeamMapPolicy",
        "teammap",
        dueling=True,
        per_agent="harness.sb3.policies:PerAgentDuelingTeamMapPolicy",
    ),
    "SlotTeamMapPolicy": PolicyEntry(
        "harness.sb3.policies:SlotTeamMapPolicy", "teammap", slots=True
    ),
}
