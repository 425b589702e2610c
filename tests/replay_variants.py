"""The replay variants the tests run on, each a setting of :class:`harness.sb3.replay.Replay` (the
product's one buffer class, and its prioritized default), named after the classes they replaced
so that a parametrised test says which storage and sampler it runs on."""

from __future__ import annotations

from typing import Any

from harness.sb3.replay import PrioritizedReplayBuffer, Replay

__all__ = [
    "DeviceDictReplayBuffer",
    "DevicePrioritizedDictReplayBuffer",
    "DevicePrioritizedReplayBuffer",
    "DeviceReplayBuffer",
    "PerDecisionDictReplayBuffer",
    "PerDecisionPrioritizedDictReplayBuffer",
    "PrioritizedDictReplayBuffer",
]


class PrioritizedDictReplayBuffer(PrioritizedReplayBuffer):
    """Host prioritized replay; the tests give it a ``Dict`` observation space."""


class DeviceReplayBuffer(Replay):
    """Uniform replay on the device."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, placement="device", **kwargs)


class DeviceDictReplayBuffer(DeviceReplayBuffer):
    """Uniform replay on the device; the tests give it a ``Dict`` observation space."""


class DevicePrioritizedReplayBuffer(PrioritizedReplayBuffer):
    """Prioritized replay on the device."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, placement="device", **kwargs)


class DevicePrioritizedDictReplayBuffer(DevicePrioritizedReplayBuffer, PrioritizedDictReplayBuffer):
    """Prioritized replay on the device; the tests give it a ``Dict`` observation space."""


class PerDecisionDictReplayBuffer(Replay):
    """Uniform replay of one transition per decision."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, per_decision=True, **kwargs)


class PerDecisionPrioritizedDictReplayBuffer(PrioritizedReplayBuffer):
    """Prioritized replay of one transition per decision."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, per_decision=True, **kwargs)
