"""Paired comparison of goal-selection runs with their planner on *validation* episodes (the
config's ``eval.validation_seed``; never the test episodes): per run, the mean coverage, and the
mean per-episode difference to always taking slot 0 (``--policy frontier_step``, the planner
itself) on the same episodes with a 95 % bootstrap interval. How the variants of
docs/goals.md were chosen.

    python research/experiments/goal_validation.py RUN [RUN ...] [--episodes 50]
        [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from harness import DoubleDQN
from harness.config.loading import load_config
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import model_policy, run_episodes
from harness.results.rundir import RunDir
from harness.results.stats import paired_difference


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--set", action="append", default=[], dest="overrides")
    args = parser.parse_args()
    out = {}
    planner: dict[str, np.ndarray] = {}
    for run in args.runs:
        config = load_config(RunDir(run).config, args.overrides)
        env, seed = config.env, config.eval.validation_seed
        key = json.dumps(env.model_dump(), sort_keys=True, default=str)
        if key not in planner:
            slot0 = run_episodes(make_baseline("frontier_step", 0), env, args.episodes, seed)
            planner[key] = np.array([r.coverage for r in slot0])
        model = DoubleDQN.load(RunDir(run).model, device="cpu")
        policy = model_policy(model, config.eval.temperature, config.eval.shield)
        cov = np.array([r.coverage for r in run_episodes(policy, env, args.episodes, seed)])
        mean, low, high = paired_difference(cov, planner[key])
        out[str(run)] = {"coverage_mean": float(cov.mean()), "over_planner": [mean, low, high]}
        print(
            f"{run.name}: {cov.mean():.2%} (planner {planner[key].mean():.2%}); "
            f"difference {mean:+.2%} [{low:+.2%}, {high:+.2%}] over {args.episodes} episodes",
            flush=True,
        )
    print(json.dumps(out))


if __name__ == "__main__":
    main()
