"""Where a coordinated planner's time goes, per episode, beside the classical explorer's.

Plays the bench's setting (50x50 random maps, 4 agents, 1000 steps, one thread) with each
planner's baseline and times, inside the run, the parts of a step that the planner adds: the
compiled searches with the targets' costs (``envs.coverage.planners._target_costs``: the fields
up to the horizon, and the whole map for an agent with nothing within it) and the assignment.
The rest of an episode is the env, the map upkeep and Python around them, which ``frontier``
pays too. docs/performance.md quotes it.

    python experiments/planner_time.py [EPISODES]     # default 8; under a minute
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import torch

import envs.coverage.planners as planners
from harness.bench import THESIS_ENV
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import run_episodes

POLICIES = ("frontier", "frontier_hungarian", "frontier_minpos", "frontier_utility")


def timed(spent: dict[str, float], name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn``, adding its wall time to ``spent[name]``."""

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        start = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            spent[name] = spent.get(name, 0.0) + time.perf_counter() - start

    return wrapper


def main(episodes: int) -> None:
    torch.set_num_threads(1)
    spent: dict[str, float] = {}
    planners._target_costs = timed(spent, "searches and costs", planners._target_costs)
    for cls in (planners.HungarianPlanner, planners.MinPosPlanner, planners.UtilityPlanner):
        cls.assign = timed(spent, "assignment", cls.assign)
    for policy in POLICIES:
        spent.clear()
        start = time.perf_counter()
        run_episodes(make_baseline(policy, 0), THESIS_ENV, episodes, 0)
        total = time.perf_counter() - start
        parts = ", ".join(f"{k} {v / episodes * 1e3:.1f}" for k, v in sorted(spent.items()))
        print(f"{policy}: {total / episodes * 1e3:.1f} ms per episode ({parts})")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 8)
