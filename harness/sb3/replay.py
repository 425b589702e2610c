"""Replay for :class:`~harness.sb3.dqn.DoubleDQN`: what the update asks of a buffer."""

from __future__ import annotations

from typing import Any

from harness.sb3.buffers import PrioritizedReplayBuffer
from harness.sb3.device_replay import DevicePrioritizedReplayBuffer, DeviceStorage

__all__ = ["graphable", "priorities_on_device", "prioritized"]


def prioritized(buffer: Any) -> bool:
    """Whether ``buffer`` samples by priority (it has ``alpha``, ``beta`` and
    ``update_priorities``)."""
    return isinstance(buffer, PrioritizedReplayBuffer)


def priorities_on_device(buffer: Any) -> bool:
    """Whether ``buffer``'s priorities are updated where its samples are (no host read)."""
    return isinstance(buffer, DevicePrioritizedReplayBuffer)


def graphable(buffer: Any) -> bool:
    """Whether ``buffer`` samples on the device from given draws (``sample_at``, ``draw``,
    ``graph_key``): a sample a recorded CUDA graph can hold."""
    return isinstance(buffer, DeviceStorage)
