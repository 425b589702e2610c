"""The rollout teacher (``envs.coverage.teacher``): its choices and scores on a hand-built
corridor where the best slot is known and the cells can be counted by hand, and equality with
the Python rollouts of ``tests/python_rollouts.py`` (the oracle it compiles, taken from the
research script ``research/experiments/goal_oracle.py``), per decision for every planner it plays
and over whole oracle episodes. That evaluation never imports it is a
rule of ``tests/test_architecture.py``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from envs.coverage.goals import gather_candidates
from envs.coverage.planners import FrontierPlanner, HungarianPlanner
from envs.coverage.rollouts import shortest_walk
from envs.coverage.teacher import RolloutTeacher
from harness.config.loading import load_config
from harness.factory import make_env
from tests import python_rollouts as oracle

ROOT = Path(__file__).resolve().parents[1]
#: The corridor's length (a 1 x W map: outside it, wall).
W = 21


def padded(col: int) -> int:
    """The planner's padded flat cell of corridor column ``col``."""
    return (W + 2) + col + 1


def corridor(cols: list[int], tie_break: str = "pocket"):
    """A 1x21 corridor, columns 2..6 visited, the agents at ``cols``: the known unvisited
    cells are column 1 (a dead end: only column 0 lies behind it) and column 7 (14 cells of
    corridor behind it, 7..20). Returns the planner, synced and planned, and the candidates."""
    planner = FrontierPlanner(1, W, tie_break)
    walls = np.zeros((1, W), dtype=bool)
    visited = np.zeros((1, W), dtype=bool)
    visited[0, 2:7] = True
    planner.sync(0, np.array([[0, c] for c in cols]), lambda: (walls, visited))
    moves = planner.act(np.random.default_rng(0))  # the random tie-break's draws
    return planner, gather_candidates(planner, moves, 4, 1, W)


@pytest.mark.parametrize("tie_break", ["order", "pocket"])
def test_the_teacher_leaves_the_dead_end_for_the_long_corridor(tie_break: str) -> None:
    planner, cand = corridor([3], tie_break)
    # The planner heads for the nearer dead end (2 steps against 4): slot 0; slot 1 the far end.
    assert cand.cells[0].tolist() == [padded(1), padded(7), -1, -1]
    before = (planner.grid.copy(), planner.n_targets, list(planner.positions))
    slot, scores = RolloutTeacher(horizon=10).choose(planner, cand, 0, 100)
    # Slot 0: columns 1 and 0 by step 3, then 7 steps back to column 7 (step 10): 3 cells.
    # Slot 1: column 7 on step 4, then one new column a step to column 13: 7 cells.
    assert slot == 1
    np.testing.assert_array_equal(scores, [3, 7, np.nan, np.nan])
    # The rollouts ran on copies: the planner is as it was.
    assert (planner.grid == before[0]).all() and planner.n_targets == before[1]
    assert planner.positions == before[2]


def test_to_the_episodes_end_both_slots_cover_the_corridor_and_slot_0_stays() -> None:
    planner, cand = corridor([3])
    # Every one of the 16 unvisited cells either way: a tie keeps slot 0.
    slot, scores = RolloutTeacher().choose(planner, cand, 0, 100)
    assert slot == 0 and scores[:2].tolist() == [16, 16]
    # By steps to the whole map the dead end first is faster: slot 0 is done on step 3 + 7 + 13
    # = 23, slot 1 on step 4 + 13 + 20 = 37 (the way back to column 0). A step outweighs any
    # cells: -steps * (69 padded cells + 1) + cells.
    slot, scores = RolloutTeacher(reach=1.0).choose(planner, cand, 0, 100)
    assert slot == 0 and scores[:2].tolist() == [-23 * 70 + 16, -37 * 70 + 16]
    # Neither reaches it in 10 steps (counted as 11): the cells decide.
    slot, scores = RolloutTeacher(horizon=10, reach=1.0).choose(planner, cand, 0, 100)
    assert slot == 1 and scores[:2].tolist() == [-11 * 70 + 3, -11 * 70 + 7]
    # The episode's end cuts the rollouts like a horizon does.
    assert RolloutTeacher().scores(planner, cand, 0, 10)[:2].tolist() == [3, 7]


def test_a_gain_within_the_margin_keeps_slot_0() -> None:
    planner, cand = corridor([3])
    assert RolloutTeacher(horizon=10, margin=4).choose(planner, cand, 0, 100)[0] == 0
    assert RolloutTeacher(horizon=10, margin=3).choose(planner, cand, 0, 100)[0] == 1


def test_a_teammates_committed_walk_is_walked_in_every_rollout() -> None:
    planner, cand = corridor([3, 5])
    assert cand.cells[0, :2].tolist() == [padded(1), padded(7)]
    walk = [padded(c) for c in range(6, 16)]  # agent 1 walks columns 6..15: 9 new cells
    scores = RolloutTeacher(horizon=10).scores(planner, cand, 0, 100, walks={1: walk})
    # Slot 0: agent 0's dead end (2 cells), then it walks behind agent 1: 2 + 9.
    # Slot 1: agent 0 walks behind agent 1 from the start: 9.
    assert scores[:2].tolist() == [11, 9]
    # The walk the teacher commits an agent to is the rollouts' path.
    assert shortest_walk(planner, 0, padded(7)) == [padded(c) for c in range(4, 8)]
    assert shortest_walk(planner, 0, padded(3)) == []  # its own cell


def test_label_decides_in_agent_order_and_binds_the_later_agents() -> None:
    planner, cand = corridor([3, 5])
    teacher = RolloutTeacher(horizon=10)
    slots, scores = teacher.label(planner, cand, 100)
    first, first_scores = teacher.choose(planner, cand, 0, 100)
    assert slots[0] == first and np.array_equal(scores[0], first_scores, equal_nan=True)
    walks = {0: shortest_walk(planner, 0, int(cand.cells[0, first]))} if first else {}
    second, second_scores = teacher.choose(planner, cand, 1, 100, walks)
    assert slots[1] == second and np.array_equal(scores[1], second_scores, equal_nan=True)
    # A committed agent does not decide.
    slots, scores = teacher.label(planner, cand, 100, walks={1: [padded(6)]})
    assert slots[1] == -1 and np.isnan(scores[1]).all()


def test_the_teacher_refuses_planners_it_cannot_step_and_bad_options() -> None:
    planner, cand = corridor([3], "random")
    with pytest.raises(ValueError, match="random"):
        RolloutTeacher().scores(planner, cand, 0, 100)
    clusters = HungarianPlanner(1, W, candidates="clusters")
    clusters.sync(0, np.array([[0, 3]]), lambda: (np.zeros((1, W), bool), np.eye(1, W, 3, bool)))
    moves = clusters.act()
    with pytest.raises(ValueError, match="clusters"):
        RolloutTeacher().scores(clusters, gather_candidates(clusters, moves, 4, 1, W), 0, 100)
    for bad in ({"horizon": 0}, {"margin": -1}, {"reach": 0.0}, {"reach": 1.5}):
        with pytest.raises(ValueError):
            RolloutTeacher(**bad)


def _small_env(planner: str, n_agents: int, max_steps: int = 60):
    cfg = load_config(
        ROOT / "configs" / "goals_2agents.yaml",
        [
            "env.map=random",
            "env.height=15",
            "env.width=15",
            f"env.max_steps={max_steps}",
            f"env.n_agents={n_agents}",
            f"env.frontier.planner={planner}",
        ],
    )
    return make_env(cfg.env)


@pytest.mark.parametrize(
    ("planner", "n_agents"),
    [("order", 2), ("pocket", 4), ("utility", 2), ("minpos", 3), ("hungarian", 3)],
)
def test_every_slots_score_equals_the_python_rollouts(planner: str, n_agents: int) -> None:
    # The oracle's Python rollouts (clone, advance, rollout: the planner stepped by act) and
    # the compiled ones score every slot alike, on states of a played episode, with a
    # teammate committed to a walk, for each way of scoring.
    env = _small_env(planner, n_agents)
    env.reset(seed=11)
    teachers = [RolloutTeacher(), RolloutTeacher(horizon=12), RolloutTeacher(reach=0.8)]
    checked = 0
    while env.agents:
        frontier = env.frontier_state
        p, cand = frontier.planner, frontier.candidates
        stride = p.stride
        offset = (-stride, stride, -1, 1, 0)
        cells = [p.positions[a] + offset[int(cand.moves[a, 0])] for a in range(n_agents)]
        walks: dict[int, list[int]] = {}
        if cand.cells[n_agents - 1, 1] >= 0:  # the last agent walks to its slot 1
            walk = shortest_walk(p, n_agents - 1, int(cand.cells[n_agents - 1, 1]))
            walks[n_agents - 1] = walk
            cells[n_agents - 1] = walk[0]
        rests = {a: w[1:] for a, w in walks.items()}
        if env.steps % 4 == 0 and (cand.cells[0] >= 0).sum() > 1:
            left = env.max_steps - env.steps
            for teacher in teachers:
                want = oracle.python_scores(p, cand, 0, cells, rests, left, teacher)
                got = teacher.scores(p, cand, 0, left, walks)
                slots = np.flatnonzero(cand.cells[0] >= 0)
                np.testing.assert_array_equal(got[slots], want)
                assert np.isnan(np.delete(got, slots)).all()
                checked += 1
        env.step(dict.fromkeys(env.agents, 0))
    assert checked >= 9


@pytest.mark.parametrize("reach", [None, 0.9])
def test_the_oracle_plays_the_same_episode_with_either_rollouts(reach: float | None) -> None:
    # Whole oracle episodes (decisions in agent order, commitment to a chosen walk, the
    # recorded advantages) are the same with the compiled rollouts as with the Python ones.
    env = _small_env("pocket", 2, max_steps=80)
    played = []
    for python in (True, False):
        decisions: list = []
        result = oracle.play(env, 7, oracle=True, reach=reach, python=python, decisions=decisions)
        played.append((result, decisions))
    (python_result, python_decisions), (result, decisions) = played
    assert result == python_result and result[1] > 0  # it deviates
    assert len(decisions) == len(python_decisions) > 0
    for (t1, a1, s1, b1), (t2, a2, s2, b2) in zip(decisions, python_decisions):
        assert (t1, a1, b1) == (t2, a2, b2)
        np.testing.assert_array_equal(s1, s2)


def _goal_env(**overrides: int):
    sets = {"env.height": 15, "env.width": 15, "env.max_steps": 80, **overrides}
    cfg = load_config(
        ROOT / "configs" / "goals_2agents.yaml",
        ["env.map=random", *(f"{k}={v}" for k, v in sets.items())],
    )
    return make_env(cfg.env)


def test_the_rollouts_replay_the_planner_and_leave_the_env_alone() -> None:
    env = _goal_env()
    env.reset(seed=5)
    planner = env.frontier_state.planner
    before = (list(planner.visited), list(planner.positions), planner.target.copy())
    # Everybody on the planner from the reset: the copy's cells are the planner episode's.
    new, _ = oracle.rollout(oracle.clone(planner), env.max_steps, {})
    assert (list(planner.visited), list(planner.positions)) == before[:2]
    assert (planner.target == before[2]).all()
    start = int(env.visited.sum())
    coverage, deviations, _ = oracle.play(env, 5, oracle=False)
    assert deviations == 0 and coverage == pytest.approx((start + new) / env.free_cells)
    # Steps to a coverage: the rollout's count (cells still to find) is the played episode's.
    goal = int(np.ceil(0.6 * env.free_cells)) - start
    env.reset(seed=5)
    found, step = oracle.rollout(oracle.clone(env.frontier_state.planner), env.max_steps, {}, goal)
    assert found == goal or found == goal + 1  # agents moving together may pass it by one
    _, _, reached = oracle.play(env, 5, oracle=False, reach=0.6)
    assert reached == step and 0 < step < env.max_steps
    curve = []
    env.reset(seed=5)
    while env.agents and env.coverage < 0.6:
        env.step(dict.fromkeys(env.agents, 0))
        curve.append(env.coverage)
    assert len(curve) == reached
    # Every decision scores each candidate; the choice beats slot 0 (or is slot 0).
    decisions: list = []
    assert 0 < oracle.play(env, 5, oracle=True, decisions=decisions)[0] <= 1 and decisions
    for _, _, scores, best in decisions:
        assert best == 0 or scores[best] > scores[0]
    # An oracle that decides only from a coverage it never reaches plays the planner.
    assert oracle.play(env, 5, oracle=True, after=1.01)[:2] == (coverage, 0)


def test_one_agents_oracle_scored_by_steps_is_never_slower_than_the_planner() -> None:
    # Alone on the true map, the oracle's slot 0 at each decision continues the rollout it
    # committed to (everybody on the planner after the walk), and it leaves slot 0 only for a
    # strictly better rollout: its steps to the coverage can only fall below the planner's.
    env = _goal_env(**{"env.max_steps": 300, "env.n_agents": 1})
    _, _, planner_steps = oracle.play(env, 5, oracle=False, reach=0.9)
    _, deviations, oracle_steps = oracle.play(env, 5, oracle=True, reach=0.9)
    assert planner_steps is not None and oracle_steps is not None
    assert deviations > 0 and oracle_steps <= planner_steps


def test_the_reference_walks_the_shortest_path_of_the_predecessors() -> None:
    # Cells 0 -> 1 -> 2 -> 5 (a predecessor array as SciPy returns it; -9999: none).
    pred = np.array([-9999, 0, 1, -9999, -9999, 2])
    assert oracle.path_to(pred, 0, 5) == [1, 2, 5]
    assert oracle.path_to(pred, 0, 1) == [1]
