"""The goal action (``frontier: {action: {goal: {k: K}}, planner: ...}``): its candidates on
hand-built grids (which cells, in which order, their features, the mask when there are fewer
than K), the step towards a chosen candidate, the planner as slot 0, the options' errors, the
slot-scoring policy (equivariance, masking in the real env, save/load) and a tiny run end to
end."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch as th
from hypothesis import given, settings
from hypothesis import strategies as st

from envs import coverage_v0
from envs.coverage.frontier import FrontierOptions
from envs.coverage.goals import ACTION_MASK_KEY, GOAL_FEATURES, GOALS_KEY, gather_candidates
from envs.coverage.planners import FrontierPlanner, HungarianPlanner
from harness import DoubleDQN
from harness.cli import main
from harness.config.loading import config_from_dict, load_config
from harness.config.schema import ConfigError, EnvConfig, ExperimentConfig
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import run_episodes
from harness.factory import make_env
from harness.sb3.policies import SlotQNetwork, SlotTeamMapPolicy
from harness.training.adapters import make_vec_env
from tests.conftest import tiny_goal_run

UP, DOWN, LEFT, RIGHT, STAY = range(5)
ROOT = Path(__file__).resolve().parents[1]
F = {name: i for i, name in enumerate(GOAL_FEATURES)}


def corridor_planner(planner: FrontierPlanner, positions: list[int]) -> FrontierPlanner:
    """A 1x13 corridor (outside it: wall), columns 2..10 visited, the agents at ``positions``
    (columns): the known unvisited cells are column 1 and column 11, two clusters."""
    walls = np.zeros((1, 13), dtype=bool)
    visited = np.zeros((1, 13), dtype=bool)
    visited[0, 2:11] = True
    planner.sync(0, np.array([[0, c] for c in positions]), lambda: (walls, visited))
    return planner


def padded(col: int) -> int:
    """The planner's padded flat cell of corridor column ``col`` (row 0)."""
    return 1 * (13 + 2) + col + 1


def test_candidates_of_one_agent_in_a_corridor() -> None:
    planner = corridor_planner(FrontierPlanner(1, 13), [5])
    moves = planner.act()
    assert moves == [LEFT]  # the nearer end (4 against 6)
    c = gather_candidates(planner, moves, k=4, height=1, width=13)
    # Slot 0: the planner's cell and move; slot 1: the other cluster; slots 2-3 empty.
    assert c.cells[0].tolist() == [padded(1), padded(11), -1, -1]
    assert c.moves[0].tolist() == [LEFT, RIGHT, STAY, STAY]
    assert c.mask[0].tolist() == [1.0, 1.0, 0.0, 0.0]
    f = c.features[0]
    scale = 1 / (1 + 13)
    assert f[:, F["valid"]].tolist() == [1, 1, 0, 0]
    assert f[:, F["planner"]].tolist() == [1, 0, 0, 0]
    assert f[:2, F["distance"]] == pytest.approx([4 * scale, 6 * scale])
    assert f[:2, F["teammate"]] == pytest.approx([1.0, 1.0])  # no teammate
    assert f[:2, F["heading"]].tolist() == [0, 0]
    assert f[:2, F["cluster"]] == pytest.approx([np.log(2) / np.log(14)] * 2)
    # The 5x5 window around column 1 holds one unseen cell (column 0); likewise column 11.
    assert f[:2, F["unknown"]] == pytest.approx([1 / 25, 1 / 25])
    # Of column 1's four neighbours only column 0 (unseen) is open; likewise column 11.
    assert f[:2, F["open"]] == pytest.approx([1 / 4, 1 / 4])
    assert f[:2, F["row"]].tolist() == [0, 0]
    assert f[:2, F["col"]] == pytest.approx([-4 / 13, 6 / 13])
    assert not f[2:].any()  # empty slots: all-zero features


def test_teammates_distances_and_headings() -> None:
    # Agent 0 at 5, agent 1 at 3: Hungarian sends agent 0 right (6) and agent 1 left (2).
    planner = corridor_planner(HungarianPlanner(1, 13), [5, 3])
    moves = planner.act()
    assert moves == [RIGHT, LEFT]
    c = gather_candidates(planner, moves, k=3, height=1, width=13)
    assert c.cells.tolist() == [[padded(11), padded(1), -1], [padded(1), padded(11), -1]]
    assert c.moves.tolist() == [[RIGHT, LEFT, STAY], [LEFT, RIGHT, STAY]]
    scale = 1 / 14
    # Agent 0's candidates: column 11 (agent 1 is 8 away), column 1 (agent 1 is 2 away, and is
    # heading there).
    assert c.features[0, :2, F["teammate"]] == pytest.approx([8 * scale, 2 * scale])
    assert c.features[0, :2, F["heading"]].tolist() == [0, 1]
    assert c.features[1, :2, F["teammate"]] == pytest.approx([4 * scale, 6 * scale])
    assert c.features[1, :2, F["heading"]].tolist() == [0, 1]


def test_an_agent_the_planner_leaves_idle_gets_the_clusters_from_slot_0_on() -> None:
    # Three agents, two targets (columns 1 and 11): agent 0 (at 5) claims column 1, agent 1 (at
    # 6) column 11, and agent 2 (at 7) finds both claimed: the planner leaves it in place with
    # no target. It has no planner's choice, so its slots are the clusters from slot 0 on,
    # nearest first (column 11, 4 away, then column 1), slot 0's `planner` feature 0: always
    # taking slot 0 walks it on where the planner would stay (docs/goals.md).
    planner = corridor_planner(FrontierPlanner(1, 13), [5, 6, 7])
    moves = planner.act()
    assert moves == [LEFT, RIGHT, STAY]
    c = gather_candidates(planner, moves, k=3, height=1, width=13)
    assert c.cells[2].tolist() == [padded(11), padded(1), -1]
    assert c.moves[2].tolist() == [RIGHT, LEFT, STAY]
    assert c.features[2, :, F["planner"]].tolist() == [0, 0, 0]
    assert c.features[:2, 0, F["planner"]].tolist() == [1, 1]  # the others: the planner's


def test_clusters_come_nearest_first_at_their_nearest_cell() -> None:
    # A 5x9 room, all free, agent at the centre, everything visited but three groups of cells:
    # a cluster of two cells at the top-left (distances 5 and 6), a single cell at the
    # bottom-right (distance 4) and a single cell at the top-right (distance 6).
    walls = np.zeros((5, 9), dtype=bool)
    visited = np.ones((5, 9), dtype=bool)
    for r, col in [(0, 0), (0, 1), (4, 6), (0, 8)]:
        visited[r, col] = False
    planner = FrontierPlanner(5, 9)
    planner.sync(0, np.array([[2, 4]]), lambda: (walls, visited))
    moves = planner.act()
    c = gather_candidates(planner, moves, k=4, height=5, width=9)
    stride = 9 + 2
    cell = lambda r, col: (r + 1) * stride + col + 1  # noqa: E731
    # Slot 0 is the planner's (the nearest, (4, 6)); then the top-left cluster at its nearer
    # cell (0, 1) (5 away) before (0, 8) (6 away); the cluster's other cell is no candidate.
    assert c.cells[0].tolist() == [cell(4, 6), cell(0, 1), cell(0, 8), -1]
    assert c.features[0, :3, F["distance"]] * (5 + 9) == pytest.approx([4, 5, 6])
    assert c.features[0, :3, F["cluster"]] == pytest.approx(np.log1p([1, 2, 1]) / np.log1p(5 * 9))


def goal_env(k: int = 4, planner: str = "order"):
    """A 3x7 corridor (row 1 free, rows 0 and 2 wall), one agent at (1, 3)."""
    grid = np.ones((3, 7), dtype=bool)
    grid[1] = False
    env = coverage_v0.parallel_env(
        height=3,
        width=7,
        n_agents=1,
        max_steps=20,
        observation={"teammap": {"crop": 7, "global_size": 6}},
        frontier={"action": {"goal": {"k": k}}, "planner": planner},
    )
    obs, _ = env.reset(seed=0, options={"grid": grid, "starts": [(1, 3)]})
    return env, obs


def test_the_env_walks_towards_the_chosen_candidate_and_stays_on_an_empty_slot() -> None:
    env, obs = goal_env()
    assert env.action_space("agent_0").n == 4
    o = obs["agent_0"]
    # Two clusters, (1, 2) and (1, 4); the order planner takes the left one (neighbours up,
    # left, right, down).
    assert o[ACTION_MASK_KEY].tolist() == [1, 1, 0, 0]
    assert o[GOALS_KEY].shape == (4, len(GOAL_FEATURES))
    assert o[GOALS_KEY][:2, F["col"]] == pytest.approx([-1 / 7, 1 / 7])
    obs, *_ = env.step({"agent_0": 1})  # the right-hand candidate
    assert env.positions.tolist() == [[1, 4]]
    env.step({"agent_0": 3})  # an empty slot: stays
    assert env.positions.tolist() == [[1, 4]]
    env.step({"agent_0": 0})  # the planner's choice
    assert env.positions.tolist() != [[1, 4]]


@pytest.mark.parametrize(
    ("n_agents", "planner", "baseline"),
    [(2, "pocket", "frontier_pocket"), (3, "hungarian", "frontier_hungarian")],
)
def test_always_taking_slot_0_is_the_planner(n_agents: int, planner: str, baseline: str) -> None:
    goal = EnvConfig(
        n_agents=n_agents,
        height=20,
        width=20,
        max_steps=200,
        observation={"teammap": {"crop": 7, "global_size": 6}},
        frontier={"action": {"goal": {"k": 4}}, "planner": planner},
    )
    plain = EnvConfig(n_agents=n_agents, height=20, width=20, max_steps=200)
    slot0 = run_episodes(make_baseline("frontier_step", 0), goal, 3, 10)
    written = run_episodes(make_baseline(baseline, 0), plain, 3, 10)
    assert [r.coverage for r in slot0] == [r.coverage for r in written]
    assert [r.new_cells for r in slot0] == [r.new_cells for r in written]
    assert all(sum(r.wall_hits) == 0 for r in slot0)


@pytest.mark.parametrize(
    ("frontier", "message"),
    [
        ({"action": "goal"}, "frontier.action: 'goal' needs frontier.planner"),
        ({"action": {"goal": {"k": 1}}, "planner": "order"}, "goal.k must be an integer in 2..64"),
        (
            {"action": {"goal": {"n": 3}}, "planner": "order"},
            "unknown option(s) ['n']; known: k",
        ),
        ({"action": {"goal": 3}, "planner": "order"}, "options must be a mapping"),
        ({"action": {"walk": {}}, "planner": "order"}, "unknown frontier.action 'walk'"),
    ],
)
def test_goal_options_errors_name_the_key(frontier: dict, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        FrontierOptions.parse(frontier)


def test_config_form_round_trips() -> None:
    options = FrontierOptions.parse({"action": {"goal": {"k": 5}}, "planner": "minpos"})
    config = {"action": {"goal": {"k": 5}}, "planner": "minpos"}
    assert options.config() == config
    assert options.n_actions == 5 and options.expert_action == 0
    step = FrontierOptions.parse({"action": "step"})
    assert step.config() == {"action": "step", "planner": None} and step.n_actions == 6


def test_the_retired_gather_option_loads_at_clusters_and_is_refused_otherwise() -> None:
    data = load_config(ROOT / "configs" / "goals_2agents.yaml").model_dump()
    data["env"]["frontier"]["action"]["goal"]["gather"] = "clusters"
    assert config_from_dict(data, "old.yaml").env.frontier["action"] == {"goal": {"k": 8}}
    data["env"]["frontier"]["action"]["goal"]["gather"] = "nearest"
    with pytest.raises(ConfigError, match=re.escape("env.frontier.action.goal.gather: 'nearest'")):
        config_from_dict(data, "old.yaml")


def test_slot_policy_needs_the_goal_action_and_has_no_per_agent_version() -> None:
    data = load_config(ROOT / "configs" / "goals_2agents.yaml").model_dump()
    data["env"]["frontier"] = {"action": "step", "planner": "pocket"}
    with pytest.raises(
        (ValueError, ConfigError), match=re.escape("needs env.frontier.action: {goal")
    ):
        ExperimentConfig.model_validate(data)
    data = load_config(ROOT / "configs" / "goals_2agents.yaml").model_dump()
    data["algo"]["sharing"] = "per_agent"
    with pytest.raises((ValueError, ConfigError), match="has no per-agent version"):
        ExperimentConfig.model_validate(data)


@pytest.fixture(scope="module")
def slot_model():
    th.manual_seed(0)
    config = EnvConfig(
        n_agents=2,
        height=12,
        width=12,
        max_steps=30,
        observation={"teammap": {"crop": 7, "global_size": 6}},
        frontier={"action": {"goal": {"k": 4}}, "planner": "order"},
    )
    venv = make_vec_env(config, copies=1, seed=0)
    model = DoubleDQN(
        "SlotTeamMapPolicy",
        venv,
        learning_starts=10,
        buffer_size=500,
        batch_size=8,
        policy_kwargs={"net_arch": [16], "features_extractor_kwargs": {"features_dim": 16}},
        device="cpu",
    )
    return model, venv


def test_slot_values_follow_the_slots(slot_model) -> None:
    model, venv = slot_model
    assert isinstance(model.q_net, SlotQNetwork) and isinstance(model.policy, SlotTeamMapPolicy)
    obs = venv.reset()
    tensor, _ = model.policy.obs_to_tensor(obs)
    with th.no_grad():
        q = model.q_net(tensor)
        perm = th.tensor([2, 0, 3, 1])
        permuted = dict(tensor)
        permuted[GOALS_KEY] = tensor[GOALS_KEY][:, perm]
        q_perm = model.q_net(permuted)
    assert q.shape == (2, 4)
    assert th.allclose(q_perm, q[:, perm], atol=1e-6)


def test_greedy_and_random_slots_are_always_candidates(slot_model) -> None:
    model, venv = slot_model
    model.learn(200)  # warm-up (random among allowed), then ε-greedy with the mask
    obs = venv.reset()
    for _ in range(30):
        for deterministic in (True, False):
            model.exploration_rate = 1.0
            actions, _ = model.predict(obs, deterministic=deterministic)
            mask = obs[ACTION_MASK_KEY]
            allowed = mask[np.arange(len(actions)), actions] == 1
            assert allowed.all() or not mask.any(axis=1).all()
        obs, *_ = venv.step(model.predict(obs, deterministic=True)[0])


def test_slot_model_saves_and_loads(slot_model, tmp_path: Path) -> None:
    model, venv = slot_model
    model.save(tmp_path / "m.zip")
    loaded = DoubleDQN.load(tmp_path / "m.zip", device="cpu")
    obs = venv.reset()
    with th.no_grad():
        a = model.q_net(model.policy.obs_to_tensor(obs)[0])
        b = loaded.q_net(loaded.policy.obs_to_tensor(obs)[0])
    assert th.equal(a, b)
    assert loaded.policy.slots_key == GOALS_KEY


def test_a_goal_run_trains_and_evaluates_end_to_end(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    args = tiny_goal_run(ROOT / "configs" / "goals_2agents.yaml", runs)
    assert main(args) == 0
    (run,) = runs.iterdir()
    assert (run / "model.zip").is_file()
    assert main(["eval", str(run), "--episodes", "2"]) == 0
    (saved,) = run.glob("eval-2ep.json")
    assert saved.is_file()
    env = make_env(load_config(run / "config.yaml").env)
    assert env.action_space("agent_0").n == 4


@settings(max_examples=60, deadline=None)
@given(
    h=st.integers(1, 30),
    w=st.integers(1, 30),
    share=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_the_unknown_feature_equals_scipy_s_uniform_filter_value_for_value(h, w, share, seed):
    # The feature was measured (and the goal models trained) with SciPy's float32
    # uniform_filter over the planner's padded map; the compiled share must equal it exactly,
    # at every cell, not just approximately.
    from scipy.ndimage import uniform_filter

    from envs.coverage.goals import _unknown_share

    seen = np.random.default_rng(seed).random((h + 2, w + 2)) >= share
    want = uniform_filter((~seen).astype(np.float32), 5, mode="constant").ravel()
    flat = seen.ravel()
    got = np.array([_unknown_share(flat, w + 2, c) for c in range(flat.size)], dtype=np.float32)
    np.testing.assert_array_equal(got, want)
