"""Pure helpers of the coverage environment's step (SPEC §2.3), kept apart so they can be tested
and profiled on their own."""

from __future__ import annotations

import numpy as np

from envs.coverage.types import CELL_UNVISITED, CELL_VISITED, CELL_WALL, MOVES


def resolve_moves(
    cells: np.ndarray, pad: int, positions: np.ndarray, actions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Apply every agent's action at once.

    Agents never block each other (they may share a cell) and walls do not move, so resolving the
    moves "one agent at a time in index order" gives the same positions as resolving them together;
    order only matters for who is credited with a new cell (see :func:`credit_new_cells`).

    Args:
        cells: Padded cell grid (walls and the outside are ``CELL_WALL``).
        pad: Padding width of ``cells``.
        positions: ``(n, 2)`` int positions in map coordinates.
        actions: ``(n,)`` int actions in ``0..4``.

    Returns:
        ``(new_positions, hit)``: a move into a wall or off the grid leaves the agent in place and
        sets ``hit``; ``stay`` never hits.
    """
    target = positions + MOVES[actions]
    hit = cells[target[:, 0] + pad, target[:, 1] + pad] == CELL_WALL
    new_positions = np.where(hit[:, None], positions, target)
    return new_positions, hit


def credit_new_cells(
    cells: np.ndarray, pad: int, positions: np.ndarray, credited_by: np.ndarray
) -> np.ndarray:
    """Visit the agents' cells in index order; mark and credit the unvisited ones.

    When two agents enter the same unvisited cell in one step the lower index is credited, because
    it visits the cell first. Mutates ``cells`` and ``credited_by``.

    Returns:
        ``(n,)`` int array: 1 where the agent was credited with a new cell.
    """
    n = positions.shape[0]
    credited = np.zeros(n, dtype=np.int64)
    rows = (positions[:, 0] + pad).tolist()
    cols = (positions[:, 1] + pad).tolist()
    # A loop over agents (a handful), not cells: scalar reads of a few cells beat building
    # masks for n <= ~16 agents.
    for i in range(n):
        if cells[rows[i], cols[i]] == CELL_UNVISITED:
            cells[rows[i], cols[i]] = CELL_VISITED
            credited_by[rows[i] - pad, cols[i] - pad] = i
            credited[i] = 1
    return credited


def thesis_reward(
    credited: np.ndarray, hit: np.ndarray, new_cell: float, wall_hit: float, step: float
) -> np.ndarray:
    """Per-agent reward of eq. 3.1: ``new_cell * n_new + wall_hit * hit + step`` (float32)."""
    return (new_cell * credited + wall_hit * hit + step).astype(np.float32)
