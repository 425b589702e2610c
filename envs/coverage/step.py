"""The rules of the coverage env's step, compiled: one call steps every agent of every copy of a
batch (``envs/coverage/core.py`` holds the batch; ``envs/coverage_v0.py`` states the rules).

Arrays carry the batch on the first axis: ``cells`` ``(B, Hp, Wp)`` float32 (each copy's map
padded with wall, cell codes of :mod:`envs.coverage.types`), ``positions`` ``(B, N, 2)`` int64,
``actions`` ``(B, N)`` in ``0..4``. The kernels change the episode state in place (the arrays are
the state; copying a batch of padded maps each step would cost more than the step).

They are compiled with numba: the rules walk the agents of a copy in index order (the lower index
is credited first), which array operations over the batch cannot express without a loop over
agents in Python, and per-agent Python was the cost of the env before the batched core.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from envs.coverage.types import CELL_UNVISITED, CELL_VISITED, CELL_WALL, MOVES

_DR = np.ascontiguousarray(MOVES[:, 0])
_DC = np.ascontiguousarray(MOVES[:, 1])
_WALL = np.float32(CELL_WALL)
_UNVISITED = np.float32(CELL_UNVISITED)
_VISITED = np.float32(CELL_VISITED)


@njit(cache=True, nogil=True)
def move_agents(
    cells: np.ndarray, pad: int, positions: np.ndarray, actions: np.ndarray, hit: np.ndarray
) -> None:
    """Apply every agent's action (in place on ``positions``).

    A move into a wall or off the grid leaves the agent where it is and sets ``hit[b, i]`` to 1;
    ``stay`` never hits. Agents never block each other (they may share a cell) and walls do not
    move, so resolving the moves one agent at a time in index order gives the same positions as
    resolving them together; order only matters for credit (:func:`visit_cells`).
    """
    for b in range(actions.shape[0]):
        for i in range(actions.shape[1]):
            a = actions[b, i]
            r = positions[b, i, 0] + _DR[a]
            c = positions[b, i, 1] + _DC[a]
            if cells[b, r + pad, c + pad] == _WALL:
                hit[b, i] = 1
            else:
                hit[b, i] = 0
                positions[b, i, 0] = r
                positions[b, i, 1] = c


@njit(cache=True, nogil=True)
def visit_cells(
    cells: np.ndarray,
    pad: int,
    positions: np.ndarray,
    credited_by: np.ndarray,
    credited: np.ndarray,
) -> None:
    """Visit the agents' cells in index order: an unvisited cell becomes visited, the agent is
    credited (``credited[b, i] = 1``) and ``credited_by`` records it. When two agents enter the
    same unvisited cell in one step the lower index is credited: it visits the cell first."""
    for b in range(positions.shape[0]):
        for i in range(positions.shape[1]):
            r = positions[b, i, 0]
            c = positions[b, i, 1]
            if cells[b, r + pad, c + pad] == _UNVISITED:
                cells[b, r + pad, c + pad] = _VISITED
                credited_by[b, r, c] = i
                credited[b, i] = 1
            else:
                credited[b, i] = 0


@njit(cache=True, nogil=True)
def step_batch(
    cells: np.ndarray,
    pad: int,
    positions: np.ndarray,
    actions: np.ndarray,
    credited_by: np.ndarray,
    steps: np.ndarray,
    n_visited: np.ndarray,
    new_cells: np.ndarray,
    wall_hits: np.ndarray,
    weights: np.ndarray,
    hit: np.ndarray,
    credited: np.ndarray,
    reward: np.ndarray,
) -> None:
    """One step of every copy: moves, credit, the episode's counters and each agent's reward.

    The reward is eq. 3.1, ``new_cell * n_new + wall_hit * hit + step`` with ``weights`` =
    ``(new_cell, wall_hit, step, team)``; with a team share ``team > 0``, ``n_new`` is
    ``(1 - team) * own + team * all``: the agent's own new cells and the whole team's, so that at
    ``team = 1`` every agent is paid for every cell the team finds. The arithmetic is float64 in
    the order written, so a reward equals the plain Python expression's bit for bit.
    """
    move_agents(cells, pad, positions, actions, hit)
    visit_cells(cells, pad, positions, credited_by, credited)
    new_cell, wall_hit, step, team = weights[0], weights[1], weights[2], weights[3]
    for b in range(actions.shape[0]):
        steps[b] += 1
        total = 0
        for i in range(actions.shape[1]):
            total += credited[b, i]
            new_cells[b, i] += credited[b, i]
            wall_hits[b, i] += hit[b, i]
        n_visited[b] += total
        for i in range(actions.shape[1]):
            if team != 0.0:
                n_new = (1.0 - team) * credited[b, i] + team * total
                reward[b, i] = new_cell * n_new + wall_hit * hit[b, i] + step
            else:
                reward[b, i] = new_cell * credited[b, i] + wall_hit * hit[b, i] + step


@njit(cache=True, nogil=True)
def thesis_observation(
    cells: np.ndarray, pad: int, positions: np.ndarray, scale: np.ndarray, out: np.ndarray
) -> None:
    """The thesis's 13-element observation (§3.2) of every agent of every copy into ``out``
    ``(B, N, 13)`` float32 (``scale`` ``(B, 2)`` float32: 1/(H-1), 1/(W-1), or ones for raw
    coordinates): the 3x3 window row-major from the top-left, the own (row, col) times the scale,
    and the nearest other agent's (Euclidean, ties to the lower index; a lone agent sees itself).
    A coordinate is ``float32(row * float64(scale))``, numpy's promotion of an int64 position by a
    float32 scale."""
    n = positions.shape[1]
    for b in range(positions.shape[0]):
        sr = np.float64(scale[b, 0])
        sc = np.float64(scale[b, 1])
        for i in range(n):
            r = positions[b, i, 0]
            c = positions[b, i, 1]
            k = 0
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    out[b, i, k] = cells[b, r + pad + dr, c + pad + dc]
                    k += 1
            out[b, i, 9] = r * sr
            out[b, i, 10] = c * sc
            best = -1
            j_best = i
            for j in range(n):
                if j != i:
                    d_r = r - positions[b, j, 0]
                    d_c = c - positions[b, j, 1]
                    d = d_r * d_r + d_c * d_c
                    if best < 0 or d < best:  # strict: the lowest index wins a tie
                        best = d
                        j_best = j
            out[b, i, 11] = positions[b, j_best, 0] * sr
            out[b, i, 12] = positions[b, j_best, 1] * sc
