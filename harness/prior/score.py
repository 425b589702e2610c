"""A map prior's score: its log-loss on the unseen cells, beside the seen wall share's.

For each partial map the cells nobody has seen are the ones scored. ``unseen_logloss`` is the
mean over them of ``-log p(truth)`` under the prior; ``density_logloss`` the same under the
*density* prior, every unseen cell a wall with the share of walls among the seen cells (what the
``rollout`` chooser drew its maps from before priors: :func:`envs.coverage.rollouts.sampled_free`).
Probabilities are clipped to ``[EPS, 1 - EPS]`` for both. ``ratio`` is the first over the second:
below 1 the prior knows more about the unseen part than the wall share does.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from harness.prior.data import SEEN_WALL, UNSEEN, PartialMaps

#: Probabilities are clipped to ``[EPS, 1 - EPS]`` (a share of 0 walls seen would otherwise
#: make one unseen wall an infinite loss).
EPS = 1e-3


def cell_logloss(p_wall: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """``-log`` of the probability given to the truth, cell by cell (``p_wall`` clipped)."""
    p = np.clip(np.asarray(p_wall, dtype=np.float64), EPS, 1.0 - EPS)
    return -np.where(walls, np.log(p), np.log1p(-p))


def density(states: np.ndarray) -> np.ndarray:
    """The density prior's wall probability of each partial map, ``(N,)``: walls over seen
    cells."""
    seen = states != UNSEEN
    walls = (states == SEEN_WALL).sum(axis=(1, 2))
    return walls / np.maximum(seen.sum(axis=(1, 2)), 1)


def score(
    predict: Callable[[np.ndarray], np.ndarray], sets: Sequence[PartialMaps], batch: int = 32
) -> dict[str, Any]:
    """The prior ``predict`` (partial maps ``(n, H, W)`` to wall probabilities) scored on
    ``sets``: ``unseen_logloss``, ``density_logloss``, ``ratio``, ``cells`` (unseen cells
    scored) and ``maps`` (partial maps)."""
    prior_sum = density_sum = 0.0
    cells = maps = 0
    for data in sets:
        for start in range(0, len(data), batch):
            states = data.states[start : start + batch]
            walls = data.walls[start : start + batch]
            unseen = states == UNSEEN
            p = predict(states)
            prior_sum += float(cell_logloss(p, walls)[unseen].sum())
            share = np.broadcast_to(density(states)[:, None, None], states.shape)
            density_sum += float(cell_logloss(share, walls)[unseen].sum())
            cells += int(unseen.sum())
            maps += len(states)
    if cells == 0:
        raise ValueError("no unseen cell to score: every partial map was fully seen")
    unseen_logloss, density_logloss = prior_sum / cells, density_sum / cells
    return {
        "unseen_logloss": unseen_logloss,
        "density_logloss": density_logloss,
        "ratio": unseen_logloss / density_logloss,
        "cells": cells,
        "maps": maps,
    }
