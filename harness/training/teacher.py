"""The teacher's labels in training (DAgger, docs/goals.md "The teacher"): the policy plays, a
teacher that sees the true map labels the decisions it meets, and the replay buffer keeps each
label with its decision (``harness.sb3.decisions``), for DQfD's margin loss.

:class:`TeacherLabeller` is called by the core's VecEnv (:class:`~harness.training.adapters.
CoreVecEnv`) before each step, on the state the policy has just chosen in: for a share of the
copies (``algo.teacher.share``, drawn from a generator of its own, so the episodes are those of
a run without a teacher), :meth:`envs.coverage.teacher.RolloutTeacher.label` gives every
deciding agent's slot, its teammates' held targets being walks they have committed to. The
copies are labelled side by side on the run's CPU threads (``algo.threads``; the compiled
rollouts release the GIL, and a label draws nothing, so the labels are those of one thread).
Only training builds it: evaluation never does (``tests/test_architecture.py``).
"""

from __future__ import annotations

import numpy as np

from envs.coverage.core import CoverageCore
from envs.coverage.rollouts import held_walks, in_threads
from envs.coverage.teacher import RolloutTeacher
from harness.config.schema import TeacherConfig

__all__ = ["TeacherLabeller"]


class TeacherLabeller:
    """Labels the decisions of a core's copies with a :class:`RolloutTeacher`'s slots.

    Args:
        config: ``algo.teacher``.
        seed: Seeds the draw of the labelled copies.
        threads: Copies labelled side by side.
    """

    def __init__(
        self, config: TeacherConfig, seed: int | list[int] | None = None, threads: int = 1
    ) -> None:
        # The oracle's measured setting: rollouts to the episode's end, scored by the cells found
        # (or with reach, by the steps to that coverage), any gain over slot 0
        # (research/experiment-log.md "The room in the candidates").
        self.teacher = RolloutTeacher(reach=config.reach)
        self.share = config.share
        self.rng = np.random.default_rng(seed)
        self._map = in_threads(threads)

    def __call__(self, core: CoverageCore) -> np.ndarray:
        """The label of every agent of every copy at the core's current state, ``(copies,
        agents)``: the teacher's slot for a deciding agent of a labelled copy, -1 elsewhere."""
        out = np.full((core.copies, core.n_agents), -1, dtype=np.int64)
        drawn = self.rng.random(core.copies) < self.share
        copies = [
            b
            for b in np.flatnonzero(drawn).tolist()
            if core.frontiers[b] is not None and core.frontiers[b].candidates is not None
        ]

        def label(b: int) -> np.ndarray:
            frontier = core.frontiers[b]
            planner = frontier.planner
            walks = held_walks(planner, frontier.held)
            steps_left = core.max_steps - int(core.steps[b])
            return self.teacher.label(planner, frontier.candidates, steps_left, walks)[0]

        for b, slots in zip(copies, self._map(label, copies)):
            out[b] = slots
        return out
