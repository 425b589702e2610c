"""Rollouts of the goal action's candidates: each slot tried on a copy of the episode, compiled.

At a decision of agent ``i`` (docs/goals.md), every candidate slot is tried on a copy of the
planner's map whose free cells are a map the caller gives (the rollouts reveal cells from it as
the agents walk; the planner itself only plans over what the team has seen):

* slot 0 as the env plays it: one step with the slot's move, the planner re-planning after it
  (so a team that always takes slot 0 is the planner, but for an agent the planner leaves
  without a target: :mod:`envs.coverage.goals`);
* every other slot: the agent walks the shortest path to the slot's candidate through the seen
  free cells (:func:`envs.coverage.paths.distance_fields`' rule for tied paths);
* teammates keep to what they are doing: a committed walk (``walks``) to its end, else slot 0's
  move; then everybody follows the planner (targets claimed in agent index order, as the
  planner does) to the rollout's end: the episode's end, or ``horizon`` steps.

A slot scores the cells the team newly visits in its rollout; with ``reach`` (a coverage, e.g.
0.99) it scores by the steps the rollout takes to reach that coverage instead (fewer is better;
not reached within the rollout counts one step more than it has; ties by cells), as
``-steps * (cells of the padded grid + 1) + new cells``. The best slot wins; ties, and gains
of at most ``margin`` (cells, or steps with ``reach``), keep slot 0 (:class:`RolloutRule`).

Two choosers play by that rule, on two kinds of map:

* the rollout teacher (:class:`envs.coverage.teacher.RolloutTeacher`) on the *true* map: the
  rollout oracle of ``research/experiments/goal_oracle.py``, which labels training's states (DAgger)
  and must never choose in evaluation (``tests/test_architecture.py``);
* :class:`SampledChooser` on maps the team's own knowledge allows (:func:`sampled_free`), with
  a rule against chance gains: the ``rollout`` baseline of ``harness eval``, a policy that sees
  only what the team has seen (docs/planners.md, "The rollout chooser"). This module never
  reads the true map's cells the team has not seen.

One call per slot and map runs the rollout to its end in numba (the map copy, the planner's
steps, the count of visited cells), with the planners' own compiled steps
(:func:`envs.coverage.planners._plan`, :func:`_coordinated_step`) and map upkeep
(:func:`envs.coverage.planners._visit_cells`): one owner of every rule.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from envs.coverage.goals import Candidates
from envs.coverage.paths import distance_fields, walk_back
from envs.coverage.planners import (
    _FREE,
    _ORDER,
    _PASSABLE,
    _POCKET,
    _SEEN,
    _TARGET,
    _VISITED,
    CoordinatedPlanner,
    FrontierPlanner,
    _coordinated_step,
    _plan,
    _visit_cells,
)
from envs.coverage.types import STAY

__all__ = [
    "RolloutRule",
    "SampledChooser",
    "believed_coverage",
    "clear_of_noise",
    "held_walks",
    "in_threads",
    "prior_wall_probability",
    "sampled_free",
    "shortest_walk",
]

#: The planners a rollout steps (:func:`_planner_step`): the frontier explorer (``order`` or
#: ``pocket``), or a coordinated planner's compiled step.
_EXPLORER, _COORDINATED = 0, 1


class _PlannerStep(NamedTuple):
    """What a rollout needs to play the episode's planner (:func:`_planner_step`), one argument
    of the compiled functions (numba passes a named tuple as it is)."""

    window: np.ndarray  # the planner's map-upkeep window (FrontierPlanner.window)
    offsets: np.ndarray  # its neighbour offsets (offsets[3]: the padded grid's row length)
    kind: int  # _EXPLORER or _COORDINATED
    pocket: bool  # the explorer's pocket tie-break (else order)
    assign: int  # a coordinated planner's compiled assignment
    horizon: float  # its search horizon
    beta: float  # its utility weight (the utility planner)
    radius: float  # its utility radius


@njit(cache=True, nogil=True)
def _rollout(
    grid: np.ndarray,
    n_targets: int,
    positions: np.ndarray,
    paths: np.ndarray,
    lengths: np.ndarray,
    steps: int,
    by_reach: bool,
    goal: int,
    planner: _PlannerStep,
) -> tuple[int, int]:
    """One rollout on a copy of ``grid`` (:attr:`FrontierPlanner.grid`) for ``steps`` steps:
    each agent walks ``paths[a, :lengths[a]]`` first (padded cells, one a step), then follows
    the ``planner`` (the explorer with its tie-break, or a coordinated planner's compiled
    assignment). Returns the cells newly visited and, with ``by_reach``, the step (1-based) on
    which they reached ``goal`` (the rollout then ends), -1 when not reached (and without
    ``by_reach``)."""
    window, offsets, kind = planner.window, planner.offsets, planner.kind
    g = grid.copy()
    visited = g[_VISITED]
    size = visited.size
    n = positions.size
    stride = offsets[3]
    delta = np.array([-stride, stride, -1, 1, 0], dtype=np.int64)  # by move, STAY last
    pos = positions.copy()
    cells = np.empty(n, dtype=np.int64)
    at = np.zeros(n, dtype=np.int64)  # each agent's next cell of its path
    goals = np.empty(n, dtype=np.int64)
    actions = np.full(n, STAY, dtype=np.int64)
    claimed = np.zeros(size, dtype=np.bool_)
    scratch = np.empty((4, size), dtype=np.int64)
    scratch[0] = -1  # the searches' ``first`` (nearest_targets keeps it so)
    rowcol = np.empty((n, 2), dtype=np.int64)
    starts = np.empty(n, dtype=np.int64)
    dist = np.empty((n if kind == _COORDINATED else 0, size))
    new = 0
    for t in range(1, steps + 1):
        walking = 0
        for a in range(n):
            if at[a] < lengths[a]:
                walking += 1
        if walking < n:  # someone follows the planner: its moves from where everybody is
            if n_targets == 0:
                actions[:] = STAY
            elif kind == _EXPLORER:
                tie_break = _POCKET if planner.pocket else _ORDER
                _plan(g[_PASSABLE], g[_TARGET], g[_SEEN], pos, offsets, tie_break, claimed,
                      n_targets, scratch, None, goals, actions)  # fmt: skip
            else:
                for a in range(n):
                    rowcol[a, 0] = pos[a] // stride - 1
                    rowcol[a, 1] = pos[a] % stride - 1
                # Its map upkeep finds these cells visited: it only plans.
                _coordinated_step(rowcol, window, g, n_targets, stride, planner.horizon,
                                  dist, scratch[1], planner.assign, planner.beta,
                                  planner.radius, starts, goals, actions)  # fmt: skip
        for a in range(n):
            if at[a] < lengths[a]:
                cells[a] = paths[a, at[a]]
                at[a] += 1
            else:
                cells[a] = pos[a] + delta[actions[a]]
        for a in range(n):  # in agent order: two agents on one new cell count it once
            p = cells[a]
            if not visited[p]:
                new += 1
                n_targets += _visit_cells(cells[a : a + 1], window, g)
            pos[a] = p
        if by_reach and new >= goal:
            return new, t
        if n_targets == 0 and walking == 0:
            break  # nothing left to walk to: everybody stays to the end
    return new, -1


@njit(cache=True, nogil=True)
def _slot_scores(
    grid: np.ndarray,
    n_targets: int,
    positions: np.ndarray,
    paths: np.ndarray,
    lengths: np.ndarray,
    agent: int,
    targets: np.ndarray,
    steps: int,
    by_reach: bool,
    goal: int,
    planner: _PlannerStep,
    scores: np.ndarray,
) -> None:
    """Every slot's rollout score into ``scores`` (module docstring): slot 0 with the agent's
    row of ``paths`` as it comes (its one step), slot ``s`` of ``targets[1:]`` with the
    shortest path to ``targets[s]`` in that row; the other rows are the teammates' walks."""
    size = grid.shape[1]
    stride = planner.offsets[3]
    dist = np.empty((1, size))
    distance_fields(grid[_PASSABLE], stride, positions[agent : agent + 1], np.inf, dist,
                    np.empty((0, 0), dtype=np.int32), np.empty(size, dtype=np.int64))  # fmt: skip
    work = np.empty((paths.shape[0], max(paths.shape[1], size)), dtype=np.int64)
    work[:, : paths.shape[1]] = paths
    own = lengths.copy()
    for s in range(targets.size):
        if s > 0:
            own[agent] = walk_back(dist[0], targets[s], stride, work[agent])
        new, step = _rollout(grid, n_targets, positions, work, own, steps, by_reach, goal,
                             planner)  # fmt: skip
        if by_reach:
            # Steps first (not reached: one more than the rollout has), then cells.
            taken = steps + 1 if step < 0 else step
            scores[s] = -taken * (size + 1.0) + new
        else:
            scores[s] = new


def _planner_step(planner: FrontierPlanner) -> _PlannerStep:
    """The compiled step a rollout plays for ``planner``.

    Raises:
        ValueError: for a planner whose step is not compiled (the ``random`` tie-break, a
            coordinated planner with cluster candidates or an assignment in Python).
    """
    if isinstance(planner, CoordinatedPlanner):
        if planner.candidates != "all" or planner._compiled_assign is None:
            raise ValueError(
                f"the rollouts need a compiled planner step; {type(planner).__name__} "
                f"with candidates={planner.candidates!r} has none"
            )
        return _PlannerStep(
            planner.window, planner.offsets, _COORDINATED, False, planner._compiled_assign,
            float(planner._horizon()), float(getattr(planner, "beta", 0.0)),
            float(getattr(planner, "radius", 1.0)),
        )  # fmt: skip
    if planner.tie_break not in ("order", "pocket"):
        raise ValueError(
            f"the rollouts play the order and pocket explorers and the coordinated "
            f"planners, not tie_break={planner.tie_break!r} (its ties are drawn)"
        )
    return _PlannerStep(
        planner.window, planner.offsets, _EXPLORER, planner.tie_break == "pocket", 0, np.inf,
        0.0, 1.0,
    )  # fmt: skip


def shortest_walk(planner: FrontierPlanner, agent: int, cell: int) -> list[int]:
    """The cells (padded, flat) of the walk the rollouts take from ``agent``'s cell
    to ``cell``, start left out: a shortest path through the seen free cells, tied paths
    broken by :mod:`envs.coverage.paths`' predecessor rule. Empty when ``cell`` is the
    agent's or out of its reach."""
    size = planner.passable.size
    dist = np.empty((1, size))
    start = np.array([planner.positions[agent]], dtype=np.int64)
    no_pred = np.empty((0, 0), dtype=np.int32)
    distance_fields(planner.passable, planner.stride, start, np.inf, dist, no_pred,
                    np.empty(size, dtype=np.int64))  # fmt: skip
    out = np.empty(size, dtype=np.int64)
    return out[: walk_back(dist[0], int(cell), planner.stride, out)].tolist()


def held_walks(planner: FrontierPlanner, held: np.ndarray) -> dict[int, list[int]]:
    """The walks of the agents that hold a target (``held``: ``Frontier.held``, the goal
    action's ``hold``; -1: none), as the rollouts play them: each a :func:`shortest_walk` to
    its target, for :meth:`RolloutRule.scores_on`'s ``walks``."""
    return {a: shortest_walk(planner, a, int(c)) for a, c in enumerate(held.tolist()) if c >= 0}


def in_threads(threads: int) -> Callable[[Callable[[Any], Any], Iterable[Any]], Iterator[Any]]:
    """``map`` on ``threads`` threads of a pool of its own (the builtin ``map`` for one): the
    results in the items' order. The compiled rollouts release the GIL, so the rollout
    choosers and the teacher run their maps and copies side by side with it; as long as
    each item draws from its own generator (or none), the results are those of one thread."""
    return ThreadPoolExecutor(threads).map if threads > 1 else map


class RolloutRule:
    """The rollouts' rule: how far a rollout runs, how it scores, and what a slot must gain
    over slot 0 to replace it (module docstring). Its rollouts play on a map they are given:
    the true one (:class:`envs.coverage.teacher.RolloutTeacher`, training only) or one the
    team's own map allows (:class:`SampledChooser`).

    Args:
        horizon: Steps a rollout runs at most (``None``: to the episode's end).
        margin: What a slot must gain over slot 0 to replace it: cells, or with ``reach``
            steps.
        reach: A coverage in (0, 1]: score by the steps to it instead of the cells at the end.
    """

    def __init__(
        self, horizon: int | None = None, margin: float = 0.0, reach: float | None = None
    ) -> None:
        if horizon is not None and (isinstance(horizon, bool) or not horizon >= 1):
            raise ValueError(f"horizon must be an integer >= 1 or None, got {horizon!r}")
        if not margin >= 0:
            raise ValueError(f"margin must be >= 0, got {margin!r}")
        if reach is not None and not 0 < reach <= 1:
            raise ValueError(f"reach must be in (0, 1] or None, got {reach!r}")
        self.horizon, self.margin, self.reach = horizon, float(margin), reach

    def scores_on(
        self,
        free: np.ndarray,
        planner: FrontierPlanner,
        candidates: Candidates,
        agent: int,
        steps_left: int,
        walks: Mapping[int, Sequence[int]] | None = None,
    ) -> np.ndarray:
        """Each slot's rollout score for ``agent`` (module docstring) on the map ``free``, NaN
        for empty slots.

        Args:
            free: Free cells of the padded grid (flat, ``planner.grid``'s shape of a row): the
                map the rollouts play on. The planner's own ``free`` row (the same array) is
                the true map.
            planner: The episode's planner, synced to this step and planned
                (``Frontier.planner``): the team's map, positions and targets.
            candidates: This step's candidates (``Frontier.candidates``).
            agent: The deciding agent.
            steps_left: Steps left in the episode, this one included (``max_steps - steps``).
            walks: Teammates' committed walks: padded cells from the next one on (an agent
                not in it, or with an empty walk, takes slot 0's move); ``agent``'s own is
                ignored.
        """
        cells = candidates.cells[agent]
        out = np.full(cells.size, np.nan)
        valid = np.flatnonzero(cells >= 0)
        if valid.size == 0 or steps_left <= 0:
            return out
        grid = planner.grid
        if np.asarray(free).ctypes.data != grid[_FREE].ctypes.data:  # not the true map's row
            grid = grid.copy()
            grid[_FREE] = np.asarray(free, dtype=bool)
        steps = steps_left if self.horizon is None else min(steps_left, self.horizon)
        goal = 0
        if self.reach is not None:  # cells still to find, on the rollouts' map
            goal = int(np.ceil(self.reach * int(grid[_FREE].sum()))) - int(planner.visited.sum())
        paths, lengths = _walk_arrays(planner, candidates, agent, walks)
        scores = np.empty(valid.size)
        _slot_scores(
            grid, int(planner.n_targets), np.asarray(planner.positions, dtype=np.int64),
            paths, lengths, int(agent), cells[valid].astype(np.int64), int(steps),
            self.reach is not None, goal, _planner_step(planner), scores,
        )  # fmt: skip
        out[valid] = scores
        return out

    def unit(self, size: int) -> float:
        """Score units of one cell, or with ``reach`` of one step (``size``: the padded grid's
        cells; a step outweighs every cell a rollout can find)."""
        return 1.0 if self.reach is None else size + 1.0

    def pick(self, scores: np.ndarray, size: int) -> int:
        """The chosen slot of the slots' ``scores``: the first best, if it beats slot 0 by more
        than the margin (in steps with ``reach``: ``size`` is the padded grid's cells), else
        0."""
        if not np.isfinite(scores[0]):
            return 0
        best = int(np.argmax(np.where(np.isnan(scores), -np.inf, scores)))
        return best if scores[best] > scores[0] + self.margin * self.unit(size) else 0


def _seen_share(planner: FrontierPlanner) -> tuple[np.ndarray, np.ndarray, float]:
    """The map inside the wall ring, ``(seen, free)`` as ``(H, W)`` views, and the share of
    free cells among the seen ones: all the team knows of the walls."""
    seen = planner.seen.reshape(-1, planner.stride)[1:-1, 1:-1]
    free = np.asarray(planner.free, dtype=bool).reshape(-1, planner.stride)[1:-1, 1:-1]
    return seen, free, free[seen].sum() / max(seen.sum(), 1)


def sampled_free(
    planner: FrontierPlanner, rng: np.random.Generator, p_wall: np.ndarray | None = None
) -> np.ndarray:
    """A map the team's knowledge allows: the free cells as they are where the team has seen,
    elsewhere drawn independently, free with the share of free cells among the seen ones (the
    random maps' own law), or with ``p_wall`` (``(H, W)`` wall probabilities: a map prior's
    prediction) a wall with that probability. The outer ring stays wall. Padded and flat, like
    ``planner.free``."""
    seen, inner, share = _seen_share(planner)
    guess = np.asarray(planner.free, dtype=bool).reshape(-1, planner.stride).copy()
    draw = rng.random(inner.shape)
    unseen_free = draw < share if p_wall is None else draw >= p_wall
    guess[1:-1, 1:-1] = np.where(seen, inner, unseen_free)
    return guess.ravel()


#: What a map prior is to the choosers: ``prior(seen, free)`` with the team's ``(H, W)`` seen
#: cells and free cells (read only where seen) to ``(H, W)`` wall probabilities. The harness
#: hands one in (``harness.prior.model.MapPrior``); this module never imports a network.
MapPriorFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def prior_wall_probability(planner: FrontierPlanner, prior: MapPriorFn) -> np.ndarray:
    """``prior``'s wall probabilities ``(H, W)`` for the team's map of ``planner``."""
    seen, inner, _ = _seen_share(planner)
    p = np.asarray(prior(seen, inner), dtype=np.float64)
    if p.shape != seen.shape:
        raise ValueError(f"the map prior gave a {p.shape} map for a {seen.shape} one")
    return p


def believed_coverage(planner: FrontierPlanner) -> float:
    """The team's coverage as its own map can tell it: visited cells over the free cells it
    expects (the seen free ones, and the unseen ones at the seen share of free cells)."""
    seen, free, share = _seen_share(planner)
    expected = free[seen].sum() + share * (seen.size - seen.sum())
    return float(planner.visited.sum() / max(expected, 1.0))


def clear_of_noise(per_map: np.ndarray, sigmas: float) -> np.ndarray:
    """The options' mean scores over the sampled maps ``per_map`` ``(maps, options)``, slot 0
    first; with ``sigmas`` (and two maps or more) an option whose mean paired gain over slot 0
    is not above ``sigmas`` standard errors of that gain scores as slot 0 (the best of several
    noisy means is biased upwards)."""
    scores = per_map.mean(axis=0)
    if not sigmas or per_map.shape[0] < 2:
        return scores
    gains = per_map - per_map[:, :1]
    se = gains.std(axis=0, ddof=1) / np.sqrt(per_map.shape[0])
    noisy = gains.mean(axis=0) <= sigmas * se
    noisy[0] = False
    return np.where(noisy, scores[0], scores)


class SampledChooser(RolloutRule):
    """A chooser of goal-action slots that sees only the team's map: every slot is rolled out
    on ``samples`` maps the team's knowledge allows (:func:`sampled_free`), all slots on the
    same maps, and a slot replaces slot 0 only where its mean paired gain over the maps
    exceeds ``sigmas`` standard errors (:func:`clear_of_noise`) and the margin. It decides only
    from coverage ``after`` on (as the team's map tells it, :func:`believed_coverage`; slot 0,
    the planner, before it): the end game, where the measured gain lies and its rollouts are
    short (docs/planners.md, "The rollout chooser").

    Its rollouts run to the episode's end, score by the steps to 99 % coverage of their map and
    need no margin (the rule measured on validation episodes; the research script
    ``research/experiments/goal_oracle.py`` varies them).

    Args:
        samples: Sampled maps a decision.
        sigmas: Standard errors an option's mean gain must clear (0: the best mean wins).
        after: The team's coverage from which it decides.
        threads: Maps scored side by side (the compiled rollouts release the GIL); the
            choices do not depend on it, as every map is drawn before any is scored.
        prior: A map prior (:data:`MapPriorFn`) the unseen cells are drawn from, called once a
            decision step; ``None``: the seen cells' free share.
    """

    def __init__(
        self,
        samples: int = 4,
        sigmas: float = 4.0,
        after: float = 0.8,
        threads: int = 1,
        prior: MapPriorFn | None = None,
    ) -> None:
        super().__init__(horizon=None, margin=0.0, reach=0.99)
        if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
            raise ValueError(f"samples must be an integer >= 1, got {samples!r}")
        if not sigmas >= 0:
            raise ValueError(f"sigmas must be >= 0, got {sigmas!r}")
        if not 0 <= after <= 1:
            raise ValueError(f"after must be in [0, 1], got {after!r}")
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
            raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
        self.samples, self.sigmas, self.after = int(samples), float(sigmas), float(after)
        self.threads = int(threads)
        self.prior = prior
        # One pool for the chooser's life (a decision takes ~10 ms), made here so that the
        # copies of an evaluation, deciding side by side, share it; threads start on first use.
        self._map = in_threads(min(self.threads, self.samples))

    def __getstate__(self) -> dict[str, object]:
        return {k: v for k, v in self.__dict__.items() if k != "_map"}

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)
        self._map = in_threads(min(self.threads, self.samples))  # a copy makes its own threads

    def per_map(
        self,
        planner: FrontierPlanner,
        candidates: Candidates,
        agent: int,
        steps_left: int,
        rng: np.random.Generator,
        walks: Mapping[int, Sequence[int]] | None = None,
        p_wall: np.ndarray | None = None,
    ) -> np.ndarray:
        """Every valid slot's score (slot order) on each sampled map: ``(samples, slots)``
        (``p_wall``: the prior's wall probabilities the maps are drawn with)."""
        valid = np.flatnonzero(candidates.cells[agent] >= 0)
        # Every map is drawn before any is scored (scoring draws nothing), so the generator
        # gives the same maps in the same order whatever the threads.
        maps = [sampled_free(planner, rng, p_wall) for _ in range(self.samples)]

        def score(free: np.ndarray) -> np.ndarray:
            return self.scores_on(free, planner, candidates, agent, steps_left, walks)[valid]

        return np.array(list(self._map(score, maps))).reshape(self.samples, valid.size)

    def decide(
        self,
        planner: FrontierPlanner,
        candidates: Candidates,
        steps_left: int,
        rng: np.random.Generator,
        held: np.ndarray | None = None,
    ) -> np.ndarray:
        """Every agent's slot at this step, in agent index order (``(agents,)``; 0 for an agent
        that does not decide): an agent decides from coverage :attr:`after` on, when it holds
        no target (``held``: ``Frontier.held``, -1 for none) and has at least two candidates;
        one that leaves slot 0 commits to walking to its candidate, which the agents after it
        see, as they see the walks of those that hold."""
        n = candidates.cells.shape[0]
        slots = np.zeros(n, dtype=np.int64)
        holding = np.zeros(n, dtype=bool) if held is None else np.asarray(held) >= 0
        deciding = ~holding & ((candidates.cells >= 0).sum(axis=1) >= 2)
        if steps_left <= 0 or not deciding.any() or believed_coverage(planner) < self.after:
            return slots
        committed = held_walks(planner, held) if held is not None else {}
        size = planner.passable.size
        # The team's map is the same for every agent deciding at this step: one prediction.
        p_wall = None if self.prior is None else prior_wall_probability(planner, self.prior)
        for a in np.flatnonzero(deciding).tolist():
            valid = np.flatnonzero(candidates.cells[a] >= 0)
            per_map = self.per_map(planner, candidates, a, steps_left, rng, committed, p_wall)
            slots[a] = valid[self.pick(clear_of_noise(per_map, self.sigmas), size)]
            if slots[a] != 0:
                committed[a] = shortest_walk(planner, a, int(candidates.cells[a, slots[a]]))
        return slots


def _walk_arrays(
    planner: FrontierPlanner,
    candidates: Candidates,
    agent: int,
    walks: Mapping[int, Sequence[int]] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Each agent's walk as rows of one array and their lengths: a committed walk, else one
    step with slot 0's move (``agent``'s own always so: its slot 0)."""
    stride = planner.stride
    delta = (-stride, stride, -1, 1, 0)  # by move, STAY last
    rows: list[list[int]] = []
    for a, start in enumerate(planner.positions):
        walk = list(walks.get(a, ())) if walks is not None and a != agent else []
        rows.append(walk or [start + delta[int(candidates.moves[a, 0])]])
    lengths = np.array([len(r) for r in rows], dtype=np.int64)
    paths = np.zeros((len(rows), int(lengths.max())), dtype=np.int64)
    for a, r in enumerate(rows):
        paths[a, : len(r)] = r
    return paths, lengths
