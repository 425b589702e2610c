"""The rollout oracle in plain Python: the reference that the compiled
:class:`~envs.coverage.teacher.RolloutTeacher` must equal (tests/test_teacher.py). Taken from the
research script ``research/experiments/goal_oracle.py`` (its ``--rollouts python``) so that no test
imports research code: a planner's map copied (:func:`clone`), stepped (:func:`advance`,
:func:`rollout`), each slot scored (:func:`python_scores`), and whole episodes played with
commitment to a chosen walk (:func:`play`) with either rollouts."""

from __future__ import annotations

import numpy as np

from envs.coverage.env import CoverageEnv
from envs.coverage.goals import Candidates
from envs.coverage.planners import FrontierPlanner
from envs.coverage.rollouts import shortest_walk
from envs.coverage.teacher import RolloutTeacher


def clone(planner: FrontierPlanner) -> FrontierPlanner:
    """A copy of the planner's map that can be stepped on its own (its per-cell state, ``grid``,
    is copied, and the searches' scratch arrays are its own)."""
    copy = object.__new__(type(planner))
    copy.__dict__.update(planner.__dict__)
    copy.grid = planner.grid.copy()
    copy.free, copy.visited, copy.seen, copy.passable, copy.target = copy.grid
    copy.positions, copy.goals = list(planner.positions), list(planner.goals)
    copy._scratch = copy._claimed = copy._distances = None
    return copy


def advance(planner: FrontierPlanner, cells: list[int]) -> int:
    """Moves every agent to ``cells`` (one step); returns how many new cells were visited."""
    planner.positions = list(cells)
    planner.steps += 1
    new = 0
    for cell in cells:
        if not planner.visited[cell]:
            planner._visit(cell)
            new += 1
    return new


def rollout(
    planner: FrontierPlanner, steps: int, paths: dict[int, list[int]], reach: int | None = None
) -> tuple[int, int | None]:
    """Steps the planner's map ``steps`` times, the agents in ``paths`` walking them first and
    everybody following the planner after. Returns the cells newly visited and, when ``reach``
    (a number of newly visited cells) is given, the step (1-based) on which they reached it
    (``None``: not within ``steps``; with ``reach <= 0``, 0); the rollout then ends."""
    offset = {0: -planner.stride, 1: planner.stride, 2: -1, 3: 1, 4: 0}
    paths = {a: list(p) for a, p in paths.items() if p}
    new = 0
    if reach is not None and reach <= 0:
        return 0, 0
    for step in range(1, steps + 1):
        moves = planner.act()
        cells = [
            paths[a].pop(0) if paths.get(a) else pos + offset[m]
            for a, (pos, m) in enumerate(zip(planner.positions, moves))
        ]
        new += advance(planner, cells)
        if reach is not None and new >= reach:
            return new, step
        if planner.n_targets == 0 and not any(paths.values()):
            break
    return new, None


def path_to(pred: np.ndarray, start: int, goal: int) -> list[int]:
    """The cells of the shortest path from ``start`` to ``goal`` (without ``start``)."""
    cells = [goal]
    while (prev := int(pred[cells[-1]])) != start:
        cells.append(prev)
    return cells[::-1]


def python_scores(
    planner: FrontierPlanner,
    cand: Candidates,
    i: int,
    cells: list[int],
    rests: dict[int, list[int]],
    steps_left: int,
    teacher: RolloutTeacher,
) -> np.ndarray:
    """Agent ``i``'s rollout score of each of its candidate slots, stepped in Python: what
    :meth:`RolloutTeacher.scores <envs.coverage.teacher.RolloutTeacher.scores>` compiles.
    ``cells``: every agent's next cell, ``rests``: the committed walks after it; the teacher's
    ``horizon`` and ``reach`` set the rollouts' length and score."""
    slots = np.flatnonzero(cand.cells[i] >= 0)
    pred = planner.distance_fields()[1]
    options = [[cells[i]]] + [
        path_to(pred[i], planner.positions[i], int(cand.cells[i, j])) for j in slots[1:]
    ]
    left = steps_left - 1
    if teacher.horizon is not None:
        left = min(left, teacher.horizon - 1)
    goal = None  # with ``reach``: cells still to find
    if teacher.reach is not None:
        goal = int(np.ceil(teacher.reach * sum(planner.free))) - sum(planner.visited)
    scores = np.zeros(len(options))
    for o, path in enumerate(options):
        sim = clone(planner)
        first = list(cells)
        first[i] = path[0]
        new = advance(sim, first)
        if goal is None:
            scores[o] = new + rollout(sim, left, {**rests, i: path[1:]})[0]
            continue
        more, step = rollout(sim, left, {**rests, i: path[1:]}, goal - new)
        # Steps first (not reached: one more than the rollout had), then cells.
        steps = 1 + (left + 1 if step is None else step)
        scores[o] = -steps * (len(planner.free) + 1) + new + more
    return scores


def play(
    env: CoverageEnv,
    seed: int,
    oracle: bool,
    reach: float | None = None,
    python: bool = False,
    after: float = 0.0,
    decisions: list | None = None,
) -> tuple[float, int, int | None]:
    """One episode on the true map; with ``oracle`` the rollout oracle chooses (from coverage
    ``after`` on), otherwise slot 0 throughout. ``reach`` (a coverage): the slots are scored by
    the steps their rollout takes to reach it (fewer is better, ties by cells). ``python``: the
    rollouts of :func:`python_scores`, else the compiled teacher's. ``decisions`` collects
    ``(step, agent, scores, choice)``. Returns the coverage, the number of deviations from slot 0
    and the steps to ``reach`` (``None`` when not reached or not asked)."""
    env.reset(seed=seed)
    teacher = RolloutTeacher(reach=reach)
    n = env.n_agents
    walk: list[list[int]] = [[] for _ in range(n)]  # each agent's committed path
    deviations = 0
    reached: int | None = None
    while env.agents:
        frontier = env.frontier_state
        planner, cand = frontier.planner, frontier.candidates
        offset = {0: -planner.stride, 1: planner.stride, 2: -1, 3: 1, 4: 0}
        move_of = {d: m for m, d in offset.items()}
        for a in range(n):
            if walk[a] and not planner.target[walk[a][-1]]:
                walk[a] = []  # its target was visited: decide again
        cells = [
            walk[a][0] if walk[a] else planner.positions[a] + offset[int(cand.moves[a, 0])]
            for a in range(n)
        ]
        rests = {a: walk[a][1:] for a in range(n) if walk[a]}
        deciding = [a for a in range(n) if not walk[a] and (cand.cells[a] >= 0).sum() > 1]
        if oracle and deciding and env.coverage >= after:
            steps_left = env.max_steps - env.steps  # this step included
            for i in deciding:
                slots = np.flatnonzero(cand.cells[i] >= 0)
                if python:
                    scores = python_scores(planner, cand, i, cells, rests, steps_left, teacher)
                else:
                    walks = {a: w for a, w in enumerate(walk) if w}
                    scores = teacher.scores_on(planner.free, planner, cand, i, steps_left, walks)
                    scores = scores[slots]
                best = teacher.pick(scores, len(planner.free))
                if decisions is not None:
                    decisions.append((env.steps, i, scores, best))
                if best != 0:
                    goal = int(cand.cells[i, best])
                    if python:
                        path = path_to(planner.distance_fields()[1][i], planner.positions[i], goal)
                    else:
                        path = shortest_walk(planner, i, goal)
                    cells[i], rests[i], walk[i] = path[0], path[1:], path
                    deviations += 1
        for a in range(n):
            # Slot 0 carries each agent's move (the goal action resolves slots to moves).
            cand.moves[a, 0] = move_of[cells[a] - planner.positions[a]]
            if walk[a]:
                walk[a] = walk[a][1:]
        env.step(dict.fromkeys(env.agents, 0))
        if reach is not None and reached is None and env.coverage >= reach:
            reached = env.steps
    return env.coverage, deviations, reached
