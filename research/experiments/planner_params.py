"""Choose the coordinated planners' parameters on validation episodes (never the test ones).

Every combination below plays the same validation episodes (``eval.validation_seed`` of the
configs, 2000003, episode ``k`` seeded ``2000003 + k``) on three settings: 50x50 random maps with
2 and with 4 agents (``configs/ddqn_2agents.yaml``, ``configs/ddqn_4agents.yaml``) and the cave
with 2 agents (``configs/cave_2agents.yaml``). The choice, per planner, is the highest mean
coverage over the three settings, then the fewest median steps to 99 % with 4 agents (where
every planner covers everything). Writes ``docs/planners/validation.json``; docs/planners.md
quotes it.

    python research/experiments/planner_params.py [EPISODES]  # default 20; 15 min on 2 cores
"""

from __future__ import annotations

import itertools
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SETTINGS = ("ddqn_2agents", "ddqn_4agents", "cave_2agents")
GRID = {
    "utility": [
        {"beta": beta, "radius": radius}
        for beta, radius in itertools.product((0.01, 0.05, 0.2), (3.0, 5.0, 10.0))
    ],
    "minpos": [{}],
    "hungarian": [{}],
}
CANDIDATES = ("all", "clusters")
HORIZONS = (15, None)


def evaluate(job: tuple[str, dict, str, int]) -> dict:
    planner, params, setting, episodes = job
    import torch

    torch.set_num_threads(1)
    from envs.coverage import planners
    from harness.config import load_config
    from harness.evaluation.baselines import FrontierPolicy
    from harness.evaluation.episodes import run_episodes, summarize

    cls = {
        "utility": planners.UtilityPlanner,
        "minpos": planners.MinPosPlanner,
        "hungarian": planners.HungarianPlanner,
    }[planner]
    config = load_config(ROOT / "configs" / f"{setting}.yaml")
    policy = FrontierPolicy(lambda h, w: cls(h, w, **params))
    summary = summarize(run_episodes(policy, config.env, episodes, config.eval.validation_seed))
    return {
        "planner": planner,
        "params": params,
        "setting": setting,
        "coverage_mean": summary["coverage_mean"],
        "steps_to_99": summary["steps_to_99"],
    }


def score(rows: list[dict], key: str) -> tuple[float, float]:
    """The choice rule: mean coverage over the settings, then fewer steps to 99 % (4 agents)."""
    group = [r for r in rows if json.dumps(r["params"], sort_keys=True) == key]
    mean = sum(r["coverage_mean"] for r in group) / len(group)
    steps = [r["steps_to_99"] for r in group if r["setting"] == "ddqn_4agents"]
    return (mean, -(steps[0] if steps and steps[0] is not None else 1e9))


def main() -> None:
    episodes = int(sys.argv[1]) if len(sys.argv) > 1 else 20
    jobs = []
    for planner, grid in GRID.items():
        for base, candidates, horizon in itertools.product(grid, CANDIDATES, HORIZONS):
            if horizon is None and candidates != "all":
                continue  # the horizon is a speed setting: checked once, on "all"
            params = {**base, "candidates": candidates, "horizon": horizon}
            jobs += [(planner, params, setting, episodes) for setting in SETTINGS]
    with ProcessPoolExecutor(2) as pool:
        rows = list(pool.map(evaluate, jobs))
    chosen = {}
    for planner in GRID:
        mine = [r for r in rows if r["planner"] == planner]
        keys = sorted({json.dumps(r["params"], sort_keys=True) for r in mine})
        scores = {key: score(mine, key) for key in keys}
        best = max(keys, key=scores.__getitem__)
        chosen[planner] = {"params": json.loads(best), "score": scores[best]}
    out = ROOT / "docs" / "planners" / "validation.json"
    out.write_text(json.dumps({"episodes": episodes, "chosen": chosen, "rows": rows}, indent=1))
    print(json.dumps(chosen, indent=1))


if __name__ == "__main__":
    main()
