"""coverage-harness: SB3 extensions, SuperSuit adapters and the ``harness`` command."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from harness.buffers import PrioritizedReplayBuffer
    from harness.dqn import DoubleDQN
    from harness.policies import DuelingDQNPolicy

__all__ = ["DoubleDQN", "DuelingDQNPolicy", "PrioritizedReplayBuffer"]

# Lazy exports (PEP 562): `import harness` (e.g. for the CLI's --help) should not pay for
# importing torch and SB3 until one of these classes is actually used.
_EXPORTS = {
    "DoubleDQN": "harness.dqn",
    "DuelingDQNPolicy": "harness.policies",
    "PrioritizedReplayBuffer": "harness.buffers",
}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'harness' has no attribute {name!r}")
