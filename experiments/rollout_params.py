"""The rollout baseline (``harness eval --policy rollout``, docs/planners.md "The rollout
chooser") with other parameters than its default, paired with written planners on the same
episodes: the sampled maps per decision (``--samples``), the standard errors a gain must clear
(``--sigmas``) and the team's coverage from which it decides (``--after``). On validation
episodes (the config's ``eval.validation_seed``) unless ``--test`` (its ``eval.seed``: once, for
parameters already chosen on validation). Prints one JSON object: the chooser's mean coverage
and, per planner, the mean difference in points of coverage and in steps to 99 % (on the
episodes both reach it in) with 95 % bootstrap intervals over the paired episodes.

    python experiments/rollout_params.py --config configs/goals_2agents.yaml --set env.map=random
        [--samples 16] [--sigmas 4] [--after 0.6] [--episodes 20] [--test]
        [--against frontier_pocket frontier_minpos]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from envs.coverage.rollouts import SampledChooser
from harness.commands import paired_steps_to_99
from harness.config.loading import load_config
from harness.evaluation.baselines import BASELINES, RolloutPolicy, make_baseline
from harness.evaluation.episodes import run_episodes
from harness.results.stats import paired_difference


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True)
    parser.add_argument("--set", action="append", default=[], dest="overrides")
    parser.add_argument("--samples", type=int, default=4)
    parser.add_argument("--sigmas", type=float, default=4.0)
    parser.add_argument("--after", type=float, default=0.8)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--test", action="store_true", help="the test episodes (eval.seed)")
    parser.add_argument("--against", nargs="+", default=["frontier_pocket", "frontier_minpos"])
    args = parser.parse_args()
    config = load_config(args.config, args.overrides)
    env = config.env
    seed = config.eval.seed if args.test else config.eval.validation_seed
    chooser = SampledChooser(args.samples, args.sigmas, args.after)
    start = time.perf_counter()
    policy = RolloutPolicy(chooser)
    ours = run_episodes(policy, BASELINES["rollout"].env_config(env), args.episodes, seed)
    coverage = np.array([r.coverage for r in ours])
    out: dict = {
        "seed": seed,
        "episodes": args.episodes,
        "chooser": {"samples": args.samples, "sigmas": args.sigmas, "after": args.after},
        "minutes": (time.perf_counter() - start) / 60,
        "coverage_mean": float(coverage.mean()),
        "wall_hits": int(sum(sum(r.wall_hits) for r in ours)),
    }
    for name in args.against:
        planner = make_baseline(name, 0)
        theirs = run_episodes(planner, BASELINES[name].env_config(env), args.episodes, seed)
        other = np.array([r.coverage for r in theirs])
        difference, low, high = paired_difference(coverage, other)
        steps = paired_steps_to_99(
            [r.steps_to["steps_to_99"] for r in ours], [r.steps_to["steps_to_99"] for r in theirs]
        )
        out[name] = {
            "coverage_mean": float(other.mean()),
            "difference_points": [100 * difference, 100 * low, 100 * high],
            "ahead": int((coverage > other).sum()),
            "behind": int((coverage < other).sum()),
            "steps_to_99": steps,
        }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
