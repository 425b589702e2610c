"""Observation kinds of the coverage environment.

An observation kind turns the environment's state into one float32 vector per agent. It is a
small class with a ``space()`` and a ``build(state)`` so that new kinds (a wider egocentric view of
the team map, for example) can be added without touching the step logic: register the class in
:data:`OBSERVATIONS` and pass ``observation="<name>"`` to the env.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np
from gymnasium import spaces

from envs.coverage.types import CELL_UNVISITED, CELL_WALL, GridState

COORD_MODES = ("normalized", "raw")


class ObservationBuilder(ABC):
    """Builds every agent's observation from a :class:`GridState` in one vectorised call.

    Args:
        height: Rows of the map.
        width: Columns of the map.
        coords: ``"normalized"`` (row/(H-1), col/(W-1)) or ``"raw"`` (row, col).
    """

    name: ClassVar[str]
    #: Cells of padding around the grid that :meth:`build` reads (``state.cells`` is padded by
    #: the largest padding of the builder in use, so windows never need bounds checks).
    padding: ClassVar[int] = 1

    def __init__(self, height: int, width: int, coords: str = "normalized") -> None:
        if coords not in COORD_MODES:
            raise ValueError(f"coords must be one of {COORD_MODES}, got {coords!r}")
        self.height, self.width, self.coords = height, width, coords
        if coords == "normalized":
            # max(.., 1) keeps a one-row or one-column map finite (its coordinate is always 0).
            self._scale = np.array(
                [1.0 / max(height - 1, 1), 1.0 / max(width - 1, 1)], dtype=np.float32
            )
        else:
            self._scale = np.ones(2, dtype=np.float32)

    @abstractmethod
    def space(self) -> spaces.Box:
        """The observation space of one agent."""

    @abstractmethod
    def build(self, state: GridState) -> np.ndarray:
        """Return a float32 array ``(n_agents, *space().shape)``, a fresh array every call."""

    def _coords_high(self) -> np.ndarray:
        if self.coords == "normalized":
            return np.ones(2, dtype=np.float32)
        return np.array([self.height - 1, self.width - 1], dtype=np.float32)


class ThesisObservation(ObservationBuilder):
    """The thesis's 13-element observation (§3.2).

    * 0-8: the 3x3 window around the agent, row-major from the top-left: -1 unvisited free,
      0 visited free, 1 wall or outside the grid. Element 4 is the agent's own cell (0).
    * 9-10: the agent's own (row, col).
    * 11-12: (row, col) of the nearest other agent (Euclidean, ties to the lower index); a lone
      agent sees its own position again.
    """

    name = "thesis"
    padding = 1
    # Row and column offsets of the 3x3 window in row-major order.
    _DR = np.repeat(np.arange(-1, 2), 3)
    _DC = np.tile(np.arange(-1, 2), 3)

    def space(self) -> spaces.Box:
        high_xy = self._coords_high()
        low = np.concatenate([np.full(9, CELL_UNVISITED), np.zeros(4)]).astype(np.float32)
        high = np.concatenate([np.full(9, CELL_WALL), high_xy, high_xy]).astype(np.float32)
        return spaces.Box(low=low, high=high, shape=(13,), dtype=np.float32)

    def build(self, state: GridState) -> np.ndarray:
        pos = state.positions
        n = pos.shape[0]
        p = state.pad
        width = state.cells.shape[1]
        if self._width != width:  # flat offsets of the 3x3 window in the padded grid
            self._offsets = self._DR * width + self._DC
            self._width = width
        obs = np.empty((n, 13), dtype=np.float32)
        # One gather from the padded grid for all agents: no copy of the grid, no bounds checks.
        centre = (pos[:, 0] + p) * width + (pos[:, 1] + p)
        obs[:, :9] = state.cells.ravel().take(centre[:, None] + self._offsets)
        own = pos * self._scale
        obs[:, 9:11] = own
        obs[:, 11:13] = own[nearest_teammate(pos)]
        return obs

    _width = -1
    _offsets: np.ndarray


def nearest_teammate(positions: np.ndarray) -> list[int] | np.ndarray:
    """Index of each agent's nearest other agent (Euclidean distance, ties to the lower index).

    A lone agent is its own nearest teammate.
    """
    n = positions.shape[0]
    if n == 1:
        return [0]
    if n <= 8:  # plain Python beats numpy's call overhead for a few agents
        pts = positions.tolist()
        out = []
        for i, (r, c) in enumerate(pts):
            best, best_j = -1, i
            for j, (r2, c2) in enumerate(pts):
                if j != i:
                    d = (r - r2) * (r - r2) + (c - c2) * (c - c2)
                    if best < 0 or d < best:  # strict: the first (lowest index) minimum wins
                        best, best_j = d, j
            out.append(best_j)
        return out
    diff = positions[:, None, :] - positions[None, :, :]
    d2 = (diff * diff).sum(axis=-1)
    np.fill_diagonal(d2, np.iinfo(d2.dtype).max)
    return d2.argmin(axis=1)  # argmin returns the first (lowest index) minimum


#: Observation kinds by name (the env's ``observation=`` argument).
OBSERVATIONS: dict[str, type[ObservationBuilder]] = {ThesisObservation.name: ThesisObservation}
