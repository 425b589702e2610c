"""How well a map prior knows the unseen cells by their distance from the seen ones: on the
team maps of a config's validation episodes (slot 0, the planner, every ``--every`` steps), for
each chessboard distance band from the seen cells, the share of unseen cells that are walls,
the prior's most likely cell's accuracy (a wall where p > 0.5), the density prior's (the seen
wall share: every cell its majority) and the two log-losses per cell.

    python research/experiments/prior_bands.py configs/goals_4agents.yaml \
        runs/reference/prior_rooms \
        --set 'env.map={rooms: {height: 50, width: 100}}' --set 'env.test_maps=[]' --episodes 3
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import distance_transform_cdt

from envs.coverage.rollouts import _seen_share, prior_wall_probability
from harness.config.loading import load_config
from harness.factory import make_env
from harness.prior.model import load_prior

BANDS = ((1, 1), (2, 2), (3, 3), (4, 5), (6, 8), (9, 16), (17, 10_000))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("config")
    parser.add_argument("prior")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--every", type=int, default=50)
    args = parser.parse_args()
    config = load_config(args.config, args.overrides)
    env = make_env(config.env)
    prior = load_prior(args.prior)
    eps = 1e-3
    sums = {b: np.zeros(6) for b in BANDS}  # cells, walls, prior right, density right, losses
    for e in range(args.episodes):
        env.reset(seed=config.eval.validation_seed + e)
        while env.agents:
            if env.steps % args.every == 0 and env.steps > 0:
                planner = env.frontier_state.planner
                seen, _, share = _seen_share(planner)
                truth = np.asarray(planner.free, bool).reshape(-1, planner.stride)[1:-1, 1:-1]
                p = np.clip(prior_wall_probability(planner, prior), eps, 1 - eps)
                d_wall = np.clip(1 - share, eps, 1 - eps)
                dist = distance_transform_cdt(~seen, metric="chessboard")
                wall = ~truth
                for lo, hi in BANDS:
                    cells = (dist >= lo) & (dist <= hi)
                    w, q = wall[cells], p[cells]
                    sums[(lo, hi)] += [
                        cells.sum(),
                        w.sum(),
                        ((q > 0.5) == w).sum(),
                        ((d_wall > 0.5) == w).sum(),
                        -np.log(np.where(w, q, 1 - q)).sum(),
                        -np.log(np.where(w, d_wall, 1 - d_wall)).sum(),
                    ]
            env.step({a: 0 for a in env.agents})
    print("band | cells | walls | prior's most likely right | density's | prior log-loss | density")
    for (lo, hi), s in sums.items():
        n = max(s[0], 1)
        band = f"{lo}" if lo == hi else f"{lo}-{hi}"
        print(
            f"{band} | {int(s[0])} | {s[1] / n:.3f} | {s[2] / n:.3f} | {s[3] / n:.3f} | "
            f"{s[4] / n:.3f} | {s[5] / n:.3f}"
        )


if __name__ == "__main__":
    main()
