"""Map sources (``envs/coverage/generators.py``) and their config form (``harness/config/maps.py``):
seeded, sized as asked, connected, mixed in the asked proportions, never the shipped test maps,
and ``map="random"`` draws exactly the maps it drew before map sources existed."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from envs import coverage_v0
from envs.coverage import cave, maps, maze, rooms
from envs.coverage.generators import (
    GENERATORS,
    CaveMaps,
    FileMap,
    FixedMap,
    MapGenerator,
    MazeMaps,
    MixGenerator,
    OfficeMaps,
    RandomMaps,
    RoomsMaps,
    ShippedMap,
    WithoutMaps,
    from_name,
)
from harness.config.loading import config_from_dict, load_config
from harness.config.schema import ConfigError
from harness.factory import env_kwargs

SOURCES = {
    "random": lambda: RandomMaps(20, 30, (0.15, 0.2)),
    "cave": lambda: CaveMaps(30, 40, rock_share=0.45),
    "maze": lambda: MazeMaps(25, 31, n_chambers=3),
    "rooms": lambda: RoomsMaps(30, 45),
    "office": lambda: OfficeMaps(30, 45),
}


@pytest.mark.parametrize("kind", list(SOURCES))
def test_each_source_is_seeded_sized_and_connected(kind):
    make = SOURCES[kind]
    gen = make()
    assert gen.name == kind and GENERATORS[kind] is type(gen)
    a = gen(np.random.default_rng(1))
    np.testing.assert_array_equal(a, make()(np.random.default_rng(1)))
    assert not np.array_equal(a, gen(np.random.default_rng(2)))
    rng = np.random.default_rng(0)
    for _ in range(10):
        walls = gen(rng)
        assert walls.shape == (gen.height, gen.width) and walls.dtype == bool
        assert maps.count_unreachable(walls) == 0 and (~walls).sum() > 0


def test_random_source_honours_the_wall_fraction():
    # 40 % walls exactly (before pockets are filled, which only adds walls).
    walls = RandomMaps(10, 20, (0.4, 0.4))(np.random.default_rng(0))
    assert walls.sum() >= 80


def test_cave_rock_share_makes_tighter_caves():
    rng = np.random.default_rng(0)
    free = {
        share: np.mean([(~CaveMaps(40, 60, rock_share=share)(rng)).sum() for _ in range(5)])
        for share in (0.40, 0.55)
    }
    assert free[0.55] < free[0.40]


def test_a_perfect_maze_is_a_tree_of_passages():
    # All 10x10 lattice nodes carved, no loops, no chambers: 100 nodes joined by 99 passages.
    gen = MazeMaps(21, 21, node_share=1.0, n_chambers=0, loop_prob=0.0)
    walls = gen(np.random.default_rng(4))
    assert int((~walls).sum()) == 100 + 99


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: RandomMaps(0, 5), "height must be an integer >= 1"),
        (lambda: RandomMaps(5, 5, (0.5, 0.2)), "wall_fraction must satisfy"),
        (lambda: CaveMaps(2, 9), "a cave needs at least 3x3 cells"),
        (lambda: CaveMaps(9, 9, rock_share=1.5), "rock_share must be in"),
        (lambda: CaveMaps(251, 250), r"a 251x250 cave has 62,750 cells, over the limit of 62,500"),
        (lambda: MazeMaps(3, 30_001), r"a 3x30001 maze has 90,003 cells, over the limit of 90,000"),
        (lambda: MazeMaps(9, 9, n_chambers=-1), r"n_chambers must be an integer in \[0, 10,000\]"),
        (lambda: OfficeMaps(11, 30), "an office floor needs at least 12x12 cells"),
        (lambda: ShippedMap("nope"), "unknown shipped map 'nope'"),
        (lambda: FileMap("/no/such/map.txt"), "does not exist"),
        (lambda: MixGenerator([]), "at least one source"),
        (lambda: MixGenerator([(0.0, RandomMaps(5, 5))]), "weights must be positive"),
    ],
)
def test_bad_source_parameters_are_refused(make, message):
    with pytest.raises(ValueError, match=message):
        make()


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["cave", "maze", "rooms", "office"])
def test_a_map_at_its_kinds_cell_limit_draws_in_seconds(kind):
    # The limit is what one reset can afford (about a second here); a square map at it, with the
    # defaults, draws within a generous bound on a busy machine. A kind without a limit of its
    # own (office) is bounded by the harness's.
    import time

    from harness.config.schema import MAX_MAP_CELLS

    side = int((GENERATORS[kind].max_cells or MAX_MAP_CELLS) ** 0.5)
    source = GENERATORS[kind](side, side)
    start = time.perf_counter()
    walls = source(np.random.default_rng(0))
    assert time.perf_counter() - start < 10.0
    assert walls.shape == (side, side) and (~walls).any()


#: sha256 (first 16 hex) of 12 maps and start cells per env, recorded with main's code before
#: map sources were registry objects (see the loop below): ``map="random"`` must not change.
RANDOM_MAP_HASHES = {
    (50, 50, 4, False): "8f7e49f4997beee3",
    (20, 30, 2, False): "b4c77a013f6c89d0",
    (15, 15, 3, True): "5c1ddcbe902b7dbb",
}


@pytest.mark.parametrize(("height", "width", "n_agents", "fixed"), list(RANDOM_MAP_HASHES))
def test_random_maps_are_the_ones_drawn_before_map_sources(height, width, n_agents, fixed):
    starts = [(0, 0), (1, 1), (2, 2)] if fixed else None
    env = coverage_v0.parallel_env(height=height, width=width, n_agents=n_agents, starts=starts)
    digest = hashlib.sha256()
    for seed in (0, 1, 7, 123):
        env.reset(seed=seed)
        for _ in range(3):
            digest.update(env.walls.tobytes())
            digest.update(env.positions.tobytes())
            env.reset()
    assert digest.hexdigest()[:16] == RANDOM_MAP_HASHES[(height, width, n_agents, fixed)]


def test_the_env_takes_a_generator_or_its_name_alike():
    by_name = coverage_v0.parallel_env(height=20, width=20, n_agents=2)
    by_object = coverage_v0.parallel_env(map=RandomMaps(20, 20, (0.15, 0.20)), n_agents=2)
    for seed in (0, 5):
        by_name.reset(seed=seed)
        by_object.reset(seed=seed)
        np.testing.assert_array_equal(by_name.walls, by_object.walls)
        np.testing.assert_array_equal(by_name.positions, by_object.positions)


def test_names_become_sources():
    assert isinstance(from_name("random", 7, 9), RandomMaps)
    shipped = from_name("cave_100x50")
    assert isinstance(shipped, ShippedMap) and shipped.shapes == {(50, 100)}
    np.testing.assert_array_equal(
        shipped(np.random.default_rng(0)), maps.load_map("cave_100x50").grid
    )


def test_a_map_file_source_keeps_its_start_cells(tmp_path):
    path = tmp_path / "room.txt"
    path.write_text("#####\n#S.S#\n#...#\n#####\n")
    env = coverage_v0.parallel_env(map=FileMap(str(path)), n_agents=2)
    env.reset(seed=0)
    assert env.positions.tolist() == [[1, 1], [1, 3]]
    assert env.walls.shape == (4, 5)


class _Marker(MapGenerator):
    """A 3x4 map whose first row holds ``mark`` walls: which source drew it."""

    name = "marker"

    def __init__(self, mark: int) -> None:
        self.mark = mark
        self.shapes = frozenset({(3, 4)})

    def __call__(self, rng, keep_free=None):
        walls = np.zeros((3, 4), dtype=bool)
        walls[0, : self.mark] = True
        return walls


def test_mix_picks_sources_in_proportion_to_their_weights():
    mix = MixGenerator([(2.0, _Marker(0)), (1.0, _Marker(1)), (1.0, _Marker(2))])
    rng = np.random.default_rng(0)
    n = 4000
    counts = np.bincount([int(mix(rng)[0].sum()) for _ in range(n)], minlength=3)
    expected = n * np.array([0.5, 0.25, 0.25])
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 < 13.8  # chi-square, 2 degrees of freedom, p = 0.001


def test_a_mix_of_sizes_draws_each_size_and_sizes_the_space_for_the_largest():
    mix = MixGenerator([(1.0, RandomMaps(10, 30)), (1.0, MazeMaps(21, 15))])
    assert mix.max_shape == (21, 30) and mix.min_shape == (10, 15)
    env = coverage_v0.parallel_env(map=mix, n_agents=2, coords="raw")
    high = env.observation_space("agent_0").high
    np.testing.assert_array_equal(high[9:], [20, 29, 20, 29])  # largest rows - 1, cols - 1
    env.reset(seed=0)
    seen = set()
    for _ in range(12):
        seen.add(env.walls.shape)
        assert (env.height, env.width) == env.walls.shape
        obs, *_ = env.step({a: 4 for a in env.agents})
        for o in obs.values():
            assert env.observation_space("agent_0").contains(o)
        env.reset()
    assert seen == {(10, 30), (21, 15)}


def test_the_team_map_takes_maps_of_any_size_in_one_env():
    mix = MixGenerator([(1.0, RandomMaps(12, 20)), (1.0, CaveMaps(30, 18))])
    env = coverage_v0.parallel_env(map=mix, n_agents=2, observation={"teammap": {"crop": 7}})
    space = env.observation_space("agent_0")
    env.reset(seed=1)
    for _ in range(6):
        obs, *_ = env.step({a: 1 for a in env.agents})
        assert all(space.contains(o) for o in obs.values())
        env.reset()


def test_fixed_starts_must_fit_the_smallest_map_of_a_mix():
    mix = MixGenerator([(1.0, RandomMaps(10, 10, (0.0, 0.0))), (1.0, RandomMaps(5, 5))])
    with pytest.raises(ValueError, match=r"start cell \(7, 7\) is off the 5x5 map"):
        coverage_v0.parallel_env(map=mix, n_agents=1, starts=[(7, 7)])


def test_procedural_caves_mazes_and_floor_plans_never_draw_the_shipped_seeds():
    class Scripted:
        """A stand-in rng whose first seed draw is the shipped map's seed."""

        def __init__(self, first: int) -> None:
            self.draws = iter([first, 7])

        def integers(self, high: int) -> int:
            return next(self.draws)

    for gen, seed, name in (
        (CaveMaps(*cave.CAVE_SHAPE), cave.CAVE_SEED, "cave_100x50"),
        (MazeMaps(*maze.MAZE_SHAPE), maze.MAZE_SEED, "maze_100x50"),
        (RoomsMaps(*rooms.ROOMS_SHAPE), rooms.ROOMS_SEED, "rooms_100x50"),
    ):
        shipped = maps.load_map(name).grid
        # Seeded with the shipped seed, the generator remakes the shipped map ...
        np.testing.assert_array_equal(
            {
                "cave_100x50": cave.generate_cave,
                "maze_100x50": maze.generate_maze,
                "rooms_100x50": rooms.generate_rooms,
            }[name](seed),
            shipped,
        )
        # ... but the source refuses that seed and draws another.
        assert not np.array_equal(gen(Scripted(seed)), shipped)


def test_generated_maps_never_equal_a_shipped_map_over_many_draws():
    shipped = [maps.load_map(name).grid for name in maps.shipped_maps()]
    rng = np.random.default_rng(11)
    for gen in (CaveMaps(50, 100), MazeMaps(50, 100), RoomsMaps(50, 100), OfficeMaps(50, 100)):
        for _ in range(100):
            walls = gen(rng)
            assert not any(np.array_equal(walls, s) for s in shipped)


def test_test_only_maps_are_drawn_again_and_never_returned():
    test_map = _Marker(1)(None)

    class FirstTheTestMap(MapGenerator):
        name = "scripted"
        shapes = frozenset({(3, 4)})

        def __init__(self) -> None:
            self.marks = iter([1, 1, 2])

        def __call__(self, rng, keep_free=None):
            return _Marker(next(self.marks))(rng)

    gen = WithoutMaps(FirstTheTestMap(), [test_map])
    assert int(gen(None)[0].sum()) == 2  # two test maps skipped
    shipped = ShippedMap("cave_100x50")
    with pytest.raises(ValueError, match="test-only map"):
        WithoutMaps(MixGenerator([(1.0, RandomMaps(5, 5)), (1.0, shipped)]), [shipped.spec.grid])


# ---------------------------------------------------------------------- configs
THESIS_MIX = {
    "mix": [
        {"weight": 2, "random": {"height": 30, "width": 30, "wall_fraction": [0.15, 0.2]}},
        {"weight": 1, "cave": {"height": 30, "width": 48, "rock_share": 0.5}},
        {"weight": 1, "maze": {"height": 21, "width": 21}},
    ]
}


def test_a_mix_in_a_config_builds_the_mix_and_survives_the_run_folders_yaml(tmp_path):
    config = config_from_dict({"env": {"n_agents": 2, "map": THESIS_MIX}})
    mix = env_kwargs(config.env)["map"]
    assert isinstance(mix, MixGenerator)
    np.testing.assert_allclose(mix.probabilities, [0.5, 0.25, 0.25])
    assert [type(g) for g in mix.sources] == [RandomMaps, CaveMaps, MazeMaps]
    assert mix.sources[1].shape["rock_share"] == 0.5
    assert mix.shapes == {(30, 30), (30, 48), (21, 21)}
    # The kept YAML holds every parameter and loads back to the same config.
    saved = tmp_path / "config.yaml"
    saved.write_text(config.to_yaml())
    assert load_config(saved).env.map == config.env.map
    assert config.env.map["mix"][2]["maze"]["n_chambers"] == 14


def test_a_source_without_a_size_takes_the_envs():
    config = config_from_dict({"env": {"height": 24, "width": 36, "map": {"cave": None}}})
    assert env_kwargs(config.env)["map"].shapes == {(24, 36)}


def test_a_map_file_source_is_stored_with_its_absolute_path(tmp_path, monkeypatch):
    (tmp_path / "room.txt").write_text("....\n....\n")
    monkeypatch.chdir(tmp_path)
    config = config_from_dict({"env": {"n_agents": 2, "map": {"file": {"path": "room.txt"}}}})
    digest = hashlib.sha256(b"....\n....\n").hexdigest()  # kept: a changed file is refused
    assert config.env.map == {"file": {"path": str(tmp_path / "room.txt"), "sha256": digest}}


@pytest.mark.parametrize(
    ("value", "line"),
    [
        ("random", "random 24x36"),
        ("cave_100x50", "cave_100x50"),
        ({"cave": None}, "cave 24x36"),
        ({"maze": {"height": 41, "width": 41}}, "maze 41x41"),
        ({"file": {"path": "room.txt"}}, "file room.txt"),
        (
            {"mix": [{"weight": 3, "random": {}}, {"weight": 0.5, "maze": {"height": 41}}]},
            "mix by weight: 3 random 24x36, 0.5 maze 41x36",
        ),
    ],
)
def test_eval_names_a_map_in_one_short_line(value, line, tmp_path, monkeypatch):
    # harness eval's printout: a mix by its sources, not the whole normalised mapping.
    from harness.commands import format_summary
    from harness.config.maps import describe_map

    (tmp_path / "room.txt").write_text("....\n....\n")
    monkeypatch.chdir(tmp_path)
    env = config_from_dict({"env": {"height": 24, "width": 36, "map": value}}).env
    assert describe_map(env.map, env.height, env.width) == line
    summary = {
        "policy": "random", "episodes": 2, "seed": 0, "coverage_at_median": {},
        "env": {"map": env.map, "height": 24, "width": 36, "n_agents": 2, "max_steps": 9},
        **dict.fromkeys(["coverage_median", "coverage_mean", "coverage_iqr", "bound"], 0.5),
        **dict.fromkeys(["coverage_q1", "coverage_q3", "efficiency", "wall_hits_mean"], 0.5),
        "steps_to_90": None, "steps_to_99": None, "wall_hits_episodes": 0, "per_agent": [],
    }  # fmt: skip
    assert format_summary(summary).splitlines()[1] == (
        f"episodes  2 (seed 0), {line}; 2 agent(s), 9 steps"
    )


@pytest.mark.parametrize(
    ("source", "message"),
    [
        (
            {"caves": {}},
            "env.map: unknown map kind 'caves'; known: random, cave, maze, rooms, office, file, "
            "shipped, mix",
        ),
        ({"cave": {"rocks": 0.4}}, "env.map: cave.rocks: Extra inputs are not permitted"),
        ({"cave": {"rock_share": 2}}, r"env.map: cave: rock_share must be in \[0.0, 1.0\]"),
        ({"maze": {"height": "tall"}}, "env.map: maze.height: Input should be a valid integer"),
        ({"mix": [{"cave": {}}]}, "env.map: mix.0.weight: Field required"),
        ({"mix": [{"weight": -1, "cave": {}}]}, "env.map: mix.0.weight: Input should be greater"),
        ({"mix": [{"weight": 1, "mix": []}]}, "env.map: mix.0: unknown map kind 'mix'"),
        ({"mix": [{"weight": 1, "maze": {"loop_prob": 3}}]}, "env.map: mix.0.maze: loop_prob"),
        ({"cave": {}, "maze": {}}, "env.map: give exactly one map kind of .*got cave, maze"),
        ({"shipped": {"name": "cave"}}, "env.map: shipped: unknown shipped map 'cave'"),
    ],
)
def test_bad_map_sources_are_one_line_config_errors(source, message):
    with pytest.raises(ConfigError, match=message) as err:
        config_from_dict({"env": {"map": source}})
    assert "\n" not in str(err.value)


def test_test_maps_keep_generated_training_maps_apart_from_the_shipped_ones():
    config = config_from_dict({"env": {"map": {"cave": {}}, "test_maps": ["cave_100x50"]}})
    assert isinstance(env_kwargs(config.env)["map"], WithoutMaps)
    with pytest.raises(ConfigError, match="'cave_100x50' is a test-only map"):
        config_from_dict(
            {
                "env": {
                    "map": {"mix": [{"weight": 1, "shipped": {"name": "cave_100x50"}}]},
                    "test_maps": ["cave_100x50"],
                }
            }
        )
    # A fixed test map named in env.map is used as given (evaluating a run on it) ...
    fixed = config_from_dict({"env": {"map": "cave_100x50", "test_maps": ["cave_100x50"]}})
    assert isinstance(env_kwargs(fixed.env)["map"], str)
    # ... and `harness run` refuses to train on it.
    with pytest.raises(ValueError, match="test-only map"):
        fixed.env.check_training_map()
    with pytest.raises(ConfigError, match=r"env\.test_maps: 'nope' is neither a shipped map"):
        config_from_dict({"env": {"test_maps": ["nope"]}})


def test_fixed_maps_are_the_same_every_time():
    spec = maps.load_map("maze_100x50")
    gen = FixedMap(spec)
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(gen(rng), spec.grid)
    np.testing.assert_array_equal(gen(rng), spec.grid)


def test_a_cave_whose_settings_leave_too_many_pockets_is_refused_when_built(monkeypatch):
    from envs.coverage.generators import CaveMaps

    CaveMaps(250, 250)  # the largest default cave: about a second a draw
    with pytest.raises(ValueError, match=r"150x150 cave .* leaves 1,994 pockets to join"):
        CaveMaps(150, 150, iterations=0, min_region=1)
    # The count bounds the tunnels the generator digs for that seed (a tunnel may join more
    # than two regions at once, never fewer).
    dug = []
    real = cave._dig_tunnel
    monkeypatch.setattr(cave, "_dig_tunnel", lambda *a, **k: (dug.append(1), real(*a, **k)))
    for size, settings in (((50, 100), {}), ((60, 60), {"iterations": 0, "min_region": 1})):
        dug.clear()
        cave.generate_cave(cave.CAVE_SEED, *size, **settings)
        pockets = cave.count_pockets(cave.CAVE_SEED, *size, **settings)
        assert 0 < len(dug) <= pockets - 1, (size, len(dug), pockets)
