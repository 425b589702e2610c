"""The planners of the planner extension (``envs.coverage.frontier`` registers them).

**The classical frontier explorer** (Yamauchi 1997, :class:`FrontierPlanner`) on the team's
shared map, for one episode.

Every agent walks, by a shortest 4-connected path through free cells the team has *seen*, to the
nearest *target*: a seen free cell nobody has visited yet. Targets are claimed in agent index
order (agent 0 first), and an agent skips targets a lower-index teammate already claimed this
step, so a team spreads out instead of chasing one cell. "Seen" is the env's *known*: the visited
cells and the 3x3 window around each of them (start windows included, start cells being visited).

Ties between equally near targets (``tie_break``) are frequent, and how they break matters:

- ``"order"`` (the classical explorer, the default): the first target the search discovers,
  neighbours visited up, left, right, down, so the team keeps sweeping in one consistent way;
- ``"pocket"``: the target with the fewest *open* neighbours (unseen, or seen free and not yet
  visited), then ``"order"``: finish a pocket before leaving it, so less ground is left behind to
  walk back to;
- ``"random"``: uniformly among them, from a generator the caller passes (the episode's): what a
  policy that is right about *how far* but noisy about *which* looks like.

Speed: the team's map only grows, so the planner keeps it incrementally (updated from the
agents' positions each step, rebuilt when an episode starts). The search is one compiled
breadth-first search per agent (:func:`nearest_targets`, numba) that visits neighbours up, left,
right, down and stops when the nearest distance layer holding an unclaimed target is complete
(``"order"``: at the first such target it discovers); most of the time that target is a step or
two away.

**Coordinated planners** (:class:`CoordinatedPlanner`): the team's assignment of targets is
chosen together, from one distance field per agent per step (a compiled breadth-first search
through the seen free cells, :mod:`envs.coverage.paths`, reused for every candidate; its rule
for tied paths is that of SciPy's ``dijkstra``, on which the planners were measured):
:class:`UtilityPlanner` (Burgard et al. 2005), :class:`MinPosPlanner` (Bautin et al. 2012) and
:class:`HungarianPlanner` (an optimal assignment by :func:`scipy.optimize.linear_sum_assignment`,
compiled: :func:`linear_sum_assignment_compiled`, SciPy's algorithm step for step).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numba import njit, types
from numba.experimental import structref
from scipy.ndimage import label

from envs.coverage.paths import breadth_first, distance_fields, first_step, move_towards
from envs.coverage.types import STAY

__all__ = [
    "CANDIDATES",
    "TIE_BREAKS",
    "CoordinatedPlanner",
    "FrontierPlanner",
    "HungarianPlanner",
    "MinPosPlanner",
    "UtilityPlanner",
]


@structref.register
class _GeneratorRefType(types.StructRef):
    """numba's type of :class:`_GeneratorRef`."""


class _GeneratorRef(structref.StructRefProxy):
    """A NumPy ``Generator`` held for compiled code (its field ``rng``).

    numba types and unboxes a ``Generator`` argument anew on every call (about 15 µs, reading
    its bit generator's ctypes pointers), a third of the random explorer's step; a struct
    holding it is unboxed once, when made, and then passes as a pointer (under 1 µs) while
    still drawing from the generator's own state: the draws are NumPy's, interleaved with the
    caller's, in order.
    """

    def __new__(cls, rng: np.random.Generator) -> _GeneratorRef:
        return structref.StructRefProxy.__new__(cls, rng)


structref.define_proxy(_GeneratorRef, _GeneratorRefType, ["rng"])

#: Rows of :attr:`FrontierPlanner.grid`: the per-cell state of the team's map.
_FREE, _VISITED, _SEEN, _PASSABLE, _TARGET = range(5)
#: How :class:`FrontierPlanner` chooses among equally near unclaimed targets (module docstring).
TIE_BREAKS = ("order", "pocket", "random")


@njit(cache=True, nogil=True)
def nearest_targets(
    passable: np.ndarray,
    target: np.ndarray,
    claimed: np.ndarray,
    start: int,
    offsets: np.ndarray,
    all_ties: bool,
    first: np.ndarray,
    queue: np.ndarray,
    ties: np.ndarray,
    firsts: np.ndarray,
) -> int:
    """Breadth-first search from ``start`` through ``passable`` cells (flat, padded; neighbours
    in the order of ``offsets``) for unclaimed ``target`` cells.

    Writes the targets of the nearest distance layer that holds any, in the order the search
    discovers them, to ``ties`` and the first cell of each one's path (the search tree's) to
    ``firsts``, and returns how many; with ``all_ties`` False it stops at the first (the
    classical explorer's choice). ``first`` and ``queue`` are scratch arrays of the grid's size;
    ``first`` comes in all -1 and is left so (only the cells the search reached are reset: the
    nearest target is mostly a few steps away, the grid thousands of cells).
    """
    first[start] = start
    queue[0] = start
    head, tail, layer_end, count = 0, 1, 1, 0
    done = False
    while head < tail and not done:
        c = queue[head]
        head += 1
        f = first[c]
        for d in offsets:
            m = c + d
            if passable[m] and first[m] < 0:
                first[m] = m if c == start else f
                queue[tail] = m
                tail += 1
                if target[m] and not claimed[m]:
                    ties[count] = m
                    firsts[count] = first[m]
                    count += 1
                    if not all_ties:
                        done = True
                        break
        if head == layer_end:  # a distance layer is complete
            if count > 0:
                done = True
            layer_end = tail
    for j in range(tail):
        first[queue[j]] = -1
    return count


@njit(cache=True, nogil=True)
def _visit_cells(cells: np.ndarray, window: np.ndarray, grid: np.ndarray) -> int:
    """Mark ``cells`` visited in order, and each one's 3x3 ``window`` seen, in the planner's
    ``grid`` (:attr:`FrontierPlanner.grid`): a seen free cell becomes passable, and a target
    until it is visited. Returns the change in the number of targets."""
    free, visited, seen = grid[_FREE], grid[_VISITED], grid[_SEEN]
    passable, target = grid[_PASSABLE], grid[_TARGET]
    change = 0
    for p in cells:
        if visited[p]:
            continue
        visited[p] = True
        if target[p]:
            target[p] = False
            change -= 1
        for d in window:
            q = p + d
            if not seen[q]:
                seen[q] = True
                if free[q]:
                    passable[q] = True
                    if not visited[q]:
                        target[q] = True
                        change += 1
    return change


#: Tie-breaks as the compiled step takes them (:data:`TIE_BREAKS`' order).
_ORDER, _POCKET, _RANDOM = range(3)


@njit(cache=True, nogil=True)
def _plan(
    passable: np.ndarray,
    target: np.ndarray,
    seen: np.ndarray,
    starts: np.ndarray,
    offsets: np.ndarray,
    tie: int,
    claimed: np.ndarray,
    n_targets: int,
    scratch: np.ndarray,
    held: _GeneratorRef | None,
    goals: np.ndarray,
    actions: np.ndarray,
) -> None:
    """The frontier explorer's step for every agent: targets claimed in agent index order, each
    agent's nearest unclaimed target (``goals``, -1 for none) and its first move (``actions``).

    Ties between equally near targets by ``tie`` (:data:`_ORDER`, :data:`_POCKET` or
    :data:`_RANDOM`; the module docstring): with ``_RANDOM`` a uniform draw from ``held.rng``
    (``rng.integers(n)``; no draw when there is one), the episode's generator itself (numba's
    ``Generator`` draws NumPy's numbers from its state); ``held`` is ``None`` for the others.
    ``claimed`` comes in all False and is left so; ``n_targets`` is the number of targets (once
    every one is claimed, the agents left stay without a search); ``scratch`` ``(4, cells)``
    int64, its first row all -1 (:func:`nearest_targets`)."""
    stride = offsets[3]
    first, queue, ties, firsts = scratch[0], scratch[1], scratch[2], scratch[3]
    for i in range(starts.size):
        start = starts[i]
        # Once every target is claimed (each agent before claimed at most one), none is left.
        n = 0
        if i < n_targets:
            n = nearest_targets(passable, target, claimed, start, offsets, tie != _ORDER, first,
                                queue, ties, firsts)  # fmt: skip
        if n == 0:
            goals[i], actions[i] = -1, STAY
            continue
        pick = 0
        if tie == _POCKET:  # the fewest open neighbours (unseen, or a target); the first of equals
            fewest = 5
            for j in range(n):
                g = ties[j]
                count = 0
                for d in offsets:
                    if not seen[g + d] or target[g + d]:
                        count += 1
                if count < fewest:
                    pick, fewest = j, count
        elif held is not None and n > 1:  # (compiled away where held is None)
            pick = held.rng.integers(0, n)
        goal, step = ties[pick], firsts[pick]
        claimed[goal] = True
        goals[i] = goal
        actions[i] = move_towards(step, start, stride)
    for i in range(starts.size):
        if goals[i] >= 0:
            claimed[goals[i]] = False


@njit(cache=True, nogil=True)
def _sync(
    positions: np.ndarray, stride: int, window: np.ndarray, grid: np.ndarray, starts: np.ndarray
) -> int:
    """The agents' padded cells (``starts``) from ``positions`` ``(agents, 2)``, and the map
    brought up to date (:func:`_visit_cells`); returns the change in the number of targets."""
    for i in range(starts.size):
        starts[i] = (positions[i, 0] + 1) * stride + positions[i, 1] + 1
    return _visit_cells(starts, window, grid)


@njit(cache=True, nogil=True)
def _sync_and_plan(
    positions: np.ndarray,
    window: np.ndarray,
    grid: np.ndarray,
    n_targets: int,
    offsets: np.ndarray,
    tie: int,
    claimed: np.ndarray,
    scratch: np.ndarray,
    held: _GeneratorRef | None,
    starts: np.ndarray,
    goals: np.ndarray,
    actions: np.ndarray,
) -> int:
    """One step of :class:`FrontierPlanner` in one call: the agents' padded cells and the map
    (:func:`_sync`) and, while targets are left, the moves (:func:`_plan`, ``tie`` and
    ``held`` as there; else every agent stays with no goal). Returns the number of targets
    now."""
    n_targets += _sync(positions, offsets[3], window, grid, starts)
    if n_targets == 0:
        goals[:] = -1
        actions[:] = STAY
        return n_targets
    _plan(
        grid[_PASSABLE], grid[_TARGET], grid[_SEEN], starts, offsets, tie, claimed, n_targets,
        scratch, held, goals, actions,
    )  # fmt: skip
    return n_targets


class FrontierPlanner:
    """The frontier explorer's team map of one episode, on a flat grid padded with one ring of
    wall, and its moves (see the module docstring).

    Call :meth:`sync` with the episode's state after every reset and step, then :meth:`act`.
    ``tie_break`` is one of :data:`TIE_BREAKS`.

    Padding lets neighbour lookups skip bounds checks. The per-cell state, ``grid`` (bool
    ``(5, cells)`` over the padded grid, flat; its rows also named ``free``, ``visited``,
    ``seen``, ``passable`` and ``target``), is kept up to date and searched by compiled
    functions, one call per step (:meth:`step`).
    """

    def __init__(self, height: int, width: int, tie_break: str = "order") -> None:
        if tie_break not in TIE_BREAKS:
            raise ValueError(f"unknown tie_break {tie_break!r}; known: {', '.join(TIE_BREAKS)}")
        self.tie_break = tie_break
        self.rng: np.random.Generator | None = None  # act()'s generator, for "random" ties
        self._held_rng: tuple[np.random.Generator, _GeneratorRef] | None = None  # for _plan
        self.shape = (height, width)
        self.stride = width + 2
        # Neighbour offsets in ascending index order (up, left, right, down); the compiled search
        # visits neighbours in the same order, so both break ties between equally near targets
        # the same way.
        s = self.stride
        self.offsets = np.array([-s, -1, 1, s], dtype=np.int64)
        self.window = np.array([dr * s + dc for dr in (-1, 0, 1) for dc in (-1, 0, 1)], np.int64)
        self.steps = -1
        self.positions: list[int] = []
        #: Per agent: the padded cell of its target at the last :meth:`act` (-1: none).
        self.goals: list[int] = []
        self._scratch: np.ndarray | None = None
        #: :meth:`work_arrays`'s pair, kept while the team and the map's size stay.
        self._work: tuple[np.ndarray, np.ndarray] | None = None
        self._claimed: np.ndarray | None = None

    # ------------------------------------------------------------------ map upkeep
    def sync(
        self,
        steps: int,
        positions: np.ndarray,
        read_map: Callable[[], tuple[np.ndarray, np.ndarray]],
    ) -> None:
        """Bring the map up to date: incrementally when the planner saw the previous step (only
        the agents' current cells can be new), from scratch otherwise.

        Args:
            steps: Steps taken in the episode (0 right after a reset).
            positions: ``(n_agents, 2)`` (row, col) of each agent.
            read_map: Returns ``(walls, visited)``, both ``bool (H, W)``; called only when the
                map is rebuilt (an episode's start, or a step the planner did not see), so the
                per-step path never builds whole-map arrays.
        """
        starts = ((positions[:, 0] + 1) * self.stride + positions[:, 1] + 1).astype(np.int64)
        self.positions = starts.tolist()
        if steps == 0 or not (self.steps <= steps <= self.steps + 1):
            self._rebuild(*read_map())
        else:
            self.n_targets += _visit_cells(starts, self.window, self.grid)
        self.steps = steps

    def _rebuild(self, walls: np.ndarray, visited_map: np.ndarray) -> None:
        free = np.pad(~walls, 1, constant_values=False)
        visited = np.pad(visited_map, 1, constant_values=False)
        seen = visited.copy()
        # 3x3 dilation of the visited cells: what the agents' observation windows revealed.
        seen[1:, :] |= visited[:-1, :]
        seen[:-1, :] |= visited[1:, :]
        rows = seen.copy()
        seen[:, 1:] |= rows[:, :-1]
        seen[:, :-1] |= rows[:, 1:]
        # Outside the grid is known wall (as in the env's team map), never open ground.
        seen[[0, -1], :] = seen[:, [0, -1]] = True
        passable = (seen & free).ravel()
        target = passable & ~visited.ravel()
        self.grid = np.stack([free.ravel(), visited.ravel(), seen.ravel(), passable, target])
        self.free, self.visited, self.seen, self.passable, self.target = self.grid
        self.n_targets = int(target.sum())

    def _visit(self, p: int) -> None:
        """Mark cell ``p`` visited (and its 3x3 window seen), as a step onto it does."""
        self.n_targets += _visit_cells(np.array([p], dtype=np.int64), self.window, self.grid)

    # ------------------------------------------------------------------ acting
    def act(self, rng: np.random.Generator | None = None) -> list[int]:
        """One action per agent; targets are claimed in agent index order.

        Args:
            rng: Draws the ``"random"`` tie-break (required then, unused otherwise).
        """
        held = self._held(rng)
        self.rng = rng
        n = len(self.positions)
        self.goals = [-1] * n
        if self.n_targets == 0:  # everything seen is visited: nothing left to walk to
            return [STAY] * n
        size = self.passable.size
        if self._claimed is None or self._claimed.size != size:
            self._claimed = np.zeros(size, dtype=np.bool_)
        goals, actions = np.empty((2, n), dtype=np.int64)
        _plan(
            self.passable, self.target, self.seen, np.asarray(self.positions, dtype=np.int64),
            self.offsets, TIE_BREAKS.index(self.tie_break), self._claimed, self.n_targets,
            self._scratch_arrays(size), held, goals, actions,
        )  # fmt: skip
        self.goals = goals.tolist()
        return actions.tolist()

    def step(
        self,
        steps: int,
        positions: np.ndarray,
        read_map: Callable[[], tuple[np.ndarray, np.ndarray]],
        rng: np.random.Generator | None = None,
    ) -> list[int]:
        """:meth:`sync` then :meth:`act`: one action per agent, both in one compiled call
        (:func:`_sync_and_plan`) on the steps that only bring the map up to date."""
        incremental = steps != 0 and self.steps <= steps <= self.steps + 1
        if not incremental:
            self.sync(steps, positions, read_map)
            return self.act(rng)
        held = self._held(rng)
        n = positions.shape[0]
        starts, goals, actions = np.empty((3, n), dtype=np.int64)
        size = self.passable.size
        if self._claimed is None or self._claimed.size != size:
            self._claimed = np.zeros(size, dtype=np.bool_)
        self.n_targets = _sync_and_plan(
            positions, self.window, self.grid, self.n_targets, self.offsets,
            TIE_BREAKS.index(self.tie_break), self._claimed, self._scratch_arrays(size), held,
            starts, goals, actions,
        )  # fmt: skip
        self.steps, self.rng = steps, rng
        self.positions, self.goals = starts.tolist(), goals.tolist()
        return actions.tolist()

    def distance_fields(self, predecessors: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Every agent's shortest path lengths through the seen free cells to every padded cell
        and the predecessors on those paths, ``(agents, cells)`` each (one compiled search per
        agent, :func:`envs.coverage.paths.distance_fields`: ``inf`` and
        :data:`~envs.coverage.paths.UNREACHED` where a cell cannot be reached).
        With ``predecessors`` False, ``None`` for them (:func:`envs.coverage.paths.first_step`
        walks a path back from the distances)."""
        starts = np.asarray(self.positions, dtype=np.int64)
        size = self.passable.size
        dist = np.empty((starts.size, size))
        pred = np.empty((starts.size if predecessors else 0, size), dtype=np.int32)
        queue = self._scratch_arrays(size)[1]
        distance_fields(self.passable, self.stride, starts, np.inf, dist, pred, queue)
        return dist, pred if predecessors else None

    def _held(self, rng: np.random.Generator | None) -> _GeneratorRef | None:
        """The ``"random"`` tie-break's ``rng`` held for compiled code, made once per generator
        (an episode's); ``None`` for the other tie-breaks.

        Raises:
            ValueError: with the ``"random"`` tie-break and no generator.
        """
        if self.tie_break != "random":
            return None
        if rng is None:
            raise ValueError('tie_break="random" needs a generator: act(rng=...)')
        if self._held_rng is None or self._held_rng[0] is not rng:
            self._held_rng = (rng, _GeneratorRef(rng))
        return self._held_rng[1]

    def _scratch_arrays(self, size: int) -> np.ndarray:
        """The searches' working arrays (4, cells), made once per map size."""
        if self._scratch is None or self._scratch.shape[1] != size:
            self._scratch = np.empty((4, size), dtype=np.int64)
            self._scratch[0] = -1  # the searches' ``first`` (nearest_targets keeps it so)
        return self._scratch

    def work_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Working arrays for a search after :meth:`act` (the goal action's candidates):
        ``float64 (agents, cells)`` for distance fields and ``int64 (3, cells)``, made once
        per map size and team, overwritten by the next search."""
        n, size = len(self.positions), self.passable.size
        work = self._work  # a coordinated planner asks every step: one check, no new views
        if work is None or work[0].shape != (n, size) or work[1].base is not self._scratch:
            work = self._work = (np.empty((n, size)), self._scratch_arrays(size)[1:4])
        return work


# ---------------------------------------------------------------------- coordinated planners
#: How a coordinated planner gathers its candidate targets: every known free unvisited cell
#: (``"all"``), or one per frontier cluster (``"clusters"``: a 4-connected group of such cells,
#: reached at its cell nearest to the agent).
CANDIDATES = ("all", "clusters")
#: Cost of an unreachable candidate in an assignment (any path is shorter).
_UNREACHABLE = 1e9
#: 4-connectivity of frontier clusters (SciPy's ``label`` structure, made once).
_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=bool)


class CoordinatedPlanner(FrontierPlanner):
    """A planner that chooses every agent's target together, re-planning every step.

    Each step it computes one distance field per agent (shortest paths through the seen free
    cells, :func:`envs.coverage.paths.distance_fields`), reads the cost of every
    candidate target for every agent from them, lets :meth:`assign` choose one candidate per
    agent, and moves each agent one step along a shortest path to its own. It keeps the team's
    map as :class:`FrontierPlanner` does (:meth:`sync`), plans only over what the team knows and
    only steps into seen free cells, so it never hits a wall; it draws no random numbers, so an
    episode repeats from its seed. Ties go to the lower candidate index (cells in row-major
    order), then the lower agent index.

    The distance fields reach ``horizon`` cells: candidates farther than
    that from an agent cost it nothing it can plan with (as if unreachable), which keeps a step's
    searches local; an agent with no candidate within the horizon searches the whole map.

    The defaults (every known unvisited cell a candidate; for the utility planner
    ``beta=0.2``, ``radius=3``) were chosen on validation episodes by
    ``research/experiments/planner_params.py`` (``docs/planners/validation.json``,
    docs/planners.md); the horizon of 15 cells costs at most 0.15 points there and makes the
    planners about twice as fast (docs/planners.md).

    Args:
        height: Rows of the map.
        width: Columns of the map.
        candidates: One of :data:`CANDIDATES`.
        horizon: Path length the distance fields reach (``None``: the whole map).
    """

    def __init__(
        self, height: int, width: int, candidates: str = "all", horizon: int | None = 15
    ) -> None:
        super().__init__(height, width, "order")
        if candidates not in CANDIDATES:
            raise ValueError(f"unknown candidates {candidates!r}; known: {', '.join(CANDIDATES)}")
        if horizon is not None and not horizon >= 1:
            raise ValueError(f"horizon must be >= 1 or None, got {horizon!r}")
        self.candidates, self.horizon = candidates, horizon

    #: The compiled assignment of :func:`_coordinated_step` (:data:`_MINPOS`, :data:`_UTILITY`,
    #: :data:`_HUNGARIAN`) that :meth:`step` runs in place of :meth:`assign`, or ``None``:
    #: :meth:`assign` in Python, after the compiled costs. A subclass that overrides
    #: :meth:`assign` without setting it gets ``None`` (:meth:`__init_subclass__`), so its own
    #: rule is played, not the compiled one of the class it extends.
    _compiled_assign: int | None = None

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        if "assign" in vars(cls) and "_compiled_assign" not in vars(cls):
            cls._compiled_assign = None

    def step(
        self,
        steps: int,
        positions: np.ndarray,
        read_map: Callable[[], tuple[np.ndarray, np.ndarray]],
        rng: np.random.Generator | None = None,
    ) -> list[int]:
        """:meth:`sync` then :meth:`act`; with every known unvisited cell a candidate and a
        compiled assignment, both in one compiled call (:func:`_coordinated_step`) on the steps
        that only bring the map up to date."""
        incremental = steps != 0 and self.steps <= steps <= self.steps + 1
        if not (incremental and self.candidates == "all"):
            self.sync(steps, positions, read_map)
            return self.act(rng)
        n = positions.shape[0]
        starts, goals, actions = np.empty((3, n), dtype=np.int64)
        dist, rows = self.work_arrays()  # the team is the one of the last sync: n agents
        queue = rows[0]
        kind = self._compiled_assign
        if kind is not None:
            beta, radius = getattr(self, "beta", 0.0), getattr(self, "radius", 1.0)
            self.n_targets = _coordinated_step(
                positions, self.window, self.grid, self.n_targets, self.stride, self._horizon(),
                dist, queue,
                kind, beta, radius, starts, goals, actions,
            )  # fmt: skip
        else:  # the assignment in Python (a subclass's own), around two compiled calls
            self.n_targets, cells, costs = _sync_and_costs(
                positions, self.window, self.grid, self.n_targets, self.stride, self._horizon(),
                dist, queue, starts,
            )  # fmt: skip
            goals[:], actions[:] = -1, STAY
            if self.n_targets:
                goal_cells = np.repeat(cells[None, :], n, axis=0)
                chosen = np.asarray(self.assign(costs, goal_cells), dtype=np.int64)
                goals, actions = _first_moves(dist, starts, costs, goal_cells, chosen, self.stride)
        self.steps, self.rng = steps, rng
        self.positions, self.goals = starts.tolist(), goals.tolist()
        return actions.tolist()

    def _horizon(self) -> float:
        return np.inf if self.horizon is None else float(self.horizon)

    def act(self, rng: np.random.Generator | None = None) -> list[int]:
        """One action per agent (``rng`` is unused: the choice is deterministic)."""
        n = len(self.positions)
        self.goals = [-1] * n
        if self.n_targets == 0:
            return [STAY] * n
        starts = np.asarray(self.positions, dtype=np.int64)
        size = self.passable.size
        dist = np.empty((n, size))
        cells, costs = _target_costs(
            self.passable, self.target, self.stride, starts, self._horizon(), dist,
            self._scratch_arrays(size)[1],
        )  # fmt: skip
        cost, goal_cells = self._candidate_costs(costs, cells)
        chosen = np.asarray(self.assign(cost, goal_cells), dtype=np.int64)
        goals, actions = _first_moves(dist, starts, cost, goal_cells, chosen, self.stride)
        self.goals = goals.tolist()
        return actions.tolist()

    def _candidate_costs(
        self, costs: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(agents, candidates)`` path lengths and the cell each agent would head for, from
        the agents' path lengths ``costs`` to the target ``cells`` ``(agents, cells)``."""
        if self.candidates == "all":
            return costs, np.repeat(cells[None, :], costs.shape[0], axis=0)
        labels, _ = label(self.target.reshape(-1, self.stride), structure=_CROSS)
        ids = labels.ravel()[cells]
        # Per agent, cells sorted by cluster, then cost, then cell (lexsort is stable and the
        # cells come in row-major order): the first of each cluster is its nearest cell.
        n_agents = costs.shape[0]
        order = np.lexsort((costs, ids[None, :].repeat(n_agents, axis=0)), axis=-1)
        sorted_ids = ids[order[0]]
        firsts = np.flatnonzero(np.concatenate(([True], sorted_ids[1:] != sorted_ids[:-1])))
        picks = order[:, firsts]  # (agents, clusters): column of each cluster's nearest cell
        best = np.take_along_axis(costs, picks, axis=1)
        return best, cells[picks].reshape(n_agents, -1)

    def assign(self, cost: np.ndarray, goal_cells: np.ndarray) -> list[int]:
        """Each agent's candidate (a column of ``cost``; -1 for none)."""
        raise NotImplementedError


class HungarianPlanner(CoordinatedPlanner):
    """Distinct targets minimising the team's total path length, an optimal assignment
    (:func:`scipy.optimize.linear_sum_assignment`, here compiled:
    :func:`linear_sum_assignment_compiled`). With fewer reachable candidates than agents the
    agents left over head for their nearest candidate."""

    _compiled_assign = 2  # _HUNGARIAN

    def assign(self, cost: np.ndarray, goal_cells: np.ndarray) -> list[int]:
        return _hungarian_choices(cost).tolist()


class MinPosPlanner(CoordinatedPlanner):
    """MinPos (Bautin, Simonin & Charpillet 2012): an agent's rank for a candidate is the number
    of teammates closer to it; each agent heads for the candidate where its rank is lowest, ties
    by its own distance. As printed, two agents that meet on one cell have equal distances and
    ranks everywhere and move in lockstep for the rest of the episode; here, as in the other
    planners, candidates are claimed in agent index order: an agent skips a candidate a
    lower-index teammate chose this step."""

    _compiled_assign = 0  # _MINPOS

    def assign(self, cost: np.ndarray, goal_cells: np.ndarray) -> list[int]:
        return _minpos_choices(cost).tolist()


class UtilityPlanner(CoordinatedPlanner):
    """Coordinated exploration by utility (Burgard, Moors, Stachniss & Schneider 2005): every
    candidate starts with utility 1; agents in index order take the candidate that maximises
    ``utility - beta * path length``, then lower the utility of the candidates near the chosen
    one by how likely they are to be seen from it, ``max(0, 1 - d / radius)`` for the Euclidean
    distance ``d`` between the two cells, so teammates spread out.

    Args:
        height, width, candidates, horizon: As :class:`CoordinatedPlanner`.
        beta: Utility traded for one cell of path (the paper's cost weight).
        radius: Cells beyond which a chosen target does not lower another's utility.
    """

    def __init__(
        self,
        height: int,
        width: int,
        candidates: str = "all",
        horizon: int | None = 15,
        beta: float = 0.2,
        radius: float = 3.0,
    ) -> None:
        super().__init__(height, width, candidates, horizon)
        if not beta >= 0 or not radius > 0:
            raise ValueError(f"beta must be >= 0 and radius > 0, got {beta} and {radius}")
        self.beta, self.radius = float(beta), float(radius)

    _compiled_assign = 1  # _UTILITY

    def assign(self, cost: np.ndarray, goal_cells: np.ndarray) -> list[int]:
        # Where each candidate would be reached by each agent: the visibility is between those
        # cells and the chosen one.
        rows, cols = np.divmod(goal_cells, self.stride)
        return _utility_choices(cost, rows, cols, self.beta, self.radius).tolist()


# A coordinated planner's step around its assignment, compiled (the searches, the costs of the
# targets, the walk back along the chosen paths).
@njit(cache=True, nogil=True)
def _target_costs(
    passable: np.ndarray,
    target: np.ndarray,
    stride: int,
    starts: np.ndarray,
    horizon: float,
    dist: np.ndarray,
    queue: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Every agent's distance field up to ``horizon`` (on over the whole map for an agent with
    no target within it, and only until every target is reached:
    :func:`~envs.coverage.paths.breadth_first`) into ``dist``; returns the target cells (ascending)
    and the agents' path lengths to them ``(agents, targets)``."""
    # The target cells in one pass without branches (np.flatnonzero takes two, with them).
    cells = np.empty(target.size, dtype=np.int64)
    k = 0
    for c in range(target.size):
        cells[k] = c
        k += target[c]
    cells = cells[:k]
    costs = np.empty((starts.size, cells.size))
    for i in range(starts.size):
        breadth_first(passable, stride, starts[i], horizon, dist[i], queue, target, cells.size)
        for j in range(cells.size):
            costs[i, j] = dist[i, cells[j]]
    return cells, costs


@njit(cache=True, nogil=True)
def _first_moves(
    dist: np.ndarray,
    starts: np.ndarray,
    cost: np.ndarray,
    goal_cells: np.ndarray,
    chosen: np.ndarray,
    stride: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Each agent's goal cell (-1: none) and the first move of its path there (``STAY`` when
    it has no reachable candidate), walked back along its distance field (:func:`first_step`)."""
    n = starts.size
    goals = np.full(n, -1, dtype=np.int64)
    actions = np.full(n, STAY, dtype=np.int64)
    for i in range(n):
        c = chosen[i]
        if c < 0 or not cost[i, c] < np.inf:
            continue
        goal = goal_cells[i, c]
        goals[i] = goal
        actions[i] = move_towards(first_step(dist[i], goal, stride), starts[i], stride)
    return goals, actions


# The assignments' loops, compiled: per step they run over every candidate (every known unvisited
# cell) once per agent. Written with the same floating-point operations in the same order as
# their NumPy form (no fastmath), so they choose exactly as it did.
@njit(cache=True, nogil=True)
def _minpos_choices(cost: np.ndarray) -> np.ndarray:
    """MinPos's candidate per agent (-1: none reachable), see :class:`MinPosPlanner`."""
    n, m = cost.shape
    span = 0.0  # the largest finite cost, + 1: a rank outweighs any distance
    for i in range(n):
        for c in range(m):
            if cost[i, c] < np.inf and cost[i, c] > span:
                span = cost[i, c]
    span += 1.0
    key = np.empty((n, m))
    for i in range(n):
        for c in range(m):
            if cost[i, c] < np.inf:
                rank = 0  # teammates strictly closer to candidate c
                for j in range(n):
                    if cost[j, c] < cost[i, c]:
                        rank += 1
                key[i, c] = rank * span + cost[i, c]
            else:
                key[i, c] = np.inf
    chosen = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        pick = 0
        for c in range(1, m):  # the first minimum: the lowest candidate index
            if key[i, c] < key[i, pick]:
                pick = c
        if m > 0 and key[i, pick] < np.inf:
            chosen[i] = pick
            key[:, pick] = np.inf  # claimed: the next agents skip it
    return chosen


@njit(cache=True, nogil=True)
def _utility_choices(
    cost: np.ndarray, rows: np.ndarray, cols: np.ndarray, beta: float, radius: float
) -> np.ndarray:
    """The utility planner's candidate per agent (-1: none reachable), see
    :class:`UtilityPlanner`."""
    n, m = cost.shape
    utility = np.ones(m)
    reach = radius**2
    chosen = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        pick, best = -1, -np.inf
        for c in range(m):
            score = utility[c] - (beta * cost[i, c] if cost[i, c] < np.inf else np.inf)
            if pick < 0 or score > best:  # the first maximum: the lowest candidate index
                pick, best = c, score
        if pick < 0 or not best > -np.inf:
            continue  # nothing reachable
        chosen[i] = pick
        for c in range(m):  # candidates within the radius lose utility
            dr, dc = rows[i, c] - rows[i, pick], cols[i, c] - cols[i, pick]
            d2 = dr * dr + dc * dc
            if d2 < reach:
                utility[c] -= 1.0 - np.sqrt(d2) / radius
    return chosen


# SciPy's rectangular linear sum assignment (scipy/optimize/rectangular_lsap/rectangular_lsap.cpp,
# SciPy 1.17.1; Crouse 2016, "On implementing 2D rectangular assignment algorithms"), compiled so
# that the Hungarian planner's step runs in one call. Its operations are SciPy's in SciPy's order
# (the columns scanned from the last, ties to a column with no row yet, the dual updates as
# written), so on the planner's tie-heavy integer costs it picks SciPy's assignment, not just
# another optimal one.
@njit(cache=True, nogil=True)
def _augmenting_path(
    cost: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    path: np.ndarray,
    row4col: np.ndarray,
    shortest: np.ndarray,
    i: int,
    in_rows: np.ndarray,
    in_cols: np.ndarray,
    remaining: np.ndarray,
) -> tuple[int, float]:
    """The sink column of a shortest augmenting path from row ``i`` (-1: infeasible) and its
    length; ``path``, ``shortest``, ``in_rows`` and ``in_cols`` (SciPy's SR, SC) are left as
    the dual update needs them."""
    nc = cost.shape[1]
    min_val = 0.0
    n_remaining = nc
    for it in range(nc):
        # In reverse, so that a constant matrix is solved by the identity (SciPy's #11602).
        remaining[it] = nc - it - 1
    in_rows[:] = False
    in_cols[:] = False
    shortest[:] = np.inf
    sink = -1
    while sink == -1:
        index = -1
        lowest = np.inf
        in_rows[i] = True
        for it in range(n_remaining):
            j = remaining[it]
            r = min_val + cost[i, j] - u[i] - v[j]
            if r < shortest[j]:
                path[j] = i
                shortest[j] = r
            # Among equally short, a column with no row yet: it ends the path.
            if shortest[j] < lowest or (shortest[j] == lowest and row4col[j] == -1):
                lowest = shortest[j]
                index = it
        min_val = lowest
        if min_val == np.inf:
            return -1, min_val
        j = remaining[index]
        if row4col[j] == -1:
            sink = j
        else:
            i = row4col[j]
        in_cols[j] = True
        n_remaining -= 1
        remaining[index] = remaining[n_remaining]
    return sink, min_val


@njit(cache=True, nogil=True)
def linear_sum_assignment_compiled(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`scipy.optimize.linear_sum_assignment` (minimising) of a float64 matrix, compiled:
    the same row and column indices as SciPy 1.17.1 for every matrix, ties included. Raises
    ``ValueError`` where SciPy does (NaN or -inf entries, no complete assignment of finite
    cost)."""
    nr, nc = cost.shape
    if nr == 0 or nc == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    transpose = nc < nr  # a tall matrix is solved transposed
    if transpose:
        nr, nc = nc, nr
    work = np.empty((nr, nc))  # SciPy's copy (C order, transposed if tall)
    for i in range(nr):
        for j in range(nc):
            work[i, j] = cost[j, i] if transpose else cost[i, j]
            if np.isnan(work[i, j]) or work[i, j] == -np.inf:
                raise ValueError("matrix contains invalid numeric entries")
    u = np.zeros(nr)
    v = np.zeros(nc)
    shortest = np.empty(nc)
    path = np.full(nc, -1, dtype=np.int64)
    col4row = np.full(nr, -1, dtype=np.int64)
    row4col = np.full(nc, -1, dtype=np.int64)
    in_rows = np.zeros(nr, dtype=np.bool_)
    in_cols = np.zeros(nc, dtype=np.bool_)
    remaining = np.empty(nc, dtype=np.int64)
    for cur_row in range(nr):
        sink, min_val = _augmenting_path(
            work, u, v, path, row4col, shortest, cur_row, in_rows, in_cols, remaining
        )
        if sink < 0:
            raise ValueError("cost matrix is infeasible")
        # The dual variables.
        u[cur_row] += min_val
        for i in range(nr):
            if in_rows[i] and i != cur_row:
                u[i] += min_val - shortest[col4row[i]]
        for j in range(nc):
            if in_cols[j]:
                v[j] -= min_val - shortest[j]
        # The augmentation along the path.
        j = sink
        while True:
            i = path[j]
            row4col[j] = i
            col4row[i], j = j, col4row[i]
            if i == cur_row:
                break
    if transpose:  # by original row (the columns found are distinct: the order is unique)
        order = np.argsort(col4row)
        return col4row[order], order.astype(np.int64)
    return np.arange(nr, dtype=np.int64), col4row


@njit(cache=True, nogil=True)
def _hungarian_choices(cost: np.ndarray) -> np.ndarray:
    """The Hungarian planner's candidate per agent, see :class:`HungarianPlanner`: the optimal
    assignment of the costs with every non-finite one :data:`_UNREACHABLE`; an agent it leaves
    out, or gives an unreachable candidate, takes its nearest candidate (the first minimum)."""
    n, m = cost.shape
    if m == 0:
        return np.full(n, -1, dtype=np.int64)
    finite = np.empty((n, m))
    for i in range(n):
        for c in range(m):
            finite[i, c] = cost[i, c] if np.isfinite(cost[i, c]) else _UNREACHABLE
    chosen = np.zeros(n, dtype=np.int64)
    for i in range(n):  # the first minimum of each row
        for c in range(1, m):
            if finite[i, c] < finite[i, chosen[i]]:
                chosen[i] = c
    rows, cols = linear_sum_assignment_compiled(finite)
    for k in range(rows.size):
        if finite[rows[k], cols[k]] < _UNREACHABLE:
            chosen[rows[k]] = cols[k]
    return chosen


@njit(cache=True, nogil=True)
def _sync_and_costs(
    positions: np.ndarray,
    window: np.ndarray,
    grid: np.ndarray,
    n_targets: int,
    stride: int,
    horizon: float,
    dist: np.ndarray,
    queue: np.ndarray,
    starts: np.ndarray,
) -> tuple[int, np.ndarray, np.ndarray]:
    """A coordinated planner's step up to its assignment: the agents' padded cells and the map
    (:func:`_sync`) and, while targets are left, the costs (:func:`_target_costs`). Returns the
    number of targets now, the target cells and the costs (empty when none is left)."""
    n_targets += _sync(positions, stride, window, grid, starts)
    if n_targets == 0:
        return n_targets, np.empty(0, dtype=np.int64), np.empty((starts.size, 0))
    cells, costs = _target_costs(
        grid[_PASSABLE], grid[_TARGET], stride, starts, horizon, dist, queue
    )
    return n_targets, cells, costs


#: The assignments :func:`_coordinated_step` runs compiled.
_MINPOS, _UTILITY, _HUNGARIAN = 0, 1, 2


@njit(cache=True, nogil=True)
def _coordinated_step(
    positions: np.ndarray,
    window: np.ndarray,
    grid: np.ndarray,
    n_targets: int,
    stride: int,
    horizon: float,
    dist: np.ndarray,
    queue: np.ndarray,
    kind: int,
    beta: float,
    radius: float,
    starts: np.ndarray,
    goals: np.ndarray,
    actions: np.ndarray,
) -> int:
    """One step of a coordinated planner with every known unvisited cell a candidate and a
    compiled assignment (``kind``: :data:`_MINPOS`, :data:`_UTILITY` with ``beta`` and
    ``radius``, or :data:`_HUNGARIAN`), in one call: the map brought up to date
    (:func:`_visit_cells`), the costs (:func:`_target_costs`), the assignment and the first
    moves (:func:`_first_moves`), as :meth:`CoordinatedPlanner.act` does them one call after
    another. Returns the number of targets now."""
    goals[:] = -1
    actions[:] = STAY
    n_targets, cells, costs = _sync_and_costs(
        positions, window, grid, n_targets, stride, horizon, dist, queue, starts,
    )  # fmt: skip
    if n_targets == 0:
        return n_targets
    goal_cells = np.empty(costs.shape, dtype=np.int64)
    for i in range(starts.size):
        goal_cells[i] = cells
    if kind == _MINPOS:
        chosen = _minpos_choices(costs)
    elif kind == _HUNGARIAN:
        chosen = _hungarian_choices(costs)
    else:
        # Every agent's candidates are the same cells: one division per cell, not per agent
        # and cell (integer division is the slowest arithmetic here).
        rows, cols = np.empty_like(goal_cells), np.empty_like(goal_cells)
        cell_rows = cells // stride
        cell_cols = cells - cell_rows * stride
        for i in range(starts.size):
            rows[i], cols[i] = cell_rows, cell_cols
        chosen = _utility_choices(costs, rows, cols, beta, radius)
    g, a = _first_moves(dist, starts, costs, goal_cells, chosen, stride)
    goals[:] = g
    actions[:] = a
    return n_targets
