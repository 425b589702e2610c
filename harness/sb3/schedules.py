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
    the transitions of one training phase.

    ``DoubleDQN.start_phase`` makes ``progress_remaining`` the share of the phase still to run,
    ``1 - t / phase_timesteps`` with ``t`` the transitions done in the phase (from the model's own
    counter), so ``t = (1 - progress_remaining) * phase_timesteps``. The value is a function of
    ``t`` alone: the same in a fresh run, in a later phase and in a run resumed mid-phase.
    """

    start: float
    end: float
    steps: int
    phase_timesteps: int

    def __call__(self, progress_remaining: float) -> float:
        t = (1.0 - progress_remaining) * self.phase_timesteps
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
