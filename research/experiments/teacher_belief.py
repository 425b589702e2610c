"""How much of the rollout teacher's choice the team's own map decides: the true-map teacher
(``envs.coverage.teacher``, the labels ``algo.teacher`` distils) against the same teacher on
maps whose unseen cells are sampled (``envs.coverage.rollouts.sampled_free``, as
``research/experiments/goal_oracle.py`` samples: each unseen cell free with the share of free cells
among the seen ones), on the states of the
planner's own episodes (every agent always takes slot 0; *validation* seeds).

A label that the seen map decides is one a policy that sees only the team's map can learn; one
that only the unseen cells decide is foresight. At every ``--every``-th step each deciding agent
(two or more candidates) is labelled by the true-map teacher and by two teachers on independently
sampled maps. Reported: decisions, the share of true-map labels other than slot 0, the agreement
of the true-map label with a sampled-map one and of the two sampled ones, the same agreement
among the true-map teacher's deviations, and chance (the mean of ``1 / candidates``).

    python research/experiments/teacher_belief.py [--config configs/goals_2agents_teacher.yaml]
        [--episodes 4] [--every 10] [--reach Q] [--set KEY=VALUE ...]

``--reach Q`` scores by the steps to coverage ``Q`` (the teacher's ``reach``, for teams that
cover whole maps).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from envs.coverage.core import CoverageCore
from envs.coverage.rollouts import sampled_free
from envs.coverage.teacher import RolloutTeacher
from harness.config.loading import load_config
from harness.factory import make_core_spec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/goals_2agents_teacher.yaml")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--every", type=int, default=10)
    parser.add_argument("--reach", type=float, help="score by the steps to this coverage")
    parser.add_argument("--set", action="append", default=[], dest="overrides")
    args = parser.parse_args()
    if not any(o.startswith("env.map=") for o in args.overrides):
        args.overrides.insert(0, "env.map=random")  # 50x50 random maps, as the oracle's figures
    config = load_config(args.config, args.overrides)
    core = CoverageCore(make_core_spec(config.env), args.episodes)
    seed = config.eval.validation_seed
    for b in range(args.episodes):
        core.reset(b, seed=seed + b)
    core.observe()
    teacher, rng = RolloutTeacher(reach=args.reach), np.random.default_rng(seed)
    rows = []
    for step in range(config.env.max_steps):
        if step % args.every == 0:
            for b in range(args.episodes):
                frontier = core.frontiers[b]
                planner, candidates = frontier.planner, frontier.candidates
                left = core.max_steps - int(core.steps[b])
                size = planner.passable.size
                for a in range(core.n_agents):
                    valid = int((candidates.cells[a] >= 0).sum())
                    if valid < 2:
                        continue
                    picks = [teacher.pick(teacher.scores(planner, candidates, a, left), size)]
                    for _ in range(2):
                        free = sampled_free(planner, rng)
                        scores = teacher.scores_on(free, planner, candidates, a, left)
                        picks.append(teacher.pick(scores, size))
                    rows.append((*picks, valid))
        core.step(np.zeros((core.copies, core.n_agents), dtype=np.int64))
        core.observe()
    r = np.array(rows)
    dev = r[:, 0] > 0
    out = {
        "config": args.config,
        "overrides": args.overrides,
        "reach": args.reach,
        "decisions": len(r),
        "true_deviates": float(dev.mean()),
        "true_vs_sampled": float((r[:, 0] == r[:, 1]).mean()),
        "sampled_vs_sampled": float((r[:, 1] == r[:, 2]).mean()),
        "true_vs_sampled_on_true_deviations": float((r[dev, 0] == r[dev, 1]).mean()),
        "chance": float((1.0 / r[:, 3]).mean()),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
