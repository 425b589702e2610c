"""coverage-harness: SB3 extensions, SuperSuit adapters and the ``harness`` command.

Packages by layer, each importing only from the ones above it in this list (the architecture
test, ``tests/test_architecture.py``, keeps it so):

* :mod:`harness.sb3`: the Stable-Baselines3 extensions (no ``envs`` import);
* :mod:`harness.config`: the typed config, YAML loading, ``--set``, map sources, migration;
* :mod:`harness.factory`: the one env factory;
* :mod:`harness.evaluation`: the episode loop, test policies, baselines;
* :mod:`harness.results`: the run folder, seed groups, statistics, plots;
* :mod:`harness.training`: the VecEnv adapters, the phase loop, callbacks, checkpoints, sweeps;
* :mod:`harness.cli` (parsing and printing) and :mod:`harness.bench`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from harness.sb3.buffers import PrioritizedReplayBuffer
    from harness.sb3.dqn import DoubleDQN
    from harness.sb3.policies import DuelingDQNPolicy

__all__ = ["DoubleDQN", "DuelingDQNPolicy", "PrioritizedReplayBuffer"]


def __getattr__(name: str) -> Any:
    # Lazy (PEP 562): `import harness` (e.g. for the CLI's --help) does not import torch.
    if name in __all__:
        import harness.sb3

        return getattr(harness.sb3, name)
    raise AttributeError(f"module 'harness' has no attribute {name!r}")
