"""The Stable-Baselines3 extensions: ``DoubleDQN``, the dueling and team-map policies, the
prioritized replay buffers (on the host, or on the model's device), the TD targets and schedules,
and the policy registry.

This layer imports nothing from ``envs`` or from the rest of ``harness``: it works on any
Gymnasium env or VecEnv. Anything env-specific (which actions are masked, which action is the
expert's) comes in through an argument or through an ``action_mask`` key of a ``Dict``
observation (PettingZoo's convention).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from harness.sb3.buffers import PrioritizedDictReplayBuffer, PrioritizedReplayBuffer
    from harness.sb3.device_replay import (
        DevicePrioritizedDictReplayBuffer,
        DevicePrioritizedReplayBuffer,
    )
    from harness.sb3.dqn import DoubleDQN
    from harness.sb3.policies import DuelingDQNPolicy

__all__ = [
    "DevicePrioritizedDictReplayBuffer",
    "DevicePrioritizedReplayBuffer",
    "DoubleDQN",
    "DuelingDQNPolicy",
    "PrioritizedDictReplayBuffer",
    "PrioritizedReplayBuffer",
]

# Lazy (PEP 562): the config layer reads the policy registry without importing torch.
_EXPORTS = {
    "DoubleDQN": "harness.sb3.dqn",
    "DuelingDQNPolicy": "harness.sb3.policies",
    "PrioritizedReplayBuffer": "harness.sb3.buffers",
    "PrioritizedDictReplayBuffer": "harness.sb3.buffers",
    "DevicePrioritizedReplayBuffer": "harness.sb3.device_replay",
    "DevicePrioritizedDictReplayBuffer": "harness.sb3.device_replay",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'harness.sb3' has no attribute {name!r}")
