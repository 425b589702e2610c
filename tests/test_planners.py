"""The coordinated planners (utility, MinPos, Hungarian) on hand-built grids where their choice
is known and differs from the nearest-frontier explorer's, their safety and repeatability on
whole episodes, and the physical bound of every evaluation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linear_sum_assignment

from envs.coverage.frontier import PLANNERS
from envs.coverage.planners import (
    FrontierPlanner,
    HungarianPlanner,
    MinPosPlanner,
    UtilityPlanner,
    linear_sum_assignment_compiled,
)
from harness.config.schema import EnvConfig
from harness.evaluation.baselines import BASELINES, make_baseline
from harness.evaluation.episodes import EpisodeResult, physical_bound, run_episodes, summarize

UP, DOWN, LEFT, RIGHT, STAY = range(5)
COORDINATED = {"utility": UtilityPlanner, "minpos": MinPosPlanner, "hungarian": HungarianPlanner}


def corridor(planner: FrontierPlanner, positions: list[int], visited: range) -> list[int]:
    """Plan one step in a 1x13 corridor (outside it: wall) with the columns ``visited`` visited
    and the agents at ``positions`` (columns); returns the planner's actions."""
    walls = np.zeros((1, 13), dtype=bool)
    seen = np.zeros((1, 13), dtype=bool)
    seen[0, list(visited)] = True
    planner.sync(0, np.array([[0, c] for c in positions]), lambda: (walls, seen))
    return planner.act()


# Visited columns 2..10: the known unvisited cells are column 1 (left) and 11 (right). Agent 0
# at column 5 is 4 from the left one and 6 from the right one; agent 1 at column 3 is 2 and 8.
AGENTS, VISITED = [5, 3], range(2, 11)


def test_the_nearest_frontier_explorer_sends_agent_0_left_and_agent_1_round_it() -> None:
    # Agent 0 claims its nearest cell (left, 4 away); agent 1 must walk 8 to the right one.
    assert corridor(FrontierPlanner(1, 13), AGENTS, VISITED) == [LEFT, RIGHT]


def test_hungarian_assigns_the_shorter_total_path() -> None:
    # Agent 0 right (6) + agent 1 left (2) = 8 < 4 + 8 = 12.
    planner = HungarianPlanner(1, 13)
    assert corridor(planner, AGENTS, VISITED) == [RIGHT, LEFT]
    stride = 13 + 2
    assert planner.goals == [1 * stride + 12, 1 * stride + 2]  # padded cells of columns 11, 1


def test_minpos_makes_the_farther_agent_yield() -> None:
    # Agent 0's rank is 1 on the left cell (agent 1 is closer) and 0 on the right one.
    assert corridor(MinPosPlanner(1, 13), AGENTS, VISITED) == [RIGHT, LEFT]


def test_minpos_claims_keep_agents_on_one_cell_from_moving_in_lockstep() -> None:
    # Both at column 5 (equal ranks and distances everywhere): agent 0 takes the nearer left
    # cell, agent 1 the other one, instead of following agent 0 (MinPos as printed).
    assert corridor(MinPosPlanner(1, 13), [5, 5], VISITED) == [LEFT, RIGHT]


def test_utility_radius_pushes_the_second_agent_away_from_the_firsts_target() -> None:
    # Three candidates on a 1x13 strip: A at column 4 and A' at column 5 (next to it), B at
    # column 10. Both agents cost 2 to A, 3 to A' and 6 to B.
    planner = UtilityPlanner(1, 13, beta=0.05, radius=5.0)
    stride = 15
    goals = np.array([[stride + 5, stride + 6, stride + 11]] * 2)
    cost = np.array([[2.0, 3.0, 6.0], [2.0, 3.0, 6.0]])
    # Agent 0: utility 1 - 0.05 * cost -> A (0.9). A' is 1 cell from A: its utility drops by
    # 1 - 1/5 to 0.2, so agent 1 scores A' 0.2 - 0.15 = 0.05, B 1 - 0.3 = 0.7 -> B.
    assert planner.assign(cost, goals) == [0, 2]
    # Without the spreading (a radius too small to reach A'), agent 1 follows to A'.
    assert UtilityPlanner(1, 13, beta=0.05, radius=0.5).assign(cost, goals) == [0, 1]


def test_clusters_are_one_candidate_each_reached_at_their_nearest_cell() -> None:
    planner = HungarianPlanner(1, 13, candidates="clusters")
    # Columns 0..1 unvisited on the left (seen: 1), 11..12 on the right (seen: 11).
    assert corridor(planner, AGENTS, VISITED) == [RIGHT, LEFT]


@pytest.mark.parametrize("name", sorted(COORDINATED))
def test_bad_parameters_are_refused(name: str) -> None:
    with pytest.raises(ValueError, match="unknown candidates"):
        COORDINATED[name](5, 5, candidates="some")
    with pytest.raises(ValueError, match="horizon must be >= 1"):
        COORDINATED[name](5, 5, horizon=0)
    if name == "utility":
        with pytest.raises(ValueError, match="beta must be >= 0 and radius > 0"):
            UtilityPlanner(5, 5, radius=0)


@pytest.mark.parametrize("name", sorted(COORDINATED))
def test_the_planners_are_registry_entries_and_baselines(name: str) -> None:
    entry = PLANNERS[name]
    assert entry.baseline == f"frontier_{name}" and entry.baseline in BASELINES
    assert entry.in_env  # deterministic: the env's compass and step can follow them
    assert isinstance(entry.make(7, 9), COORDINATED[name])


@pytest.mark.parametrize("name", sorted(COORDINATED))
@pytest.mark.parametrize(
    "env",
    [
        EnvConfig(height=12, width=12, n_agents=3, max_steps=80),
        EnvConfig(map={"cave": {"height": 20, "width": 30}}, n_agents=2, max_steps=120),
    ],
    ids=["random", "cave"],
)
def test_never_a_wall_and_an_episode_repeats_from_its_seed(name: str, env: EnvConfig) -> None:
    policy = f"frontier_{name}"
    results = run_episodes(make_baseline(policy, 0), env, episodes=3, seed=7)
    again = run_episodes(make_baseline(policy, 0), env, episodes=3, seed=7)
    assert all(sum(r.wall_hits) == 0 for r in results)
    assert [r.new_cells for r in again] == [r.new_cells for r in results]
    assert all(r.coverage > 0.4 for r in results)  # it explores


def test_a_team_that_always_steps_with_a_coordinated_planner_plays_its_baseline() -> None:
    from envs import coverage_v0

    env = coverage_v0.parallel_env(
        height=14, width=14, n_agents=3, max_steps=60, observation={"teammap": {"crop": 7}},
        frontier={"action": "step", "planner": "hungarian"},
    )  # fmt: skip
    planner = HungarianPlanner(14, 14)
    env.reset(seed=3)
    while env.agents:
        planner.sync(env.steps, env.positions, lambda: (env.walls, env.visited))
        expected = planner.act()
        before = env.positions
        env.step(dict.fromkeys(env.agents, 5))
        moves = np.array([[-1, 0], [1, 0], [0, -1], [0, 1], [0, 0]])
        np.testing.assert_array_equal(env.positions, before + moves[expected])


# ---------------------------------------------------------------------- the physical bound
def test_physical_bound_by_hand() -> None:
    assert physical_bound(1, 1000, 2000) == pytest.approx(1001 / 2000)
    assert physical_bound(4, 1000, 2000) == 1.0
    assert physical_bound(2, 9, 40) == pytest.approx(0.5)


def test_summary_reports_bound_and_efficiency_by_hand() -> None:
    def episode(coverage: float, free: int) -> EpisodeResult:
        return EpisodeResult(coverage, [coverage] * 3, [0, 0], [1, 1], 9, free)

    # Two agents, 9 steps: at most 20 cells. Bounds 20/40 = 0.5 and 1 (10 free cells).
    summary = summarize([episode(0.25, 40), episode(1.0, 10)])
    assert summary["bound"] == pytest.approx(0.75)
    assert summary["coverage_mean"] == pytest.approx(0.625)
    assert summary["efficiency"] == pytest.approx(0.625 / 0.75)
    low, high = summary["coverage_mean_ci"]
    assert 0.25 <= low <= 0.625 <= high <= 1.0


def test_cluster_candidates_match_a_from_scratch_reference() -> None:
    # A planner mid-episode on a random map: every cluster of known unvisited cells (4-connected)
    # costs each agent its path length to the cluster's nearest cell, the first in row-major
    # order among equally near ones.
    from scipy.ndimage import label

    from envs import coverage_v0

    env = coverage_v0.parallel_env(height=20, width=24, n_agents=3, max_steps=200)
    env.reset(seed=5)
    planner = HungarianPlanner(20, 24, candidates="clusters")
    for _ in range(30):
        planner.sync(env.steps, env.positions, lambda: (env.walls, env.visited))
        env.step(dict(zip(env.agents, planner.act())))
    planner.sync(env.steps, env.positions, lambda: (env.walls, env.visited))
    dist, _ = planner.distance_fields()
    cells = np.flatnonzero(planner.target)
    cost, goals = planner._candidate_costs(dist[:, cells], cells)
    labels, n = label(planner.target.reshape(-1, planner.stride))
    assert cost.shape == (3, n) and n > 1
    for k in range(1, n + 1):
        members = [c for c in cells.tolist() if labels.ravel()[c] == k]
        for i in range(3):
            nearest = min(members, key=lambda c: (dist[i, c], c))
            column = list(goals[i]).index(nearest)
            assert cost[i, column] == dist[i, nearest]


@pytest.mark.parametrize("name", sorted(COORDINATED))
def test_a_planner_reused_over_episodes_plays_each_as_a_fresh_one(name: str) -> None:
    # A baseline keeps one planner per env copy over many episodes: each new episode must start
    # from its own map (a graph left from the last episode once stopped agents for good).
    env = EnvConfig(height=15, width=15, n_agents=2, max_steps=150)
    reused = run_episodes(make_baseline(f"frontier_{name}", 0), env, episodes=12, seed=2000003)
    fresh = [
        run_episodes(make_baseline(f"frontier_{name}", 0), env, episodes=1, seed=2000003 + k)[0]
        for k in range(12)
    ]
    assert [r.new_cells for r in reused] == [r.new_cells for r in fresh]
    assert min(r.coverage for r in reused) > 0.9


@pytest.mark.parametrize(
    "make",
    [
        lambda h, w: FrontierPlanner(h, w, "order"),
        lambda h, w: FrontierPlanner(h, w, "pocket"),
        *(lambda h, w, c=c: c(h, w) for c in COORDINATED.values()),
        lambda h, w: UtilityPlanner(h, w, horizon=None, beta=0.5, radius=2.0),
        lambda h, w: MinPosPlanner(h, w, candidates="clusters"),
    ],
    ids=["order", "pocket", *COORDINATED, "utility-whole-map", "minpos-clusters"],
)
def test_the_one_call_step_plays_as_sync_then_act(make) -> None:
    # step() runs a planner's whole step in one compiled call where it can; it must choose
    # every goal and move as sync() followed by act() does, over whole episodes.
    from envs import coverage_v0

    env = coverage_v0.parallel_env(height=15, width=18, n_agents=4, max_steps=300)
    for seed in (0, 1):
        env.reset(seed=seed)
        fused, plain = make(15, 18), make(15, 18)
        while env.agents:
            read = lambda: (env.walls, env.visited)  # noqa: E731
            moves = fused.step(env.steps, env.positions, read)
            plain.sync(env.steps, env.positions, read)
            assert moves == plain.act(), f"seed {seed}, step {env.steps}"
            assert fused.goals == plain.goals and fused.n_targets == plain.n_targets
            env.step(dict(zip(env.possible_agents, moves)))


# ---------------------------------------------------------------------- the compiled assignment
@st.composite
def cost_matrices(draw) -> np.ndarray:
    """A planner's kind of cost matrix: 1..6 agents by 0..40 candidates, or transposed (tall),
    of small integers (many ties) with some entries 1e9 (the planner's unreachable), or
    floats."""
    short, long = draw(st.integers(1, 6)), draw(st.integers(0, 40))
    shape = (long, short) if draw(st.booleans()) else (short, long)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if draw(st.booleans()):
        cost = rng.integers(0, draw(st.integers(1, 6)), size=shape).astype(float)
    else:
        cost = rng.random(shape) * draw(st.sampled_from([1.0, 30.0]))
    cost[rng.random(shape) < draw(st.sampled_from([0.0, 0.2, 0.6]))] = 1e9
    return cost


@settings(max_examples=500, deadline=None)
@given(cost=cost_matrices())
def test_the_compiled_assignment_is_scipys(cost: np.ndarray) -> None:
    # Not just as cheap: the very rows and columns SciPy picks among tied optima.
    rows, cols = linear_sum_assignment_compiled(cost)
    expected_rows, expected_cols = linear_sum_assignment(cost)
    assert rows.dtype == cols.dtype == np.int64
    np.testing.assert_array_equal(rows, expected_rows)
    np.testing.assert_array_equal(cols, expected_cols)


def test_the_compiled_assignment_refuses_what_scipy_refuses() -> None:
    for cost in (np.array([[1.0, np.nan]]), np.array([[-np.inf, 1.0]])):
        with pytest.raises(ValueError, match="invalid numeric entries"):
            linear_sum_assignment_compiled(cost)
    infeasible = np.array([[np.inf, np.inf], [1.0, 2.0]])
    with pytest.raises(ValueError, match="infeasible"):
        linear_sum_assignment(infeasible)
    with pytest.raises(ValueError, match="infeasible"):
        linear_sum_assignment_compiled(infeasible)


def scipy_hungarian(cost: np.ndarray) -> list[int]:
    """The Hungarian planner's rule as it was written around SciPy's assignment."""
    finite = np.where(np.isfinite(cost), cost, 1e9)
    rows, cols = linear_sum_assignment(finite)
    chosen = finite.argmin(axis=1).tolist()  # the agents the assignment leaves out
    for r, c in zip(rows.tolist(), cols.tolist()):
        if finite[r, c] < 1e9:
            chosen[r] = c
    return chosen


@settings(max_examples=300, deadline=None)
@given(agents=st.integers(1, 6), candidates=st.integers(1, 40), seed=st.integers(0, 2**32 - 1))
def test_the_hungarian_rule_is_the_one_around_scipy(agents, candidates, seed) -> None:
    rng = np.random.default_rng(seed)
    cost = rng.integers(0, 8, size=(agents, candidates)).astype(float)
    cost[rng.random(cost.shape) < rng.choice([0.0, 0.3, 0.8])] = np.inf  # beyond the horizon
    planner = HungarianPlanner(3, 3)
    assert planner.assign(cost, np.zeros(cost.shape, dtype=np.int64)) == scipy_hungarian(cost)


class Farthest(HungarianPlanner):
    """A user's rule: every agent heads for its farthest reachable candidate."""

    calls = 0

    def assign(self, cost: np.ndarray, goal_cells: np.ndarray) -> list[int]:
        Farthest.calls += 1
        return np.where(np.isfinite(cost), cost, -1.0).argmax(axis=1).tolist()


class Renamed(HungarianPlanner):
    """A subclass that keeps the Hungarian rule."""


def test_a_subclass_that_overrides_assign_plays_its_own_rule_in_step() -> None:
    # The compiled assignment would silently replace the subclass's rule: it is switched off.
    from envs import coverage_v0

    assert Farthest._compiled_assign is None
    assert Renamed._compiled_assign == HungarianPlanner._compiled_assign is not None
    env = coverage_v0.parallel_env(height=12, width=12, n_agents=3, max_steps=40)
    env.reset(seed=5)
    fused, plain, hungarian = Farthest(12, 12), Farthest(12, 12), HungarianPlanner(12, 12)
    differs = False
    while env.agents:
        read = lambda: (env.walls, env.visited)  # noqa: E731
        calls = Farthest.calls
        moves = fused.step(env.steps, env.positions, read)
        assert Farthest.calls == calls + (fused.n_targets > 0)  # step() asked its assign
        plain.sync(env.steps, env.positions, read)
        assert moves == plain.act(), f"step {env.steps}"
        hungarian.sync(env.steps, env.positions, read)
        differs |= moves != hungarian.act()
        env.step(dict(zip(env.possible_agents, moves)))
    assert differs  # the rule played is not the Hungarian one
