"""How a map prior reads a team's map: each cell coded as :data:`SEEN_FREE`, :data:`SEEN_WALL`
or :data:`UNSEEN`. Its own module (NumPy alone, no torch, no episodes), so that the network
(:mod:`harness.prior.model`) sits in the factory's layer, which hands a prior to the env
(``env.prior``)."""

from __future__ import annotations

import numpy as np

#: Codes of a partial map's cells.
SEEN_FREE, SEEN_WALL, UNSEEN = 0, 1, 2


def code_team_map(seen: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """The partial map of a team that has seen ``seen`` of a map whose walls are ``walls``
    (only the seen cells of ``walls`` are read): ``uint8`` codes, same shape."""
    seen = np.asarray(seen, dtype=bool)
    out = np.full(seen.shape, UNSEEN, dtype=np.uint8)
    out[seen] = np.where(np.asarray(walls, dtype=bool)[seen], SEEN_WALL, SEEN_FREE)
    return out
