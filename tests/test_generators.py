"""Map sources (``envs/coverage/generators.py``): seeded, connected, mixed in the asked
proportions, never the shipped test maps, and reachable from a config."""

from __future__ import annotations

import numpy as np
import pytest

from envs import coverage_v0
from envs.coverage import cave, maps, maze
from envs.coverage.generators import (
    CaveMaps,
    FixedMap,
    MazeMaps,
    MixGenerator,
    RandomMaps,
    from_spec,
)
from harness.config import ConfigError, config_from_dict


@pytest.mark.parametrize(
    "make",
    [
        lambda: RandomMaps(20, 30, (0.15, 0.2)),
        lambda: CaveMaps(30, 40, rock_share=0.45),
        lambda: MazeMaps(25, 31, n_chambers=3),
    ],
    ids=["random", "cave", "maze"],
)
def test_sources_are_seeded_sized_and_connected(make):
    gen = make()
    a = gen(np.random.default_rng(1))
    b = make()(np.random.default_rng(1))
    c = gen(np.random.default_rng(2))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a.shape == (gen.height, gen.width) and a.dtype == bool
    assert maps.count_unreachable(a) == 0 and (~a).sum() > 0


def test_random_source_gives_the_envs_own_random_maps():
    # map="random" and map=RandomMaps(...) draw the same maps from the same seeds.
    by_name = coverage_v0.parallel_env(height=20, width=20, n_agents=2)
    by_object = coverage_v0.parallel_env(map=RandomMaps(20, 20, (0.15, 0.20)), n_agents=2)
    for seed in (0, 5):
        by_name.reset(seed=seed)
        by_object.reset(seed=seed)
        np.testing.assert_array_equal(by_name.walls, by_object.walls)
        np.testing.assert_array_equal(by_name.positions, by_object.positions)


def test_mix_picks_sources_in_proportion_to_their_weights():
    class Marker(RandomMaps):
        def __init__(self, mark: int) -> None:
            super().__init__(4, 4, (0.0, 0.0))
            self.mark = mark

        def __call__(self, rng, keep_free=None):
            walls = np.zeros((4, 4), dtype=bool)
            walls[0, : self.mark] = True
            return walls

    mix = MixGenerator([(1.0, Marker(1)), (3.0, Marker(2))])
    rng = np.random.default_rng(0)
    draws = [int(mix(rng)[0].sum()) for _ in range(4000)]
    share = draws.count(2) / len(draws)
    assert abs(share - 0.75) < 5 * np.sqrt(0.75 * 0.25 / 4000)


def test_procedural_caves_and_mazes_are_never_the_shipped_test_maps():
    shipped_cave = maps.load_map("cave_100x50").grid
    shipped_maze = maps.load_map("maze_100x50").grid

    class Scripted:
        """A stand-in generator whose first seed draw is the shipped map's seed."""

        def __init__(self, first: int) -> None:
            self.draws = iter([first, 7])

        def integers(self, high: int) -> int:
            return next(self.draws)

    # The source must refuse the shipped seed and draw again.
    walls = CaveMaps(*shipped_cave.shape)(Scripted(cave.CAVE_SEED))
    assert not np.array_equal(walls, shipped_cave)
    walls = MazeMaps(*shipped_maze.shape)(Scripted(maze.MAZE_SEED))
    assert not np.array_equal(walls, shipped_maze)
    # And the maps drawn in practice differ from the shipped ones too.
    rng = np.random.default_rng(3)
    for _ in range(3):
        assert not np.array_equal(MazeMaps(*shipped_maze.shape)(rng), shipped_maze)


def test_fixed_map_is_the_same_every_time():
    spec = maps.load_map("cave_100x50")
    gen = FixedMap(spec)
    np.testing.assert_array_equal(gen(np.random.default_rng(0)), spec.grid)


def test_a_mix_from_a_config_trains_on_fresh_maps_each_reset():
    config = config_from_dict(
        {
            "env": {
                "height": 30,
                "width": 30,
                "n_agents": 2,
                "max_steps": 20,
                "map": {"mix": [{"weight": 1, "cave": {}}, {"weight": 1, "maze": {}}]},
            }
        }
    )
    env = coverage_v0.parallel_env(**config.env.kwargs())
    seen = set()
    env.reset(seed=0)
    for _ in range(6):
        seen.add(env.walls.tobytes())
        env.reset()
    assert len(seen) == 6
    assert "mix" in config.to_yaml()


@pytest.mark.parametrize(
    ("source", "message"),
    [
        ({"caves": {}}, "unknown map kind 'caves'"),
        ({"cave": {"rocks": 0.4}}, "cave: unknown parameter(s) rocks"),
        ({"mix": [{"cave": {}}]}, "every source needs a weight"),
        ({"mix": [{"weight": -1, "cave": {}}]}, "weights must be positive"),
        ({"cave": {}, "maze": {}}, "a map source is one of"),
    ],
)
def test_bad_map_sources_are_config_errors(source, message):
    with pytest.raises(ConfigError, match=rf"env\.map: .*{message[:20]}"):
        config_from_dict({"env": {"map": source}})


def test_from_spec_builds_each_kind():
    assert isinstance(from_spec({"random": {"wall_fraction": [0.1, 0.2]}}, 9, 9), RandomMaps)
    mix = from_spec({"mix": [{"weight": 2, "cave": {}}, {"weight": 1, "random": None}]}, 20, 20)
    assert isinstance(mix, MixGenerator)
    np.testing.assert_allclose(mix.probabilities, [2 / 3, 1 / 3])
