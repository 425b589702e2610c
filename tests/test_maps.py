"""Maps: random maps, the text format and its errors, shipped maps, cave and maze."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from envs import coverage_v0
from envs.coverage import cave, maps, maze
from envs.coverage.cave import generate_cave
from envs.coverage.maze import generate_maze


def n_components(grid: np.ndarray) -> int:
    return maps.label_free_components(grid)[1]


@pytest.mark.parametrize("seed", range(10))
def test_random_maps_are_connected(seed):
    grid = maps.random_grid(30, 40, (0.15, 0.35), np.random.default_rng(seed))
    assert grid.shape == (30, 40)
    assert n_components(grid) == 1


def test_random_maps_are_seeded():
    a = maps.random_grid(25, 25, (0.15, 0.2), np.random.default_rng(3))
    b = maps.random_grid(25, 25, (0.15, 0.2), np.random.default_rng(3))
    c = maps.random_grid(25, 25, (0.15, 0.2), np.random.default_rng(4))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_random_wall_share_is_drawn_from_the_range():
    rng = np.random.default_rng(0)
    for _ in range(50):
        grid = maps.random_grid(50, 50, (0.15, 0.20), rng)
        # Walls placed = round(w * 2500) with w in [0.15, 0.20]; filling pockets only adds walls.
        assert grid.sum() >= round(0.15 * 2500)
    shares = [maps.random_grid(50, 50, (0.15, 0.20), rng).mean() for _ in range(50)]
    assert 0.15 <= np.median(shares) <= 0.24
    assert np.std(shares) > 0.005  # the share varies from map to map


def test_fixed_wall_fraction_places_exactly_that_many_walls_before_filling():
    grid = maps.random_grid(10, 10, (0.0, 0.0), np.random.default_rng(0))
    assert not grid.any()


def test_fill_unreachable_keeps_the_largest_component():
    grid = maps.parse_map("..#.\n###.\n.#..\n").grid
    filled = maps.fill_unreachable(grid)
    assert maps.count_unreachable(grid) == 3  # (0,0), (0,1), (2,0)
    assert filled.tolist() == maps.parse_map("###.\n###.\n##..\n").grid.tolist()


def test_parse_map_with_starts_and_tolerated_endings():
    spec = maps.parse_map("#S.#\r\n#..S\r\n\n\n", "m.txt")
    assert spec.grid.tolist() == [[True, False, False, True], [True, False, False, False]]
    assert spec.starts == ((0, 1), (1, 3))
    assert maps.parse_map("..\n..").starts is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("..\n.x\n", "m.txt: line 2, column 2: unexpected character 'x'"),
        ("...\n..\n", "m.txt: line 2: row has 2 columns, expected 3"),
        ("..\n\n..\n", "m.txt: line 2: row has 0 columns"),
        ("", "m.txt: map file is empty"),
        ("##\n##\n", "m.txt: map has no free cell"),
        ("..\t\n", "line 1, column 3"),
    ],
)
def test_parse_map_errors_name_file_line_and_column(text, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        maps.parse_map(text, "m.txt")


def test_format_map_round_trips():
    spec = maps.parse_map("#S..\n.#.S\n")
    text = maps.format_map(spec.grid, list(spec.starts))
    assert text == "#S..\n.#.S\n"


def test_map_file_by_path_and_its_starts(tmp_path):
    path = tmp_path / "room.txt"
    path.write_text("#####\n#S.S#\n#...#\n#####\n")
    env = coverage_v0.parallel_env(map=str(path), n_agents=2)
    env.reset(seed=0)
    assert env.positions.tolist() == [[1, 1], [1, 3]]
    assert env.free_cells == 6


def test_map_file_start_count_must_match_n_agents(tmp_path):
    path = tmp_path / "room.txt"
    path.write_text("#S.S#\n")
    with pytest.raises(ValueError, match="2 start cell"):
        coverage_v0.parallel_env(map=str(path), n_agents=3)


def test_malformed_map_file_error_names_the_path(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("..\n.?\n")
    with pytest.raises(ValueError, match=r"bad.txt: line 2, column 2"):
        coverage_v0.parallel_env(map=str(path), n_agents=1)


def test_unreachable_cells_in_a_given_map_warn_and_still_count(tmp_path):
    path = tmp_path / "split.txt"
    path.write_text("..#..\n")
    with pytest.warns(UserWarning, match="2 free cell"):
        env = coverage_v0.parallel_env(map=str(path), n_agents=1)
    env.reset(seed=0)
    assert env.free_cells == 4


def test_unreachable_cells_in_grid_option_warn():
    env = coverage_v0.parallel_env(height=1, width=5, n_agents=1)
    with pytest.warns(UserWarning, match="options"):
        env.reset(options={"grid": np.array([[False, True, False, False, False]])})


def free_neighbours(grid: np.ndarray) -> np.ndarray:
    """Number of free 4-neighbours of every cell (outside the grid counts as wall)."""
    free = np.pad(~grid, 1)
    return free[:-2, 1:-1].astype(int) + free[2:, 1:-1] + free[1:-1, :-2] + free[1:-1, 2:]


@pytest.mark.parametrize("name", ["cave_100x50", "maze_100x50", "rooms_100x50"])
def test_shipped_maps_are_found_by_name(name):
    assert name in maps.shipped_maps()
    spec = maps.load_map(name)
    assert spec.grid.shape == (50, 100)
    env = coverage_v0.parallel_env(map=name, n_agents=4)
    env.reset(seed=0)
    assert env.walls.shape == (50, 100)


def test_cave_is_connected_with_chambers_passages_and_dead_ends():
    grid = maps.load_map("cave_100x50").grid
    free = ~grid
    assert n_components(grid) == 1
    assert 0.2 < free.mean() < 0.35  # mostly rock, like a surveyed cave
    # Chambers: many 3x3 blocks entirely free.
    open_blocks = ndimage.minimum_filter(free.astype(int), size=3, mode="constant")
    assert open_blocks.sum() >= 100
    # Narrow passages: free cells walled in on both sides (one cell wide).
    walled = np.pad(grid, 1, constant_values=True)
    one_wide = free & (
        (walled[:-2, 1:-1] & walled[2:, 1:-1]) | (walled[1:-1, :-2] & walled[1:-1, 2:])
    )
    assert one_wide.sum() >= 20
    # Dead ends: free cells with a single free neighbour.
    assert (free & (free_neighbours(grid) == 1)).sum() >= 10


def test_cave_file_is_what_the_generator_makes():
    assert np.array_equal(generate_cave(), maps.load_map("cave_100x50").grid)


@pytest.mark.parametrize("seed", range(4))
def test_caves_of_other_seeds_are_connected_and_of_similar_size(seed):
    grid = generate_cave(seed=seed)
    assert n_components(grid) == 1
    assert 1000 < (~grid).sum() < 1700
    assert grid[[0, -1], :].all() and grid[:, [0, -1]].all()


def test_cave_smoothing_follows_the_4_5_rule():
    rock = np.zeros((7, 7), dtype=bool)
    rock[0, :] = rock[-1, :] = rock[:, 0] = rock[:, -1] = True
    rock[2, 2:5] = rock[3:5, 2] = True  # an L of rock around (3, 3)
    out = cave._smooth(rock)
    assert out[3, 3]  # free with 5 rock neighbours: turns to rock
    assert not out[4, 4]  # free with no rock neighbour: stays free
    assert not out[2, 2]  # rock with 2 rock neighbours: turns free
    assert not out[2, 3]  # rock with 3 rock neighbours: turns free
    # Every cell, against a plain loop over the 8 neighbours (outside the grid counts as rock).
    noise = np.random.default_rng(0).random((9, 11)) < 0.5
    noise[[0, -1], :] = True
    noise[:, [0, -1]] = True
    expected = np.ones_like(noise)
    for r in range(1, 8):
        for c in range(1, 10):
            n = sum(
                noise[r + dr, c + dc]
                for dr in (-1, 0, 1)
                for dc in (-1, 0, 1)
                if (dr, dc) != (0, 0)
            )
            expected[r, c] = n >= 4 if noise[r, c] else n >= 5
    assert np.array_equal(cave._smooth(noise), expected)


def test_cave_nearest_pair_and_tunnel_join_two_regions():
    rock = np.ones((9, 12), dtype=bool)
    rock[2:4, 1:3] = False  # region A
    rock[6:8, 8:11] = False  # region B
    a_region = ~rock & (np.arange(12) < 5)[None, :]
    a, b = cave._nearest_pair(a_region, ~rock & ~a_region)
    assert a.tolist() == [3, 2] and b.tolist() == [6, 8]  # the closest corners
    cave._dig_tunnel(rock, a, b, wide=False, wander=0.0, rng=np.random.default_rng(0))
    assert n_components(rock) == 1
    # Without wandering the tunnel is a shortest (Manhattan) path: 3 + 6 - 1 new cells.
    assert (~rock).sum() == 4 + 6 + (abs(6 - 3) + abs(8 - 2) - 1)


def test_cave_generator_command_writes_variants_and_rejects_bad_shares(tmp_path, capsys):
    out = tmp_path / "open_cave.txt"
    cave.main(["--rock-share", "0.5", "--out", str(out)])
    variant = maps.load_map(str(out)).grid
    assert np.array_equal(variant, generate_cave(rock_share=0.5))
    # less rock in the noise leaves more free cells than the shipped map
    assert (~variant).sum() > (~maps.load_map("cave_100x50").grid).sum()
    for share, message in (("1.5", "must be in"), ("0.95", "no free cell")):
        with pytest.raises(SystemExit) as exit_info:
            cave.main(["--rock-share", share, "--out", str(tmp_path / "bad.txt")])
        assert exit_info.value.code == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "bad.txt").exists()


def test_maze_is_connected_winding_and_has_dead_ends_and_chambers():
    grid = maps.load_map("maze_100x50").grid
    free = ~grid
    assert n_components(grid) == 1
    assert 0.3 < free.mean() < 0.6
    neighbours = free_neighbours(grid)
    assert (free & (neighbours == 1)).sum() >= 30  # many dead ends
    # Narrow passages: most free cells have at most two free neighbours.
    assert (neighbours[free] <= 2).mean() > 0.6
    # Chambers: some 3x3 blocks are entirely free.
    open_blocks = ndimage.minimum_filter(free.astype(int), size=3, mode="constant")
    assert open_blocks.sum() >= 5


def test_maze_file_is_what_the_generator_makes():
    assert np.array_equal(generate_maze(), maps.load_map("maze_100x50").grid)


def test_maze_generator_command_writes_variants_and_rejects_bad_shares(tmp_path, capsys):
    out = tmp_path / "open_maze.txt"
    maze.main(["--node-share", "0.4", "--out", str(out)])
    variant = maps.load_map(str(out)).grid
    assert np.array_equal(variant, generate_maze(node_share=0.4))
    # a smaller share of the lattice carved leaves fewer free cells than the shipped map
    assert (~variant).sum() < (~maps.load_map("maze_100x50").grid).sum()
    with pytest.raises(SystemExit) as exit_info:
        maze.main(["--node-share", "1.5", "--out", str(tmp_path / "bad.txt")])
    assert exit_info.value.code == 2
    assert "--node-share" in capsys.readouterr().err
    assert not (tmp_path / "bad.txt").exists()
