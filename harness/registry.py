"""Named choices of a config that live in ``harness``: one registry per kind, names only.

Importing this module imports neither torch nor SB3 (a config is checked against it before any of
them loads); the objects are imported when used. The other registries: observation kinds in
``envs.coverage.observations.OBSERVATIONS``, baselines in ``harness.baselines.BASELINES``,
optimizers in ``torch.optim`` (resolved by ``harness.dqn.resolve_optimizer_class``).
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

    def load(self) -> Any:
        module, _, attribute = self.target.partition(":")
        return getattr(importlib.import_module(module), attribute)


#: Policies by the name ``algo.policy`` takes (and ``DoubleDQN`` accepts as a string).
POLICIES: dict[str, PolicyEntry] = {
    "MlpPolicy": PolicyEntry("stable_baselines3.dqn.policies:MlpPolicy", "thesis"),
    "DuelingMlpPolicy": PolicyEntry("harness.policies:DuelingDQNPolicy", "thesis", dueling=True),
    "TeamMapPolicy": PolicyEntry("harness.policies:TeamMapPolicy", "teammap"),
    "DuelingTeamMapPolicy": PolicyEntry(
        "harness.policies:DuelingTeamMapPolicy", "teammap", dueling=True
    ),
}
