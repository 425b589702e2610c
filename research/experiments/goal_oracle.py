"""How much the goal action's candidates could give: a rollout oracle against the planner,
paired on the same episodes (research/experiment-log.md, "The room in the candidates").

At every step each agent that is not walking to a chosen target tries each of its candidate
slots (docs/goals.md) on a copy of the planner's map: it walks a shortest path to the
candidate, teammates keep to what they are doing, then everybody follows the planner
(``frontier.planner``) to the episode's end (``--horizon``: for so many steps). The slot whose
rollout ends with the most visited cells wins (ties, and gains of at most ``--margin`` cells,
keep slot 0, the planner's own choice); the agent then walks to that candidate without
deciding again until it is visited, by it or by a teammate. Committing matters: re-deciding
every step, with rollouts that assume the walk is finished, lets two targets take turns and an
agent stall (one validation episode lost 30 points that way).

With ``--belief true`` (the default) the copies hold the *true* walls: one step of policy
improvement over the planner with a perfect model of the map, an estimate of the room in the
candidate set rather than a policy anyone can run. With ``--belief sampled`` the cells nobody
has seen are drawn (free with the share of free cells among the seen ones), ``--samples`` maps
per decision: a rollout planner that sees only what the agents see. An option's value then
moves by tens of cells from one sampled map to the next, and the best of several noisy means
is biased upwards: ``--sigmas Z`` lets an option replace slot 0 only where its mean paired gain
over the maps exceeds ``Z`` standard errors.

``--model`` plays a trained goal policy the same way (a slot other than 0 is walked to until
visited). ``--save`` writes every decision's candidate features, each slot's advantage (its
rollout's cells minus slot 0's), the oracle's slot, each slot's mean gain over the sampled maps
before the noise rule (``gain``, ``gain_se``; in score units: with ``--reach``, steps times the
padded grid's cells + 1, saved as ``unit``), the coverage and the deciding agent's observation,
the data a learned selector can be fitted to. ``--after C``: the oracle (or the model) decides
only from coverage ``C`` on, slot 0 before it. ``--reach Q`` scores by speed instead: an option
by the steps its rollout takes to coverage ``Q`` (ties by cells), an episode by its steps to
``Q`` (a team that covers the whole map, 4 agents on 50x50, ends every rollout with the same
cells).

The rollouts are the rollout teacher's (:class:`envs.coverage.teacher.RolloutTeacher`, compiled;
docs/goals.md "The teacher"): one owner of the oracle's rule, which training's labels use too.
``--rollouts python`` steps them in Python instead (:func:`python_scores`, the reference the
teacher was checked against, tests/test_teacher.py): the same choices, 3 to 12 times slower.

    python research/experiments/goal_oracle.py [--config configs/goals_2agents.yaml] [--episodes 10]
        [--seed 2000003] [--set KEY=VALUE ...] [--horizon H] [--belief true|sampled]
        [--samples M] [--sigmas Z] [--margin CELLS] [--model RUN/model.zip] [--save DECISIONS.npz]
        [--reach Q] [--after C] [--rollouts compiled|python] [--known D]
        [--prior RUN] [--likely-band D]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from envs.coverage.env import CoverageEnv
from envs.coverage.goals import Candidates
from envs.coverage.planners import FrontierPlanner
from envs.coverage.rollouts import (
    clear_of_noise,
    prior_wall_probability,
    sampled_free,
    shortest_walk,
)
from envs.coverage.teacher import RolloutTeacher
from harness import DoubleDQN
from harness.config.loading import load_config
from harness.factory import make_env
from harness.results.stats import paired_difference


class Decision(NamedTuple):
    """One oracle decision as ``--save`` records it."""

    features: np.ndarray  # the deciding agent's candidate features (slots, features)
    advantages: np.ndarray  # each slot's score minus slot 0's after the noise rule; NaN: empty
    time: float  # steps / max_steps
    obs: dict  # the deciding agent's observation
    slot: int  # the oracle's choice
    coverage: float
    gain: np.ndarray  # (2, slots): mean paired gain over the maps and its standard error
    unit: float  # score units a step with --reach (the padded map's cells + 1), else 1 (cells)


def clone(planner: FrontierPlanner, free: np.ndarray | None = None) -> FrontierPlanner:
    """A copy of the planner's map that can be stepped on its own (its per-cell state, ``grid``,
    is copied, and the searches' scratch arrays are its own). ``free`` replaces the true free
    cells (a sampled map) for the cells nobody has seen."""
    copy = object.__new__(type(planner))
    copy.__dict__.update(planner.__dict__)
    copy.grid = planner.grid.copy()
    if free is not None:
        copy.grid[0] = np.asarray(free, dtype=bool)
    copy.free, copy.visited, copy.seen, copy.passable, copy.target = copy.grid
    copy.positions, copy.goals = list(planner.positions), list(planner.goals)
    copy._scratch = copy._claimed = copy._distances = None
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


def rollout(
    planner: FrontierPlanner, steps: int, paths: dict[int, list[int]], reach: int | None = None
) -> tuple[int, int | None]:
    """Steps the planner's map ``steps`` times, the agents in ``paths`` walking them first and
    everybody following the planner after. Returns the cells newly visited and, when ``reach``
    (a number of newly visited cells) is given, the step (1-based) on which they reached it
    (``None``: not within ``steps``; with ``reach <= 0``, 0); the rollout then ends."""
    offset = {0: -planner.stride, 1: planner.stride, 2: -1, 3: 1, 4: 0}
    paths = {a: list(p) for a, p in paths.items() if p}
    new = 0
    if reach is not None and reach <= 0:
        return 0, 0
    for step in range(1, steps + 1):
        moves = planner.act()
        cells = [
            paths[a].pop(0) if paths.get(a) else pos + offset[m]
            for a, (pos, m) in enumerate(zip(planner.positions, moves))
        ]
        new += advance(planner, cells)
        if reach is not None and new >= reach:
            return new, step
        if planner.n_targets == 0 and not any(paths.values()):
            break
    return new, None


def path_to(pred: np.ndarray, start: int, goal: int) -> list[int]:
    """The cells of the shortest path from ``start`` to ``goal`` (without ``start``)."""
    cells = [goal]
    while (prev := int(pred[cells[-1]])) != start:
        cells.append(prev)
    return cells[::-1]


def python_scores(
    planner: FrontierPlanner,
    cand: Candidates,
    i: int,
    cells: list[int],
    rests: dict[int, list[int]],
    steps_left: int,
    teacher: RolloutTeacher,
    free: np.ndarray | None = None,
) -> np.ndarray:
    """Agent ``i``'s rollout score of each of its candidate slots, stepped in Python
    (:func:`clone`, :func:`advance`, :func:`rollout`): the reference that
    :meth:`RolloutTeacher.scores <envs.coverage.teacher.RolloutTeacher.scores>` compiles
    (``--rollouts python``; tests/test_teacher.py checks that the two agree). ``cells``: every
    agent's next cell, ``rests``: the committed walks after it; the teacher's ``horizon`` and
    ``reach`` set the rollouts' length and score."""
    slots = np.flatnonzero(cand.cells[i] >= 0)
    pred = planner.distance_fields()[1]
    options = [[cells[i]]] + [
        path_to(pred[i], planner.positions[i], int(cand.cells[i, j])) for j in slots[1:]
    ]
    left = steps_left - 1
    if teacher.horizon is not None:
        left = min(left, teacher.horizon - 1)
    goal = None  # with ``reach``: cells still to find, on the rollouts' map
    if teacher.reach is not None:
        total = sum(planner.free if free is None else free)
        goal = int(np.ceil(teacher.reach * total)) - sum(planner.visited)
    scores = np.zeros(len(options))
    for o, path in enumerate(options):
        sim = clone(planner, free)
        first = list(cells)
        first[i] = path[0]
        new = advance(sim, first)
        if goal is None:
            scores[o] = new + rollout(sim, left, {**rests, i: path[1:]})[0]
            continue
        more, step = rollout(sim, left, {**rests, i: path[1:]}, goal - new)
        # Steps first (not reached: one more than the rollout had), then cells.
        steps = 1 + (left + 1 if step is None else step)
        scores[o] = -steps * (len(planner.free) + 1) + new + more
    return scores


def with_known_band(planner: FrontierPlanner, free: np.ndarray, known: int) -> np.ndarray:
    """``free`` (a sampled map, padded and flat) with the true cells up to ``known`` cells
    (chessboard distance) from the cells the team has seen."""
    from scipy.ndimage import distance_transform_cdt

    seen = planner.seen.reshape(-1, planner.stride)
    near = distance_transform_cdt(~seen, metric="chessboard") <= known
    out = np.asarray(free, dtype=bool).reshape(-1, planner.stride).copy()
    truth = np.asarray(planner.free, dtype=bool).reshape(-1, planner.stride)
    out[near] = truth[near]
    return out.ravel()


def with_likely_band(planner: FrontierPlanner, p_wall: np.ndarray, band: int) -> np.ndarray:
    """The prior's wall probabilities ``p_wall`` ``(H, W)`` rounded to 0 or 1 up to ``band``
    cells (chessboard distance) from the seen cells: the maps drawn from it hold the prior's
    most likely cells there."""
    if band <= 0:
        return p_wall
    from scipy.ndimage import distance_transform_cdt

    seen = planner.seen.reshape(-1, planner.stride)[1:-1, 1:-1]
    near = distance_transform_cdt(~seen, metric="chessboard") <= band
    return np.where(near, (p_wall > 0.5).astype(float), p_wall)


def play(
    env: CoverageEnv,
    seed: int,
    oracle: bool,
    records: list[Decision] | None = None,
    belief: str = "true",
    samples: int = 1,
    margin: float = 0.0,
    horizon: int | None = None,
    model: DoubleDQN | None = None,
    reach: float | None = None,
    python: bool = False,
    sigmas: float = 0.0,
    after: float = 0.0,
    coverages: list | None = None,
    known: int = 0,
    prior: Any = None,
    likely_band: int = 0,
) -> tuple[float, int, int | None]:
    """One episode; with ``oracle`` the rollout oracle chooses, with ``model`` a trained goal policy
    (greedy, committed like the oracle), otherwise slot 0 throughout. ``belief``: the rollouts'
    map, the ``"true"`` one or ``samples`` maps ``"sampled"`` per decision
    (:func:`envs.coverage.rollouts.sampled_free`), the options scored by their mean; an option
    replaces slot 0 when it scores more than ``margin`` cells above it. ``reach`` (a coverage,
    e.g. 0.99): the options are scored by the steps their rollout takes to reach it instead
    (fewer is better, ties by cells; ``margin`` then counts steps). Returns the coverage, the
    number of deviations from slot 0 and the steps to ``reach`` (``None`` when not reached or
    not asked). ``horizon``: rollouts end after so many steps (``None``: at the episode's end).
    ``sigmas``: with several sampled maps, a slot replaces slot 0 only where its mean paired
    gain exceeds so many standard errors over the maps. ``after``: the oracle decides only from
    this coverage on (slot 0 before it); ``coverages`` collects the coverage at each deviation.
    ``known``: with sampled maps, the cells up to so many cells (chessboard) from the seen ones
    are the true ones (a partly clairvoyant oracle: how far ahead a map must be right).
    ``prior``: a map prior (``harness.prior.model.MapPrior``) the sampled maps are drawn from,
    cell by cell, its most likely cell (a wall where p > 0.5) up to ``likely_band`` cells from
    the seen ones."""
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    teacher = RolloutTeacher(horizon, margin, reach)
    n = env.n_agents
    walk: list[list[int]] = [[] for _ in range(n)]  # each agent's committed path
    deviations = 0
    reached: int | None = None
    while env.agents:
        frontier = env.frontier_state  # the env's planner extension (its planner and candidates)
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
        if oracle and deciding and env.coverage >= after:
            # Steps left in the episode, this one included: the rollouts' length (at most
            # ``horizon``).
            steps_left = env.max_steps - env.steps
            for i in deciding:
                slots = np.flatnonzero(cand.cells[i] >= 0)
                n_maps = samples if belief == "sampled" else 1
                per_map = np.zeros((n_maps, len(slots)))
                for m in range(n_maps):
                    # One map for every option of a sample: their differences are paired.
                    p_wall = None
                    if belief == "sampled" and prior is not None:
                        if m == 0:  # one prediction a decision
                            p_wall = prior_wall_probability(planner, prior)
                            likely = with_likely_band(planner, p_wall, likely_band)
                        p_wall = likely
                    free = sampled_free(planner, rng, p_wall) if belief == "sampled" else None
                    if free is not None and known:
                        free = with_known_band(planner, free, known)
                    if python:
                        per_map[m] = python_scores(
                            planner, cand, i, cells, rests, steps_left, teacher, free
                        )
                    else:
                        walks = {a: w for a, w in enumerate(walk) if w}
                        on = planner.free if free is None else free  # None: the true map
                        per_map[m] = teacher.scores_on(on, planner, cand, i, steps_left, walks)[
                            slots
                        ]
                scores = clear_of_noise(per_map, sigmas)
                best = teacher.pick(scores, len(planner.free))
                if records is not None:
                    adv = np.full(cand.cells.shape[1], np.nan)
                    adv[slots] = scores - scores[0]
                    # Each slot's mean paired gain over the maps before the noise rule, and
                    # its standard error (NaN with one map): dense targets for a student.
                    gains = per_map - per_map[:, :1]
                    gain = np.full((2, cand.cells.shape[1]), np.nan)
                    gain[0, slots] = gains.mean(axis=0)
                    if n_maps > 1:
                        gain[1, slots] = gains.std(axis=0, ddof=1) / np.sqrt(n_maps)
                    agent_obs = obs[env.possible_agents[i]]
                    when = env.steps / env.max_steps
                    features = cand.features[i].copy()
                    unit = teacher.unit(len(planner.free))
                    records.append(
                        Decision(features, adv, when, agent_obs, best, env.coverage, gain, unit)
                    )
                if best != 0:
                    goal = int(cand.cells[i, best])
                    if python:
                        pred = planner.distance_fields()[1]
                        path = path_to(pred[i], planner.positions[i], goal)
                    else:
                        path = shortest_walk(planner, i, goal)
                    cells[i], rests[i], walk[i] = path[0], path[1:], path
                    deviations += 1
                    if coverages is not None:
                        coverages.append(env.coverage)
        elif model is not None and deciding and env.coverage >= after:
            batch = {
                key: np.stack([obs[agent][key] for agent in env.agents])
                for key in obs[env.agents[0]]
            }
            slots = model.predict(batch, deterministic=True)[0]  # masked: no empty slot
            pred = None
            for i in deciding:
                if slots[i] != 0:
                    if pred is None:
                        pred = planner.distance_fields()[1]
                    walk[i] = path_to(pred[i], planner.positions[i], int(cand.cells[i, slots[i]]))
                    cells[i] = walk[i][0]
                    deviations += 1
                    if coverages is not None:
                        coverages.append(env.coverage)
        for a in range(n):
            # Slot 0 carries each agent's move (the goal action resolves slots to moves).
            cand.moves[a, 0] = move_of[cells[a] - planner.positions[a]]
            if walk[a]:
                walk[a] = walk[a][1:]
        obs = env.step({agent: 0 for agent in env.agents})[0]
        if reach is not None and reached is None and env.coverage >= reach:
            reached = env.steps
    return env.coverage, deviations, reached


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/goals_2agents.yaml")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=2000003, help="first episode's seed")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        dest="overrides",
        help="config overrides (env.map defaults to random, 50x50 maps, not the training mix)",
    )
    parser.add_argument(
        "--belief",
        choices=("true", "sampled"),
        default="true",
        help="the rollouts' map: the true one (clairvoyant) or one sampled per decision",
    )
    parser.add_argument("--samples", type=int, default=1, help="sampled maps per decision")
    parser.add_argument(
        "--margin", type=float, default=0.0, help="cells an option must gain over slot 0"
    )
    parser.add_argument(
        "--sigmas",
        type=float,
        default=0.0,
        help="with --samples > 1: the standard errors an option's mean gain must clear",
    )
    parser.add_argument(
        "--horizon", type=int, help="steps a rollout looks ahead (default: to the episode's end)"
    )
    parser.add_argument(
        "--model", type=Path, help="play this goal model (committed) instead of the oracle"
    )
    parser.add_argument("--save", type=Path, help="write the decisions' features and advantages")
    parser.add_argument(
        "--reach",
        type=float,
        help="score by the steps to this coverage (e.g. 0.99) instead of the cells at the end",
    )
    parser.add_argument(
        "--after",
        type=float,
        default=0.0,
        help="the oracle (or --model) decides only from this coverage on (slot 0 before it)",
    )
    parser.add_argument(
        "--rollouts",
        choices=("compiled", "python"),
        default="compiled",
        help="the rollouts' code: the teacher's compiled one or the Python reference",
    )
    parser.add_argument(
        "--known",
        type=int,
        default=0,
        help="with --belief sampled: the cells up to this many cells from the seen ones are true",
    )
    parser.add_argument(
        "--prior", help="with --belief sampled: a map prior run the maps are drawn from"
    )
    parser.add_argument(
        "--likely-band",
        type=int,
        default=0,
        help="with --prior: the prior's most likely cells up to this many cells from the seen ones",
    )
    args = parser.parse_args()
    prior = None
    if args.prior:
        from harness.prior.model import load_prior

        prior = load_prior(args.prior)
    if not any(o.startswith("env.map=") for o in args.overrides):
        args.overrides.insert(0, "env.map=random")
    env = make_env(load_config(args.config, args.overrides).env)
    model = DoubleDQN.load(args.model, device="cpu") if args.model else None
    label = "model" if model is not None else "oracle"
    records: list[Decision] | None = [] if args.save else None
    rows, steps, coverages, episode_records = [], [], [], []
    start = time.perf_counter()
    for seed in range(args.seed, args.seed + args.episodes):
        planner, _, planner_steps = play(env, seed, oracle=False, reach=args.reach)
        first = len(coverages)
        oracle, deviations, oracle_steps = play(
            env,
            seed,
            oracle=model is None,
            records=records,
            belief=args.belief,
            samples=args.samples,
            margin=args.margin,
            horizon=args.horizon,
            model=model,
            reach=args.reach,
            python=args.rollouts == "python",
            sigmas=args.sigmas,
            after=args.after,
            coverages=coverages,
            known=args.known,
            prior=prior,
            likely_band=args.likely_band,
        )
        rows.append((planner, oracle))
        if records is not None:
            episode_records.append(len(records) - sum(episode_records))
        steps.append((planner_steps, oracle_steps))
        where = ""
        if coverages[first:]:
            where = f" (at coverage {', '.join(f'{100 * c:.0f}' for c in coverages[first:])} %)"
        reached = ""
        if args.reach is not None:
            reached = (
                f"steps to {100 * args.reach:g} %: planner {planner_steps}, "
                f"{label} {oracle_steps}; "
            )
        print(
            f"seed {seed}: planner {100 * planner:.2f} %  {label} {100 * oracle:.2f} %  "
            f"({100 * (oracle - planner):+.2f}, {reached}{deviations} deviations{where}; "
            f"{time.perf_counter() - start:.0f} s)",
            flush=True,
        )
        if args.save:
            np.savez_compressed(
                args.save,
                features=np.stack([r.features for r in records]),
                advantages=np.stack([r.advantages for r in records]),
                time=np.array([r.time for r in records]),
                label=np.array([r.slot for r in records]),
                coverage=np.array([r.coverage for r in records]),
                gain=np.stack([r.gain[0] for r in records]),
                gain_se=np.stack([r.gain[1] for r in records]),
                unit=np.array([r.unit for r in records]),
                episode=np.repeat(np.arange(len(rows)), episode_records),
                # The deciding agent's observation, key by key: what a student is fitted on.
                **{f"obs_{key}": np.stack([r.obs[key] for r in records]) for key in records[0].obs},
            )
    p, o = (100 * np.array(c) for c in zip(*rows))
    mean, low, high = paired_difference(o, p)
    print(
        f"{len(rows)} episodes: planner {p.mean():.2f} %, {label} {o.mean():.2f} %, "
        f"difference {mean:+.2f} [{low:+.2f}, {high:+.2f}] points"
    )
    both = [(a, b) for a, b in steps if a is not None and b is not None]
    if args.reach is not None and both:
        ps, os_ = (np.array(c, dtype=float) for c in zip(*both))
        mean, low, high = paired_difference(os_, ps)
        print(
            f"steps to {100 * args.reach:g} % ({len(both)} episodes where both reach it): "
            f"planner {ps.mean():.1f}, {label} {os_.mean():.1f} "
            f"(ratio {os_.mean() / ps.mean():.3f}), "
            f"difference {mean:+.1f} [{low:+.1f}, {high:+.1f}] steps"
        )


if __name__ == "__main__":
    main()
