"""The classical frontier explorer (Yamauchi 1997) on the team's shared map, for one episode.

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

This module is the env's *planner extension*, its one owner: the option ``frontier=`` of the env
(:class:`FrontierOptions`: which planner-backed action kind, which planner), the registries of
planners (:data:`PLANNERS`) and of planner-backed action kinds (:data:`ACTIONS`), and
:class:`Frontier`, the extension's state during an episode, which the env asks for the moves of
planner-backed actions. A new planner or action kind is an entry of a registry, not a flag.
The ``frontier*`` baselines (``harness.evaluation.baselines``) play the planners' moves; the
team-map observation shows them in its frontier compass.

Speed: the team's map only grows, so the planner keeps it incrementally (updated from the
agents' positions each step, rebuilt when an episode starts). The search is a breadth-first search
in Python that stops at the first unclaimed target; most of the time that target is a step or two
away. When a search grows past ``SEARCH_BUDGET`` cells (late in an episode, when the remaining
ground is far away) it is redone by SciPy's compiled breadth-first search on a graph of the seen
free cells, rebuilt only when a cell became passable since the last such search; an agent whose
target was far goes straight to SciPy on the next step. Both searches visit neighbours in the same
order, so the choice of target does not depend on which one ran.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order

from envs.coverage.types import CELL_VISITED, CELL_WALL, FRONTIER_STEP, STAY, GridState

__all__ = [
    "ACTIONS",
    "PLANNERS",
    "TIE_BREAKS",
    "ActionKind",
    "Frontier",
    "FrontierOptions",
    "FrontierPlanner",
    "PlannerEntry",
]

#: Cells a Python search may reach before the compiled search takes over. Below it the Python
#: search wins (no graph to build); above it SciPy's search is cheaper even with a fresh graph.
SEARCH_BUDGET = 128
#: Path length above which an agent's next search skips the Python search.
FAR = 8
#: How :class:`FrontierPlanner` chooses among equally near unclaimed targets (module docstring).
TIE_BREAKS = ("order", "pocket", "random")


class FrontierPlanner:
    """The frontier explorer's team map of one episode, on a flat grid padded with one ring of
    wall, and its moves (see the module docstring).

    Call :meth:`sync` with the episode's state after every reset and step, then :meth:`act`.
    ``tie_break`` is one of :data:`TIE_BREAKS`.

    Padding lets neighbour lookups skip bounds checks; the per-cell state is kept in Python lists
    because the search reads single cells, which lists do several times faster than numpy.
    """

    def __init__(self, height: int, width: int, tie_break: str = "order") -> None:
        if tie_break not in TIE_BREAKS:
            raise ValueError(f"unknown tie_break {tie_break!r}; known: {', '.join(TIE_BREAKS)}")
        self.tie_break = tie_break
        self.rng: np.random.Generator | None = None  # act()'s generator, for "random" ties
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
        self.positions = ((positions[:, 0] + 1) * self.stride + positions[:, 1] + 1).tolist()
        if steps == 0 or not (self.steps <= steps <= self.steps + 1):
            self._rebuild(*read_map())
        else:
            for p in self.positions:
                if not self.visited[p]:
                    self._visit(p)
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
    def act(self, rng: np.random.Generator | None = None) -> list[int]:
        """One action per agent; targets are claimed in agent index order.

        Args:
            rng: Draws the ``"random"`` tie-break (required then, unused otherwise).
        """
        if self.tie_break == "random" and rng is None:
            raise ValueError('tie_break="random" needs a generator: act(rng=...)')
        self.rng = rng
        if self.n_targets == 0:  # everything seen is visited: nothing left to walk to
            return [STAY] * len(self.positions)
        claimed: set[int] = set()
        actions = []
        for i, start in enumerate(self.positions):
            if self.far[i]:
                found = self._search_compiled(start, claimed, i)
            elif self.tie_break == "order":
                found = self._search(start, claimed, i)
            else:
                found = self._search_ties(start, claimed, i)
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
            if len(first) > SEARCH_BUDGET:
                return self._search_compiled(start, claimed, agent)
        return None

    def _search_ties(self, start: int, claimed: set[int], agent: int) -> tuple[int, int] | None:
        """:meth:`_search` for the tie-breaks other than ``"order"``: the same search, one
        distance layer at a time, so that every target of the nearest layer is a candidate."""
        passable, target, offsets = self.passable, self.target, self.offsets
        first = {start: start}
        layer = [start]
        while layer:
            ties: list[int] = []
            next_layer = []
            for c in layer:
                f = first[c]
                for d in offsets:
                    n = c + d
                    if passable[n] and n not in first:
                        first[n] = n if c == start else f
                        if target[n] and n not in claimed:
                            ties.append(n)
                        next_layer.append(n)
            if ties:
                goal = self._choose(ties)
                return goal, first[goal]
            if len(first) > SEARCH_BUDGET:
                return self._search_compiled(start, claimed, agent)
            layer = next_layer
        return None

    def _search_compiled(self, start: int, claimed: set[int], agent: int) -> tuple[int, int] | None:
        """:meth:`_search` by SciPy's breadth-first search (for far targets). It visits
        neighbours in the same order, so both searches pick the same target."""
        order, pred = breadth_first_order(
            self._graph_now(), start, directed=True, return_predecessors=True
        )

        def first_step(goal: int) -> tuple[int, int]:
            step, distance = goal, 1
            while pred[step] != start:
                step = int(pred[step])
                distance += 1
            return step, distance

        candidates = [g for g in order[self.target_np[order]].tolist() if g not in claimed]
        if not candidates:
            # Nothing left for this agent (teammates claimed the last targets): that search saw
            # the whole reachable map, so the next one goes straight to SciPy too.
            self.far[agent] = True
            return None
        goal = candidates[0]
        step, distance = first_step(goal)
        if self.tie_break != "order":
            # BFS order lists targets by distance: the nearest layer is a prefix of it.
            steps = {goal: step}
            for g in candidates[1:]:
                s, d = first_step(g)
                if d > distance:
                    break
                steps[g] = s
            goal = self._choose(list(steps))
            step = steps[goal]
        self.far[agent] = distance > FAR
        return goal, step

    def _choose(self, ties: list[int]) -> int:
        """The tie-break among equally near targets, listed in the order the search found them."""
        if self.tie_break == "random":
            return ties[int(self.rng.integers(len(ties)))]
        if self.tie_break == "pocket":
            seen, target, offsets = self.seen, self.target, self.offsets
            return min(
                ties, key=lambda g: sum(not seen[g + d] or target[g + d] for d in offsets)
            )  # min keeps the first of equals: "order" breaks the remaining ties
        return ties[0]

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


# ---------------------------------------------------------------------- the extension
@dataclass(frozen=True)
class PlannerEntry:
    """A planner of the registry :data:`PLANNERS`."""

    make: Callable[[int, int], FrontierPlanner]
    """Builds the planner for a map of ``(height, width)``."""
    baseline: str
    """Its baseline's name (``harness eval --policy NAME``)."""
    in_env: bool = True
    """Whether the env's compass and planner-backed actions can follow it: its move must be a
    function of the team's map (a planner that draws from a generator is a baseline only)."""


#: Planners by the name ``frontier.planner`` (and the baselines) take.
PLANNERS: dict[str, PlannerEntry] = {
    "order": PlannerEntry(lambda h, w: FrontierPlanner(h, w, "order"), "frontier"),
    "pocket": PlannerEntry(lambda h, w: FrontierPlanner(h, w, "pocket"), "frontier_pocket"),
    "random": PlannerEntry(
        lambda h, w: FrontierPlanner(h, w, "random"), "frontier_random", in_env=False
    ),
}


@dataclass(frozen=True)
class ActionKind:
    """A planner-backed action kind of the registry :data:`ACTIONS`: actions numbered from
    ``FRONTIER_STEP`` (after the five moves) that the env turns into moves by asking
    :class:`Frontier`."""

    n_actions: int
    """Actions it adds to the five moves."""
    resolve: Callable[[Frontier, list[int], np.random.Generator], list[int]]
    """``(frontier, actions, rng) -> moves``: every action of this kind replaced by a move."""


def _step_moves(frontier: Frontier, actions: list[int], rng: np.random.Generator) -> list[int]:
    """The frontier step: one of the moves the current compass marks (drawn from ``rng`` when
    several tie, so teammates at one spot may part), stay when it marks none."""
    compass = frontier.compass
    out = list(actions)
    for i, a in enumerate(actions):
        if a == FRONTIER_STEP:
            moves = np.flatnonzero(compass[i, :4])
            if moves.size == 0:
                out[i] = STAY
            elif moves.size == 1:
                out[i] = int(moves[0])
            else:
                out[i] = int(moves[rng.integers(moves.size)])
    return out


#: Planner-backed action kinds by the name ``frontier.action`` takes.
ACTIONS: dict[str, ActionKind] = {"step": ActionKind(1, _step_moves)}


def _choice(value: Any, registry: Mapping[str, Any], key: str) -> None:
    if value is not None and value not in registry:
        known = ", ".join(registry)
        raise ValueError(f"frontier.{key}: unknown {key} {value!r}; known: {known} (or null)")


@dataclass(frozen=True)
class FrontierOptions:
    """The env's ``frontier=`` option: the frontier field and compass in the team-map
    observation, and what is built on them.

    Attributes:
        action: A planner-backed action kind of :data:`ACTIONS` (``"step"``: a sixth action,
            one step along the compass), or ``None``: the five moves only.
        planner: A planner of :data:`PLANNERS` whose move the compass marks (targets claimed in
            agent index order), or ``None``: the compass marks every move that starts a
            shortest path to the nearest known unvisited cell (and the step draws among them).
    """

    action: str | None = None
    planner: str | None = None

    def __post_init__(self) -> None:
        _choice(self.action, ACTIONS, "action")
        _choice(self.planner, PLANNERS, "planner")
        if self.planner is not None and not PLANNERS[self.planner].in_env:
            raise ValueError(
                f"frontier.planner: {self.planner!r} draws its ties from a generator: it is a "
                f"baseline only (--policy {PLANNERS[self.planner].baseline}); in the env use one "
                f"of {', '.join(n for n, p in PLANNERS.items() if p.in_env)}"
            )

    @classmethod
    def parse(cls, value: FrontierOptions | Mapping[str, Any] | None) -> FrontierOptions | None:
        """The options from their config form: ``None`` (off), a mapping of
        ``action``/``planner``, or options already made.

        Raises:
            ValueError: naming the key, for an unknown key or choice.
        """
        if value is None or isinstance(value, FrontierOptions):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(
                f"frontier must be null or a mapping with action and planner, got {value!r}"
            )
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(value) - set(names))
        if unknown:
            raise ValueError(f"frontier: unknown key(s) {unknown}; known: {', '.join(names)}")
        return cls(**value)

    @staticmethod
    def check_fits(observation: Any, options: FrontierOptions | None) -> None:
        """The rule between the observation and the extension: its field and compass live in
        an observation that takes them (the team map), whose options must hold the field
        (``observation.check(frontier=True)``: the crop's channels).

        Args:
            observation: An observation's options (``envs.coverage.observations.TeamMap``,
                ``Thesis``), read by duck typing: ``name``, ``takes_frontier``, ``check``.
            options: The extension's options, ``None`` when off.

        Raises:
            ValueError: when they do not fit.
        """
        if options is None:
            return
        if not observation.takes_frontier:
            raise ValueError(
                "frontier needs the teammap observation (its field and compass are part of it), "
                f"not {observation.name!r}"
            )
        observation.check(frontier=True)

    @property
    def expert_action(self) -> int | None:
        """The first planner-backed action (the planner's own move, which imitation learns
        from), ``None`` without one."""
        return FRONTIER_STEP if self.action is not None else None

    @property
    def extra_actions(self) -> int:
        """Actions added to the five moves."""
        return ACTIONS[self.action].n_actions if self.action is not None else 0


class Frontier:
    """The planner extension during an episode, for one map size: the planner (when the options
    name one) and the frontier compass of the last observation, which the team-map observation
    writes and planner-backed actions follow.

    Args:
        options: What is on.
        height: Rows of the map.
        width: Columns of the map.
    """

    def __init__(self, options: FrontierOptions, height: int, width: int) -> None:
        self.options = options
        self.planner = (
            PLANNERS[options.planner].make(height, width) if options.planner is not None else None
        )
        #: ``(agents, 5)``: the compass of the last observation (see the team-map observation).
        self.compass = np.zeros((0, 5), dtype=np.float32)

    def planned_moves(self, state: GridState) -> list[int]:
        """Each agent's move by the planner on the team's map of ``state`` (needs a planner)."""
        assert self.planner is not None
        interior = state.interior
        self.planner.sync(
            state.steps,
            state.positions,
            lambda: (interior == CELL_WALL, interior == CELL_VISITED),
        )
        return self.planner.act()

    def resolve(self, actions: Sequence[int], rng: np.random.Generator) -> list[int]:
        """``actions`` with every planner-backed action replaced by its move (rules: the kind's
        :attr:`ActionKind.resolve`)."""
        acts = list(actions)
        if self.options.action is None:
            return acts
        return ACTIONS[self.options.action].resolve(self, acts, rng)
