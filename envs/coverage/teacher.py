"""The rollout teacher of the goal action: a chooser that sees the true map, for training only.

At a decision of agent ``i`` (docs/goals.md), the teacher tries every candidate slot on a copy
of the planner's map, whose free cells are the *true* ones (the planner's ``free`` row is the
episode's map; the planner itself only plans over what the team has seen):

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
of at most ``margin`` (cells, or steps with ``reach``), keep slot 0.

It is the rollout oracle of ``experiments/goal_oracle.py`` (docs/experiment-log.md, "The room
in the candidates"), compiled: one call per decision runs every slot's rollout to its end in
numba (the map copy, the planner's steps, the count of visited cells), with the planners' own
compiled steps (:func:`envs.coverage.planners._plan`, :func:`_coordinated_step`) and map
upkeep (:func:`envs.coverage.planners._visit_cells`): one owner of every rule. Its choices
label the policy's own states (DAgger); it must never choose in evaluation, where no policy
sees the true map (``tests/test_architecture.py`` keeps it out of the evaluation code).

Use, per deciding agent of a core's copy ``b`` (after its observation, so that the planner and
the candidates are this step's)::

    teacher = RolloutTeacher(horizon=None, margin=0, reach=None)
    frontier = core.frontiers[b]
    slot, scores = teacher.choose(
        frontier.planner, frontier.candidates, agent, core.max_steps - int(core.steps[b])
    )

or :meth:`RolloutTeacher.label` for every deciding agent of the step, in index order (an
agent's choice binds the agents after it, as the oracle decides).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

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

__all__ = ["RolloutTeacher", "shortest_walk"]

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
                f"the rollout teacher needs a compiled planner step; {type(planner).__name__} "
                f"with candidates={planner.candidates!r} has none"
            )
        return _PlannerStep(
            planner.window, planner.offsets, _COORDINATED, False, planner._compiled_assign,
            float(planner._horizon()), float(getattr(planner, "beta", 0.0)),
            float(getattr(planner, "radius", 1.0)),
        )  # fmt: skip
    if planner.tie_break not in ("order", "pocket"):
        raise ValueError(
            f"the rollout teacher plays the order and pocket explorers and the coordinated "
            f"planners, not tie_break={planner.tie_break!r} (its ties are drawn)"
        )
    return _PlannerStep(
        planner.window, planner.offsets, _EXPLORER, planner.tie_break == "pocket", 0, np.inf,
        0.0, 1.0,
    )  # fmt: skip


def shortest_walk(planner: FrontierPlanner, agent: int, cell: int) -> list[int]:
    """The cells (padded, flat) of the walk the teacher's rollouts take from ``agent``'s cell
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


class RolloutTeacher:
    """The rollout oracle as a chooser of goal-action slots (module docstring).

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

    def scores(
        self,
        planner: FrontierPlanner,
        candidates: Candidates,
        agent: int,
        steps_left: int,
        walks: Mapping[int, Sequence[int]] | None = None,
        free: np.ndarray | None = None,
    ) -> np.ndarray:
        """Each slot's rollout score for ``agent`` (module docstring), NaN for empty slots.

        Args:
            planner: The episode's planner, synced to this step and planned
                (``Frontier.planner``; its ``free`` row is the true map).
            candidates: This step's candidates (``Frontier.candidates``).
            agent: The deciding agent.
            steps_left: Steps left in the episode, this one included (``max_steps - steps``).
            walks: Teammates' committed walks: padded cells from the next one on (an agent
                not in it, or with an empty walk, takes slot 0's move); ``agent``'s own is
                ignored.
            free: Free cells of the padded grid (flat) to roll out on in place of the true
                ones, for the cells nobody has seen (a sampled map; research only).
        """
        cells = candidates.cells[agent]
        out = np.full(cells.size, np.nan)
        valid = np.flatnonzero(cells >= 0)
        if valid.size == 0 or steps_left <= 0:
            return out
        grid = planner.grid
        if free is not None:
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
        """The chosen slot of :meth:`scores`' ``scores``: the first best, if it beats slot 0
        by more than the margin (in steps with ``reach``: ``size`` is the padded grid's
        cells), else 0."""
        if not np.isfinite(scores[0]):
            return 0
        best = int(np.argmax(np.where(np.isnan(scores), -np.inf, scores)))
        return best if scores[best] > scores[0] + self.margin * self.unit(size) else 0

    def choose(
        self,
        planner: FrontierPlanner,
        candidates: Candidates,
        agent: int,
        steps_left: int,
        walks: Mapping[int, Sequence[int]] | None = None,
    ) -> tuple[int, np.ndarray]:
        """``agent``'s slot and every slot's score (:meth:`scores`, on the true map)."""
        scores = self.scores(planner, candidates, agent, steps_left, walks)
        return self.pick(scores, planner.passable.size), scores

    def label(
        self,
        planner: FrontierPlanner,
        candidates: Candidates,
        steps_left: int,
        walks: Mapping[int, Sequence[int]] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every deciding agent's slot at this step, in agent index order: an agent decides
        when it has no committed walk and at least two candidates; one that leaves slot 0
        commits to walking to its candidate, which the agents after it see (the oracle's
        order). Returns the slots ``(agents,)`` (-1: not deciding) and the scores
        ``(agents, k)`` (NaN where not scored)."""
        n, k = candidates.cells.shape
        committed = {a: list(w) for a, w in (walks or {}).items() if len(w)}
        slots = np.full(n, -1, dtype=np.int64)
        scores = np.full((n, k), np.nan)
        deciding = [
            a for a in range(n) if a not in committed and (candidates.cells[a] >= 0).sum() > 1
        ]
        for a in deciding:
            slots[a], scores[a] = self.choose(planner, candidates, a, steps_left, committed)
            if slots[a] != 0:
                committed[a] = shortest_walk(planner, a, int(candidates.cells[a, slots[a]]))
        return slots, scores


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
