"""The team-map observation (``observation={"teammap": {...}}``) and the planner extension
(``frontier={...}``) on it: hand-built grids, crop padding at the border, pooling of maps of any
size, the incremental arrays against a from-scratch recomputation, old configs that still load,
and PettingZoo's own API and seed tests."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo.test import parallel_api_test, parallel_seed_test

from envs import coverage_v0
from envs.coverage.env import CoverageEnv
from envs.coverage.frontier import PLANNERS, Frontier, FrontierOptions
from envs.coverage.observations import TeamMap, TeamMapObservation
from harness.config.loading import config_from_dict, load_config
from harness.config.schema import ConfigError, EnvConfig
from tests.conftest import grid_from

UP, DOWN, LEFT, RIGHT, STAY = range(5)
ROOM = """
#######
#.....#
#.#...#
#.....#
#######
"""


def teammap_env(text: str, starts: list[tuple[int, int]], frontier=None, **options):
    """An env with the team map (``options``: crop, global_size, ego_size, ego_block) reset on
    the text grid with fixed start cells."""
    grid = grid_from(text)
    env = coverage_v0.parallel_env(
        height=grid.shape[0],
        width=grid.shape[1],
        n_agents=len(starts),
        observation={"teammap": options},
        frontier=frontier,
    )
    obs, _ = env.reset(seed=0, options={"grid": grid, "starts": starts})
    return env, obs


def reference(env, crop: int, g: int) -> dict[str, np.ndarray]:
    """The observation computed from scratch from the env's public state (slow and plain)."""
    walls, visited, known = env.walls, env.visited, env.known
    height, width = walls.shape
    cat = np.full((height, width), 3)  # unknown
    cat[known & walls] = 0
    cat[known & visited] = 1
    cat[known & ~walls & ~visited] = 2
    half = crop // 2
    positions = env.positions
    n = len(positions)
    local = np.zeros((n, 5, crop, crop), dtype=np.uint8)
    for i, (r, c) in enumerate(positions):
        for dr in range(-half, half + 1):
            for dc in range(-half, half + 1):
                rr, cc = r + dr, c + dc
                k = cat[rr, cc] if 0 <= rr < height and 0 <= cc < width else 0
                local[i, k, dr + half, dc + half] = 255
        for j, (r2, c2) in enumerate(positions):
            if j != i and abs(r2 - r) <= half and abs(c2 - c) <= half:
                local[i, 4, r2 - r + half, c2 - c + half] = 255
    glob = np.zeros((n, 6, g, g), dtype=np.uint8)
    rows = [range(i * height // g, (i + 1) * height // g) for i in range(g)]
    cols = [range(j * width // g, (j + 1) * width // g) for j in range(g)]
    for bi, rr in enumerate(rows):
        for bj, cc in enumerate(cols):
            block = cat[np.ix_(list(rr), list(cc))]
            if block.size == 0:
                glob[:, 3, bi, bj] = 255
                continue
            for channel, k in enumerate((1, 2, 3, 0)):
                glob[:, channel, bi, bj] = round(255 * (block == k).mean())
    block_of = [
        (
            next(b for b, rr in enumerate(rows) if r in rr),
            next(b for b, cc in enumerate(cols) if c in cc),
        )
        for r, c in positions
    ]
    for i, (bi, bj) in enumerate(block_of):
        glob[i, 4, bi, bj] = 255
        for j, (bi2, bj2) in enumerate(block_of):
            if j != i:
                glob[i, 5, bi2, bj2] = 255
    vector = np.array(
        [[r / (height - 1), c / (width - 1), env.steps / env.max_steps] for r, c in positions],
        dtype=np.float32,
    )
    return {"local": local, "global": glob, "vector": vector}


def reference_ego(env, e: int, b: int) -> np.ndarray:
    """The ego views computed cell by cell from the env's public state (slow and plain)."""
    walls, visited, known = env.walls, env.visited, env.known
    height, width = walls.shape
    cat = np.full((height, width), 3)
    cat[known & walls] = 0
    cat[known & visited] = 1
    cat[known & ~walls & ~visited] = 2
    positions = env.positions
    out = np.zeros((len(positions), 5, e, e), dtype=np.uint8)
    for i, (r, c) in enumerate(positions):
        for bi in range(e):
            for bj in range(e):
                top, left = r + (bi - e // 2) * b - b // 2, c + (bj - e // 2) * b - b // 2
                counts = np.zeros(4)
                for rr in range(top, top + b):
                    for cc in range(left, left + b):
                        inside = 0 <= rr < height and 0 <= cc < width
                        counts[cat[rr, cc] if inside else 0] += 1
                for channel, k in enumerate((1, 2, 3, 0)):
                    out[i, channel, bi, bj] = round(255 * counts[k] / b**2)
        for j, (r2, c2) in enumerate(positions):
            bi, bj = (r2 - r + b // 2) // b + e // 2, (c2 - c + b // 2) // b + e // 2
            if j != i and 0 <= bi < e and 0 <= bj < e:
                out[i, 4, bi, bj] = 255
    return out


def check(env, obs, crop: int = 15, g: int = 13, ego: tuple[int, int] | None = None) -> None:
    expected = reference(env, crop, g)
    if ego is not None:
        expected["ego"] = reference_ego(env, *ego)
    for i, agent in enumerate(env.possible_agents):
        assert ("ego" in obs[agent]) == (ego is not None)
        for key in ("local", "global", "ego")[: 3 if ego else 2]:
            np.testing.assert_array_equal(obs[agent][key], expected[key][i], err_msg=key)
        np.testing.assert_allclose(obs[agent]["vector"], expected["vector"][i], rtol=1e-6)


def test_known_cells_after_a_few_moves_on_a_hand_built_grid():
    env, obs = teammap_env(ROOM, [(1, 1)], crop=5, global_size=7)
    local = obs["agent_0"]["local"]
    # The crop is centred on (1, 1): its centre is visited, the 3x3 window around it is known.
    assert local[1, 2, 2] == 255  # visited
    assert local[0, 1, 1] == 255 and local[0, 1, 3] == 255  # walls at (0, 0) and (0, 2)
    assert local[2, 3, 3] == 0 and local[0, 3, 3] == 255  # (2, 2) is a wall, now known
    assert local[2, 2, 3] == 255  # (1, 2): known free, not visited
    assert local[3, 2, 4] == 255  # (1, 3): outside the window, unknown
    assert local[0, 0, 0] == 255  # row -1: outside the grid, known wall
    obs, *_ = env.step({"agent_0": RIGHT})
    obs, *_ = env.step({"agent_0": RIGHT})  # now at (1, 3)
    local = obs["agent_0"]["local"]
    assert local[1, 2, 1] == 255 and local[1, 2, 0] == 255  # (1, 2), (1, 1) visited
    assert local[2, 2, 3] == 255  # (1, 4) known free
    assert local[3, 4, 4] == 255  # (3, 5): still unknown
    assert env.known.sum() == 15  # columns 0..4 of rows 0..2
    check(env, obs, crop=5, g=7)


LOOP = """
#########
#.......#
#.#####.#
#.......#
#########
"""


def test_frontier_field_and_compass_on_a_hand_built_grid():
    env, obs = teammap_env(LOOP, [(1, 1)], crop=7, global_size=7, frontier={})
    o = obs["agent_0"]
    assert o["local"].shape == (6, 7, 7) and o["frontier"].shape == (5,)
    # Known after the start: the 3x3 window of (1, 1); unvisited known free: (1, 2) and (2, 1),
    # one step away (d = 1): down and right lead there, up and left are walls.
    np.testing.assert_allclose(o["frontier"], [0, 1, 0, 1, 1 / (5 + 9)])
    field = o["local"][5]  # crop centre (3, 3) is the agent's cell (1, 1)
    assert field[3, 3] == 128  # d(agent) - d(agent) = 0
    assert field[3, 4] == field[4, 3] == 128 + 16  # d = 0: one step nearer
    assert field.astype(int).sum() == 128 + 2 * 144  # walls and unknown cells are 0
    for _ in range(3):
        obs, *_ = env.step({"agent_0": RIGHT})
    # At (1, 4): row 1 visited up to column 4, known up to column 5; the unvisited known free
    # cells are (1, 5) (d = 1 from here, to the right) and (2, 1) (4 steps back).
    o = obs["agent_0"]
    np.testing.assert_allclose(o["frontier"], [0, 0, 0, 1, 1 / 14])
    field = o["local"][5]
    row = [int(v) for v in field[3, :]]  # columns 1 .. 7 of the map; (1, 6) still unknown
    # d: (1,1)=1 via (2,1), (1,2)=2, (1,3)=2, (1,4)=1, (1,5)=0, (1,6) unknown, (1,7) unknown.
    assert row == [128, 112, 112, 128, 144, 0, 0]
    assert field[4, 0] == 144  # (2, 1): a frontier cell, d = 0
    assert (field[4, 1:] == 0).all()  # row 2, columns 2..7: walls or unknown


FRONTIER_STEP = 5


def test_frontier_step_follows_the_compass_and_stays_when_none_is_left():
    env, obs = teammap_env(LOOP, [(1, 1)], crop=7, global_size=7, frontier={"action": "step"})
    assert env.action_space("agent_0").n == 6
    # At (1, 1) the compass marks down and right (both one step from a frontier cell): a tie,
    # drawn from the episode's generator.
    obs, *_ = env.step({"agent_0": FRONTIER_STEP})
    assert tuple(env.positions[0]) in {(2, 1), (1, 2)}
    for _ in range(40):  # the compass walks the whole loop: every free cell is visited
        obs, *_ = env.step({"agent_0": FRONTIER_STEP})
    assert env.coverage == 1.0 and env.visited.sum() == env.free_cells
    assert obs["agent_0"]["frontier"][:4].sum() == 0 and obs["agent_0"]["frontier"][4] == 1
    held = tuple(env.positions[0])
    env.step({"agent_0": FRONTIER_STEP})  # nothing left: the frontier step stays
    assert tuple(env.positions[0]) == held
    _, rewards, *_ = env.step({"agent_0": FRONTIER_STEP})
    assert rewards["agent_0"] == -1.0  # a step's cost, never a wall hit


def test_frontier_step_ties_repeat_with_the_episode_seed():
    def walk(seed: int) -> list[tuple[int, int]]:
        env = coverage_v0.parallel_env(
            height=20,
            width=20,
            n_agents=3,
            observation={"teammap": {"crop": 7}},
            frontier={"action": "step"},
            max_steps=60,
        )
        env.reset(seed=seed)
        path = []
        while env.agents:
            env.step(dict.fromkeys(env.agents, FRONTIER_STEP))
            path += [tuple(p) for p in env.positions.tolist()]
        return path

    assert walk(3) == walk(3)
    assert walk(3) != walk(4)


CORRIDOR = """
#########
#.......#
#########
"""


def test_frontier_claims_keep_a_teammate_from_following_into_a_dead_end():
    # Agent 1 at (1, 1) is behind agent 0 at (1, 2) in a corridor closed on the left: the one
    # unvisited known cell is (1, 3), one step from agent 0, two from agent 1.
    starts = [(1, 2), (1, 1)]
    plain, obs_plain = teammap_env(CORRIDOR, starts, crop=7, global_size=7, frontier={})
    for a, d in (("agent_0", 1), ("agent_1", 2)):  # without claims both head right
        np.testing.assert_allclose(obs_plain[a]["frontier"], [0, 0, 0, 1, d / 12])
    env, obs = teammap_env(
        CORRIDOR, starts, crop=7, global_size=7, frontier={"action": "step", "planner": "order"}
    )
    # With claims agent 0 takes (1, 3); nothing is left for agent 1, so no move is marked (its
    # step stays), and the distance is still the nearest cell's.
    np.testing.assert_allclose(obs["agent_0"]["frontier"], [0, 0, 0, 1, 1 / 12])
    np.testing.assert_allclose(obs["agent_1"]["frontier"], [0, 0, 0, 0, 2 / 12])
    np.testing.assert_array_equal(obs["agent_1"]["local"], obs_plain["agent_1"]["local"])
    while env.coverage < 1.0:
        env.step({"agent_0": FRONTIER_STEP, "agent_1": FRONTIER_STEP})
        assert tuple(env.positions[1]) == (1, 1)  # it waits rather than follow
    assert env.steps == 5 and tuple(env.positions[0]) == (1, 7)
    obs, *_ = env.step({"agent_0": FRONTIER_STEP, "agent_1": FRONTIER_STEP})
    assert obs["agent_0"]["frontier"][:4].sum() == 0  # nothing left: no move marked, stay


@pytest.mark.parametrize(("n_agents", "planner"), [(1, "order"), (3, "order"), (3, "pocket")])
def test_always_stepping_with_a_planner_is_the_frontier_explorer(n_agents, planner):
    from harness.evaluation.baselines import make_baseline
    from harness.evaluation.episodes import run_episodes

    size = {"height": 18, "width": 22, "n_agents": n_agents, "max_steps": 120}
    steps = EnvConfig(
        **size,
        observation={"teammap": {"crop": 7}},
        frontier={"action": "step", "planner": planner},
    )
    stepped = run_episodes(make_baseline("frontier_step", 0), steps, episodes=3, seed=5)
    baseline = {"order": "frontier", "pocket": "frontier_pocket"}[planner]
    assert baseline == PLANNERS[planner].baseline
    planned = run_episodes(make_baseline(baseline, 0), EnvConfig(**size), episodes=3, seed=5)
    assert [r.coverage for r in stepped] == [r.coverage for r in planned]
    assert [r.new_cells for r in stepped] == [r.new_cells for r in planned]
    assert all(sum(r.wall_hits) == 0 for r in stepped)


def test_always_taking_the_step_with_the_pocket_planner_plays_the_frontier_pocket_moves():
    # Move for move, not only the same totals: the env's step with frontier.planner: pocket is
    # the frontier_pocket baseline's move for every agent at every step.
    from harness.evaluation.baselines import make_baseline

    def make(**kwargs) -> CoverageEnv:
        return coverage_v0.parallel_env(height=18, width=22, n_agents=3, max_steps=150, **kwargs)

    stepped = make(
        observation={"teammap": {"crop": 7}}, frontier={"action": "step", "planner": "pocket"}
    )
    planned = make()  # the thesis observation, no planner extension
    baseline = make_baseline("frontier_pocket", 0)
    for seed in (5, 6):
        stepped.reset(seed=seed)
        obs, _ = planned.reset(seed=seed)
        np.testing.assert_array_equal(stepped.walls, planned.walls)
        np.testing.assert_array_equal(stepped.positions, planned.positions)
        while planned.agents:
            moves = baseline(np.stack([obs[a] for a in planned.agents]), [planned])
            obs, *_ = planned.step(dict(zip(planned.agents, moves.tolist())))
            _, _, _, _, infos = stepped.step(dict.fromkeys(stepped.agents, FRONTIER_STEP))
            np.testing.assert_array_equal(stepped.positions, planned.positions)
            assert all(info["wall_hits"] == 0 for info in infos.values())
        assert not stepped.agents and stepped.coverage == planned.coverage
        np.testing.assert_array_equal(stepped.credited_by, planned.credited_by)


def test_the_frontier_planner_needs_the_team_map_and_a_known_name():
    # The planner (the old frontier_claims) is part of the frontier option: it cannot be asked
    # for without the compass, which needs the team map.
    with pytest.raises(ValueError, match="frontier needs the teammap observation"):
        coverage_v0.parallel_env(frontier={"planner": "order"})  # the thesis observation
    with pytest.raises(ValueError, match=r"frontier\.planner: unknown planner 'yes'"):
        coverage_v0.parallel_env(observation="teammap", frontier={"planner": "yes"})
    with pytest.raises(ValueError, match="frontier needs the teammap observation"):
        EnvConfig(frontier={"planner": "order"})
    with pytest.raises(ValueError, match=r"frontier\.planner: unknown planner 'yes'"):
        EnvConfig(observation={"teammap": {"crop": 7}}, frontier={"planner": "yes"})
    # A planner without a planner-backed action: the compass marks its move, five actions.
    env = coverage_v0.parallel_env(observation="teammap", frontier={"planner": "order"})
    assert env.action_space("agent_0").n == 5


def test_the_env_planner_choices_are_the_registry_s_in_env_planners():
    in_env = [name for name, entry in PLANNERS.items() if entry.in_env]
    assert in_env == ["order", "pocket", "utility", "minpos", "hungarian"]
    baseline_only = (
        "frontier.planner: 'random' draws its ties from a generator: it is a baseline only"
    )
    with pytest.raises(ValueError, match=baseline_only):
        coverage_v0.parallel_env(
            observation="teammap", frontier={"action": "step", "planner": "random"}
        )
    # The config offers exactly the env's choices.
    for name in PLANNERS:
        frontier = {"action": "step", "planner": name}
        if name in in_env:
            env = EnvConfig(observation={"teammap": {"crop": 7}}, frontier=frontier)
            assert env.frontier == frontier
            assert env.frontier_options == FrontierOptions(action="step", planner=name)
        else:
            with pytest.raises(ValueError, match=baseline_only):
                EnvConfig(observation={"teammap": {"crop": 7}}, frontier=frontier)


def frontier_distances(env) -> np.ndarray:
    """Shortest path lengths through known free cells to the nearest known free unvisited cell
    (a plain breadth-first search on the env's public state; inf where none is reachable)."""
    passable = env.known & ~env.walls
    frontier = passable & ~env.visited
    dist = np.full(passable.shape, np.inf)
    queue = [tuple(c) for c in np.argwhere(frontier)]
    for c in queue:
        dist[c] = 0
    while queue:
        nxt = []
        for r, c in queue:
            for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
                inside = 0 <= rr < dist.shape[0] and 0 <= cc < dist.shape[1]
                if inside and passable[rr, cc] and dist[rr, cc] == np.inf:
                    dist[rr, cc] = dist[r, c] + 1
                    nxt.append((rr, cc))
        queue = nxt
    return dist


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_frontier_views_equal_a_search_through_known_cells_only(seed):
    # The env searches all free cells (built once per episode); unknown ground must never make a
    # path shorter than the one through known cells.
    crop, height, width = 9, 23, 31
    env = coverage_v0.parallel_env(
        height=height,
        width=width,
        n_agents=3,
        observation={"teammap": {"crop": crop}},
        frontier={},
        max_steps=400,
    )
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    half = crop // 2
    for t in range(400):
        if t % 10 == 0:
            dist = frontier_distances(env)
            for i, (r, c) in enumerate(env.positions):
                o = obs[f"agent_{i}"]
                own = dist[r, c]
                for k, (dr, dc) in enumerate(((-1, 0), (1, 0), (0, -1), (0, 1))):
                    rr, cc = r + dr, c + dc
                    inside = 0 <= rr < height and 0 <= cc < width
                    assert o["frontier"][k] == (inside and dist[rr, cc] == own - 1)
                assert o["frontier"][4] == pytest.approx(min(own / (height + width), 1.0))
                field = o["local"][5]
                for dr in range(-half, half + 1):
                    for dc in range(-half, half + 1):
                        rr, cc = r + dr, c + dc
                        inside = 0 <= rr < height and 0 <= cc < width
                        d = dist[rr, cc] if inside else np.inf
                        want = (
                            0
                            if d == np.inf or own == np.inf
                            else min(max(128 + 16 * (own - d), 1), 255)
                        )
                        assert field[dr + half, dc + half] == want
        obs, *_ = env.step({a: int(rng.integers(5)) for a in env.agents})


def test_crop_is_padded_with_known_wall_at_the_border():
    env, obs = teammap_env(ROOM, [(3, 5)], crop=9, global_size=7)
    local = obs["agent_0"]["local"]
    # Rows 8 .. 7 of the crop lie below the grid (row 3 + 4 > 4), columns past 6 right of it.
    assert (local[0, 6:, :] == 255).all()  # rows 5..7 of the map do not exist
    assert (local[0, :, 7:] == 255).all()
    assert (local[1:4, 6:, :] == 0).all()
    check(env, obs, crop=9, g=7)


def test_teammates_in_the_crop_and_on_the_global_view():
    env, obs = teammap_env(ROOM, [(1, 1), (3, 4), (1, 5)], crop=5, global_size=7)
    a0 = obs["agent_0"]
    assert a0["local"][4].sum() == 0  # (3, 4) and (1, 5) are 3 and 4 cells away: outside 5x5
    a1 = obs["agent_1"]["local"]
    assert a1[4, 0, 3] == 255  # agent_2 at (1, 5) is (-2, +1) from (3, 4)
    assert a1[4].sum() == 255
    assert (obs["agent_2"]["global"][5] > 0).sum() == 2  # two teammates' blocks
    check(env, obs, crop=5, g=7)


def test_ego_view_on_a_hand_built_grid():
    # ROOM is 5x7; an ego view of 5x5 blocks of 3x3 cells, centred on the agent at (1, 1).
    env, obs = teammap_env(ROOM, [(1, 1), (3, 5)], crop=5, global_size=7, ego_size=5, ego_block=3)
    ego = obs["agent_0"]["ego"]
    assert ego.shape == (5, 5, 5)
    # The centre block is the agent's 3x3 window: rows 0..2, columns 0..2, all known: walls
    # (0,0) (0,1) (0,2) (1,0) (2,0) (2,2), visited (1,1), known free (1,2) (2,1).
    assert ego[3, 2, 2] == round(255 * 6 / 9) and ego[0, 2, 2] == round(255 / 9)
    assert ego[1, 2, 2] == round(255 * 2 / 9) and ego[2, 2, 2] == 0
    # The block to its right: rows 0..2, columns 3..5. Only agent_1's window (rows 2..4,
    # columns 4..6) reaches it: (2, 4) and (2, 5) are known free; the other 7 cells are unknown
    # (the walls of row 0 too: nobody has seen them yet).
    assert ego[0, 2, 3] == 0 and ego[1, 2, 3] == round(255 * 2 / 9)
    assert ego[2, 2, 3] == round(255 * 7 / 9) and ego[3, 2, 3] == 0
    # Blocks above and left lie outside the grid: known wall.
    assert (ego[3, :2, :] == 255).all() and (ego[3, :, :2] == 255).all()
    # agent_1 at (+2, +4) from agent_0: block (2 + (2+1)//3, 2 + (4+1)//3) = (3, 3).
    assert ego[4, 3, 3] == 255 and ego[4].sum() == 255
    check(env, obs, crop=5, g=7, ego=(5, 3))
    obs, *_ = env.step({"agent_0": RIGHT, "agent_1": STAY})
    check(env, obs, crop=5, g=7, ego=(5, 3))


@pytest.mark.parametrize("seed", [0, 1])
def test_ego_view_equals_a_cell_by_cell_recomputation_after_many_steps(seed):
    env = coverage_v0.parallel_env(
        height=23,
        width=31,
        n_agents=3,
        observation={"teammap": {"crop": 7, "ego_size": 7, "ego_block": 5}},
        max_steps=200,
    )
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for t in range(200):
        if t % 50 == 0:
            check(env, obs, crop=7, ego=(7, 5))
        obs, *_ = env.step({a: int(rng.integers(5)) for a in env.agents})


def test_pooling_of_a_100x50_map_matches_the_hand_computed_blocks():
    env = coverage_v0.parallel_env(
        map="cave_100x50", n_agents=2, observation="teammap", max_steps=200
    )
    obs, _ = env.reset(seed=4)
    rng = np.random.default_rng(1)
    for _ in range(120):
        obs, *_ = env.step({a: int(rng.integers(5)) for a in env.agents})
    assert obs["agent_0"]["global"].shape == (6, 13, 13)
    check(env, obs)
    # Blocks split 50 rows and 100 columns as evenly as the integer cuts allow.
    shares = obs["agent_0"]["global"][:4].astype(int)
    assert (np.abs(shares.sum(axis=0) - 255) <= 2).all()  # the four shares add up to 1


def test_pooling_of_an_open_100x50_map_by_hand():
    # 50 rows, 100 columns, G = 13: block 0 holds rows 0..2 and columns 0..6 (21 cells); block 1
    # rows 3..6 (28 cells with column block 0); block 12 rows 46..49 and columns 92..99 (32 cells).
    grid = np.zeros((50, 100), dtype=bool)
    grid[0, 2] = True
    env = coverage_v0.parallel_env(height=50, width=100, n_agents=2, observation="teammap")
    obs, _ = env.reset(seed=0, options={"grid": grid, "starts": [(1, 1), (48, 98)]})
    glob = obs["agent_0"]["global"].astype(int)  # channels visited, known free, unknown, wall
    # Block (0, 0): 9 cells known around (1, 1): 1 visited, 1 wall (0, 2), 7 free; 12 unknown.
    assert glob[:4, 0, 0].tolist() == [12, 85, 146, 12]  # round(255 * k / 21)
    # Block (12, 12): 9 cells known around (48, 98): 1 visited, 8 free; 23 unknown.
    assert glob[:4, 12, 12].tolist() == [8, 64, 183, 0]  # round(255 * k / 32)
    assert glob[:4, 1, 0].tolist() == [0, 0, 255, 0]
    assert glob[2].sum() == 255 * (169 - 2) + 146 + 183 and glob[3].sum() == 12  # the rest unknown
    assert np.argwhere(glob[4]).tolist() == [[0, 0]] and np.argwhere(glob[5]).tolist() == [[12, 12]]
    other = obs["agent_1"]["global"]
    assert np.argwhere(other[4]).tolist() == [[12, 12]] and np.argwhere(other[5]).tolist() == [
        [0, 0]
    ]
    obs, *_ = env.step({"agent_0": DOWN, "agent_1": STAY})  # agent_0 to (2, 1): sees row 3
    glob = obs["agent_0"]["global"].astype(int)
    assert glob[:4, 0, 0].tolist() == [24, 73, 146, 12]  # 2 visited, 6 free, 12 unknown, 1 wall
    assert glob[:4, 1, 0].tolist() == [0, 27, 228, 0]  # 3 of 28 known free
    check(env, obs)


def test_teammates_in_one_block_see_it_as_a_teammates_block():
    open_room = "\n".join(["." * 12] * 10)
    env, obs = teammap_env(open_room, [(1, 2), (2, 3), (8, 11)], crop=5, global_size=6)
    # 10 rows in 6 blocks start at rows 0, 1, 3, 5, 6, 8; 12 columns at 0, 2, 4, 6, 8, 10:
    # (1, 2) and (2, 3) share block (1, 1); (8, 11) is in block (5, 5).
    for agent in ("agent_0", "agent_1"):
        glob = obs[agent]["global"]
        assert np.argwhere(glob[4]).tolist() == [[1, 1]]
        assert np.argwhere(glob[5]).tolist() == [[1, 1], [5, 5]]
    glob = obs["agent_2"]["global"]
    assert np.argwhere(glob[4]).tolist() == [[5, 5]]
    assert np.argwhere(glob[5]).tolist() == [[1, 1]]
    check(env, obs, crop=5, g=6)


def test_map_smaller_than_the_global_view_has_wall_blocks():
    env, obs = teammap_env(ROOM, [(1, 1)], crop=5, global_size=9)  # 5 rows, 7 columns < 9
    glob = obs["agent_0"]["global"]
    # Block i holds rows floor(i*5/9) .. floor((i+1)*5/9) - 1: blocks 0, 2, 4, 6 hold none, and
    # columns likewise (7 columns): blocks 0 and 4 hold none. Empty blocks count as wall.
    for i in (0, 2, 4, 6):
        assert (glob[3, i, :] == 255).all() and (glob[:3, i, :] == 0).all()
    for j in (0, 4):
        assert (glob[3, :, j] == 255).all()
    # Rows 0..4 fall in blocks 1, 3, 5, 7, 8 and columns 0..6 in 1, 2, 3, 5, 6, 7, 8: the agent
    # at (1, 1) is in block (3, 2).
    assert glob[4, 3, 2] == 255 and glob[4].sum() == 255
    check(env, obs, crop=5, g=9)


def windows_of(positions: list[tuple[int, int]], height: int, width: int) -> np.ndarray:
    """Cells inside the 3x3 window of any of ``positions`` (plain loops)."""
    known = np.zeros((height, width), dtype=bool)
    for r, c in positions:
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if 0 <= r + dr < height and 0 <= c + dc < width:
                    known[r + dr, c + dc] = True
    return known


@pytest.mark.parametrize("seed", [0, 1])
def test_incremental_arrays_equal_a_recomputation_after_many_steps(seed):
    env = coverage_v0.parallel_env(
        height=23, width=31, n_agents=3, observation={"teammap": {"crop": 7}}, max_steps=300
    )
    obs, _ = env.reset(seed=seed)
    held = [tuple(p) for p in env.positions.tolist()]
    rng = np.random.default_rng(seed)
    for t in range(300):
        if t % 60 == 0:
            check(env, obs, crop=7)
            np.testing.assert_array_equal(env.known, windows_of(held, 23, 31))
        obs, *_ = env.step({a: int(rng.integers(5)) for a in env.agents})
        held += [tuple(p) for p in env.positions.tolist()]
    check(env, obs, crop=7)
    np.testing.assert_array_equal(env.known, windows_of(held, 23, 31))
    # A second episode starts from nothing known again.
    obs, _ = env.reset(seed=seed + 10)
    assert env.known.sum() <= 27
    check(env, obs, crop=7)


@pytest.mark.parametrize(
    ("height", "width", "sizes", "frontier"),
    [
        (12, 40, {}, None),
        (4, 5, {"crop": 5, "global_size": 6}, None),
        (12, 40, {"ego_size": 9, "ego_block": 3}, None),
        (12, 40, {"crop": 7}, {}),
    ],
)
def test_observations_lie_in_the_space(height, width, sizes, frontier):
    env = coverage_v0.parallel_env(
        height=height, width=width, n_agents=2, observation={"teammap": sizes}, frontier=frontier
    )
    obs, _ = env.reset(seed=2)
    space = env.observation_space("agent_0")
    rng = np.random.default_rng(0)
    for _ in range(50):
        for o in obs.values():
            assert space.contains(o)
        obs, *_ = env.step({a: int(rng.integers(5)) for a in env.agents})


#: The team map's default sizes, by keyword.
TEAM_MAP_DEFAULTS = {"crop": 15, "global_size": 13, "ego_size": 0, "ego_block": 5}


@pytest.mark.parametrize(
    ("options", "frontier", "message"),
    [
        ({"crop": 4}, None, "crop must be an odd integer in 5..2000, got 4"),
        ({"crop": 3}, None, "crop must be an odd integer in 5..2000, got 3"),
        ({"crop": 7.0}, None, "crop must be an odd integer"),
        ({"global_size": 5}, None, "global_size must be an integer in 6..2000, got 5"),
        ({"global_size": True}, None, "global_size must be an integer"),
        ({"ego_size": 4}, None, "ego_size must be 0 .off. or an odd integer in 5..2000, got 4"),
        ({"ego_size": 3}, None, "ego_size must be 0 .off. or an odd integer in 5..2000, got 3"),
        ({"ego_block": 2}, None, "ego_block must be an odd integer in 1..2000, got 2"),
        ({"crop": 5}, {}, "crop must be an odd integer in 7..2000 with the frontier field, got 5"),
        ({}, 1, "frontier must be null or a mapping with action and planner, got 1"),
        ({}, True, "frontier must be null or a mapping with action and planner, got True"),
        ({}, {"action": "yes"}, "unknown frontier.action 'yes'"),
        ({}, {"claims": True}, r"frontier: unknown key\(s\) \['claims'\]"),
        ({"trail": 3}, None, r"observation 'teammap': unknown option\(s\) \['trail'\]"),
    ],
)
def test_bad_sizes_are_value_errors(options, frontier, message):
    with pytest.raises(ValueError, match=message):
        coverage_v0.parallel_env(observation={"teammap": options}, frontier=frontier)
    if "trail" not in options and (frontier is None or frontier == {}):
        # The builder checks its sizes too, when made by hand (the field: a Frontier object).
        ext = None if frontier is None else Frontier(FrontierOptions(), 9, 9)
        with pytest.raises(ValueError, match=message):
            TeamMapObservation(
                9, 9, "normalized", 100, **{**TEAM_MAP_DEFAULTS, **options}, frontier=ext
            )


def test_the_frontier_action_needs_the_team_map():
    with pytest.raises(ValueError, match="frontier needs the teammap observation"):
        coverage_v0.parallel_env(observation="thesis", frontier={"action": "step"})
    with pytest.raises(ValueError, match="frontier needs the teammap observation"):
        coverage_v0.parallel_env(frontier={})  # the thesis observation is the default


def test_smallest_sizes_are_read_as_channel_first_images_by_sb3():
    # The reason for the bounds: SB3 transposes a uint8 image whose first axis is not the smallest.
    from stable_baselines3.common.preprocessing import (
        is_image_space,
        is_image_space_channels_first,
    )

    space = coverage_v0.parallel_env(
        observation=TeamMap(crop=5, global_size=6, ego_size=5)
    ).observation_space("agent_0")
    for key in ("local", "global", "ego"):
        assert is_image_space(space[key]) and is_image_space_channels_first(space[key])
    # The frontier field's sixth channel needs a crop of 7.
    with_field = coverage_v0.parallel_env(observation=TeamMap(crop=7), frontier={})
    local = with_field.observation_space("agent_0")["local"]
    assert local.shape == (6, 7, 7) and is_image_space_channels_first(local)
    too_small = spaces.Box(0, 255, (5, 3, 3), np.uint8)  # what crop=3 would give
    with pytest.warns(UserWarning, match="channels-last"):
        assert not is_image_space_channels_first(too_small)


@pytest.mark.parametrize(
    ("env_yaml", "message"),
    [
        (
            "{observation: {teammap: {crop: 4}}}",
            r"env.observation: crop must be an odd integer in 5..2000, got 4",
        ),
        (
            "{observation: {teammap: {crop: 3}}}",
            r"env.observation: crop must be an odd integer in 5..2000, got 3",
        ),
        (
            "{observation: {teammap: {global_size: 5}}}",
            r"env.observation: global_size must be an integer in 6..2000, got 5",
        ),
        (
            "{observation: {teammap: {ego_size: 4}}}",
            r"env.observation: ego_size must be 0 \(off\) or an odd integer in 5..2000",
        ),
        (
            "{observation: {teammap: {ego_block: 4}}}",
            r"env.observation: ego_block must be an odd integer in 1..2000, got 4",
        ),
        (
            "{observation: {teammap: {crop: 5}}, frontier: {}}",
            r"env: crop must be an odd integer in 7..2000 with the frontier field",
        ),
        ("{observation: teammap, frontier: 2}", r"env.frontier: Input should be a valid dict"),
        (
            "{observation: teammap, frontier: {planner: nope}}",
            r"env.frontier: frontier.planner: unknown planner 'nope'",
        ),
        (
            "{observation: teammap, frontier: {claims: true}}",
            r"env.frontier: frontier: unknown key\(s\)",
        ),
        ("{frontier: {action: step}}", r"env: frontier needs the teammap observation"),
    ],
)
def test_config_refuses_bad_sizes(tmp_path, env_yaml, message):
    path = tmp_path / "exp.yaml"
    path.write_text(f"name: tm\nenv: {env_yaml}\n")
    with pytest.raises(ConfigError, match=message):
        load_config(path)


def test_config_sizes_reach_the_env(tmp_path):
    from harness.factory import make_env

    path = tmp_path / "exp.yaml"
    path.write_text(
        "name: tm\nenv: {observation: {teammap: {crop: 9, global_size: 8, ego_size: 11}},"
        " frontier: {}}\nalgo: {policy: TeamMapPolicy}\n"
    )
    env = make_env(load_config(path).env)
    space = env.observation_space("agent_0")
    assert space["local"].shape == (6, 9, 9) and space["global"].shape == (6, 8, 8)
    assert space["frontier"].shape == (5,)
    assert env.action_space("agent_0").n == 5
    path.write_text(
        "name: tm\nenv: {observation: teammap, frontier: {action: step}}\n"
        "algo: {policy: TeamMapPolicy}\n"
    )
    env = make_env(load_config(path).env)
    assert env.action_space("agent_0").n == 6
    assert space["ego"].shape == (5, 11, 11)


def test_an_old_config_loads_and_a_retired_knob_turned_on_is_refused():
    old = {
        "observation": "teammap",
        "trail": 0,
        "crop": 9,
        "frontier": True,
        "frontier_action": True,
        "frontier_claims": True,
        "frontier_tie_break": "pocket",
    }

    def load(env: dict) -> EnvConfig:
        return config_from_dict({"env": env, "algo": {"policy": "TeamMapPolicy"}}).env

    env = load(old)
    assert env.observation == {"teammap": {"crop": 9}}
    assert env.frontier == {"action": "step", "planner": "pocket"}
    # The own trail is retired: its old default (0, off) loads, a trail turned on does not.
    with pytest.raises(ConfigError, match=r"env\.trail: 5: .*research/experiment-log\.md"):
        load({**old, "trail": 5})
    # The old flags' rules: the tie-break needed the claims, the claims needed the compass.
    with pytest.raises(ConfigError, match=r"env\.frontier_tie_break needed env\.frontier_claims"):
        load({**old, "frontier_claims": False})
    with pytest.raises(
        ConfigError, match=r"frontier_action and frontier_claims needed env\.frontier"
    ):
        load({**old, "frontier": False})
    with pytest.raises(
        ConfigError, match=r"env: frontier_action are old keys: write env\.frontier"
    ):
        load({"observation": "teammap", "frontier_action": True})


def test_the_env_takes_at_most_13_constructor_arguments():
    parameters = list(inspect.signature(CoverageEnv.__init__).parameters)
    assert parameters[0] == "self"
    assert len(parameters) - 1 <= 13, parameters


def test_parallel_api_and_seed_tests_pass_with_the_team_map():
    parallel_api_test(
        coverage_v0.parallel_env(
            height=14,
            width=17,
            n_agents=3,
            max_steps=60,
            observation={"teammap": {"crop": 7}},
            frontier={},
        ),
        num_cycles=100,
    )
    parallel_seed_test(
        lambda: coverage_v0.parallel_env(
            height=10, width=10, n_agents=2, max_steps=40, observation={"teammap": {"crop": 5}}
        )
    )
