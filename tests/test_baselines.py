"""The non-learned baselines: repeatable random actions, the memoryless local rule and the
frontier explorer.

Speed of the frontier policy (50x50 random maps, 4 agents, 1000 steps, 100 episodes)::

    python -c "import time; from harness.config.schema import EnvConfig; \
from harness.evaluation.episodes import run_episodes; \
from harness.evaluation.baselines import make_baseline; \
t = time.perf_counter(); run_episodes(make_baseline('frontier', 0), EnvConfig(), 100, 0); \
print(100 / (time.perf_counter() - t), 'episodes/s')"
"""

from __future__ import annotations

import copy
from collections import deque

import numpy as np
import pytest

from envs import coverage_v0
from envs.coverage import planners
from envs.coverage.rollouts import SampledChooser
from harness.config.loading import load_config
from harness.config.schema import EnvConfig, EvalConfig
from harness.evaluation import baselines
from harness.evaluation.baselines import BASELINES, RolloutPolicy, make_baseline
from harness.evaluation.episodes import run_episodes


def small_maps(n_agents: int, max_steps: int, size: int = 8) -> EnvConfig:
    return EnvConfig(height=size, width=size, n_agents=n_agents, max_steps=max_steps)


# ---------------------------------------------------------------------- factory
def test_names_and_unknown_name() -> None:
    assert tuple(BASELINES) == (
        "random",
        "local",
        "frontier",
        "frontier_pocket",
        "frontier_random",
        "frontier_utility",
        "frontier_minpos",
        "frontier_hungarian",
        "frontier_step",
        "rollout",
    )
    for name in BASELINES:
        assert callable(make_baseline(name, 0))
    with pytest.raises(ValueError, match="greedy"):
        make_baseline("greedy", 0)


# ---------------------------------------------------------------------- frontier_step
def test_frontier_step_baseline_walks_the_compass_and_needs_the_action() -> None:
    step_env = EnvConfig(
        height=12, width=12, n_agents=2, max_steps=40, observation={"teammap": {"crop": 7}},
        frontier={"action": "step"},
    )  # fmt: skip
    results = run_episodes(make_baseline("frontier_step", 0), step_env, episodes=3, seed=4)
    # Every step heads for unexplored ground through known free cells: never a wall, and a lone
    # agent's path is short of new ground only where it walks back through visited cells.
    assert all(r.wall_hits == [0, 0] for r in results)
    assert all(r.coverage > 0.5 for r in results)
    again = run_episodes(make_baseline("frontier_step", 0), step_env, episodes=3, seed=4)
    assert [r.coverage for r in again] == [r.coverage for r in results]  # ties: episode seed
    with pytest.raises(ValueError, match=r"needs env\.frontier\.action \(step, or goal"):
        run_episodes(make_baseline("frontier_step", 0), small_maps(2, 10), episodes=1, seed=0)


# ---------------------------------------------------------------------- rollout
def goal_env(n_agents: int = 4) -> EnvConfig:
    """The goal action on 15x15 random maps, as ``rollout`` plays it (``hold`` on)."""
    config = load_config(
        "configs/goals_4agents.yaml",
        ["env.map=random", "env.height=15", "env.width=15", "env.max_steps=150",
         f"env.n_agents={n_agents}"],
    )  # fmt: skip
    return BASELINES["rollout"].env_config(config.env)


def _played(results) -> list[tuple]:
    return [(r.coverage, r.steps_to, r.new_cells, r.wall_hits) for r in results]


def test_rollout_turns_the_goal_actions_hold_on_and_needs_that_action() -> None:
    env = goal_env()
    assert env.frontier_options.action.hold
    assert BASELINES["rollout"].env_config(env) == env
    BASELINES["rollout"].check(env.frontier_options)
    step = EnvConfig(observation={"teammap": {"crop": 7}}, frontier={"action": "step"})
    for options in (None, step.frontier_options):
        with pytest.raises(ValueError, match=r"needs env\.frontier\.action \{goal"):
            BASELINES["rollout"].check(options)


def test_a_rollout_chooser_that_never_deviates_is_its_planner_episode_for_episode() -> None:
    env = goal_env()
    # A coverage the team's map never shows while a target is left: slot 0 throughout.
    never = RolloutPolicy(SampledChooser(after=1.0))
    planner = run_episodes(make_baseline("frontier_step", 0), env, episodes=3, seed=7)
    assert _played(run_episodes(never, env, episodes=3, seed=7)) == _played(planner)


def test_rollout_takes_its_parameters_from_the_configs_eval_rollout() -> None:
    env = goal_env()
    options = EvalConfig(rollout={"samples": 2, "after": 0.0})
    policy = make_baseline("rollout", 0, options)
    assert isinstance(policy, RolloutPolicy)
    chooser = policy.chooser
    assert (chooser.samples, chooser.sigmas, chooser.after) == (2, 4.0, 0.0)
    # The section's defaults are the chooser's own (one measured default).
    default, own = make_baseline("rollout", 0).chooser, SampledChooser()
    assert (default.samples, default.sigmas, default.after) == (own.samples, own.sigmas, own.after)
    direct = RolloutPolicy(SampledChooser(samples=2, after=0.0), threads=1)
    played = _played(run_episodes(policy, env, episodes=2, seed=7))
    assert played == _played(run_episodes(direct, env, episodes=2, seed=7))


def test_rollout_deviates_repeats_from_the_seed_and_never_hits_a_wall() -> None:
    env = goal_env()

    def eager(threads: int) -> RolloutPolicy:
        chooser = SampledChooser(samples=2, sigmas=0.0, after=0.0, threads=threads)
        return RolloutPolicy(chooser, threads=threads)

    one = run_episodes(eager(1), env, episodes=3, seed=7, copies=1)
    assert all(sum(r.wall_hits) == 0 for r in one)
    # Its sampled maps come from each episode's generator: the copies side by side, and the
    # threads that decide for them and score their maps, do not matter.
    assert _played(run_episodes(eager(3), env, episodes=3, seed=7, copies=3)) == _played(one)
    # It chooses: its episodes are not the planner's.
    planner = run_episodes(make_baseline("frontier_step", 0), env, episodes=3, seed=7)
    assert _played(one) != _played(planner)


# ---------------------------------------------------------------------- random
def test_random_is_repeatable_and_uses_every_action() -> None:
    obs = np.zeros((32, 13), dtype=np.float32)
    a, b, c = (make_baseline("random", s) for s in (7, 7, 8))
    first = np.concatenate([a(obs, []) for _ in range(10)])
    again = np.concatenate([b(obs, []) for _ in range(10)])
    other = np.concatenate([c(obs, []) for _ in range(10)])
    assert first.shape == (320,)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    assert set(first.tolist()) == {0, 1, 2, 3, 4}
    # Roughly uniform: each action near 1/5 of 320.
    assert np.bincount(first, minlength=5).min() > 40


def test_random_runs_in_evaluation() -> None:
    env = small_maps(n_agents=2, max_steps=30)
    first = run_episodes(make_baseline("random", 3), env, episodes=3, seed=0)
    again = run_episodes(make_baseline("random", 3), env, episodes=3, seed=0)
    assert [r.coverage for r in first] == [r.coverage for r in again]


# ---------------------------------------------------------------------- local
U, V, W = -1.0, 0.0, 1.0  # window cells: unvisited, visited, wall


def local_obs(*windows: list[float]) -> np.ndarray:
    """Thesis observations with the given 3x3 windows (row-major) and dummy positions."""
    return np.array([[*w, 0.5, 0.5, 0.5, 0.5] for w in windows], dtype=np.float32)


def test_local_steps_into_an_unvisited_neighbour_first() -> None:
    # Unvisited: right (5) and down (7); the up-left diagonal is unvisited too, but a
    # neighbour wins. The draw picks among the candidates in action order (1 down, 3 right).
    obs = local_obs([U, V, V, V, V, U, V, U, V])
    picks = [baselines.local_actions(obs, np.array([u]))[0] for u in (0.0, 0.49, 0.5, 0.99)]
    assert picks == [1, 1, 3, 3]


def test_local_heads_for_an_unvisited_diagonal_then_any_free_neighbour() -> None:
    obs = local_obs(
        [V, V, U, V, V, V, V, V, V],  # up-right diagonal: up (0) or right (3) lead beside it
        [V, W, U, V, V, W, V, V, V],  # ... but up and right are walls: left or down, at random
        [W, V, W, V, V, W, W, W, W],  # all visited: the free moves, up (0) and left (2)
        [V, W, V, W, V, W, V, W, V],  # boxed in: stay
    )
    low, high = np.zeros(4), np.full(4, 0.99)
    np.testing.assert_array_equal(baselines.local_actions(obs, low), [0, 1, 0, 4])
    np.testing.assert_array_equal(baselines.local_actions(obs, high), [3, 2, 2, 4])


def test_local_tie_breaks_uniformly() -> None:
    obs = local_obs(*[[V, U, V, U, V, U, V, U, V]] * 4000)
    actions = baselines.local_actions(obs, np.random.default_rng(0).random(4000))
    counts = np.bincount(actions, minlength=5)
    assert counts[4] == 0
    assert np.all(np.abs(counts[:4] / 4000 - 0.25) < 0.03)


@pytest.mark.parametrize("copies", [1, 4])
def test_local_never_hits_walls_repeats_and_beats_random(copies: int) -> None:
    env = small_maps(n_agents=2, max_steps=60, size=12)
    local = run_episodes(make_baseline("local", 0), env, episodes=8, seed=21, copies=copies)
    # The draws come from each episode's generator: the same episodes with any number of copies.
    alone = run_episodes(make_baseline("local", 0), env, episodes=8, seed=21, copies=1)
    rand = run_episodes(make_baseline("random", 0), env, episodes=8, seed=21)
    assert [r.coverage for r in local] == [r.coverage for r in alone]
    assert all(sum(r.wall_hits) == 0 for r in local)
    assert np.median([r.coverage for r in local]) > np.median([r.coverage for r in rand]) + 0.2


def test_local_rule_acts_the_same_whatever_the_observation() -> None:
    # It reads each agent's 3x3 window from the env's state, so the team-map observation gives
    # the same episodes as the thesis one (same maps, starts and tie-breaking draws).
    thesis = EnvConfig(height=12, width=12, n_agents=2, max_steps=60)
    teammap = thesis.model_copy(update={"observation": {"teammap": {"crop": 5, "global_size": 7}}})
    a = run_episodes(make_baseline("local", 0), thesis, episodes=3, seed=4, record_paths=True)
    b = run_episodes(make_baseline("local", 0), teammap, episodes=3, seed=4, record_paths=True)
    for x, y in zip(a, b, strict=True):
        assert x.coverage == y.coverage
        for p, q in zip(x.paths, y.paths, strict=True):
            np.testing.assert_array_equal(p, q)


# ---------------------------------------------------------------------- frontier
@pytest.mark.parametrize("copies", [1, 3])
def test_frontier_covers_small_maps_without_wall_hits(copies: int) -> None:
    env = small_maps(n_agents=2, max_steps=200)
    results = run_episodes(make_baseline("frontier", 0), env, episodes=6, seed=11, copies=copies)
    for r in results:
        # The bound min(1, N (T+1) / F) is 1 here: 402 agent-cells for at most 64 free cells.
        assert min(1.0, 2 * 201 / r.free_cells) == 1.0
        assert r.coverage == 1.0
        assert sum(r.wall_hits) == 0


def test_frontier_single_agent_and_cave_never_hit_walls() -> None:
    for env in (
        small_maps(n_agents=1, max_steps=150, size=12),
        EnvConfig(map="cave_100x50", n_agents=3, max_steps=150),
    ):
        results = run_episodes(make_baseline("frontier", 0), env, episodes=2, seed=5)
        for r in results:
            assert sum(r.wall_hits) == 0
            # Every step of a lone agent early on finds new ground (frontier is always adjacent
            # or close), so it beats the random walk by far.
            assert r.coverage > 0.5 * min(1.0, env.n_agents * 151 / r.free_cells)


def test_frontier_claims_keep_teammates_off_the_same_target(make_env) -> None:
    # A dead end on the left: the only target at reset is (0, 3). Agent 0 claims it; agent 1,
    # behind it, has nothing unclaimed left and waits instead of following.
    env, obs = make_env("#.......", starts=[(0, 2), (0, 1)])
    policy = make_baseline("frontier", 0)
    actions = policy(np.stack(list(obs.values())), [env])
    assert actions.tolist() == [3, 4]


def test_frontier_agents_split_up_in_a_corridor(make_env) -> None:
    # Both agents start at the left end of a corridor that branches up and down at column 3:
    # 11 free cells. One agent needs more than 12 steps to walk all three branches; two that
    # split up (claims) finish in time, each covering ground of its own.
    text = """
        ###.###
        ###.###
        .......
        ###.###
        ###.###
    """
    policy = make_baseline("frontier", 0)
    coverage = {}
    for starts in ([(2, 0)], [(2, 0), (2, 1)]):
        env, obs = make_env(text, starts=starts, max_steps=12)
        while env.agents:
            actions = policy(np.stack(list(obs.values())), [env]).tolist()
            obs, *_ = env.step(dict(zip(env.possible_agents, actions)))
        coverage[len(starts)] = env.coverage
        assert env.coverage > 0.5
    assert coverage[1] < 1.0
    assert coverage[2] == 1.0
    assert min(np.bincount(env.credited_by[env.credited_by >= 0])) >= 4


def test_frontier_team_beats_lone_agent() -> None:
    # Step budget too small for either to finish, so a team that spreads out covers more.
    one = run_episodes(make_baseline("frontier", 0), small_maps(1, 40, size=14), 4, seed=2)
    two = run_episodes(make_baseline("frontier", 0), small_maps(2, 40, size=14), 4, seed=2)
    for a, b in zip(one, two):
        assert b.coverage > 1.5 * a.coverage
    # They do not walk in each other's footsteps: each agent is credited with real ground.
    assert all(min(r.new_cells) > 10 for r in two)


def test_frontier_tie_breaks_choose_between_equally_near_targets(make_env) -> None:
    # Left and right of the start are equally near targets. The fixed order (up, left, right,
    # down) takes the left one; the right one has one open neighbour (the left one two), so
    # "pocket" finishes it first; "random" takes either.
    text = """
        .#.
        ...
        .##
    """
    env, obs = make_env(text, starts=[(1, 1)])
    batch = np.stack(list(obs.values()))
    assert make_baseline("frontier", 0)(batch, [env]).tolist() == [2]
    assert make_baseline("frontier_pocket", 0)(batch, [env]).tolist() == [3]
    planner = planners.FrontierPlanner(3, 3, tie_break="random")
    planner.sync(0, env.positions, lambda: (env.walls, env.visited))
    moves = [planner.act(np.random.default_rng(seed))[0] for seed in range(40)]
    assert set(moves) == {2, 3}
    with pytest.raises(ValueError, match="needs a generator"):
        planner.act()
    with pytest.raises(ValueError, match="unknown tie_break"):
        planners.FrontierPlanner(3, 3, tie_break="nearest")


def test_frontier_random_repeats_an_episode_whatever_the_copies() -> None:
    # Its ties come from each episode's generator, so the episodes of a seed are the same
    # whether they run one at a time or side by side; and they do change the play (the same
    # episodes with the fixed order go otherwise).
    env = small_maps(n_agents=2, max_steps=60, size=14)
    runs = [
        run_episodes(make_baseline(name, 0), env, 4, seed=3, copies=copies)
        for name, copies in (("frontier_random", 1), ("frontier_random", 4), ("frontier", 1))
    ]
    alone, side_by_side, order = ([r.new_cells for r in rs] for rs in runs)
    assert alone == side_by_side
    assert alone != order


# ---------------------------------------------------------------------- exactness
def reference_actions(
    env, tie_break: str = "order", rng: np.random.Generator | None = None
) -> list[int]:
    """The frontier rule computed from scratch (no caches), one plain BFS per agent over the
    whole reachable map, then the tie-break among the nearest unclaimed targets."""
    walls, visited = env.walls, env.visited
    h, w = walls.shape
    seen = np.zeros_like(visited)
    for r, c in zip(*np.nonzero(visited)):
        seen[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2] = True
    passable = seen & ~walls
    target = passable & ~visited

    def inside(cell: tuple[int, int]) -> bool:
        return 0 <= cell[0] < h and 0 <= cell[1] < w

    def open_neighbours(cell: tuple[int, int]) -> int:  # unseen, or a target; outside is wall
        near = [(cell[0] + dr, cell[1] + dc) for dr, dc, _ in order]
        return sum(inside(n) and (not seen[n] or target[n]) for n in near)

    claimed: set[tuple[int, int]] = set()
    actions = []
    # Same neighbour order as the policy (up, left, right, down) so the search finds alike.
    order = [(-1, 0, 0), (0, -1, 2), (0, 1, 3), (1, 0, 1)]
    for start in map(tuple, env.positions.tolist()):
        first, distance, found = {start: None}, {start: 0}, []
        queue = deque([start])
        while queue:
            cell = queue.popleft()
            for dr, dc, a in order:
                n = (cell[0] + dr, cell[1] + dc)
                if inside(n) and passable[n] and n not in first:
                    first[n] = a if cell == start else first[cell]
                    distance[n] = distance[cell] + 1
                    if target[n] and n not in claimed:
                        found.append(n)
                    queue.append(n)
        if not found:
            actions.append(4)
            continue
        ties = [n for n in found if distance[n] == distance[found[0]]]
        if tie_break == "pocket":
            goal = min(ties, key=open_neighbours)
        elif tie_break == "random":
            goal = ties[int(rng.integers(len(ties)))]
        else:
            goal = ties[0]
        claimed.add(goal)
        actions.append(first[goal])
    return actions


@pytest.mark.parametrize("tie_break", ["order", "pocket", "random"])
def test_frontier_matches_reference_rule(tie_break: str) -> None:
    # The compiled search (envs.coverage.planners.nearest_targets) against a plain BFS.
    name = {"order": "frontier"}.get(tie_break, f"frontier_{tie_break}")
    env = coverage_v0.parallel_env(height=16, width=20, n_agents=4, max_steps=250)
    for seed in (0, 1):
        obs, _ = env.reset(seed=seed)
        policy = make_baseline(name, 0)
        while env.agents:
            if env.steps == 120:
                policy = make_baseline(name, 0)  # a fresh policy mid-episode rebuilds
            # The random tie-break draws from the episode's generator: the reference from a copy.
            rng = copy.deepcopy(env.np_random)
            actions = policy(np.stack(list(obs.values())), [env]).tolist()
            assert actions == reference_actions(env, tie_break, rng), f"seed {seed}, {env.steps}"
            obs, *_ = env.step(dict(zip(env.possible_agents, actions)))
        assert env.coverage == 1.0


def test_frontier_copies_are_independent(make_env) -> None:
    # Two different envs in one batch: actions come out copy-major, each from its own map.
    a, obs_a = make_env("#.......", starts=[(0, 2), (0, 1)])
    b, obs_b = make_env(".......#", starts=[(0, 5), (0, 6)])
    obs = np.concatenate([np.stack(list(o.values())) for o in (obs_a, obs_b)])
    actions = make_baseline("frontier", 0)(obs, [a, b])
    assert actions.tolist() == [3, 4, 2, 4]
