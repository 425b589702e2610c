"""Helpers of the coverage environment's step (dynamics: ``envs/coverage_v0.py``), kept apart so
they can be tested and profiled on their own.

:func:`resolve_moves` and :func:`thesis_reward` are pure (they return new lists and change
nothing). :func:`credit_new_cells` updates the episode's grid in place (``cells`` and
``credited_by``): the grid is the env's state, and copying a padded map every step would cost
more than the rest of the step.

They work on Python lists of a handful of agents: per-agent numpy calls on arrays of 1-16
elements cost more in call overhead than the arithmetic they do, and the step runs millions of
times per training run. Nothing here loops over cells.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from envs.coverage.types import CELL_UNVISITED, CELL_VISITED, CELL_WALL, MOVES

_MOVES = tuple(tuple(m) for m in MOVES.tolist())


def resolve_moves(
    cells: np.ndarray, pad: int, positions: Sequence[Sequence[int]], actions: Sequence[int]
) -> tuple[list[tuple[int, int]], list[int]]:
    """Apply every agent's action.

    Agents never block each other (they may share a cell) and walls do not move, so resolving the
    moves "one agent at a time in index order" gives the same positions as resolving them together;
    order only matters for who is credited with a new cell (see :func:`credit_new_cells`).

    Args:
        cells: Padded cell grid (walls and the outside are ``CELL_WALL``).
        pad: Padding width of ``cells``.
        positions: ``(row, col)`` of each agent in map coordinates.
        actions: Each agent's action in ``0..4``.

    Returns:
        ``(new_positions, hit)``: a move into a wall or off the grid leaves the agent in place and
        sets ``hit`` to 1; ``stay`` never hits.
    """
    new_positions: list[tuple[int, int]] = []
    hit: list[int] = []
    item = cells.item
    for (r, c), a in zip(positions, actions):
        dr, dc = _MOVES[a]
        if item(r + dr + pad, c + dc + pad) == CELL_WALL:
            new_positions.append((r, c))
            hit.append(1)
        else:
            new_positions.append((r + dr, c + dc))
            hit.append(0)
    return new_positions, hit


def credit_new_cells(
    cells: np.ndarray, pad: int, positions: Sequence[Sequence[int]], credited_by: np.ndarray
) -> list[int]:
    """Visit the agents' cells in index order; mark and credit the unvisited ones.

    When two agents enter the same unvisited cell in one step the lower index is credited, because
    it visits the cell first. Not pure: it changes ``cells`` and ``credited_by`` in place (they
    are the episode's state; see the module docstring).

    Args:
        cells: Padded cell grid; each newly visited cell becomes ``CELL_VISITED`` (in place).
        pad: Padding width of ``cells``.
        positions: ``(row, col)`` of each agent in map coordinates, in index order.
        credited_by: ``(H, W)`` agent index per visited cell; set for the new cells (in place).

    Returns:
        1 for each agent credited with a new cell, else 0.
    """
    credited: list[int] = []
    item = cells.item
    for i, (r, c) in enumerate(positions):
        if item(r + pad, c + pad) == CELL_UNVISITED:
            cells[r + pad, c + pad] = CELL_VISITED
            credited_by[r, c] = i
            credited.append(1)
        else:
            credited.append(0)
    return credited


def thesis_reward(
    credited: Sequence[int],
    hit: Sequence[int],
    new_cell: float,
    wall_hit: float,
    step: float,
    team: float = 0.0,
) -> list[float]:
    """Per-agent reward of eq. 3.1: ``new_cell * n_new + wall_hit * hit + step`` (pure: a new
    list), where with a team share ``team`` > 0 ``n_new`` is ``(1 - team) * own + team * all``:
    the agent's own new cells and the whole team's, so that at ``team=1`` every agent is paid
    for every cell the team finds (a team reward)."""
    if team:
        total = sum(credited)
        return [
            new_cell * ((1.0 - team) * n + team * total) + wall_hit * h + step
            for n, h in zip(credited, hit)
        ]
    return [new_cell * n + wall_hit * h + step for n, h in zip(credited, hit)]
