"""torch's CPU threads, set once per process: training takes ``algo.threads``, evaluation one
(a module of its own so that evaluation asks it without reaching the training loop)."""

from __future__ import annotations

import torch

__all__ = ["configure_torch"]


def configure_torch(threads: int | None) -> None:
    """Set torch's CPU thread count (``None`` keeps torch's default, one per core)."""
    if threads is not None:
        torch.set_num_threads(threads)
