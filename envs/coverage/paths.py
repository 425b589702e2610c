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

__all__ = ["UNREACHED", "distance_fields", "first_step", "move_towards", "walk_back"]

#: Predecessor of a cell no path reaches (and of each start), as SciPy writes it.
UNREACHED = -9999


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
        starts: Start cells, one search each (a start need not be passable: then it reaches
            nothing but itself).
        limit: Paths longer than this are not followed (``inf``: the whole map).
        dist: ``float64 (len(starts), cells)``, written: path lengths, ``inf`` where none.
        pred: ``int32 (len(starts), cells)``, written: predecessors, :data:`UNREACHED` where
            none and at the start; an array with no rows skips them (:func:`first_step` walks
            a path back from the distances alone).
        queue: ``int64 (cells,)`` scratch.
    """
    with_pred = pred.shape[0] > 0
    offsets = (stride, 1, -1, -stride)  # highest neighbour index first: the predecessor rule
    for i in range(starts.size):
        d = dist[i]
        d[:] = np.inf
        s = starts[i]
        d[s] = 0.0
        head, tail = 0, 1
        queue[0] = s
        if passable[s]:
            while head < tail:
                v = queue[head]
                head += 1
                nd = d[v] + 1.0
                if nd > limit:
                    break  # cells leave the queue in distance order: the rest are as far
                for k in range(4):
                    w = v + offsets[k]
                    if passable[w] and d[w] == np.inf:
                        d[w] = nd
                        queue[tail] = w
                        tail += 1
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
