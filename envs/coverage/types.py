"""Data types shared by the coverage environment's pieces (state, observations, rendering)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Cell codes of GridState.cells; they are also the observation's window values (§2.4), which is
# why the grid stores them directly: building an observation is a plain read.
CELL_UNVISITED = -1.0
CELL_VISITED = 0.0
CELL_WALL = 1.0

#: Action index -> (d_row, d_col): 0 up, 1 down, 2 left, 3 right, 4 stay.
MOVES = np.array([[-1, 0], [1, 0], [0, -1], [0, 1], [0, 0]], dtype=np.int64)
#: The stay action.
STAY = 4
#: With ``frontier={"action": "step"}``: one step along a shortest path to the nearest known free
#: cell not yet visited (the frontier compass's move), stay when there is none.
FRONTIER_STEP = 5


@dataclass
class GridState:
    """Mutable state of one episode.

    Attributes:
        cells: float32 ``(H + 2*pad, W + 2*pad)``: the map padded with wall, each cell
            ``CELL_WALL``, ``CELL_VISITED`` or ``CELL_UNVISITED``.
        pad: Width of the wall border around the map in ``cells``.
        positions: int64 ``(n_agents, 2)``: (row, col) of each agent in map coordinates.
        credited_by: int16 ``(H, W)``: the agent credited with each visited cell (start cells go
            to the agent that starts there), -1 elsewhere. Used to draw per-agent paths.
        steps: Steps taken this episode.
    """

    cells: np.ndarray
    pad: int
    positions: np.ndarray
    credited_by: np.ndarray
    steps: int = 0

    @property
    def interior(self) -> np.ndarray:
        """View of ``cells`` without the padding."""
        p = self.pad
        return self.cells[p:-p, p:-p]
