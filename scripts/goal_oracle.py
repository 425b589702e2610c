"""How much the goal action's candidates could give: a clairvoyant rollout oracle against the
planner, paired on the same episodes (docs/experiment-log.md, "The room in the candidates").

At every step each agent that is not walking to a chosen target tries each of its candidate
slots (docs/goals.md) on a copy of the planner's map, which holds the *true* walls: it walks a
shortest path to the candidate, teammates keep to what they are doing, then everybody follows
the planner (``frontier.planner``) to the episode's end. The slot whose rollout ends with the
most visited cells wins (ties keep slot 0, the planner's own choice); the agent then walks to
that candidate without deciding again until it is visited, by it or by a teammate. Committing
matters: re-deciding every step, with rollouts that assume the walk is finished, lets two
targets take turns and an agent stall (one validation episode lost 30 points that way).

This is one step of policy improvement over the planner with a perfect model of the map, an
estimate of the room in the candidate set rather than a policy anyone can run: it sees ground
no agent has seen. ``--save`` writes every decision's candidate features and each slot's
advantage (its rollout's cells minus slot 0's), the data a learned selector can be fitted to.

    python scripts/goal_oracle.py [--config configs/goals_2agents.yaml] [--episodes 10]
        [--seed 2000003] [--set KEY=VALUE ...] [--save DECISIONS.npz]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from envs.coverage.planners import FrontierPlanner
from harness.config.loading import load_config
from harness.factory import make_env
from harness.results.stats import paired_difference


def clone(planner: FrontierPlanner) -> FrontierPlanner:
    """A copy of the planner's map that can be stepped on its own (its true ``free`` list and
    cached graph are shared read-only; every per-cell state it changes is copied)."""
    copy = object.__new__(type(planner))
    copy.__dict__.update(planner.__dict__)
    for name in ("visited", "seen", "passable", "target", "positions", "goals", "far"):
        setattr(copy, name, list(getattr(planner, name)))
    for name in ("passable_np", "target_np", "seen_np"):
        setattr(copy, name, getattr(planner, name).copy())
    return copy


def advance(planner: FrontierPlanner, cells: list[int]) -> int:
    """Moves every agent to ``cells`` (one step); returns how many new cells were visited."""
    planner.positions = list(cells)
    planner.steps += 1
    new = 0
    for cell in cells:
        if not planner.visited[cell]:
            planner._visit(cell)
            new += 1
    return new


def rollout(planner: FrontierPlanner, steps: int, paths: dict[int, list[int]]) -> int:
    """Steps the planner's map ``steps`` times, the agents in ``paths`` walking them first and
    everybody following the planner after; returns the cells newly visited."""
    offset = {0: -planner.stride, 1: planner.stride, 2: -1, 3: 1, 4: 0}
    paths = {a: list(p) for a, p in paths.items() if p}
    new = 0
    for _ in range(steps):
        moves = planner.act()
        cells = [
            paths[a].pop(0) if paths.get(a) else pos + offset[m]
            for a, (pos, m) in enumerate(zip(planner.positions, moves))
        ]
        new += advance(planner, cells)
        if planner.n_targets == 0 and not any(paths.values()):
            break
    return new


def path_to(pred: np.ndarray, start: int, goal: int) -> list[int]:
    """The cells of the shortest path from ``start`` to ``goal`` (without ``start``)."""
    cells = [goal]
    while (prev := int(pred[cells[-1]])) != start:
        cells.append(prev)
    return cells[::-1]


def play(env, seed: int, oracle: bool, records: list | None = None) -> tuple[float, int]:
    """One episode; with ``oracle`` the rollout oracle chooses, otherwise slot 0 throughout.
    Returns the coverage and the number of deviations from slot 0."""
    env.reset(seed=seed)
    n = env.n_agents
    walk: list[list[int]] = [[] for _ in range(n)]  # each agent's committed path
    deviations = 0
    while env.agents:
        frontier = env._frontier  # the env's planner extension (its planner and candidates)
        planner, cand = frontier.planner, frontier.candidates
        offset = {0: -planner.stride, 1: planner.stride, 2: -1, 3: 1, 4: 0}
        move_of = {d: m for m, d in offset.items()}
        for a in range(n):
            if walk[a] and not planner.target[walk[a][-1]]:
                walk[a] = []  # its target was visited: decide again
        cells = [
            walk[a][0] if walk[a] else planner.positions[a] + offset[int(cand.moves[a, 0])]
            for a in range(n)
        ]
        rests = {a: walk[a][1:] for a in range(n) if walk[a]}
        deciding = [a for a in range(n) if not walk[a] and (cand.cells[a] >= 0).sum() > 1]
        if oracle and deciding:
            pred = planner.distance_fields()[1]
            left = env.max_steps - env.steps - 1
            for i in deciding:
                slots = np.flatnonzero(cand.cells[i] >= 0)
                options = [[cells[i]]] + [
                    path_to(pred[i], planner.positions[i], int(cand.cells[i, j])) for j in slots[1:]
                ]
                scores = []
                for path in options:
                    sim = clone(planner)
                    first = list(cells)
                    first[i] = path[0]
                    new = advance(sim, first)
                    scores.append(new + rollout(sim, left, {**rests, i: path[1:]}))
                if records is not None:
                    adv = np.full(cand.cells.shape[1], np.nan)
                    adv[slots] = np.asarray(scores, dtype=float) - scores[0]
                    records.append((cand.features[i].copy(), adv, env.steps / env.max_steps))
                best = int(np.argmax(scores))
                if scores[best] > scores[0]:
                    cells[i], rests[i], walk[i] = options[best][0], options[best][1:], options[best]
                    deviations += 1
        for a in range(n):
            # Slot 0 carries each agent's move (the goal action resolves slots to moves).
            cand.moves[a, 0] = move_of[cells[a] - planner.positions[a]]
            if walk[a]:
                walk[a] = walk[a][1:]
        env.step({agent: 0 for agent in env.agents})
    return env.coverage, deviations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/goals_2agents.yaml")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=2000003, help="first episode's seed")
    parser.add_argument("--set", action="append", default=["env.map=random"], dest="overrides")
    parser.add_argument("--save", type=Path, help="write the decisions' features and advantages")
    args = parser.parse_args()
    env = make_env(load_config(args.config, args.overrides).env)
    records: list | None = [] if args.save else None
    rows = []
    start = time.perf_counter()
    for seed in range(args.seed, args.seed + args.episodes):
        planner, _ = play(env, seed, oracle=False)
        oracle, deviations = play(env, seed, oracle=True, records=records)
        rows.append((planner, oracle))
        print(
            f"seed {seed}: planner {100 * planner:.2f} %  oracle {100 * oracle:.2f} %  "
            f"({100 * (oracle - planner):+.2f}, {deviations} deviations; "
            f"{time.perf_counter() - start:.0f} s)",
            flush=True,
        )
        if args.save:
            np.savez_compressed(
                args.save,
                features=np.stack([r[0] for r in records]),
                advantages=np.stack([r[1] for r in records]),
                time=np.array([r[2] for r in records]),
            )
    p, o = (100 * np.array(c) for c in zip(*rows))
    mean, low, high = paired_difference(o, p)
    print(
        f"{len(rows)} episodes: planner {p.mean():.2f} %, oracle {o.mean():.2f} %, "
        f"difference {mean:+.2f} [{low:+.2f}, {high:+.2f}] points"
    )


if __name__ == "__main__":
    main()
