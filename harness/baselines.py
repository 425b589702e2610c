"""Non-learned reference policies: ``random``, the memoryless ``local`` rule and the classical
``frontier`` explorer.

Both are :data:`harness.evaluation.BatchPolicy` callables, so ``run_episodes`` evaluates them on
exactly the maps and start cells a trained model sees (``harness eval --policy frontier``).

``local`` is a hand-written rule that sees exactly what a learned agent sees (its own 13-number
observation, no memory): step into an unvisited neighbour if there is one; otherwise towards an
unvisited diagonal cell of the 3x3 window (a free neighbour beside it); otherwise into any free
neighbour; ties broken at random, ``stay`` only when boxed in. It never hits a wall. It answers
"what does this observation allow without learning?", the fair bar for a learned policy, where
the frontier explorer is the bar for any policy. Its random draws come from each env copy's
``np_random`` (seeded by the episode's reset), like the Boltzmann test policy, so an episode
repeats whatever the number of copies.

``frontier_step`` (only on an env with ``frontier_action``) always takes the env's frontier
step: the frontier explorer without claims, each agent heading for its own nearest unvisited
known cell.

``frontier`` is the classical frontier-based explorer (Yamauchi 1997) on the team's shared map:
every agent walks, by a shortest 4-connected path through free cells the team has *seen*, to the
nearest *target*: a seen free cell nobody has visited yet. Targets are claimed in agent index
order (agent 0 first), and an agent skips targets a lower-index teammate already claimed this
step, so a team spreads out instead of chasing one cell. "Seen" is what the thesis's observation
reveals: the visited cells and the 3x3 window around each of them. The frontier agent knows the
whole team's map, which a learned agent (13 numbers of local view) does not: it is a strong
reference, not a fair opponent. It only ever steps into seen free cells, so it never hits a wall.

Speed: the team's map only grows, so each env copy keeps it incrementally (updated from the
agents' positions each step, rebuilt when an episode starts). The search is a breadth-first search
in Python that stops at the first unclaimed target; most of the time that target is a step or two
away. When a search grows past ~100 cells (late in an episode, when the remaining ground is far
away) it is redone by SciPy's compiled breadth-first search on a graph of the seen free cells,
rebuilt only when a cell became passable since the last such search; an agent whose target was
far goes straight to SciPy on the next step. Both searches visit neighbours in the same order, so
the choice of target does not depend on which one ran. On a 2-core machine this evaluates about
7-8 episodes/s on 50x50 maps with 4 agents and 1000 steps (the env alone, stepped with random
actions, runs 13-17/s); ``tests/test_baselines.py`` has the timing command.
"""

from __future__ import annotations

import weakref
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order

from envs.coverage import CoverageEnv
from envs.coverage.types import CELL_UNVISITED, CELL_WALL, FRONTIER_STEP, STAY
from harness.evaluation import BatchPolicy, batch_len, episode_draws, sample_categorical

#: The baselines by the name ``--policy`` takes (the one list of them), each made from the
#: evaluation's seed (only ``random`` uses it: the others draw from each episode's generator or
#: none).
BASELINES: dict[str, Callable[[int], BatchPolicy]] = {
    "random": lambda seed: RandomPolicy(seed),
    "local": lambda seed: LocalPolicy(),
    "frontier": lambda seed: FrontierPolicy(),
    "frontier_step": lambda seed: FrontierStepPolicy(),
}

#: Cells a Python search may reach before the compiled search takes over. Below it the Python
#: search wins (no graph to build); above it SciPy's search is cheaper even with a fresh graph.
_PY_SEARCH_BUDGET = 128
#: Path length above which an agent's next search skips the Python search.
_FAR = 8


def make_baseline(name: str, seed: int) -> BatchPolicy:
    """Make a baseline batched policy.

    Args:
        name: One of :data:`BASELINES`.
        seed: Seeds the random policy's generator (``local`` draws from each episode's own
            generator, ``frontier`` is deterministic).

    Returns:
        A ``policy(obs, envs) -> actions`` callable (see ``harness.evaluation.BatchPolicy``).

    Raises:
        ValueError: For an unknown name.
    """
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}; known: {', '.join(BASELINES)}")
    return BASELINES[name](seed)


class FrontierStepPolicy:
    """Every agent always takes the env's frontier step (``env.frontier_action``): one step along
    a shortest way to its nearest unvisited known cell, ties drawn from the episode's generator,
    no coordination. The bar a learned policy with that action must beat to show it learned
    more than "always take it" (to split up, say)."""

    def __call__(self, obs: Any, envs: Sequence[CoverageEnv]) -> np.ndarray:
        """The frontier step for every agent of every env copy."""
        if not all(env.frontier_action for env in envs):
            raise ValueError("the frontier_step baseline needs env.frontier_action: true")
        return np.full(batch_len(obs), FRONTIER_STEP, dtype=np.int64)


class RandomPolicy:
    """Uniform random actions 0..4 from a seeded generator (repeatable for a given seed)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs: np.ndarray, envs: Sequence[CoverageEnv]) -> np.ndarray:
        """One uniform action per agent in the batch."""
        return self.rng.integers(0, 5, size=batch_len(obs))


#: Window index (row-major 3x3, agent in the centre, 4) of the cell that each move
#: (0 up, 1 down, 2 left, 3 right) enters, and of the two diagonal cells beside that cell.
_MOVE_CELL = np.array([1, 7, 3, 5])
_MOVE_DIAGONALS = np.array([[0, 2], [6, 8], [0, 6], [2, 8]])


def local_actions(obs: np.ndarray, uniform: np.ndarray) -> np.ndarray:
    """The ``local`` rule for a batch of thesis observations (see the module docstring).

    Args:
        obs: ``(batch, >= 9)``: the 3x3 windows of thesis observations (-1 unvisited,
            0 visited, 1 wall) in their first 9 columns.
        uniform: ``(batch,)`` draws from U[0, 1), one per row, that break ties.

    Returns:
        ``(batch,)`` actions: a move among the rule's best candidates, ``stay`` (4) when no
        neighbour is free.
    """
    window = obs[:, :9]
    entered = window[:, _MOVE_CELL]
    free = entered != CELL_WALL
    unvisited = entered == CELL_UNVISITED
    toward = free & (window[:, _MOVE_DIAGONALS] == CELL_UNVISITED).any(axis=2)
    # The first non-empty class of candidates, per row: unvisited, then towards, then free.
    candidates = np.where(
        unvisited.any(axis=1, keepdims=True),
        unvisited,
        np.where(toward.any(axis=1, keepdims=True), toward, free),
    )
    boxed_in = ~candidates.any(axis=1, keepdims=True)  # then stay (action 4) is the candidate
    return sample_categorical(np.concatenate([candidates, boxed_in], axis=1).astype(float), uniform)


def thesis_windows(env: CoverageEnv) -> np.ndarray:
    """``(n_agents, 9)``: each agent's 3x3 window as the thesis observation shows it (-1
    unvisited free, 0 visited, 1 wall or outside), read from the env's state, so the local rule
    runs whatever observation the env gives its agents."""
    cells = np.where(env.walls, CELL_WALL, np.where(env.visited, 0.0, CELL_UNVISITED))
    padded = np.pad(cells, 1, constant_values=CELL_WALL)
    rows, cols = env.positions[:, 0], env.positions[:, 1]
    dr, dc = np.divmod(np.arange(9), 3)
    return padded[rows[:, None] + dr[None, :], cols[:, None] + dc[None, :]]


class LocalPolicy:
    """The memoryless ``local`` rule on each agent's 3x3 window (see the module docstring)."""

    def __call__(self, obs: np.ndarray, envs: Sequence[CoverageEnv]) -> np.ndarray:
        """Actions for every agent of every env copy, copy-major like ``obs``."""
        windows = np.concatenate([thesis_windows(env) for env in envs])
        return local_actions(windows, episode_draws(envs, len(windows) // len(envs)))


class FrontierPolicy:
    """Nearest-unclaimed-frontier explorer on the team's known map (see the module docstring)."""

    def __init__(self) -> None:
        # One team map per env copy; weak keys so finished envs do not pile up.
        self._maps: weakref.WeakKeyDictionary[CoverageEnv, _TeamMap] = weakref.WeakKeyDictionary()

    def __call__(self, obs: np.ndarray, envs: Sequence[CoverageEnv]) -> np.ndarray:
        """Actions for every agent of every env copy, copy-major like ``obs``."""
        actions: list[int] = []
        for env in envs:
            team = self._maps.get(env)
            if team is None or team.shape != (env.height, env.width):
                team = self._maps[env] = _TeamMap(env.height, env.width)
            team.sync(env)
            actions.extend(team.act())
        return np.asarray(actions, dtype=np.int64)


class _TeamMap:
    """The team's known map of one env copy, on a flat grid padded with one ring of wall.

    Padding lets neighbour lookups skip bounds checks; the per-cell state is kept in Python lists
    because the search reads single cells, which lists do several times faster than numpy.
    """

    def __init__(self, height: int, width: int) -> None:
        self.shape = (height, width)
        self.stride = width + 2
        # Neighbour offsets in ascending index order (up, left, right, down); the compiled search
        # visits neighbours in the same order, so both break ties between equally near targets
        # the same way.
        s = self.stride
        self.offsets = (-s, -1, 1, s)
        self.action_of = {-s: 0, s: 1, -1: 2, 1: 3}
        self.window = tuple(dr * s + dc for dr in (-1, 0, 1) for dc in (-1, 0, 1))
        self.steps = -1
        self.positions: list[int] = []
        #: Per agent: its last target was far, so its next search goes straight to SciPy (the
        #: distance shrinks by one a step, and the Python search would only hit its budget).
        self.far: list[bool] = []
        self._neighbours: np.ndarray | None = None

    # ------------------------------------------------------------------ map upkeep
    def sync(self, env: CoverageEnv) -> None:
        """Bring the map up to date with ``env``: incrementally when the policy saw the previous
        step (only the agents' current cells can be new), from scratch otherwise."""
        steps = env.steps
        pos = env.positions
        self.positions = ((pos[:, 0] + 1) * self.stride + pos[:, 1] + 1).tolist()
        if steps == 0 or not (self.steps <= steps <= self.steps + 1):
            self._rebuild(env)
        else:
            for p in self.positions:
                if not self.visited[p]:
                    self._visit(p)
        self.steps = steps

    def _rebuild(self, env: CoverageEnv) -> None:
        free = np.pad(~env.walls, 1, constant_values=False)
        visited = np.pad(env.visited, 1, constant_values=False)
        seen = visited.copy()
        # 3x3 dilation of the visited cells: what the agents' observation windows revealed.
        seen[1:, :] |= visited[:-1, :]
        seen[:-1, :] |= visited[1:, :]
        rows = seen.copy()
        seen[:, 1:] |= rows[:, :-1]
        seen[:, :-1] |= rows[:, 1:]
        passable = (seen & free).ravel()
        target = passable & ~visited.ravel()
        self.free = free.ravel().tolist()
        self.visited = visited.ravel().tolist()
        self.seen = seen.ravel().tolist()
        self.passable = passable.tolist()
        self.target = target.tolist()
        # numpy mirrors of the two lists the compiled search needs whole.
        self.passable_np = passable
        self.target_np = target
        self.n_targets = int(target.sum())
        self.graph_version = 0  # bumped whenever a cell becomes passable
        self.far = [False] * len(self.positions)
        self._graph: tuple[int, csr_matrix] | None = None

    def _visit(self, p: int) -> None:
        self.visited[p] = True
        if self.target[p]:
            self.target[p] = self.target_np[p] = False
            self.n_targets -= 1
        for d in self.window:
            q = p + d
            if not self.seen[q]:
                self.seen[q] = True
                if self.free[q]:
                    self.passable[q] = self.passable_np[q] = True
                    self.graph_version += 1
                    if not self.visited[q]:
                        self.target[q] = self.target_np[q] = True
                        self.n_targets += 1

    # ------------------------------------------------------------------ acting
    def act(self) -> list[int]:
        """One action per agent; targets are claimed in agent index order."""
        if self.n_targets == 0:  # everything seen is visited: nothing left to walk to
            return [STAY] * len(self.positions)
        claimed: set[int] = set()
        actions = []
        for i, start in enumerate(self.positions):
            if self.far[i]:
                found = self._search_compiled(start, claimed, i)
            else:
                found = self._search(start, claimed, i)
            if found is None:
                actions.append(STAY)
                continue
            goal, step = found
            claimed.add(goal)
            actions.append(self.action_of[step - start])
        return actions

    def _search(self, start: int, claimed: set[int], agent: int) -> tuple[int, int] | None:
        """Nearest unclaimed target from ``start`` and the first cell of a shortest path to it,
        or ``None`` when no unclaimed target is reachable through seen free cells."""
        passable, target, offsets = self.passable, self.target, self.offsets
        # Each reached cell remembers the first step of its path, so no back-tracking is needed.
        first = {start: start}
        queue = deque()
        for d in offsets:
            n = start + d
            if passable[n]:
                first[n] = n
                # Checked on discovery: BFS discovers cells in order of distance, so the first
                # unclaimed target discovered is a nearest one.
                if target[n] and n not in claimed:
                    return n, n
                queue.append(n)
        while queue:
            c = queue.popleft()
            f = first[c]
            for d in offsets:
                n = c + d
                if passable[n] and n not in first:
                    first[n] = f
                    if target[n] and n not in claimed:
                        return n, f
                    queue.append(n)
            if len(first) > _PY_SEARCH_BUDGET:
                return self._search_compiled(start, claimed, agent)
        return None

    def _search_compiled(self, start: int, claimed: set[int], agent: int) -> tuple[int, int] | None:
        """:meth:`_search` by SciPy's breadth-first search (for far targets). It visits
        neighbours in the same order, so both searches pick the same target."""
        order, pred = breadth_first_order(
            self._graph_now(), start, directed=True, return_predecessors=True
        )
        for goal in order[self.target_np[order]].tolist():
            if goal not in claimed:
                step, distance = goal, 1
                while pred[step] != start:
                    step = int(pred[step])
                    distance += 1
                self.far[agent] = distance > _FAR
                return goal, step
        # Nothing left for this agent (teammates claimed the last targets): that search saw the
        # whole reachable map, so the next one goes straight to SciPy too.
        self.far[agent] = True
        return None

    def _graph_now(self) -> csr_matrix:
        """Adjacency (CSR) of the seen free cells, cached until a cell becomes passable.

        Built straight in CSR form: each cell's neighbours in ascending index order (up, left,
        right, down), as :meth:`_search` visits them. The padding ring has no edges, so only the
        rows of the inner cells are computed.
        """
        if self._graph is not None and self._graph[0] == self.graph_version:
            return self._graph[1]
        p, s = self.passable_np, self.stride
        n = p.size
        inner = p[s:-s]
        mask = np.empty((n - 2 * s, 4), dtype=bool)
        np.logical_and(inner, p[: -2 * s], out=mask[:, 0])
        np.logical_and(inner, p[s - 1 : -s - 1], out=mask[:, 1])
        np.logical_and(inner, p[s + 1 : n - s + 1], out=mask[:, 2])
        np.logical_and(inner, p[2 * s :], out=mask[:, 3])
        if self._neighbours is None or len(self._neighbours) != n - 2 * s:
            cells = np.arange(s, n - s, dtype=np.int32)
            self._neighbours = cells[:, None] + np.array(self.offsets, dtype=np.int32)
        indices = self._neighbours[mask]
        counts = mask.view(np.uint8)
        degree = counts[:, 0] + counts[:, 1]  # summing columns beats count_nonzero(axis=1)
        degree += counts[:, 2]
        degree += counts[:, 3]
        indptr = np.zeros(n + 1, dtype=np.int32)
        np.cumsum(degree, out=indptr[s + 1 : n - s + 1])
        indptr[n - s + 1 :] = indptr[n - s]
        graph = csr_matrix((np.ones(indices.size), indices, indptr), shape=(n, n), copy=False)
        self._graph = (self.graph_version, graph)
        return graph
