"""The Stable-Baselines3 extensions: ``DoubleDQN``, the dueling and team-map policies, the
replay buffer (a storage and a sampler: uniform or prioritized, on the host or the model's
device), the loss's parts, the TD targets and schedules, and the policy registry.

This layer imports nothing from ``envs`` or from the rest of ``harness``: it works on any
Gymnasium env or VecEnv. Anything env-specific (which actions are masked, which action is the
expert's) comes in through an argument or through an ``action_mask`` key of a ``Dict``
observation (PettingZoo's convention).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from harness.sb3.dqn import DoubleDQN
    from harness.sb3.policies import DuelingDQNPolicy
    from harness.sb3.replay import PrioritizedReplayBuffer, Replay

__all__ = ["DoubleDQN", "DuelingDQNPolicy", "PrioritizedReplayBuffer", "Replay"]

# Lazy (PEP 562): the config layer reads the policy registry without importing torch.
_EXPORTS = {
    "DoubleDQN": "harness.sb3.dqn",
    "DuelingDQNPolicy": "harness.sb3.policies",
    "PrioritizedReplayBuffer": "harness.sb3.replay",
    "Replay": "harness.sb3.replay",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'harness.sb3' has no attribute {name!r}")
