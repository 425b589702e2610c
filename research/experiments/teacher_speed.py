"""What a label of the rollout teacher costs (docs/goals.md, "The teacher"): decisions labelled
per CPU second (``time.process_time``) by the compiled teacher
(:class:`envs.coverage.teacher.RolloutTeacher`) and by the oracle's Python rollouts
(``research/experiments/goal_oracle.py``'s :func:`python_scores`), on the same states, with a
check that both give every slot the same score.

The states are those of planner episodes (every agent on slot 0) of ``--config``'s env on
random 50x50 maps, every ``--every`` steps from the start; at each, every agent with at least
two candidates is labelled, its rollouts running to the episode's end (full horizon).

    python research/experiments/teacher_speed.py [--config configs/goals_2agents.yaml]
        [--agents 2 4]
        [--episodes 2] [--every 100] [--seed 2000003]
"""

from __future__ import annotations

import argparse
import importlib.util
import time
from pathlib import Path

import numpy as np

from envs.coverage.teacher import RolloutTeacher
from harness.config.loading import load_config
from harness.factory import make_env


def _oracle():
    """``goal_oracle.py`` beside this script, as a module."""
    path = Path(__file__).with_name("goal_oracle.py")
    spec = importlib.util.spec_from_file_location("goal_oracle", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def measure(config: str, n_agents: int, episodes: int, every: int, seed: int) -> dict:
    """Labels and CPU seconds of both rollouts over the sampled states of ``episodes``
    planner episodes with ``n_agents`` agents."""
    oracle = _oracle()
    overrides = ["env.map=random", "env.height=50", "env.width=50", f"env.n_agents={n_agents}"]
    env = make_env(load_config(config, overrides).env)
    teacher = RolloutTeacher()
    labels, python_s, compiled_s = 0, 0.0, 0.0
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        while env.agents:
            frontier = env.frontier_state
            planner, cand = frontier.planner, frontier.candidates
            if env.steps % every == 0:
                stride = planner.stride
                offset = (-stride, stride, -1, 1, 0)  # by move, STAY last
                moves = cand.moves[:, 0].tolist()  # slot 0's: every agent's next cell
                cells = [pos + offset[m] for pos, m in zip(planner.positions, moves)]
                left = env.max_steps - env.steps
                for i in range(n_agents):
                    slots = np.flatnonzero(cand.cells[i] >= 0)
                    if slots.size < 2:
                        continue
                    start = time.process_time()
                    got = teacher.scores(planner, cand, i, left)
                    middle = time.process_time()
                    want = oracle.python_scores(planner, cand, i, cells, {}, left, teacher)
                    python_s += time.process_time() - middle
                    compiled_s += middle - start
                    if not np.array_equal(got[slots], want):
                        raise AssertionError(f"scores differ at step {env.steps}, agent {i}")
                    labels += 1
            env.step(dict.fromkeys(env.agents, 0))
    return {"labels": labels, "python_s": python_s, "compiled_s": compiled_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/goals_2agents.yaml")
    parser.add_argument("--agents", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--every", type=int, default=100, help="steps between labelled states")
    parser.add_argument("--seed", type=int, default=2000003, help="first episode's seed")
    args = parser.parse_args()
    _warm_up(args.config)
    for n in args.agents:
        m = measure(args.config, n, args.episodes, args.every, args.seed)
        py, co = m["labels"] / m["python_s"], m["labels"] / m["compiled_s"]
        print(
            f"{n} agents: {m['labels']} labels, scores equal; Python {py:.2f} labels/s, "
            f"compiled {co:.1f} labels/s ({co / py:.0f}x)",
            flush=True,
        )


def _warm_up(config: str) -> None:
    """One label on a small map, so that compiling (or loading the cache) is not timed."""
    env = make_env(load_config(config, ["env.map=random", "env.height=10", "env.width=10"]).env)
    env.reset(seed=0)
    frontier = env.frontier_state
    RolloutTeacher().scores(frontier.planner, frontier.candidates, 0, env.max_steps)


if __name__ == "__main__":
    main()
