"""The replay buffer's names as saved models and older code know them: the numbers
(:mod:`harness.sb3.kernels`) and ``PrioritizedReplayBuffer`` (:mod:`harness.sb3.replay`; a saved
prioritized model names ``harness.sb3.buffers.PrioritizedReplayBuffer``)."""

from __future__ import annotations

from harness.sb3.kernels import (
    _BAD_INDEX,
    _BAD_VALUE,
    PrioritizedReplayBufferSamples,
    SumTree,
    _last_occurrences,
    check_n_step_returns,
    importance_weights,
    n_step_returns,
    n_step_returns_on_device,
    replay_memory_bytes,
)
from harness.sb3.replay import PrioritizedReplayBuffer

__all__ = [
    "_BAD_INDEX",
    "_BAD_VALUE",
    "PrioritizedReplayBuffer",
    "PrioritizedReplayBufferSamples",
    "SumTree",
    "_last_occurrences",
    "check_n_step_returns",
    "importance_weights",
    "n_step_returns",
    "n_step_returns_on_device",
    "replay_memory_bytes",
]
