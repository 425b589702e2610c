"""The compiled distance fields (envs.coverage.paths): hand-built grids, and SciPy's Dijkstra on
the same graph giving the same distances and predecessors, cell for cell (the planners' first
moves, and so their published numbers, are read from the predecessors)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from envs.coverage.paths import UNREACHED, breadth_first, distance_fields, first_step


def scipy_graph(passable: np.ndarray, stride: int, all_edges: bool) -> csr_matrix:
    """The grid as the planners gave it to SciPy, written out edge by edge: the edges of every
    cell between the padding rows in ascending index order, of weight 1 between two passable
    cells; with ``all_edges`` the others too, of infinite weight (the coordinated planners'
    weighted grid), else none (the goal action's graph)."""
    n = passable.size
    indptr, indices, data = [0], [], []
    for v in range(n):
        if stride <= v < n - stride:
            for w in (v - stride, v - 1, v + 1, v + stride):
                both = bool(passable[v] and passable[w])
                if both or all_edges:
                    indices.append(w)
                    data.append(1.0 if both else np.inf)
        indptr.append(len(indices))
    return csr_matrix((np.array(data), np.array(indices), np.array(indptr)), shape=(n, n))


def padded(free: np.ndarray) -> np.ndarray:
    return np.pad(free, 1, constant_values=False).ravel()


def fields(passable: np.ndarray, stride: int, starts, limit: float = np.inf):
    starts = np.asarray(starts, dtype=np.int64)
    dist = np.empty((starts.size, passable.size))
    pred = np.empty((starts.size, passable.size), dtype=np.int32)
    distance_fields(passable, stride, starts, limit, dist, pred, np.empty(passable.size, np.int64))
    return dist, pred


@st.composite
def grids(draw) -> tuple[np.ndarray, int, np.random.Generator]:
    """A padded random grid (at least one free cell), its stride and a generator for starts."""
    h, w = draw(st.integers(1, 12)), draw(st.integers(1, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    free = rng.random((h, w)) >= draw(st.floats(0.0, 0.6))
    free.flat[rng.integers(free.size)] = True
    return padded(free), w + 2, rng


@settings(max_examples=300, deadline=None)
@given(
    grid=grids(),
    n_starts=st.integers(1, 4),
    limit=st.sampled_from([np.inf, 0.0, 1.0, 3.0, 15.0, 2.5]),
    all_edges=st.booleans(),
)
def test_equals_scipy(grid, n_starts, limit, all_edges) -> None:
    passable, stride, rng = grid
    starts = rng.choice(np.flatnonzero(passable), n_starts)  # repeats allowed (agents meet)
    want_d, want_p = dijkstra(
        scipy_graph(passable, stride, all_edges),
        indices=starts,
        return_predecessors=True,
        limit=limit,
    )
    dist, pred = fields(passable, stride, starts, limit)
    np.testing.assert_array_equal(dist, want_d)
    np.testing.assert_array_equal(pred, want_p)


def test_open_room_by_hand() -> None:
    """A 2x3 room (padded stride 5), start at its top left (cell 6): distances by hand; the
    cell below-right of the start (12) has two neighbours one step nearer, 7 (above) and 11
    (left): the higher index, 11, is its predecessor."""
    passable = padded(np.ones((2, 3), dtype=bool))
    dist, pred = fields(passable, 5, [6])
    np.testing.assert_array_equal(dist[0].reshape(4, 5)[1:3, 1:4], [[0, 1, 2], [1, 2, 3]])
    assert np.isinf(dist[0, 0])  # the padding
    assert pred[0, 6] == UNREACHED
    assert pred[0, 7] == 6 and pred[0, 11] == 6 and pred[0, 12] == 11 and pred[0, 13] == 12


def test_walls_and_limit_by_hand() -> None:
    """A corridor bent round a wall: the far side is 4 steps away, and cut off by a limit."""
    free = np.array([[1, 1, 1], [0, 0, 1], [1, 1, 1]], dtype=bool)  # padded stride 5
    passable = padded(free)
    start, far = 1 * 5 + 1, 3 * 5 + 1
    dist, pred = fields(passable, 5, [start])
    assert dist[0, far] == 6 and pred[0, far] == far + 1
    assert np.isinf(dist[0, 2 * 5 + 1])  # a wall
    dist, pred = fields(passable, 5, [start], limit=3.0)
    assert dist[0, 2 * 5 + 3] == 3 and np.isinf(dist[0, 3 * 5 + 3])
    assert pred[0, 3 * 5 + 3] == UNREACHED


def test_unpassable_start_reaches_nothing() -> None:
    passable = padded(np.array([[1, 0, 1]], dtype=bool))
    dist, pred = fields(passable, 5, [7])
    assert dist[0, 7] == 0 and np.isinf(np.delete(dist[0], 7)).all()
    assert (pred == UNREACHED).all()


@pytest.mark.parametrize("limit", [np.inf, 2.0])
def test_several_starts_are_independent(limit: float) -> None:
    passable = padded(np.ones((3, 4), dtype=bool))
    both_d, both_p = fields(passable, 6, [7, 20], limit)
    for i, s in enumerate([7, 20]):
        d, p = fields(passable, 6, [s], limit)
        np.testing.assert_array_equal(both_d[i], d[0])
        np.testing.assert_array_equal(both_p[i], p[0])


@settings(max_examples=200, deadline=None)
@given(grid=grids(), limit=st.sampled_from([np.inf, 3.0, 15.0]))
def test_first_step_walks_the_predecessors_back(grid, limit) -> None:
    """The first cell of every path, walked back from the distances alone, is the one the
    predecessors give."""
    passable, stride, rng = grid
    start = int(rng.choice(np.flatnonzero(passable)))
    dist, pred = fields(passable, stride, [start], limit)
    for goal in np.flatnonzero((dist[0] > 0) & (dist[0] < np.inf)).tolist():
        step = goal
        while pred[0, step] != start:
            step = pred[0, step]
        assert first_step(dist[0], goal, stride) == step


def test_no_predecessors_asked_for() -> None:
    passable = padded(np.ones((2, 3), dtype=bool))
    dist = np.empty((1, passable.size))
    none = np.empty((0, 0), dtype=np.int32)
    queue = np.empty(passable.size, np.int64)
    distance_fields(passable, 5, np.array([6]), np.inf, dist, none, queue)
    assert dist[0, 13] == 3 and first_step(dist[0], 13, 5) == 11  # via the cell below the start


def test_breadth_first_stops_once_every_target_is_reached_and_passes_the_limit_for_one() -> None:
    # A 1x7 corridor, start at its left end (padded: stride 9, the corridor cells 10-16).
    passable = padded(np.ones((1, 7), dtype=bool))
    queue = np.empty(passable.size, np.int64)
    d = np.empty(passable.size)
    target = np.zeros(passable.size, dtype=bool)
    target[12] = True  # 2 steps away
    reached = breadth_first(passable, 9, 10, np.inf, d, queue, target, 1)
    # cells 10, 11, 12 reached, then the search ends: the farther cells keep no length
    assert reached == 3 and queue[:3].tolist() == [10, 11, 12]
    assert d[12] == 2 and d[13] == np.inf
    # No target within a limit of 2: it goes on until the one 5 steps away, the same lengths.
    target[:] = False
    target[15] = True
    assert breadth_first(passable, 9, 10, 2.0, d, queue, target, 1) == 6
    assert d[15] == 5 and d[16] == np.inf
    # Without targets the limit ends it: 0, 1 and 2 steps.
    assert breadth_first(passable, 9, 10, 2.0, d, queue, target, 0) == 3
    assert d[13] == np.inf
