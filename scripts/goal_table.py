"""The learned goal selection against the strongest written planner on every test setting of
issue 37: the table of docs/results.md ("Learned goal selection"), made from stored 100-episode
evaluations (the standard test episodes, each config's ``eval.seed``).

- the learned policy: the best model of each of the three training seeds of
  ``configs/goals_2agents.yaml`` (1 and 2 agents, random / cave / maze) or
  ``configs/goals_4agents.yaml`` (4 agents), evaluated by ``scripts/goal_results.sh``; seed 0's
  files are in ``runs/reference/<config>/``, seeds 1 and 2's in ``docs/seeds/<config>/``;
- the planners: ``docs/baselines/<config>-<policy>.json`` (``scripts/planner_table.py``).

Coverage is the mean over the seeds with rliable's 95 % stratified-bootstrap interval; steps to
90 / 99 % the mean over the seeds of each seed's median episode (– when a median episode does
not get there). ``tests/test_readme_results.py`` checks that the page holds exactly this table.

    python scripts/goal_table.py       # prints the markdown table
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

from harness.results.stats import seed_statistics

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location(
    "planner_table", ROOT / "scripts" / "planner_table.py"
)
planners = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(planners)

#: (the setting in words, the planners' config, the goal config, its eval file, the goal):
#: a goal is ("coverage", points over the planner) or ("steps_to_99" / "steps_to_90", at most
#: this share of the planner's steps).
SETTINGS = (
    (
        "50x50 random, 1 agent",
        "ddqn_1agent",
        "goals_2agents",
        "env.map-random_env.n_agents-1",
        ("coverage", 0.0),
    ),
    (
        "50x50 random, 2 agents",
        "ddqn_2agents",
        "goals_2agents",
        "env.map-random",
        ("coverage", 3.0),
    ),
    (
        "50x50 random, 4 agents",
        "ddqn_4agents",
        "goals_4agents",
        "env.map-random",
        ("steps_to_99", 0.9),
    ),
    (
        "maze_100x50, 2 agents",
        "maze_2agents",
        "goals_2agents",
        "env.map-maze_100x50",
        ("coverage", 4.0),
    ),
    (
        "maze_100x50, 4 agents",
        "maze_4agents",
        "goals_4agents",
        "env.map-maze_100x50",
        ("steps_to_90", 0.9),
    ),
    (
        "cave_100x50, 2 agents",
        "cave_2agents",
        "goals_2agents",
        "env.map-cave_100x50",
        ("steps_to_99", 0.9),
    ),
    (
        "cave_100x50, 4 agents",
        "cave_4agents",
        "goals_4agents",
        "env.map-cave_100x50",
        ("steps_to_99", 0.9),
    ),
)
SEEDS = (0, 1, 2)


def eval_file(config: str, seed: int, suffix: str) -> Path:
    """Where a seed's evaluation of its best model is stored."""
    if seed == 0:
        return ROOT / "runs" / "reference" / config / f"eval-{suffix}.json"
    return ROOT / "docs" / "seeds" / config / f"{config}-seed{seed}" / f"eval-{suffix}.json"


def learned(config: str, suffix: str) -> list[dict]:
    return [json.loads(eval_file(config, s, suffix).read_text()) for s in SEEDS]


def _steps(values: list[float | None]) -> float | None:
    return None if any(v is None for v in values) else float(np.mean(values))


def row(words: str, planner_config: str, config: str, suffix: str, goal: tuple) -> str:
    best = planners.strongest(planner_config)
    plan = planners.load(planner_config, best)
    runs = learned(config, suffix)
    stats = seed_statistics({"learned": [r["coverage_mean"] for r in runs]})["learned"]
    low, high = stats.mean_ci
    steps = {k: _steps([r[k] for r in runs]) for k in ("steps_to_90", "steps_to_99")}
    efficiency = float(np.mean([r["efficiency"] for r in runs]))
    hits = sum(r["wall_hits_mean"] for r in runs)
    # The planners' cell format, with the seeds' mean and interval in the coverage's place.
    mine = planners.cell(
        {"coverage_mean": stats.mean, "coverage_mean_ci": (low, high), "efficiency": efficiency}
        | steps
    )
    kind, bar = goal
    if kind == "coverage":
        target = plan["coverage_mean"] + bar / 100
        wanted = f"≥ {target:.1%}".replace("%", " %")
        measured = f"{100 * (stats.mean - plan['coverage_mean']):+.1f} points"
        reached = stats.mean >= target
    else:
        share = kind.removeprefix("steps_to_")
        if plan[kind] is None:
            wanted, measured, reached = f"steps to {share} % (planner: –)", "–", False
        else:
            wanted = f"≤ {bar * plan[kind]:g} steps to {share} %"
            measured = "–" if steps[kind] is None else f"{steps[kind] / plan[kind]:.3f} ×"
            reached = steps[kind] is not None and steps[kind] <= bar * plan[kind]
    return (
        f"| {words} | `{best}`: {planners.cell(plan)} | {mine} | {hits:g} | {wanted} | "
        f"{measured} | {'yes' if reached else 'no'} |"
    )


def table() -> str:
    lines = [
        "| setting | strongest written planner | learned goal selection (3 seeds) | wall hits "
        "| goal | learned vs planner | reached |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [row(*setting) for setting in SETTINGS]
    return "\n".join(lines)


if __name__ == "__main__":
    print(table())
