"""How closely a goal policy follows the rollout teacher on held-out states: the student's
agreement with the teacher (docs/goals.md "The teacher in training").

A run's model plays greedily on *validation* episodes (the config's ``eval.validation_seed``;
never the test episodes), as ``harness eval`` plays them; at every step the rollout teacher
(``envs.coverage.teacher``, the run's ``algo.teacher`` options, or the defaults) labels each
deciding agent's state (every agent with two or more candidates and no held target), and the
student's choice there is compared with the label. Reported: decisions labelled, the share
where the student takes the label, the teacher's deviations from slot 0 (the planner's choice)
and the share of those the student takes too, the student's own deviations and the share of
those the teacher agrees with, and the episodes' mean coverage.

    python research/experiments/teacher_agreement.py RUN [--model best_model] [--episodes 8]
        [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from harness import DoubleDQN
from harness.config.loading import load_config
from harness.config.schema import TeacherConfig
from harness.evaluation.episodes import model_policy, run_episodes
from harness.results.rundir import RunDir
from harness.training.teacher import TeacherLabeller


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--model", default="best_model", help="a model of the run (no .zip)")
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--set", action="append", default=[], dest="overrides")
    args = parser.parse_args()
    config = load_config(RunDir(args.run).config, args.overrides)
    model = DoubleDQN.load(args.run / f"{args.model}.zip", device="cpu")
    student = model_policy(model, 0.0)
    options = config.algo.teacher or TeacherConfig()
    labeller = TeacherLabeller(options.model_copy(update={"share": 1.0}), seed=0)  # every state
    counts = {"labelled": 0, "agree": 0, "teacher_dev": 0, "both_dev": 0, "student_dev": 0}
    counts["student_dev_agreed"] = 0

    def policy(obs, envs):
        core = envs[0]._core  # the batch's core: the teacher reads its copies
        labels = labeller(core)[: len(envs)].reshape(-1)
        actions = np.asarray(student(obs, envs)).reshape(-1)
        given = labels >= 0
        counts["labelled"] += int(given.sum())
        counts["agree"] += int((actions[given] == labels[given]).sum())
        counts["teacher_dev"] += int((labels[given] > 0).sum())
        counts["both_dev"] += int(((labels > 0) & (actions == labels)).sum())
        counts["student_dev"] += int(((actions > 0) & given).sum())
        counts["student_dev_agreed"] += int(((actions > 0) & given & (actions == labels)).sum())
        return actions

    seed = config.eval.validation_seed
    results = run_episodes(policy, config.env, args.episodes, seed)
    c = counts
    out = {
        "run": str(args.run),
        "model": args.model,
        "episodes": args.episodes,
        "coverage_mean": float(np.mean([r.coverage for r in results])),
        **c,
        "agreement": c["agree"] / max(c["labelled"], 1),
        "teacher_deviations_taken": c["both_dev"] / max(c["teacher_dev"], 1),
        "student_deviations_agreed": c["student_dev_agreed"] / max(c["student_dev"], 1),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
