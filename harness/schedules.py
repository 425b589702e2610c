"""Pure schedule math: linear ε/β decay (eq. 4.1) and the epochs-by-coverage table.

These are plain functions and small picklable callables so that SB3 can save them inside a model
and tests can check them against hand-computed values.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass


def linear(start: float, end: float, steps: int, t: float) -> float:
    """Eq. 4.1: go linearly from ``start`` to ``end`` over ``steps``, then stay at ``end``.

    ``steps <= 0`` means "already at the end".
    """
    if steps <= 0 or t >= steps:
        return end
    return start + (end - start) * max(t, 0.0) / steps


@dataclass(frozen=True)
class PhaseLinearSchedule:
    """An SB3 ``Schedule`` (a callable of ``progress_remaining``) that follows :func:`linear` over
    the steps of one training phase.

    SB3 hands schedules the remaining progress of the current ``learn()`` call (1 → 0). A phase is
    one ``learn()`` call over its last ``phase_timesteps - done_before`` steps (``done_before > 0``
    when a run resumes mid-phase), so the step within the phase is
    ``done_before + (1 - progress_remaining) * (phase_timesteps - done_before)``.
    """

    start: float
    end: float
    steps: int
    phase_timesteps: int
    done_before: int = 0

    def __call__(self, progress_remaining: float) -> float:
        span = self.phase_timesteps - self.done_before
        t = self.done_before + (1.0 - progress_remaining) * span
        return linear(self.start, self.end, self.steps, t)


def epochs_for(coverage: float | None, table: Sequence[tuple[float, int]]) -> int:
    """Epochs (gradient steps per training call) for the team's recent coverage.

    ``table`` is a list of ``(threshold, epochs)`` sorted by threshold; the entry with the highest
    threshold not above ``coverage`` wins (thesis: ``0 → 1, 0.40 → 5, 0.60 → 7``). Before any
    episode has finished (``coverage is None``) the first entry applies.
    """
    epochs = table[0][1]
    if coverage is None:
        return epochs
    for threshold, value in table:
        if coverage >= threshold:
            epochs = value
    return epochs
