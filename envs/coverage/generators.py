"""Map sources: objects that draw an episode's map from the env's random generator.

As in Jumanji, the environment is handed a generator instead of switching on strings: every map
source is a :class:`MapGenerator` (``__call__(rng, keep_free) -> walls`` and a ``name``), and
:data:`GENERATORS` is the one registry of the kinds a config can name, each with the keyword
arguments of its constructor as its parameters:

* ``random``: the thesis's random maps (:func:`envs.coverage.maps.random_grid`);
* ``cave``: a new cellular-automaton cave each reset (:func:`envs.coverage.cave.generate_cave`);
* ``maze``: a new maze of corridors and chambers each reset
  (:func:`envs.coverage.maze.generate_maze`);
* ``rooms``: a new floor plan of rooms, hallways, doors and furniture each reset
  (:func:`envs.coverage.rooms.generate_rooms`);
* ``office``: a new office floor each reset, another style of floor plan: full-length hallways
  lined with rows of like rooms, and open-plan areas with pillars
  (:func:`envs.coverage.office.generate_office`; no shipped map);
* ``file``: one map file, every episode;
* ``shipped``: one shipped map (``cave_100x50``, ``maze_100x50``, ``rooms_100x50``), every
  episode.

:class:`MixGenerator` picks one of several sources per reset, with given weights, and
:class:`WithoutMaps` keeps test-only maps out of training. Every procedural map has all its free
cells connected, and the same ``rng`` state gives the same map. The procedural cave, maze and
floor plan never draw the seeds of the shipped ``cave_100x50``, ``maze_100x50`` and
``rooms_100x50``, so they never remake those test maps.

Sources may make maps of different sizes (:attr:`MapGenerator.shapes`); the env then sizes its
observation space for the largest (see ``envs/coverage_v0.py``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from envs.coverage import cave, maps, maze, office, rooms

#: Seeds a procedural source draws from: below 2**31, never the shipped maps' seeds.
_SEED_HIGH = 2**31
#: Draws :class:`WithoutMaps` makes before giving up on finding a map that is not a test map.
_MAX_REDRAWS = 100


class MapGenerator(ABC):
    """A source of maps (bool ``(rows, cols)`` arrays, True = wall).

    Attributes:
        name: The registry name of the kind (``"random"``, ``"cave"``, ...).
        shapes: Every ``(rows, cols)`` the source can make.
    """

    name: ClassVar[str]
    shapes: frozenset[tuple[int, int]]
    #: Most cells of one map the kind draws in about a second (one is drawn per reset), or
    #: ``None``: bounded only by the harness's map limit. A larger size is refused when the
    #: source is built (a config names it at validation), not found out one slow reset at a time.
    max_cells: ClassVar[int | None] = None

    @abstractmethod
    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        """A map drawn with ``rng`` (a fresh array the caller may change).

        Args:
            rng: The env's random generator; the map depends on its state alone.
            keep_free: ``(k, 2)`` cells (fixed start cells) that a source that places walls at
                random never picks; the env checks the map it gets.
        """

    @property
    def max_shape(self) -> tuple[int, int]:
        """The most rows and the most columns of any map the source makes."""
        return max(h for h, _ in self.shapes), max(w for _, w in self.shapes)

    @property
    def min_shape(self) -> tuple[int, int]:
        """The fewest rows and the fewest columns of any map the source makes."""
        return min(h for h, _ in self.shapes), min(w for _, w in self.shapes)

    @property
    def fixed(self) -> maps.MapSpec | None:
        """The map, for a source that always gives the same one (its start cells are used)."""
        return None


def _check_size(height: int, width: int) -> tuple[int, int]:
    for what, value in (("height", height), ("width", width)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{what} must be an integer >= 1, got {value!r}")
    return int(height), int(width)


#: Caps on the count parameters: a pass or a chamber costs about a map's time, so a typo
#: (``iterations: 100000000``) would make every reset take minutes.
_MAX_ITERATIONS, _MAX_MIN_REGION, _MAX_CHAMBERS = 100, 1_000_000, 10_000


def _check_count(what: str, value: Any, limit: int) -> int:
    """An integer count in ``[0, limit]``."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | np.integer)
        or not 0 <= value <= limit
    ):
        raise ValueError(f"{what} must be an integer in [0, {limit:,}], got {value!r}")
    return int(value)


def _check_share(what: str, value: float, low: float = 0.0, high: float = 1.0) -> float:
    if not low <= float(value) <= high:
        raise ValueError(f"{what} must be in [{low}, {high}], got {value!r}")
    return float(value)


class RandomMaps(MapGenerator):
    """The thesis's random maps: ``round(w*H*W)`` walls, ``w ~ U(wall_fraction)``, unreachable
    pockets filled (§4).

    Args:
        height: Rows.
        width: Columns.
        wall_fraction: ``(low, high)``, the range the wall share is drawn from each reset.
    """

    name = "random"

    def __init__(
        self, height: int, width: int, wall_fraction: tuple[float, float] = (0.15, 0.20)
    ) -> None:
        self.height, self.width = _check_size(height, width)
        self.shapes = frozenset({(self.height, self.width)})
        self.wall_fraction = maps.check_wall_fraction(wall_fraction)

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        return maps.random_grid(self.height, self.width, self.wall_fraction, rng, keep_free)


class _SeededMaps(MapGenerator):
    """A procedural generator of :mod:`envs.coverage` run with a new seed each reset, drawn from
    the env's ``rng`` and never the seed its shipped map was made with."""

    #: The seed of the shipped map this generator made (a test map: never remade).
    shipped_seed: ClassVar[int]
    #: One map in words, for messages ("a 600x600 floor plan has ..."); ``None``: the name.
    noun: ClassVar[str | None] = None

    def _set_size(self, height: int, width: int) -> None:
        self.height, self.width = _check_size(height, width)
        noun = self.noun or self.name
        if min(self.height, self.width) < 3:  # a rock border around at least one cell
            raise ValueError(f"a {noun} needs at least 3x3 cells, got {self.height}x{self.width}")
        cells, limit = self.height * self.width, self.max_cells
        if limit is not None and cells > limit:
            raise ValueError(
                f"a {self.height}x{self.width} {noun} has {cells:,} cells, over the limit "
                f"of {limit:,} ({type(self).__name__}.max_cells: a larger one takes seconds to "
                "minutes to draw, and each reset draws one)"
            )
        self.shapes = frozenset({(self.height, self.width)})

    @abstractmethod
    def _generate(self, seed: int) -> np.ndarray:
        """The map made with ``seed``."""

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        seed = int(rng.integers(_SEED_HIGH))
        while seed == self.shipped_seed:
            seed = int(rng.integers(_SEED_HIGH))
        return self._generate(seed)


class CaveMaps(_SeededMaps):
    """A new cellular-automaton cave each reset (:mod:`envs.coverage.cave` explains the steps).

    Args:
        height: Rows (at least 3: the cave has a rock border).
        width: Columns (at least 3).
        rock_share: Share of rock in the initial noise; higher gives a tighter cave.
        iterations: Smoothing passes of the cellular automaton.
        min_region: Pockets smaller than this are filled instead of joined by tunnels.
        wide_share: Share of the joining tunnels that are two cells wide.
        wander_prob: Chance per tunnel step of a random step (how much tunnels wind).
    """

    name = "cave"
    shipped_seed = cave.CAVE_SEED
    #: 250x250: about 1.2 s a map with the defaults (0.4 s at 200x200, 2.6 s at 300x300; each
    #: pocket joined relabels the whole map). docs/environment.md has the measurements.
    max_cells: ClassVar[int | None] = 62_500
    #: Most pockets to join times cells: a draw's cost is about their product (5-6 ms a join at
    #: 250x250), and the settings move the pockets as much as the size does (250x250: 243 with
    #: the defaults, 1.05 s; 3,566 with ``iterations: 0, min_region: 1``, 23 s). Twice the
    #: largest default cave's: about 2 s a draw.
    max_work: ClassVar[int] = 2 * 250 * 62_500

    def __init__(
        self,
        height: int,
        width: int,
        rock_share: float = cave.ROCK_SHARE,
        iterations: int = 4,
        min_region: int = 12,
        wide_share: float = 0.5,
        wander_prob: float = 0.25,
    ) -> None:
        self._set_size(height, width)
        self.shape = {
            "rock_share": _check_share("rock_share", rock_share),
            "iterations": int(iterations),
            "min_region": int(min_region),
            "wide_share": _check_share("wide_share", wide_share),
            "wander_prob": _check_share("wander_prob", wander_prob),
        }
        _check_count("iterations", iterations, _MAX_ITERATIONS)
        _check_count("min_region", min_region, _MAX_MIN_REGION)
        # Counted on one draw (the shipped seed's noise at this size): seeds differ little.
        pockets = cave.count_pockets(
            self.shipped_seed, self.height, self.width, rock_share, iterations, min_region
        )
        if pockets * self.height * self.width > self.max_work:
            raise ValueError(
                f"a {self.height}x{self.width} cave with rock_share {rock_share}, iterations "
                f"{iterations} and min_region {min_region} leaves {pockets:,} pockets to join "
                f"one tunnel at a time, more than a draw of about two seconds allows at this size "
                f"({self.max_work // (self.height * self.width):,}; each reset draws one): more "
                "iterations, a larger min_region, a lower rock_share or a smaller map"
            )

    def _generate(self, seed: int) -> np.ndarray:
        return cave.generate_cave(seed, self.height, self.width, **self.shape)


class MazeMaps(_SeededMaps):
    """A new maze each reset (:mod:`envs.coverage.maze` explains the steps).

    Args:
        height: Rows (at least 3: passages lie on odd rows and columns inside a rock border).
        width: Columns (at least 3).
        node_share: Share of the passage lattice that is carved.
        newest_prob: Chance to extend the newest passage rather than branch from an older one.
        straight_prob: Chance to keep a passage's direction when it can.
        n_chambers: Small chambers opened along the passages.
        loop_prob: Chance per lattice edge of an extra opening (loops).
    """

    name = "maze"
    shipped_seed = maze.MAZE_SEED
    #: 300x300: about 1 s a map with the defaults (0.3 s at 200x200; the carving loop counts the
    #: carved nodes each step). docs/environment.md has the measurements.
    max_cells: ClassVar[int | None] = 90_000

    def __init__(
        self,
        height: int,
        width: int,
        node_share: float = maze.NODE_SHARE,
        newest_prob: float = 0.7,
        straight_prob: float = 0.5,
        n_chambers: int = 14,
        loop_prob: float = maze.LOOP_PROB,
    ) -> None:
        self._set_size(height, width)
        _check_count("n_chambers", n_chambers, _MAX_CHAMBERS)
        self.shape = {
            "node_share": _check_share("node_share", node_share),
            "newest_prob": _check_share("newest_prob", newest_prob),
            "straight_prob": _check_share("straight_prob", straight_prob),
            "n_chambers": int(n_chambers),
            "loop_prob": _check_share("loop_prob", loop_prob),
        }

    def _generate(self, seed: int) -> np.ndarray:
        return maze.generate_maze(seed, self.height, self.width, **self.shape)


class RoomsMaps(_SeededMaps):
    """A new floor plan each reset (:mod:`envs.coverage.rooms` explains the steps).

    Args:
        height: Rows (at least 3: the plan has a wall border).
        width: Columns (at least 3).
        min_room: Fewest cells of a room's side where the floor is cut, in [2, 1,000].
        max_room: Most cells of a room's side, at least ``2 * min_room + 1``.
        wide_door_share: Chance in [0, 1] that a door is 2 cells wide rather than 1.
        corridor_share: Chance in [0, 1] that a cut of a long part is a 2-3 cell hallway.
        furniture_share: Share of a room's floor covered by furniture, in [0, 0.2].
        loop_share: Chance in [0, 1] of an extra door between neighbours the spanning tree of
            doors left apart (loops).
    """

    name = "rooms"
    noun = "floor plan"
    shipped_seed = rooms.ROOMS_SEED
    #: 500x500: 0.2 s a map with the defaults, up to about 1.4 s with the most rooms
    #: (``min_room: 2, max_room: 5``: the time grows with the rooms) or the most furniture.
    #: docs/environment.md has the measurements.
    max_cells: ClassVar[int | None] = 250_000

    def __init__(
        self,
        height: int,
        width: int,
        min_room: int = 4,
        max_room: int = 14,
        wide_door_share: float = 0.4,
        corridor_share: float = 0.5,
        furniture_share: float = 0.08,
        loop_share: float = 0.15,
    ) -> None:
        self._set_size(height, width)
        min_room, max_room = rooms.check_room_sides(min_room, max_room)
        self.shape = {
            "min_room": min_room,
            "max_room": max_room,
            "wide_door_share": _check_share("wide_door_share", wide_door_share),
            "corridor_share": _check_share("corridor_share", corridor_share),
            "furniture_share": _check_share(
                "furniture_share", furniture_share, *rooms.FURNITURE_RANGE
            ),
            "loop_share": _check_share("loop_share", loop_share),
        }

    def _generate(self, seed: int) -> np.ndarray:
        return rooms.generate_rooms(seed, self.height, self.width, **self.shape)


class OfficeMaps(_SeededMaps):
    """A new office floor each reset (:mod:`envs.coverage.office` explains the steps): another
    style of floor plan than ``rooms``, to test what was learned on those.

    There is no shipped office map: :attr:`shipped_seed` is -1, a seed the source never draws
    (it draws from 0 up), so no seed is skipped. The layout's numbers (room widths, rows' depth,
    door and open-plan shares) are constants of :mod:`envs.coverage.office`, not parameters.

    Args:
        height: Rows (at least 12: a hallway with a row of rooms each side, inside a wall border).
        width: Columns (at least 12).
    """

    name = "office"
    noun = "office floor"
    shipped_seed = -1
    #: None: the harness's map limit (2000x2000) bounds it. A 2000x2000 floor draws in 0.3 to
    #: 0.6 s, a 500x500 one in 0.02 s. docs/environment.md has the measurements.
    max_cells: ClassVar[int | None] = None

    def __init__(self, height: int, width: int) -> None:
        # Its own least size first: at least 12x12, and "an office floor" in the message.
        office.check_size(*_check_size(height, width))
        self._set_size(height, width)

    def _generate(self, seed: int) -> np.ndarray:
        return office.generate_office(seed, self.height, self.width)


class FixedMap(MapGenerator):
    """The same map every episode; its ``S`` start cells, if any, are the agents' starts."""

    name = "fixed"

    def __init__(self, spec: maps.MapSpec) -> None:
        self.spec = spec
        self.shapes = frozenset({spec.grid.shape})

    @property
    def fixed(self) -> maps.MapSpec:
        return self.spec

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        return self.spec.grid.copy()


class FileMap(FixedMap):
    """One map file (text format of :mod:`envs.coverage.maps`), every episode.

    Args:
        path: The file.
    """

    name = "file"

    def __init__(self, path: str) -> None:
        if not Path(path).is_file():
            raise ValueError(f"map file {str(path)!r} does not exist")
        super().__init__(maps.load_map(path))


class ShippedMap(FixedMap):
    """One shipped map (``envs/maps/<name>.txt``), every episode.

    Args:
        name: The map's name, e.g. ``"cave_100x50"``.
    """

    name = "shipped"

    def __init__(self, name: str) -> None:
        if name not in maps.shipped_maps():
            raise ValueError(
                f"unknown shipped map {name!r}; known: {', '.join(maps.shipped_maps())}"
            )
        super().__init__(maps.load_map(name))


class MixGenerator(MapGenerator):
    """A weighted mix of sources: each reset picks one with probability ``weight / sum`` (one
    draw from ``rng``), then that source draws the map from ``rng``.

    Args:
        sources: ``(weight, source)`` pairs; weights are positive.
    """

    name = "mix"

    def __init__(self, sources: Sequence[tuple[float, MapGenerator]]) -> None:
        if not sources:
            raise ValueError("a map mix needs at least one source")
        weights = np.array([float(w) for w, _ in sources])
        if not np.all(np.isfinite(weights)) or weights.min() <= 0:
            raise ValueError("mix weights must be positive numbers")
        self.sources = [g for _, g in sources]
        self.probabilities = weights / weights.sum()
        self.shapes = frozenset().union(*(g.shapes for g in self.sources))

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        index = int(rng.choice(len(self.sources), p=self.probabilities))
        return self.sources[index](rng, keep_free)


class WithoutMaps(MapGenerator):
    """``source`` with test-only maps kept out: a drawn map equal to one of ``excluded`` is
    drawn again (the random, cave, maze, rooms and office sources essentially never hit one; this
    makes it a promise rather than a likelihood).

    Args:
        source: The training source.
        excluded: Maps (bool grids) never to return.

    Raises:
        ValueError: When ``source`` always gives an excluded map (a fixed test map).
    """

    name = "without_test_maps"

    def __init__(self, source: MapGenerator, excluded: Sequence[np.ndarray]) -> None:
        self.source = source
        self.shapes = source.shapes
        self.excluded = [np.asarray(g, dtype=bool) for g in excluded]
        for spec in _fixed_maps(source):
            if self._is_excluded(spec.grid):
                raise ValueError(f"{spec.source} is a test-only map: training never draws it")

    @property
    def fixed(self) -> maps.MapSpec | None:
        return self.source.fixed

    def _is_excluded(self, walls: np.ndarray) -> bool:
        return any(g.shape == walls.shape and np.array_equal(g, walls) for g in self.excluded)

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        for _ in range(_MAX_REDRAWS):
            walls = self.source(rng, keep_free)
            if not self._is_excluded(walls):
                return walls
        raise ValueError(f"{self.source.name}: every map drawn was a test-only map")


def _fixed_maps(source: MapGenerator) -> list[maps.MapSpec]:
    """The fixed maps ``source`` can give (itself, or the fixed sources of a mix)."""
    if isinstance(source, MixGenerator):
        return [spec for g in source.sources for spec in _fixed_maps(g)]
    return [source.fixed] if source.fixed is not None else []


#: The map kinds a config can name (``env.map: {<name>: {<parameters>}}``); a kind's parameters
#: are its constructor's keyword arguments.
GENERATORS: dict[str, type[MapGenerator]] = {
    g.name: g for g in (RandomMaps, CaveMaps, MazeMaps, RoomsMaps, OfficeMaps, FileMap, ShippedMap)
}


def from_name(
    name: str | Path,
    height: int = 50,
    width: int = 50,
    wall_fraction: tuple[float, float] = (0.15, 0.20),
) -> MapGenerator:
    """The source for the env's ``map=`` string: ``"random"`` (``height`` x ``width`` maps with
    ``wall_fraction``), a shipped map's name, or a map file's path.

    Raises:
        ValueError: For an unknown name or a missing or malformed file.
    """
    name = str(name)
    if name == "random":
        return RandomMaps(height, width, wall_fraction)
    if name in maps.shipped_maps():
        return ShippedMap(name)
    return FixedMap(maps.load_map(name))  # load_map names the problem with a missing file
