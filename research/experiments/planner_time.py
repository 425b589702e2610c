"""Where a coordinated planner's time goes, per step, beside the classical explorer's.

Plays the bench's setting (50x50 random maps, 4 agents, 1000 steps, one thread) with each
planner's baseline and reports its CPU time per episode. For the coordinated planners it also
records the compiled step's inputs on the first episode (``_coordinated_step``: the map upkeep,
one search per agent for the targets' costs, the assignment and the first moves) and replays
them, each from a copy of its recorded map, timing in CPU time per step (best of three):

- ``upkeep``: the map brought up to date (``_sync``);
- ``searches``: the upkeep and the searches with the targets' costs (``_sync_and_costs``:
  every agent's field up to the horizon, on over the whole map for an agent with nothing
  within it, ``paths.breadth_first``);
- ``step``: the whole compiled step (the assignment and first moves beside the searches).

The replays call the compiled functions from Python once per step, as the planner does; the
rest of an episode is the env and Python around the planner, which ``frontier`` pays too.
research/performance-history.md quotes it.

    python research/experiments/planner_time.py [EPISODES]     # default 8; under a minute
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

import envs.coverage.planners as planners
from harness.bench import THESIS_ENV
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import run_episodes

POLICIES = ("frontier", "frontier_hungarian", "frontier_minpos", "frontier_utility")


def record(policy: str) -> list[tuple[Any, ...]]:
    """The arguments of every compiled step of ``policy``'s first episode (copies of the
    positions and of the map before the step)."""
    steps: list[tuple[Any, ...]] = []
    compiled = planners._coordinated_step

    def recording(positions: np.ndarray, window: np.ndarray, grid: np.ndarray, *rest: Any) -> Any:
        steps.append((positions.copy(), window, grid.copy(), *rest))
        return compiled(positions, window, grid, *rest)

    planners._coordinated_step = recording
    try:
        run_episodes(make_baseline(policy, 0), THESIS_ENV, 1, 0)
    finally:
        planners._coordinated_step = compiled
    return steps


def per_step(steps: list[tuple[Any, ...]], part: Callable[..., Any]) -> float:
    """CPU microseconds per step of ``part`` over the recorded steps (best of three), less the
    copy of the map each replay starts from."""

    def replay(fn: Callable[..., Any]) -> float:
        best = np.inf
        for _ in range(3):
            start = time.process_time()
            for positions, window, grid, *rest in steps:
                fn(positions, window, grid.copy(), *rest)
            best = min(best, time.process_time() - start)
        return best

    return (replay(part) - replay(lambda *args: None)) / len(steps) * 1e6


def upkeep(positions, window, grid, n_targets, stride, horizon, dist, queue, *rest) -> None:
    starts = rest[-3]
    planners._sync(positions, stride, window, grid, starts)


def searches(positions, window, grid, n_targets, stride, horizon, dist, queue, *rest) -> None:
    starts = rest[-3]
    planners._sync_and_costs(
        positions, window, grid, n_targets, stride, horizon, dist, queue, starts
    )


def main(episodes: int) -> None:
    torch.set_num_threads(1)
    for policy in POLICIES:
        run_episodes(make_baseline(policy, 0), THESIS_ENV, 1, 0)  # compiled and warm
        start = time.process_time()
        run_episodes(make_baseline(policy, 0), THESIS_ENV, episodes, 0)
        total = (time.process_time() - start) / episodes * 1e3
        line = f"{policy}: {total:.1f} ms of CPU per episode"
        if policy != "frontier":
            steps = record(policy)
            parts = {
                "upkeep": per_step(steps, upkeep),
                "searches": per_step(steps, searches),
                "step": per_step(steps, planners._coordinated_step),
            }
            line += f"; compiled step over {len(steps)} steps, us: " + ", ".join(
                f"{name} {value:.1f}" for name, value in parts.items()
            )
        print(line, flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 8)
