"""A written chooser on the goal action's prior features (MapEx's predicted information gain):
each agent takes the candidate of the highest ``far + a * near - b * distance``, slot 0 (the
planner's choice) with a bonus ``c`` (``c`` large: the planner itself). Played on the
validation episodes of a config with ``env.prior`` (never the test ones), so a grid of (a, b, c)
may be searched here.

    python research/experiments/predicted_gain.py configs/goals_prior_rooms_4agents.yaml \
        --episodes 20 --grid "0,0,1e9 1,0.5,0.05 1,1,0.1"
"""

from __future__ import annotations

import argparse

import numpy as np

from envs.coverage.goals import GOAL_FEATURES
from harness.config.loading import load_config
from harness.factory import make_env

NEAR, FAR = len(GOAL_FEATURES), len(GOAL_FEATURES) + 1
DISTANCE = GOAL_FEATURES.index("distance")


def play(env, seed: int, a: float, b: float, c: float) -> float:
    obs, _ = env.reset(seed=seed)
    coverage = 0.0
    while env.agents:
        actions = {}
        for agent, o in obs.items():
            f, mask = o["goals"], o["action_mask"].astype(bool)
            score = f[:, FAR] + a * f[:, NEAR] - b * f[:, DISTANCE]
            score[0] += c
            score[~mask] = -np.inf
            actions[agent] = int(np.argmax(score)) if mask.any() else 0
        obs, _, _, _, infos = env.step(actions)
        coverage = next(iter(infos.values()))["coverage"] if infos else coverage
    return coverage


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("config")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--grid", default="0,0,1e9 1,0.5,0.05")
    args = parser.parse_args()
    config = load_config(args.config)
    env = make_env(config.env)
    seed0 = config.eval.validation_seed
    base = None
    for point in args.grid.split():
        a, b, c = (float(x) for x in point.split(","))
        cov = np.array([play(env, seed0 + i, a, b, c) for i in range(args.episodes)])
        if base is None:
            base = cov
        d = cov - base
        print(
            f"a={a} b={b} c={c}: coverage {100 * cov.mean():.2f} %, vs first "
            f"{100 * d.mean():+.2f} ± {100 * 1.96 * d.std(ddof=1) / np.sqrt(len(d)):.2f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
