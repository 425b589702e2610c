"""Every rule of the environment (``envs/coverage_v0.py``: dynamics, observation, reward,
infos, rendering) on small hand-built grids."""

from __future__ import annotations

import numpy as np
import pytest

from envs import coverage_v0
from tests.conftest import grid_from

UP, DOWN, LEFT, RIGHT, STAY = range(5)

OPEN_3X3 = """
...
...
...
"""

CORRIDOR = """
.#..
....
"""


def act(env, *actions):
    return env.step(dict(zip(env.possible_agents, actions)))


def test_move_off_the_grid_is_a_wall_hit_and_leaves_agent_in_place(make_env):
    env, _ = make_env(OPEN_3X3, [(0, 0)])
    _, rew, _, _, info = act(env, UP)
    assert env.positions.tolist() == [[0, 0]]
    assert info["agent_0"]["wall_hits"] == 1
    assert rew["agent_0"] == -10.0 - 1.0  # wall hit + step
    _, rew, _, _, info = act(env, LEFT)
    assert info["agent_0"]["wall_hits"] == 2


def test_move_into_a_wall_is_a_wall_hit(make_env):
    env, _ = make_env(CORRIDOR, [(0, 0)])
    _, rew, _, _, info = act(env, RIGHT)  # (0, 1) is a wall
    assert env.positions.tolist() == [[0, 0]]
    assert info["agent_0"]["wall_hits"] == 1
    assert rew["agent_0"] == -11.0


def test_stay_is_never_a_wall_hit(make_env):
    env, _ = make_env(CORRIDOR, [(0, 0)])
    _, rew, _, _, info = act(env, STAY)
    assert info["agent_0"]["wall_hits"] == 0
    assert rew["agent_0"] == -1.0  # own cell was visited at reset: only the step cost


def test_new_cell_reward_and_counters(make_env):
    env, _ = make_env(CORRIDOR, [(0, 0)])
    _, rew, _, _, info = act(env, DOWN)
    assert rew["agent_0"] == 2.0 - 1.0
    assert info["agent_0"]["new_cells"] == 1
    _, rew, _, _, info = act(env, UP)  # back onto a visited cell
    assert rew["agent_0"] == -1.0
    assert info["agent_0"]["new_cells"] == 1
    assert info["agent_0"]["steps"] == 2


def test_custom_reward_weights(make_env):
    env, _ = make_env(CORRIDOR, [(0, 0)], rewards={"new_cell": 1.0, "step": 0.0})
    _, rew, *_ = act(env, DOWN)
    assert rew["agent_0"] == 1.0
    _, rew, *_ = act(
        env,
        RIGHT,
    )  # (1, 1) is new
    _, rew, *_ = act(env, UP)  # (0, 1) is a wall
    assert rew["agent_0"] == -10.0


def test_two_agents_into_one_new_cell_credit_the_lower_index(make_env):
    env, _ = make_env(OPEN_3X3, [(0, 1), (2, 1)])
    _, rew, _, _, info = act(env, DOWN, UP)  # both enter (1, 1)
    assert env.positions.tolist() == [[1, 1], [1, 1]]  # agents may share a cell
    assert info["agent_0"]["new_cells"] == 1 and info["agent_1"]["new_cells"] == 0
    assert rew == {"agent_0": 1.0, "agent_1": -1.0}
    assert env.credited_by[1, 1] == 0


def test_team_shares_one_visited_map(make_env):
    env, _ = make_env(OPEN_3X3, [(0, 0), (2, 2)])
    act(env, RIGHT, STAY)  # agent_0 visits (0, 1)
    act(env, STAY, UP)  # agent_1 visits (1, 2)
    _, rew, _, _, info = act(env, STAY, LEFT)  # agent_1 -> (1, 1): new
    assert rew["agent_1"] == 1.0
    act(env, STAY, UP)  # agent_1 -> (0, 1): visited by agent_0 before
    _, _, _, _, info = act(env, STAY, STAY)
    assert info["agent_1"]["new_cells"] == 2
    assert env.visited.sum() == 5  # two starts + (0,1), (1,2), (1,1)
    assert info["agent_0"]["coverage"] == pytest.approx(5 / 9)


def test_start_cells_are_visited_and_count_towards_coverage(make_env):
    env, _ = make_env(CORRIDOR, [(0, 0), (1, 3)])
    assert env.visited[0, 0] and env.visited[1, 3]
    assert env.free_cells == 7
    assert env.coverage == pytest.approx(2 / 7)


def test_moves_resolve_in_agent_order_with_credit_to_first_entrant(make_env):
    # agent_1 comes first in the action dict; the env still resolves agent_0 first.
    env, _ = make_env(OPEN_3X3, [(1, 0), (1, 2)])
    obs, rew, _, _, info = env.step({"agent_1": LEFT, "agent_0": RIGHT})
    assert info["agent_0"]["new_cells"] == 1 and info["agent_1"]["new_cells"] == 0


def test_observation_window_values(make_env):
    env, obs = make_env(CORRIDOR, [(0, 0)])
    window = obs["agent_0"][:9].reshape(3, 3)
    # Row above and column left are outside the grid (1); (0,1) is a wall; own cell visited (0).
    expected = np.array([[1, 1, 1], [1, 0, 1], [1, -1, -1]], dtype=np.float32)
    assert np.array_equal(window, expected)
    obs, *_ = act(env, DOWN)
    window = obs["agent_0"][:9].reshape(3, 3)
    assert np.array_equal(window, np.array([[1, 0, 1], [1, 0, -1], [1, 1, 1]], dtype=np.float32))


def test_normalized_and_raw_coordinates(make_env):
    text = "\n".join(["....."] * 3)
    env, obs = make_env(text, [(2, 3), (0, 1)])
    np.testing.assert_allclose(obs["agent_0"][9:11], [2 / 2, 3 / 4])
    np.testing.assert_allclose(obs["agent_0"][11:13], [0 / 2, 1 / 4])
    env, obs = make_env(text, [(2, 3), (0, 1)], coords="raw")
    np.testing.assert_array_equal(obs["agent_0"][9:13], [2, 3, 0, 1])
    assert env.observation_space("agent_0").high[9:11].tolist() == [2, 4]


def test_nearest_teammate_ties_go_to_the_lower_index(make_env):
    text = "\n".join(["....."] * 5)
    # agent_0 at the centre; agent_1 and agent_2 at distance 2, agent_3 at distance 2 as well.
    env, obs = make_env(text, [(2, 2), (0, 2), (2, 4), (4, 2)], coords="raw")
    np.testing.assert_array_equal(obs["agent_0"][11:13], [0, 2])  # agent_1
    np.testing.assert_array_equal(obs["agent_1"][11:13], [2, 2])  # agent_0 is nearest (2 vs ~2.83)
    # agent_2's distances: agent_0 = 2, agent_1 = agent_3 = sqrt(8): agent_0.
    np.testing.assert_array_equal(obs["agent_2"][11:13], [2, 2])


def test_nearest_teammate_is_euclidean_not_manhattan(make_env):
    text = "\n".join(["......"] * 6)
    # From (0,0): agent_1 at (2,2) is Euclidean 2.83 / Manhattan 4; agent_2 at (0,3) is 3 / 3.
    env, obs = make_env(text, [(0, 0), (2, 2), (0, 3)], coords="raw")
    np.testing.assert_array_equal(obs["agent_0"][11:13], [2, 2])


def test_single_agent_sees_itself_as_teammate(make_env):
    env, obs = make_env(OPEN_3X3, [(1, 2)], coords="raw")
    np.testing.assert_array_equal(obs["agent_0"][9:13], [1, 2, 1, 2])


def test_truncation_after_max_steps_with_timelimit_info(make_env):
    env, _ = make_env(OPEN_3X3, [(0, 0), (2, 2)], max_steps=3)
    for step in range(1, 4):
        _, _, term, trunc, info = act(env, STAY, STAY)
        assert term == {"agent_0": False, "agent_1": False}
        assert all(v == (step == 3) for v in trunc.values())
        assert all(("TimeLimit.truncated" in i) == (step == 3) for i in info.values())
    assert info["agent_0"]["TimeLimit.truncated"] is True
    assert env.agents == []
    with pytest.raises(RuntimeError, match="reset"):
        act(env, STAY, STAY)


def test_random_starts_are_distinct_free_cells():
    env = coverage_v0.parallel_env(height=6, width=6, n_agents=4, wall_fraction=(0.3, 0.3))
    for seed in range(20):
        env.reset(seed=seed)
        pos = env.positions
        assert len({tuple(p) for p in pos.tolist()}) == 4
        assert not env.walls[pos[:, 0], pos[:, 1]].any()


def test_fixed_starts_from_constructor_are_used_every_reset():
    env = coverage_v0.parallel_env(map="maze_100x50", n_agents=2, starts=[(1, 3), (1, 4)])
    for seed in (0, 1):
        env.reset(seed=seed)
        assert env.positions.tolist() == [[1, 3], [1, 4]]


def test_state_views_are_read_only(make_env):
    env, _ = make_env(OPEN_3X3, [(0, 0)])
    with pytest.raises(ValueError):
        env.walls[0, 0] = True
    env.positions[0, 0] = 2  # a copy: does not move the agent
    assert env.positions.tolist() == [[0, 0]]


def test_render_rgb_array_and_ansi(make_env):
    env, _ = make_env(CORRIDOR, [(0, 0), (1, 3)], render_mode="rgb_array")
    img = env.render()
    assert img.dtype == np.uint8 and img.shape == (2 * 8, 4 * 8, 3)
    # The two agents have different colours, and a wall differs from a free cell.
    assert not np.array_equal(img[0, 0], img[8, 24])
    assert not np.array_equal(img[0, 8], img[8, 8])
    env, _ = make_env(CORRIDOR, [(0, 0), (1, 3)], render_mode="ansi")
    act(env, DOWN, STAY)
    assert env.render() == " #..\n0..1"


def test_no_render_mode_renders_nothing(make_env):
    env, _ = make_env(CORRIDOR, [(0, 0)])
    assert env.render() is None


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n_agents": 0}, "n_agents"),
        ({"max_steps": -5}, "max_steps"),
        ({"height": 0}, "height"),
        ({"wall_fraction": (0.2, 1.0)}, "wall_fraction"),
        ({"wall_fraction": (0.3, 0.2)}, "wall_fraction"),
        ({"wall_fraction": 0.2}, "wall_fraction"),
        ({"observation": "pixels"}, "observation"),
        ({"coords": "polar"}, "coords"),
        ({"rewards": {"new_cel": 1.0}}, "new_cel"),
        ({"render_mode": "human"}, "render_mode"),
        ({"map": "no_such_map"}, "no_such_map"),
        ({"height": 2, "width": 2, "n_agents": 5}, "n_agents"),
        ({"starts": [(0, 0)], "n_agents": 2}, "start"),
        ({"starts": [(0, 0), (0, 0)], "n_agents": 2}, "distinct"),
        ({"starts": [(0, 99)], "n_agents": 1, "height": 5, "width": 5}, "off the"),
        ({"map": "cave_100x50", "starts": [(0, 0)], "n_agents": 1}, "wall"),
    ],
)
def test_bad_constructor_input_raises_value_error(kwargs, message):
    with pytest.raises(ValueError, match=message):
        coverage_v0.parallel_env(**kwargs)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"starts": [(0, 1)]}, "wall"),
        ({"starts": [(5, 0)]}, "off the"),
        ({"starts": [(0, 0), (1, 0)]}, "start cell"),
        ({"grid": np.ones((2, 4), dtype=bool)}, "no free cell"),
        ({"grid": np.zeros((3, 3), dtype=bool)}, "shape"),
        ({"grid": np.zeros(8, dtype=bool)}, "2D"),
        ({"starts": "corner"}, "pairs"),
    ],
)
def test_bad_reset_options_raise_value_error(make_env, options, message):
    env, _ = make_env(CORRIDOR, [(0, 0)])
    with pytest.raises(ValueError, match=message):
        env.reset(options={"grid": grid_from(CORRIDOR), **options})


def test_grid_with_fewer_free_cells_than_agents_is_rejected(make_env):
    env, _ = make_env(CORRIDOR, [(0, 0), (1, 0)])
    grid = np.ones((2, 4), dtype=bool)
    grid[0, 0] = False
    with pytest.raises(ValueError, match="fewer than n_agents"):
        env.reset(options={"grid": grid})


def test_missing_or_out_of_range_action_raises(make_env):
    env, _ = make_env(OPEN_3X3, [(0, 0), (2, 2)])
    with pytest.raises(ValueError, match="agent_1"):
        env.step({"agent_0": STAY})
    with pytest.raises(ValueError, match=r"0\.\.4"):
        act(env, 5, 0)
