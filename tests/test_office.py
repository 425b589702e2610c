"""Office floors (``envs/coverage/office.py``, the ``office`` map kind): seeded, walled in, every
free cell reachable, full-length hallways, rows of like rooms with one door each onto a hallway,
open-plan areas with pillars, a look unlike the ``rooms`` plans, and the config form."""

from __future__ import annotations

import inspect
import time

import numpy as np
import pytest
from scipy import ndimage

from envs import coverage_v0
from envs.coverage import office
from envs.coverage.generators import GENERATORS, OfficeMaps
from envs.coverage.office import HALL, OPEN, ROOM, Area, OfficePlan, generate_office, office_plan
from envs.coverage.rooms import floor_plan
from harness.cli import main
from harness.config.loading import config_from_dict
from harness.config.schema import ConfigError
from harness.factory import env_kwargs

#: Wide, tall (built on its side), the smallest, square, odd, a thin strip, a deep floor (many
#: hallways and rows back to back).
SHAPES = [(50, 100), (100, 50), (12, 12), (61, 61), (31, 47), (12, 200), (160, 90)]


def components(walls: np.ndarray) -> int:
    """4-connected areas of free cells."""
    return int(ndimage.label(~walls)[1])


def labels(plan: OfficePlan) -> np.ndarray:
    """Area index + 1 on each area's cells, 0 elsewhere."""
    out = np.zeros(plan.walls.shape, dtype=int)
    for i, area in enumerate(plan.areas):
        out[area.cells] = i + 1
    return out


def kinds(plan: OfficePlan, kind: str) -> list[Area]:
    return [a for a in plan.areas if a.kind == kind]


def test_the_same_seed_gives_the_same_floor_and_another_seed_another():
    np.testing.assert_array_equal(generate_office(5, 50, 100), generate_office(5, 50, 100))
    assert not np.array_equal(generate_office(5, 50, 100), generate_office(6, 50, 100))
    np.testing.assert_array_equal(
        OfficeMaps(40, 60)(np.random.default_rng(3)), OfficeMaps(40, 60)(np.random.default_rng(3))
    )


def test_the_layouts_constants_are_in_the_ranges_the_steps_need():
    # A room 3 cells wide still takes a door off its wall's ends; rows at most twice MIN_DEPTH
    # deep let some count of hallways fit every floor (the next tests check the floors).
    low, high = office.ROOM_WIDTH
    assert 3 <= low <= high
    assert office.MAX_DEPTH >= 2 * office.MIN_DEPTH
    for share in (office.WIDE_DOOR_SHARE, office.INNER_DOOR_SHARE, office.OPEN_SHARE):
        assert 0 < share < 1


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_floors_are_walled_in_connected_and_made_of_their_areas_doors_and_pillars(shape):
    for seed in range(10):
        plan = office_plan(seed, *shape)
        walls = plan.walls
        assert walls.shape == shape and walls.dtype == bool
        assert walls[[0, -1], :].all() and walls[:, [0, -1]].all()  # the border
        assert components(walls) == 1
        # The guard that fills unreachable cells finds none: the construction connects.
        np.testing.assert_array_equal(generate_office(seed, *shape), walls)
        # Areas never overlap; free ground is exactly the areas less the pillars, plus the doors.
        inside = labels(plan) > 0
        assert inside.sum() == sum(a.area for a in plan.areas)
        doors = np.zeros_like(walls)
        for _, _, cells in plan.doors:
            doors[tuple(np.array(cells).T)] = True
        pillars = np.zeros_like(walls)
        for top, left, bottom, right in plan.pillars:
            pillars[top:bottom, left:right] = True
        np.testing.assert_array_equal(~walls, (inside & ~pillars) | doors)
        assert not (doors & inside).any()


@pytest.mark.parametrize("shape", [(50, 100), (100, 50), (160, 90)], ids=["wide", "tall", "deep"])
def test_every_room_has_exactly_one_door_onto_a_hallway_through_a_one_cell_wall(shape):
    for seed in range(20):
        plan = office_plan(seed, *shape)
        lab = labels(plan)
        onto_hall: dict[int, int] = {}
        for a, b, cells in plan.doors:
            kind_a, kind_b = plan.areas[a].kind, plan.areas[b].kind
            if kind_b == HALL:
                onto_hall[a] = onto_hall.get(a, 0) + 1
                # A room's door is 1 or 2 cells, an open area's 2 (1 on a 1-cell stretch).
                assert len(cells) in (1, 2)
            else:
                assert (kind_a, kind_b) == (ROOM, ROOM) and len(cells) == 1  # an inner door
            rows, cols = zip(*cells)
            assert len(set(rows)) == 1 or len(set(cols)) == 1  # a run along one wall
            for r, c in cells:
                # One wall cell thick: area a on one side, area b on the other.
                sides = {
                    frozenset((lab[r - 1, c], lab[r + 1, c])),
                    frozenset((lab[r, c - 1], lab[r, c + 1])),
                }
                assert frozenset((a + 1, b + 1)) in sides
        for i, area in enumerate(plan.areas):
            if area.kind == ROOM:
                assert onto_hall.get(i) == 1, (seed, area)
            elif area.kind == OPEN:
                assert onto_hall.get(i, 0) >= 1, (seed, area)


@pytest.mark.parametrize("shape", [(50, 100), (100, 50), (31, 47), (200, 120)])
def test_hallways_run_the_floors_length_and_are_two_or_three_cells_wide(shape):
    for seed in range(10):
        plan = office_plan(seed, *shape)
        halls = kinds(plan, HALL)
        length = max(shape)
        longest = max(max(h.bottom - h.top, h.right - h.left) for h in halls)
        assert longest >= 0.7 * length
        for hall in halls:
            assert min(hall.bottom - hall.top, hall.right - hall.left) in (2, 3)
        # The hallways are one piece, joined directly (no door between two of them).
        floor = np.zeros(plan.walls.shape, dtype=bool)
        for hall in halls:
            floor[hall.cells] = True
        assert components(~floor) == 1


@pytest.mark.parametrize(
    ("shape", "expected"), [((30, 100), 1), ((50, 100), 2), ((100, 50), 2), ((90, 160), 3)]
)
def test_a_floor_gets_the_fewest_full_length_hallways_that_keep_rows_shallow(shape, expected):
    length, across = max(shape), min(shape)

    def full_length(plan: OfficePlan) -> list[Area]:
        return [
            h for h in kinds(plan, HALL) if max(h.bottom - h.top, h.right - h.left) == length - 2
        ]

    for seed in range(10):
        plan = office_plan(seed, *shape)
        halls = full_length(plan)
        assert len(halls) == expected, seed
        # Every row of rooms is MIN_DEPTH to MAX_DEPTH deep across the hallways (an open area
        # takes the whole depth between two hallways, back-to-back rows and their wall).
        for area in plan.areas:
            if area.kind == ROOM:
                depth = area.bottom - area.top if shape[0] < shape[1] else area.right - area.left
                assert office.MIN_DEPTH <= depth <= office.MAX_DEPTH, (seed, area)
        # One hallway fewer (2 cells wide, a wall each side) would leave rows too deep, even
        # split back to back as far as the hallways allow.
        fewer = expected - 1
        if fewer:
            for back_to_back in range(fewer):
                depth = across - 2 - 4 * fewer - back_to_back
                assert depth > (fewer + 1 + back_to_back) * office.MAX_DEPTH


def test_some_count_of_hallways_fits_every_floor_up_to_1000_cells_across():
    # MAX_DEPTH is at least twice MIN_DEPTH: the rows that k and k + 1 hallways fit overlap.
    for rows in range(office.MIN_SIDE, 1_001):
        halls, bands = office._hallways(np.random.default_rng(rows), rows)
        assert halls and len(bands) == len(halls) + 1
        for band in bands:
            for top, bottom in (
                [(band.top, band.bottom)]
                if band.split is None
                else [(band.top, band.split), (band.split + 1, band.bottom)]
            ):
                assert office.MIN_DEPTH <= bottom - top <= office.MAX_DEPTH, (rows, band)


def test_rooms_in_a_row_are_alike_in_width_and_drawn_from_the_range():
    low, high = office.ROOM_WIDTH
    seen: set[int] = set()
    for seed in range(20):
        plan = office_plan(seed, 50, 100)
        rooms = sorted(kinds(plan, ROOM), key=lambda a: (a.top, a.bottom, a.left))
        widths = [a.right - a.left for a in rooms]
        assert min(widths) >= low and max(widths) <= high
        seen.update(widths)
        # A run of rooms one wall apart in the same row: widths differ by a cell at most.
        run = [rooms[0]]
        for room in [*rooms[1:], None]:
            last = run[-1]
            if room is not None and (room.top, room.bottom, room.left) == (
                last.top,
                last.bottom,
                last.right + 1,
            ):
                run.append(room)
                continue
            run_widths = [a.right - a.left for a in run]
            assert max(run_widths) - min(run_widths) <= 1, (seed, run)
            run = [room]
    # A width is drawn per row: the rows' rooms take every width of the range.
    assert seen == set(range(low, high + 1))


def test_open_plan_areas_take_about_their_share_and_hold_a_lattice_of_pillars():
    shares = []
    for seed in range(20):
        plan = office_plan(seed, 50, 100)
        opened = sum(a.area for a in kinds(plan, OPEN))
        shares.append(opened / (opened + sum(a.area for a in kinds(plan, ROOM))))
        for area in kinds(plan, OPEN):
            inside = [
                p
                for p in plan.pillars
                if area.top <= p[0]
                and p[2] <= area.bottom
                and area.left <= p[1]
                and p[3] <= area.right
            ]
            if not inside:
                continue
            sides = {(p[2] - p[0], p[3] - p[1]) for p in inside}
            assert sides in ({(1, 1)}, {(2, 2)})  # one size per area
            side = inside[0][2] - inside[0][0]
            # Two or more cells off the area's walls; a regular lattice 3 or 4 cells apart.
            assert min(p[0] for p in inside) >= area.top + 2
            assert max(p[2] for p in inside) <= area.bottom - 2
            assert min(p[1] for p in inside) >= area.left + 2
            assert max(p[3] for p in inside) <= area.right - 2
            for axis in (0, 1):
                starts = sorted({p[axis] for p in inside})
                gaps = set(np.diff(starts) - side)
                assert len(gaps) <= 1 and gaps <= {3, 4}
    assert 0.15 <= np.mean(shares) <= 0.3  # OPEN_SHARE, 0.2: about 0.22 on average
    assert all(0 < share < 0.5 for share in shares)  # every floor has some, and rooms first


def test_inner_doors_join_some_neighbours_and_some_room_doors_are_wide():
    plans = [office_plan(seed, 50, 100) for seed in range(20)]
    inner = sum(p.areas[b].kind == ROOM for p in plans for _, b, _ in p.doors)
    rooms = sum(len(kinds(p, ROOM)) for p in plans)
    assert 0.05 < inner / rooms < 0.3  # INNER_DOOR_SHARE, 0.15, of the neighbours
    sizes = [
        len(cells)
        for p in plans
        for a, b, cells in p.doors
        if p.areas[a].kind == ROOM and p.areas[b].kind == HALL
    ]
    assert set(sizes) == {1, 2}
    assert 0.1 < sizes.count(2) / len(sizes) < 0.3  # WIDE_DOOR_SHARE, 0.2 (0.18 measured)


def test_office_floors_look_unlike_rooms_plans():
    # Measured on 20 plans of each kind at 50x100: offices have rooms of nearly one size and a
    # straight hallway the floor's length; rooms plans rooms of every size and no such run.
    def longest_run(walls: np.ndarray) -> float:
        """The longest straight run of free cells along a row, as a share of the inside."""
        best = 0
        for row in ~walls:
            edges = np.flatnonzero(np.diff(np.concatenate(([0], row.astype(int), [0]))))
            best = max(best, int(np.max(edges[1::2] - edges[::2], initial=0)))
        return best / (walls.shape[1] - 2)

    def spread(areas: list[int]) -> float:
        return float(np.std(areas) / np.mean(areas))

    offices = [office_plan(seed, 50, 100) for seed in range(20)]
    rooms = [floor_plan(seed, 50, 100) for seed in range(20)]
    office_spread = [spread([a.area for a in kinds(p, ROOM)]) for p in offices]
    rooms_spread = [spread([r.area for r in p.regions if not r.corridor]) for p in rooms]
    assert max(office_spread) < 0.3 < 0.4 < min(rooms_spread)  # about 0.16 against 0.51
    assert min(longest_run(p.walls) for p in offices) > 0.95
    assert max(longest_run(p.walls) for p in rooms) < 0.8  # 0.43 on average


def test_a_tall_floor_is_built_on_its_side():
    tall = office_plan(3, 100, 50)
    halls = kinds(tall, HALL)
    assert max(h.bottom - h.top for h in halls) == 98  # the hallways run down the columns
    assert tall.walls.shape == (100, 50)


def test_a_50x100_floor_draws_well_under_a_tenth_of_a_second():
    generate_office(0, 50, 100)  # imports and caches warm
    start = time.perf_counter()
    for seed in range(20):
        generate_office(seed, 50, 100)
    assert (time.perf_counter() - start) / 20 < 0.05  # about 1 ms on an idle machine


def test_the_source_skips_no_seed_and_draws_the_generators_floor():
    # No shipped office map: the seed to skip is one the source never draws.
    assert not 0 <= OfficeMaps.shipped_seed < 2**31

    class Scripted:
        """A stand-in rng whose seed draw is 0."""

        def integers(self, high: int) -> int:
            return 0

    np.testing.assert_array_equal(OfficeMaps(50, 100)(Scripted()), generate_office(0, 50, 100))


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"height": 2}, r"an office floor needs at least 12x12 cells .*, got 2x100"),
        ({"width": 11}, r"an office floor needs at least 12x12 cells .*, got 50x11"),
        ({"height": 0}, "height must be an integer >= 1, got 0"),
    ],
)
def test_bad_parameters_are_refused_one_line_each(settings, message):
    kwargs = {"height": 50, "width": 100, **settings}
    with pytest.raises(ValueError, match=message) as err:
        OfficeMaps(**kwargs)
    assert "\n" not in str(err.value)


def test_the_generator_function_refuses_what_would_break_the_layout():
    with pytest.raises(ValueError, match="at least 12x12"):
        generate_office(0, 11, 40)


#: The layout's numbers that were parameters of the kind until 2026-11-29 (research/README.md).
REMOVED = ["room_width", "max_depth", "wide_door_share", "inner_door_share", "open_share"]


def test_the_kind_and_the_generator_take_only_a_size():
    # The registry's config model is made from the constructor's signature.
    assert list(inspect.signature(OfficeMaps.__init__).parameters) == ["self", "height", "width"]
    for function in (generate_office, office_plan):
        assert list(inspect.signature(function).parameters) == ["seed", "height", "width"]


def test_a_config_names_the_kind_with_its_parameters():
    config = config_from_dict(
        {"env": {"n_agents": 4, "map": {"office": {"height": 50, "width": 100}}}}
    )
    assert config.env.map == {"office": {"height": 50, "width": 100}}
    assert GENERATORS["office"] is OfficeMaps
    source = env_kwargs(config.env)["map"]
    assert isinstance(source, OfficeMaps) and (source.height, source.width) == (50, 100)
    env = coverage_v0.parallel_env(**env_kwargs(config.env))
    env.reset(seed=0)
    assert env.walls.shape == (50, 100) and components(env.walls) == 1
    with pytest.raises(
        ConfigError, match=r"env: map: office: an office floor needs at least 12x12 .*got 10x50"
    ):
        config_from_dict({"env": {"height": 10, "map": {"office": None}}})
    with pytest.raises(
        ConfigError, match=r"env\.map: office\.rooms: Extra inputs are not permitted"
    ):
        config_from_dict({"env": {"map": {"office": {"rooms": 2}}}})


@pytest.mark.parametrize(
    ("name", "value"), list(zip(REMOVED, ["[4, 6]", "8", "0.5", "0", "0.4"], strict=True))
)
def test_a_config_that_sets_a_removed_parameter_is_refused_like_any_unknown_key(
    name, value, tmp_path, capsys
):
    with pytest.raises(
        ConfigError, match=rf"env\.map: office\.{name}: Extra inputs are not permitted"
    ):
        config_from_dict({"env": {"map": {"office": {"height": 50, name: value}}}})
    # The command line: one line, exit code 2, nothing written.
    config = tmp_path / "tiny.yaml"
    config.write_text(
        "name: tiny\nenv: {height: 12, width: 12, n_agents: 2, max_steps: 20}\n"
        "phases: [{name: only, timesteps: 100}]\n"
    )
    capsys.readouterr()
    argv = ["run", str(config), "--set", f"env.map={{office: {{{name}: {value}}}}}"]
    assert main([*argv, "--runs-dir", str(tmp_path / "runs")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    assert f"env.map: office.{name}: Extra inputs are not permitted" in lines[0]
    assert not (tmp_path / "runs").exists()
