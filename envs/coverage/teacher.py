"""The rollout teacher of the goal action: a chooser that sees the true map, for training only.

At a decision of agent ``i`` (docs/goals.md), the teacher rolls every candidate slot out
(:mod:`envs.coverage.rollouts`: the slot's walk, teammates keeping to theirs, then everybody
following the planner) on a copy of the planner's map whose free cells are the *true* ones
(the planner's ``free`` row is the episode's map), and keeps the best slot by the rollouts'
rule (:class:`~envs.coverage.rollouts.RolloutRule`).

It is the rollout oracle of ``research/experiments/goal_oracle.py`` (research/experiment-log.md,
"The room in the candidates"), compiled. Its choices label the policy's own states (DAgger); it must
never choose in evaluation, where no policy sees the true map (``tests/test_architecture.py``
keeps it out of the evaluation code; the ``rollout`` baseline plays the same rule on maps
the team's knowledge allows, :class:`~envs.coverage.rollouts.SampledChooser`).

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

import numpy as np

from envs.coverage.goals import Candidates
from envs.coverage.planners import FrontierPlanner
from envs.coverage.rollouts import RolloutRule, shortest_walk

__all__ = ["RolloutTeacher"]


class RolloutTeacher(RolloutRule):
    """The rollout oracle as a chooser of goal-action slots (module docstring); its arguments
    (``horizon``, ``margin``, ``reach``) are the rollouts' rule's
    (:class:`~envs.coverage.rollouts.RolloutRule`)."""

    def scores(
        self,
        planner: FrontierPlanner,
        candidates: Candidates,
        agent: int,
        steps_left: int,
        walks: Mapping[int, Sequence[int]] | None = None,
    ) -> np.ndarray:
        """Each slot's rollout score for ``agent`` on the true map (the planner's ``free``
        row), NaN for empty slots (:meth:`~envs.coverage.rollouts.RolloutRule.scores_on`, whose
        arguments these are; another map: call that on it)."""
        return self.scores_on(planner.free, planner, candidates, agent, steps_left, walks)

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
