"""Compiled distance fields on the padded grid: the coordinated planners' and the goal action's
shortest paths through the cells the team has seen.

:func:`distance_fields` gives, for several start cells, every cell's path length through
``passable`` cells (4-connected, every step costs one) and its predecessor on a shortest path.
On a grid many shortest paths tie, and a planner's first move is read from the predecessors, so
which tied predecessor a cell gets decides the episodes. The rule, one owner for every planner:

    a cell's predecessor is its neighbour one step nearer to the start with the highest cell
    index (flat, row-major): down before right before left before up.

It is the rule SciPy's :func:`scipy.sparse.csgraph.dijkstra` follows on this graph (its priority
queue takes equally near cells highest index first and keeps the first predecessor found), on
which the planners were measured and their numbers published; ``tests/test_paths.py`` checks the
two against each other, distances and predecessors cell for cell. Owning the rule here keeps the
planners' episodes from depending on the installed SciPy's queue.

Why compiled: one breadth-first search per start touches only the cells it reaches (about 500
within a planner's horizon of 15 steps, of 2,704 on a padded 50x50 map), where SciPy's call
first validates a sparse graph that the planners would have to keep up to date, and resets every
cell of it for each start.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = [
    "UNREACHED",
    "breadth_first",
    "distance_fields",
    "first_step",
    "move_towards",
    "walk_back",
]

#: Predecessor of a cell no path reaches (and of each start), as SciPy writes it.
UNREACHED = -9999


@njit(cache=True, nogil=True)
def breadth_first(
    passable: np.ndarray,
    stride: int,
    start: int,
    limit: float,
    d: np.ndarray,
    queue: np.ndarray,
    target: np.ndarray,
    n_targets: int,
) -> int:
    """One start's path lengths into ``d`` (``inf`` where not reached), breadth first through
    ``passable`` cells, neighbours highest index first (the module's rule); the one search of
    :func:`distance_fields` and of the coordinated planners' costs.

    Paths longer than ``limit`` are not followed. With ``n_targets > 0`` (the number of
    ``target`` cells) the search ends as soon as every target is reached (a farther cell is no
    target's path length, and a path to a target runs through nearer cells only, all reached
    by then), and goes on past ``limit`` from where it stopped while no target lies within it
    (the same lengths as a new search without a limit). Returns how many cells it reached; they
    are ``queue``'s first, in the order reached (the start first).
    """
    # Two things make the loop about a quarter faster than its plain form
    # (research/performance-history.md, "The searches' inner loop"): unsigned cell indices (numba
    # adds a wrap-around for negative indices to every signed one), and one byte per cell,
    # "passable and not yet reached", tested in place of two arrays (passable, then d against inf).
    d[:] = np.inf
    unseen = passable.copy()
    down, right = np.uint64(stride), np.uint64(1)
    first = np.uint64(start)
    d[first] = 0.0
    unseen[first] = False
    queue[0] = start
    found = 1 if n_targets > 0 and target[first] else 0
    if not passable[first] or (n_targets > 0 and found == n_targets):
        return 1
    bound = float(limit)
    head, tail = np.uint64(0), np.uint64(1)
    while head < tail:
        v = np.uint64(queue[head])
        nd = d[v] + 1.0
        if nd > bound:  # cells leave the queue in distance order: the rest are as far
            if n_targets == 0 or found > 0:
                break
            bound = np.inf  # no target within the limit: on over the whole map
        head += right
        for w in (v + down, v + right, v - right, v - down):  # highest index first
            if unseen[w]:
                unseen[w] = False
                d[w] = nd
                queue[tail] = w
                tail += right
                if n_targets > 0 and target[w]:
                    found += 1
        if n_targets > 0 and found == n_targets:
            break
    return int(tail)


@njit(cache=True, nogil=True)
def distance_fields(
    passable: np.ndarray,
    stride: int,
    starts: np.ndarray,
    limit: float,
    dist: np.ndarray,
    pred: np.ndarray,
    queue: np.ndarray,
) -> None:
    """Shortest path lengths and predecessors from each of ``starts`` (module docstring).

    Args:
        passable: ``bool (cells,)``, the padded flat grid (its outer ring never passable).
        stride: Row length of the padded grid.
        starts: Start cells, one search each (:func:`breadth_first`; a start need not be
            passable: then it reaches nothing but itself).
        limit: Paths longer than this are not followed (``inf``: the whole map).
        dist: ``float64 (len(starts), cells)``, written: path lengths, ``inf`` where none.
        pred: ``int32 (len(starts), cells)``, written: predecessors, :data:`UNREACHED` where
            none and at the start; an array with no rows skips them (:func:`first_step` walks
            a path back from the distances alone).
        queue: ``int64 (cells,)`` scratch.
    """
    with_pred = pred.shape[0] > 0
    offsets = (stride, 1, -1, -stride)
    for i in range(starts.size):
        d = dist[i]
        tail = breadth_first(passable, stride, starts[i], limit, d, queue, passable, 0)
        if not with_pred:
            continue
        p = pred[i]
        p[:] = UNREACHED
        for j in range(1, tail):  # every reached cell but the start
            w = queue[j]
            before = d[w] - 1.0
            for k in range(4):
                u = w + offsets[k]
                if d[u] == before:  # a start is passable or reaches nothing
                    p[w] = u
                    break


@njit(cache=True, nogil=True)
def _nearer(dist: np.ndarray, cell: int, stride: int) -> int:
    """``cell``'s predecessor in one row of :func:`distance_fields` (``0 < dist[cell] < inf``),
    from the distances alone: its highest-index neighbour one step nearer (the module's rule)."""
    before = dist[cell] - 1.0
    for u in (cell + stride, cell + 1, cell - 1, cell - stride):
        if dist[u] == before:
            return u
    return cell  # not reached: a reached cell always has a nearer neighbour


@njit(cache=True, nogil=True)
def first_step(dist: np.ndarray, goal: int, stride: int) -> int:
    """The first cell of the path to ``goal`` (reached: ``0 < dist[goal] < inf``) in one row
    of :func:`distance_fields`: the path its predecessors give, walked back from the distances
    alone (each cell's predecessor is its highest-index neighbour one step nearer)."""
    step = goal
    while dist[step] > 1.0:
        step = _nearer(dist, step, stride)
    return step


@njit(cache=True, nogil=True)
def walk_back(dist: np.ndarray, goal: int, stride: int, out: np.ndarray) -> int:
    """The cells of the shortest path to ``goal`` in one row of :func:`distance_fields` (from
    its start, which is left out), walked back as :func:`first_step` walks, into ``out``;
    returns how many (0: ``goal`` is the start or not reached)."""
    if not dist[goal] < np.inf:
        return 0
    length = int(dist[goal])
    step = goal
    for j in range(length - 1, -1, -1):
        out[j] = step
        step = _nearer(dist, step, stride)
    return length


@njit(cache=True, nogil=True)
def move_towards(step: int, start: int, stride: int) -> int:
    """The move (0-3: up, down, left, right) from ``start`` to its neighbour ``step``."""
    d = step - start
    return 0 if d == -stride else 1 if d == stride else 2 if d == -1 else 3
