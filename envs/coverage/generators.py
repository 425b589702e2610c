"""Map sources: objects that draw an episode's map from the env's random generator.

As in Jumanji, the environment is handed a generator instead of switching on strings: every map
source is a :class:`MapGenerator` (``__call__(rng, keep_free) -> walls``), and
:data:`GENERATORS` is the one registry of the procedural kinds that a config can name:

* ``random``: the thesis's random maps (:func:`envs.coverage.maps.random_grid`);
* ``cave``: a cellular-automaton cave (:func:`envs.coverage.cave.generate_cave`), a new one each
  reset, with the cave's shape parameters;
* ``maze``: a maze of corridors and chambers (:func:`envs.coverage.maze.generate_maze`);
* :class:`FixedMap`: one map (a file or a shipped name) every episode;
* :class:`MixGenerator`: a weighted mix of sources, one picked per reset.

Every generated map has all its free cells connected. The procedural cave and maze never draw the
seeds of the shipped ``cave_100x50`` and ``maze_100x50``, which are test maps only. All sources of
one environment make maps of the same size (the env's ``height`` x ``width``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from envs.coverage import cave, maps, maze

#: Seeds a procedural source draws from: below 2**31, never the shipped maps' seeds.
_SEED_HIGH = 2**31


class MapGenerator(ABC):
    """A source of maps of ``height`` x ``width`` cells (True = wall)."""

    name: ClassVar[str]

    def __init__(self, height: int, width: int) -> None:
        if height < 1 or width < 1:
            raise ValueError(f"map size must be positive, got {height}x{width}")
        self.height, self.width = int(height), int(width)

    @abstractmethod
    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        """A new map drawn with ``rng``; ``keep_free`` cells (fixed starts) are never walls
        where the source can promise it."""


class RandomMaps(MapGenerator):
    """The thesis's random maps: ``round(w*H*W)`` walls, ``w ~ U(wall_fraction)``, unreachable
    pockets filled (§4)."""

    name = "random"

    def __init__(self, height: int, width: int, wall_fraction: Sequence[float] = (0.15, 0.20)):
        super().__init__(height, width)
        self.wall_fraction = maps.check_wall_fraction(wall_fraction)

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        return maps.random_grid(self.height, self.width, self.wall_fraction, rng, keep_free)


def _fresh_seed(rng: np.random.Generator, shipped: int) -> int:
    seed = int(rng.integers(_SEED_HIGH))
    while seed == shipped:  # the shipped map is a test map: never train on it
        seed = int(rng.integers(_SEED_HIGH))
    return seed


class CaveMaps(MapGenerator):
    """A new cellular-automaton cave each reset (see :mod:`envs.coverage.cave` for the shape
    parameters: ``rock_share``, ``iterations``, ``min_region``, ``wide_share``, ``wander_prob``)."""

    name = "cave"

    def __init__(self, height: int, width: int, **shape: Any) -> None:
        super().__init__(height, width)
        self.shape = dict(shape)

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        seed = _fresh_seed(rng, cave.CAVE_SEED)
        return cave.generate_cave(seed, self.height, self.width, **self.shape)


class MazeMaps(MapGenerator):
    """A new maze each reset (see :mod:`envs.coverage.maze`: ``node_share``, ``newest_prob``,
    ``straight_prob``, ``n_chambers``, ``loop_prob``)."""

    name = "maze"

    def __init__(self, height: int, width: int, **shape: Any) -> None:
        super().__init__(height, width)
        self.shape = dict(shape)

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        seed = _fresh_seed(rng, maze.MAZE_SEED)
        return maze.generate_maze(seed, self.height, self.width, **self.shape)


class FixedMap(MapGenerator):
    """The same map every episode (a map file or a shipped map)."""

    name = "fixed"

    def __init__(self, spec: maps.MapSpec) -> None:
        super().__init__(*spec.grid.shape)
        self.spec = spec

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        return self.spec.grid.copy()


class MixGenerator(MapGenerator):
    """A weighted mix of sources: each reset picks one with probability ``weight / sum``."""

    name = "mix"

    def __init__(self, sources: Sequence[tuple[float, MapGenerator]]) -> None:
        if not sources:
            raise ValueError("a map mix needs at least one source")
        sizes = {(g.height, g.width) for _, g in sources}
        if len(sizes) != 1:
            raise ValueError(
                f"all sources of a mix must make maps of one size, got {sorted(sizes)}"
            )
        weights = np.array([float(w) for w, _ in sources])
        if not np.all(np.isfinite(weights)) or weights.min() <= 0:
            raise ValueError("mix weights must be positive numbers")
        super().__init__(*sizes.pop())
        self.sources = [g for _, g in sources]
        self.probabilities = weights / weights.sum()

    def __call__(self, rng: np.random.Generator, keep_free: np.ndarray | None = None) -> np.ndarray:
        index = int(rng.choice(len(self.sources), p=self.probabilities))
        return self.sources[index](rng, keep_free)


#: Procedural map kinds a config can name, with the keyword arguments each takes.
GENERATORS: dict[str, type[MapGenerator]] = {
    RandomMaps.name: RandomMaps,
    CaveMaps.name: CaveMaps,
    MazeMaps.name: MazeMaps,
}
_PARAMETERS: dict[str, tuple[str, ...]] = {
    "random": ("wall_fraction",),
    "cave": ("rock_share", "iterations", "min_region", "wide_share", "wander_prob"),
    "maze": ("node_share", "newest_prob", "straight_prob", "n_chambers", "loop_prob"),
}


#: Allowed values of the shape parameters: shares and chances are fractions; counts are bounded
#: so that a typo cannot make every reset take minutes (a pass or a chamber costs a map's time).
_COUNT_LIMITS: dict[str, int] = {"iterations": 100, "min_region": 1_000_000, "n_chambers": 10_000}


def _check_parameter(kind: str, name: str, value: Any) -> None:
    """A shape parameter's value: ``*_share``/``*_prob`` in [0, 1], counts in [0, limit].

    Raises:
        ValueError: naming the kind, the parameter and the allowed range.
    """
    if name in _COUNT_LIMITS:
        limit = _COUNT_LIMITS[name]
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= limit:
            raise ValueError(f"{kind}: {name} must be an integer in [0, {limit:,}], got {value!r}")
    elif name.endswith(("_share", "_prob")):
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        if not ok or not 0.0 <= value <= 1.0:  # also refuses NaN
            raise ValueError(f"{kind}: {name} must be a number in [0, 1], got {value!r}")


def from_spec(spec: Mapping[str, Any], height: int, width: int) -> MapGenerator:
    """A generator from a config mapping: ``{cave: {rock_share: 0.45}}``, ``{random: {}}`` or
    ``{mix: [{weight: 2, random: {}}, {weight: 1, maze: {n_chambers: 6}}]}``.

    Raises:
        ValueError: naming the unknown kind or parameter, or a parameter out of its range.
    """
    if not isinstance(spec, Mapping) or len(spec) != 1:
        shown = dict(spec) if isinstance(spec, Mapping) else spec
        raise ValueError(
            f"a map source is one of {', '.join([*GENERATORS, 'mix'])} with its parameters, "
            f"e.g. {{cave: {{rock_share: 0.45}}}}; got {shown!r}"
        )
    ((kind, params),) = spec.items()
    if kind == "mix":
        if not isinstance(params, list):
            raise ValueError("mix: expected a list of {weight: w, <kind>: {...}}")
        sources = []
        for item in params:
            if not isinstance(item, Mapping) or "weight" not in item:
                raise ValueError(f"mix: every source needs a weight, got {item!r}")
            rest = {k: v for k, v in item.items() if k != "weight"}
            sources.append((item["weight"], from_spec(rest, height, width)))
        return MixGenerator(sources)
    if kind not in GENERATORS:
        raise ValueError(f"unknown map kind {kind!r}; known: {', '.join([*GENERATORS, 'mix'])}")
    params = {} if params is None else params
    if not isinstance(params, Mapping):
        raise ValueError(f"{kind}: parameters must be a mapping, got {params!r}")
    unknown = set(params) - set(_PARAMETERS[kind])
    if unknown:
        raise ValueError(
            f"{kind}: unknown parameter(s) {', '.join(sorted(unknown))}; "
            f"known: {', '.join(_PARAMETERS[kind])}"
        )
    for name, value in params.items():
        _check_parameter(kind, name, value)
    return GENERATORS[kind](height, width, **params)
