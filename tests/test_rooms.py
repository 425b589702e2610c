"""Floor plans (``envs/coverage/rooms.py``, the ``rooms`` map kind): seeded, walled in, every
free cell reachable, doors 1 or 2 cells wide in one-cell walls, furniture that closes nothing
off, rooms of varied size, hallways, the shipped ``rooms_100x50`` and the config form."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from envs import coverage_v0
from envs.coverage import maps, rooms
from envs.coverage.generators import GENERATORS, RoomsMaps, WithoutMaps
from envs.coverage.rooms import FloorPlan, Region, floor_plan, generate_rooms
from harness.config.loading import config_from_dict
from harness.config.schema import ConfigError
from harness.factory import env_kwargs

#: Settings that stress each step: the defaults, many small rooms with every door and hallway,
#: the most furniture, no hallways or loops at all.
SETTINGS = [
    {},
    {"min_room": 2, "max_room": 5, "corridor_share": 1.0, "loop_share": 1.0},
    {"furniture_share": 0.2, "wide_door_share": 1.0},
    {"corridor_share": 0.0, "loop_share": 0.0, "furniture_share": 0.0},
]
SHAPES = [(50, 100), (31, 47), (80, 40)]


def components(walls: np.ndarray) -> int:
    """4-connected areas of free cells."""
    return int(ndimage.label(~walls)[1])


def region_mask(plan: FloorPlan) -> np.ndarray:
    """True on the rooms' and corridors' floor (furniture included)."""
    mask = np.zeros_like(plan.walls)
    for region in plan.regions:
        mask[region.cells] = True
    return mask


def furniture_mask(plan: FloorPlan) -> np.ndarray:
    mask = np.zeros_like(plan.walls)
    for top, left, bottom, right in plan.furniture:
        mask[top:bottom, left:right] = True
    return mask


def test_the_same_seed_gives_the_same_plan_and_another_seed_another():
    np.testing.assert_array_equal(generate_rooms(5), generate_rooms(5))
    assert not np.array_equal(generate_rooms(5), generate_rooms(6))
    source = RoomsMaps(40, 60)
    np.testing.assert_array_equal(
        source(np.random.default_rng(3)), RoomsMaps(40, 60)(np.random.default_rng(3))
    )


@pytest.mark.parametrize("settings", SETTINGS, ids=lambda s: ",".join(s) or "defaults")
@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_plans_are_walled_in_connected_and_made_of_rooms_doors_and_furniture(shape, settings):
    for seed in range(8):
        plan = floor_plan(seed, *shape, **settings)
        walls = plan.walls
        assert walls.shape == shape and walls.dtype == bool
        assert walls[[0, -1], :].all() and walls[:, [0, -1]].all()  # the border
        assert components(walls) == 1
        # The guard that fills unreachable cells finds none: the construction connects.
        np.testing.assert_array_equal(generate_rooms(seed, *shape, **settings), walls)
        # Free ground is exactly the rooms' floor less furniture, plus the doors.
        doors = np.zeros_like(walls)
        for _, _, cells in plan.doors:
            doors[tuple(np.array(cells).T)] = True
        np.testing.assert_array_equal(~walls, (region_mask(plan) & ~furniture_mask(plan)) | doors)


@pytest.mark.parametrize("settings", SETTINGS, ids=lambda s: ",".join(s) or "defaults")
def test_doors_are_one_or_two_cells_in_one_cell_walls_between_two_regions(settings):
    for seed in range(8):
        plan = floor_plan(seed, 50, 100, **settings)
        inside = region_mask(plan)
        labels = np.zeros(plan.walls.shape, dtype=int)
        for i, region in enumerate(plan.regions):
            labels[region.cells] = i + 1
        # The openings in the walls, found on the grid alone: each is one door of the plan.
        openings, n = ndimage.label(~plan.walls & ~inside)
        assert n == len(plan.doors)
        for a, b, cells in plan.doors:
            assert len({openings[c] for c in cells}) == 1
            assert (openings == openings[cells[0]]).sum() == len(cells)
            both_halls = plan.regions[a].corridor and plan.regions[b].corridor
            # A hallway junction opens across the hallway; every other door is 1 or 2 cells.
            assert len(cells) in ((2, 3) if both_halls else (1, 2))
            for r, c in cells:
                # One wall cell thick: region a on one side, region b on the other.
                sides = {
                    frozenset((labels[r - 1, c], labels[r + 1, c])),
                    frozenset((labels[r, c - 1], labels[r, c + 1])),
                }
                assert frozenset((a + 1, b + 1)) in sides


def test_a_two_room_plan_by_hand():
    # 9 rows of floor, 12 columns: longer than max_room 9, so one cut across the columns leaves
    # two rooms of 4 to 7 columns behind a wall with one door, 1 cell or, if wide, 2.
    for wide, size in ((0.0, 1), (1.0, 2)):
        for seed in range(10):
            walls = generate_rooms(
                seed, 11, 14, 4, 9, wide, corridor_share=0.0, furniture_share=0.0
            )
            wall_cols = [c for c in range(1, 13) if walls[1:10, c].sum() >= 9 - size]
            assert len(wall_cols) == 1
            col = wall_cols[0]
            assert 5 <= col <= 8  # both rooms 4 to 7 wide
            door = np.flatnonzero(~walls[1:10, col]) + 1
            assert len(door) == size and np.all(np.diff(door) == 1)
            assert door[0] >= 2 and door[-1] <= 8  # off the wall's ends
            assert int((~walls).sum()) == 9 * 11 + size


def test_furniture_is_small_blocks_with_free_ground_all_round_and_closes_nothing_off():
    for seed in range(10):
        plan = floor_plan(seed, 50, 100, furniture_share=0.2)
        assert components(plan.walls) == 1
        rooms_only = [r for r in plan.regions if not r.corridor]
        blocked = furniture_mask(plan)
        assert blocked.sum() > 0.12 * sum(r.area for r in rooms_only)  # well furnished
        for top, left, bottom, right in plan.furniture:
            assert sorted((bottom - top, right - left)) in ([1, 2], [1, 3], [2, 2], [2, 3])
            assert any(
                r.top < top and bottom < r.bottom and r.left < left and right < r.right
                for r in rooms_only
            )  # inside a room, off its walls
            around = ~plan.walls[top - 1 : bottom + 1, left - 1 : right + 1]
            assert around.sum() == around.size - (bottom - top) * (right - left)
    assert floor_plan(0, 50, 100, furniture_share=0.0).furniture == ()


def test_rooms_vary_in_size_within_min_and_max_room():
    plan = floor_plan(0, 50, 100)
    sides = [(r.bottom - r.top, r.right - r.left) for r in plan.regions if not r.corridor]
    assert all(4 <= s <= 14 for side in sides for s in side)
    areas = [h * w for h, w in sides]
    assert len(set(areas)) >= 15 and max(areas) >= 3 * min(areas)


def test_hallways_are_two_or_three_wide_and_rooms_beside_them_open_onto_them():
    halls_seen = beside_seen = 0
    for seed in range(10):
        plan = floor_plan(seed, 50, 100, corridor_share=1.0)
        halls = [i for i, r in enumerate(plan.regions) if r.corridor]
        halls_seen += len(halls)
        for i in halls:
            r = plan.regions[i]
            assert min(r.bottom - r.top, r.right - r.left) in (2, 3)
        onto_hall = {a if b in halls else b for a, b, _ in plan.doors if a in halls or b in halls}
        for i, region in enumerate(plan.regions):
            if not region.corridor and any(_share_a_wall(region, plan.regions[j]) for j in halls):
                beside_seen += 1
                assert i in onto_hall
    assert halls_seen >= 20 and beside_seen >= 100
    assert not any(r.corridor for r in floor_plan(1, 50, 100, corridor_share=0.0).regions)


def _share_a_wall(a: Region, b: Region) -> bool:
    """One wall cell between them along a stretch of at least one cell."""
    rows = min(a.bottom, b.bottom) - max(a.top, b.top)
    cols = min(a.right, b.right) - max(a.left, b.left)
    return (rows > 0 and (a.right + 1 == b.left or b.right + 1 == a.left)) or (
        cols > 0 and (a.bottom + 1 == b.top or b.bottom + 1 == a.top)
    )


def test_loop_share_adds_doors_beyond_the_spanning_tree():
    for seed in range(5):
        tree = floor_plan(seed, 50, 100, corridor_share=0.0, loop_share=0.0)
        assert len(tree.doors) == len(tree.regions) - 1
        every = floor_plan(seed, 50, 100, corridor_share=0.0, loop_share=1.0)
        pairs = sum(
            _share_a_wall(a, b) for i, a in enumerate(every.regions) for b in every.regions[i + 1 :]
        )
        assert len(every.doors) == pairs > len(every.regions) - 1


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"height": 2}, "a floor plan needs at least 3x3 cells, got 2x100"),
        ({"height": 600, "width": 600}, "a 600x600 floor plan has 360,000 cells, over the limit"),
        ({"min_room": 1}, r"min_room must be an integer in \[2, 1,000\], got 1"),
        ({"min_room": 2.5}, r"min_room must be an integer in \[2, 1,000\]"),
        ({"max_room": 8}, r"max_room must be an integer >= 2 \* min_room \+ 1 = 9, got 8"),
        ({"wide_door_share": -0.1}, r"wide_door_share must be in \[0.0, 1.0\]"),
        ({"corridor_share": 1.5}, r"corridor_share must be in \[0.0, 1.0\]"),
        ({"furniture_share": 0.3}, r"furniture_share must be in \[0.0, 0.2\]"),
        ({"loop_share": 2}, r"loop_share must be in \[0.0, 1.0\]"),
    ],
)
def test_bad_parameters_are_refused_one_line_each(settings, message):
    kwargs = {"height": 50, "width": 100, **settings}
    with pytest.raises(ValueError, match=message) as err:
        RoomsMaps(**kwargs)
    assert "\n" not in str(err.value)


def test_the_generator_function_refuses_sides_that_could_disconnect_rooms():
    with pytest.raises(ValueError, match="min_room must be"):
        generate_rooms(0, 20, 20, min_room=1)
    with pytest.raises(ValueError, match="at least 3x3"):
        generate_rooms(0, 2, 20)


def test_the_shipped_plan_is_what_the_generator_makes():
    shipped = maps.load_map("rooms_100x50").grid
    np.testing.assert_array_equal(generate_rooms(rooms.ROOMS_SEED, 50, 100), shipped)
    assert shipped.shape == rooms.ROOMS_SHAPE == (50, 100)
    plan = floor_plan(rooms.ROOMS_SEED, 50, 100)
    assert sum(r.corridor for r in plan.regions) == 3 and len(plan.furniture) > 50
    env = coverage_v0.parallel_env(map="rooms_100x50", n_agents=4)
    env.reset(seed=0)
    np.testing.assert_array_equal(env.walls, shipped)


def test_the_source_never_draws_the_shipped_seed():
    class Scripted:
        """A stand-in rng whose first seed draw is the shipped plan's seed."""

        def __init__(self) -> None:
            self.draws = iter([rooms.ROOMS_SEED, 7])

        def integers(self, high: int) -> int:
            return next(self.draws)

    walls = RoomsMaps(50, 100)(Scripted())
    np.testing.assert_array_equal(walls, generate_rooms(7, 50, 100))
    assert not np.array_equal(walls, maps.load_map("rooms_100x50").grid)


def test_generator_command_writes_variants_and_rejects_bad_shares(tmp_path, capsys):
    out = tmp_path / "halls.txt"
    rooms.main(["--corridor-share", "1", "--furniture-share", "0", "--out", str(out)])
    variant = maps.load_map(str(out)).grid
    np.testing.assert_array_equal(
        variant, generate_rooms(rooms.ROOMS_SEED, corridor_share=1.0, furniture_share=0.0)
    )
    for flag, value in (("--corridor-share", "1.5"), ("--furniture-share", "0.7")):
        with pytest.raises(SystemExit) as exit_info:
            rooms.main([flag, value, "--out", str(tmp_path / "bad.txt")])
        assert exit_info.value.code == 2
        assert flag in capsys.readouterr().err
        assert not (tmp_path / "bad.txt").exists()


def test_a_config_names_the_kind_with_its_parameters():
    config = config_from_dict(
        {
            "env": {
                "n_agents": 2,
                "map": {"rooms": {"height": 50, "width": 100, "corridor_share": 0.8}},
                "test_maps": ["rooms_100x50"],
            }
        }
    )
    assert config.env.map == {
        "rooms": {
            "height": 50,
            "width": 100,
            "min_room": 4,
            "max_room": 14,
            "wide_door_share": 0.4,
            "corridor_share": 0.8,
            "furniture_share": 0.08,
            "loop_share": 0.15,
        }
    }
    source = env_kwargs(config.env)["map"]
    assert isinstance(source, WithoutMaps) and isinstance(source.source, RoomsMaps)
    assert GENERATORS["rooms"] is RoomsMaps
    env = coverage_v0.parallel_env(**env_kwargs(config.env))
    env.reset(seed=0)
    assert env.walls.shape == (50, 100) and components(env.walls) == 1
    with pytest.raises(ConfigError, match=r"env.map: rooms: max_room must be an integer >= 2"):
        config_from_dict({"env": {"map": {"rooms": {"min_room": 7}}}})
    with pytest.raises(
        ConfigError, match=r"env\.map: rooms\.doors: Extra inputs are not permitted"
    ):
        config_from_dict({"env": {"map": {"rooms": {"doors": 2}}}})
