"""The batched simulation core: B copies of the coverage episode held in arrays and stepped
together by one call.

The PettingZoo env (:class:`envs.coverage.env.CoverageEnv`) is its batch-of-one view and
Stable-Baselines3's VecEnv over it (``harness.training.adapters.CoreVecEnv``) its batch view, so
the rules (``envs/coverage_v0.py``) are written once, here and in the compiled kernels of
:mod:`envs.coverage.step`.

State (arrays over the batch, Jumanji/NAVIX style):

* ``cells`` ``(B, Hp, Wp)`` float32: each copy's map at ``[pad : pad + h, pad : pad + w]``, padded
  with wall to the largest map the source draws (a smaller map of a mix lies in the top-left
  corner; everything around it is wall, which is what the rules say of the outside);
* ``positions`` ``(B, N, 2)``, ``credited_by`` ``(B, H, W)``, ``steps``, ``n_free``,
  ``n_visited`` ``(B,)``, ``new_cells``, ``wall_hits`` ``(B, N)``.

Every copy has its own random generator (seeded by its own reset, continued by the next), so a
copy's episodes depend on its seed alone, as an env's do. Maps and start cells are drawn per copy
at reset (once per episode); the step and the thesis observation run on the whole batch in
compiled code. Observation kinds that keep per-episode state (the team map) and the planners
run per copy on views of the batch arrays (:attr:`CoverageCore.states`), with the same
builders as a single env.

The core is built from objects (a :class:`CoreSpec`: a map source, observation options, planner
options); :meth:`CoreSpec.parse` turns the env's keyword arguments (names, mappings) into them,
in one place.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding

from envs.coverage import generators, maps
from envs.coverage.frontier import Frontier, FrontierOptions
from envs.coverage.observations import (
    ObservationBuilder,
    ObservationOptions,
    add_agent_id,
    agent_id_space,
    observation_options,
)
from envs.coverage.step import step_batch, thesis_observation, visit_cells
from envs.coverage.types import CELL_UNVISITED, CELL_VISITED, CELL_WALL, GridState

DEFAULT_REWARDS: dict[str, float] = {
    "new_cell": 2.0,
    "wall_hit": -10.0,
    "step": -1.0,
    "team": 0.0,
}
#: Attempts at drawing a random map with at least ``n_agents`` free cells before giving up.
_MAX_MAP_DRAWS = 100
#: Largest map (cells) the core builds: it keeps several arrays of the map's size per copy, and
#: a larger one would be tried until memory runs out. The harness's configs have the same bound
#: (``harness.config.schema.MAX_MAP_CELLS``).
MAX_MAP_CELLS = 4_000_000


# ---------------------------------------------------------------------- the objects
@dataclass(frozen=True, eq=False)
class CoreSpec:
    """What a core (and so an env) simulates, as objects. Build it with :meth:`parse` from the
    env's keyword arguments, or directly from objects.

    Attributes:
        source: The map source (:mod:`envs.coverage.generators`).
        n_agents: Team size.
        max_steps: Episode length.
        observation: Observation options (:mod:`envs.coverage.observations`).
        coords: ``"normalized"`` or ``"raw"``.
        rewards: The reward weights (``new_cell``, ``wall_hit``, ``step``, ``team``).
        starts: Fixed start cells ``(n_agents, 2)``, or ``None`` (random each reset).
        frontier: The planner extension's options, or ``None``.
        agent_id: Whether each observation holds the agent's one-hot index.
        map_name: The map as the user named it (``"random"``, a shipped map, a file), or the
            source's name.
    """

    source: generators.MapGenerator
    n_agents: int = 4
    max_steps: int = 1000
    observation: ObservationOptions = field(default_factory=lambda: observation_options("thesis"))
    coords: str = "normalized"
    rewards: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_REWARDS))
    starts: np.ndarray | None = None
    frontier: FrontierOptions | None = None
    agent_id: bool = False
    map_name: str = ""

    def __post_init__(self) -> None:
        if not self.map_name:
            object.__setattr__(self, "map_name", self.source.name)

    @property
    def n_actions(self) -> int:
        """Size of the action space: the five moves, and a planner-backed kind's actions."""
        return self.frontier.n_actions if self.frontier else 5

    @classmethod
    def parse(
        cls,
        map: str | Path | generators.MapGenerator = "random",
        height: int = 50,
        width: int = 50,
        wall_fraction: Sequence[float] = (0.15, 0.20),
        n_agents: int = 4,
        max_steps: int = 1000,
        observation: str | Mapping[str, Any] | ObservationOptions = "thesis",
        coords: str = "normalized",
        rewards: Mapping[str, float] | None = None,
        starts: Sequence[Sequence[int]] | None = None,
        frontier: FrontierOptions | Mapping[str, Any] | None = None,
        agent_id: bool = False,
    ) -> CoreSpec:
        """The objects from the env's keyword arguments (``envs/coverage_v0.py``).

        Raises:
            ValueError: naming the argument that is wrong.
        """
        _check_int("n_agents", n_agents, 1)
        _check_bool("agent_id", agent_id)
        _check_int("max_steps", max_steps, 1)
        observation = observation_options(observation)
        frontier = FrontierOptions.parse(frontier)
        FrontierOptions.check_fits(observation, frontier)
        merged_rewards = _check_rewards(rewards)
        map_name = map.name if isinstance(map, generators.MapGenerator) else str(map)
        if not isinstance(map, generators.MapGenerator):
            if str(map) == "random":
                _check_int("height", height, 1)
                _check_int("width", width, 1)
                _check_map_size(int(height), int(width))
                wall_fraction = maps.check_wall_fraction(wall_fraction)
            map = generators.from_name(map, height, width, wall_fraction)
        _check_map_size(*map.max_shape)
        spec = map.fixed
        if spec is not None:
            n_free = int((~spec.grid).sum())
            if n_free < n_agents:
                raise ValueError(
                    f"{spec.source} has {n_free} free cell(s), fewer than n_agents={n_agents}"
                )
        elif map.min_shape[0] * map.min_shape[1] < n_agents:
            h, w = map.min_shape
            raise ValueError(f"a {h}x{w} map has fewer cells than n_agents={n_agents}")
        # Fixed start cells: the argument's, else the map file's S marks, else random each reset.
        fixed: np.ndarray | None = None
        if starts is not None:
            fixed = _as_starts(starts)
        elif spec is not None and spec.starts is not None:
            fixed = _as_starts(spec.starts)
        if fixed is not None:
            # Fixed start cells must lie on every map size the source makes.
            grid = spec.grid if spec is not None else None
            _check_starts(fixed, int(n_agents), *map.min_shape, grid)
        return cls(
            source=map,
            n_agents=int(n_agents),
            max_steps=int(max_steps),
            observation=observation,
            coords=coords,
            rewards=merged_rewards,
            starts=fixed,
            frontier=frontier,
            agent_id=bool(agent_id),
            map_name=map_name,
        )


# ---------------------------------------------------------------------- the core
class CoverageCore:
    """B copies of the coverage episode (see the module docstring).

    Args:
        spec: What to simulate.
        copies: Batch size B.
    """

    def __init__(self, spec: CoreSpec, copies: int = 1) -> None:
        _check_int("copies", copies, 1)
        self.spec = spec
        self.copies, self.n_agents, self.max_steps = int(copies), spec.n_agents, spec.max_steps
        height, width = spec.source.max_shape
        self.max_shape = (int(height), int(width))
        # One observation builder (and planner extension) per copy and map size: builders keep
        # per-episode arrays, and a mix may draw maps of several sizes. The space is the largest
        # size's (with raw coordinates its bounds hold every smaller map's positions).
        self._observers: list[dict[tuple[int, int], tuple[ObservationBuilder, Frontier | None]]]
        self._observers = [{} for _ in range(self.copies)]
        largest, _ = self._observer_for(0, *self.max_shape)
        self.pad = largest.padding
        space = self._space = largest.space()
        self.observation_space = agent_id_space(space, self.n_agents) if spec.agent_id else space
        self.action_space = spaces.Discrete(spec.n_actions)
        #: Whether the observation kind is built for the whole batch by a compiled kernel.
        self.batched_observation = getattr(largest, "batched", False)
        b, n, p = self.copies, self.n_agents, self.pad
        self.cells = np.full((b, height + 2 * p, width + 2 * p), CELL_WALL, dtype=np.float32)
        self.positions = np.zeros((b, n, 2), dtype=np.int64)
        self.credited_by = np.full((b, height, width), -1, dtype=np.int16)
        self.steps = np.zeros(b, dtype=np.int64)
        self.n_free = np.zeros(b, dtype=np.int64)
        self.n_visited = np.zeros(b, dtype=np.int64)
        self.new_cells = np.zeros((b, n), dtype=np.int64)
        self.wall_hits = np.zeros((b, n), dtype=np.int64)
        self.scale = np.ones((b, 2), dtype=np.float32)
        # Scratch arrays of the step (overwritten each call).
        self._hit = np.zeros((b, n), dtype=np.int64)
        self._credited = np.zeros((b, n), dtype=np.int64)
        r = spec.rewards
        self._weights = np.array(
            [r["new_cell"], r["wall_hit"], r["step"], r["team"]], dtype=np.float64
        )
        #: Per copy: the episode's walls ``bool (h, w)``, its random generator, its state as
        #: views of the batch arrays (for builders, planners and rendering), its builder and
        #: planner extension.
        self.walls: list[np.ndarray] = [np.zeros((0, 0), dtype=bool)] * b
        self.rngs: list[np.random.Generator | None] = [None] * b
        self.states: list[GridState | None] = [None] * b
        self.observers: list[ObservationBuilder] = [largest] * b
        self.frontiers: list[Frontier | None] = [None] * b

    # ------------------------------------------------------------------ episodes
    def rng(self, copy: int) -> np.random.Generator:
        """Copy ``copy``'s generator (made unseeded on first use, as Gymnasium's ``np_random``)."""
        if self.rngs[copy] is None:
            self.rngs[copy], _ = seeding.np_random(None)
        return self.rngs[copy]

    def reset(
        self, copy: int, seed: int | None = None, options: Mapping[str, Any] | None = None
    ) -> None:
        """Start copy ``copy``'s next episode: draw its map and start cells from its generator
        (seeded by ``seed``, else continued), or take them from ``options`` (``"grid"``,
        ``"starts"``). The observation is :meth:`observe`'s.

        Raises:
            ValueError: naming the problem with ``options`` or with the map source.
        """
        if options is not None and not isinstance(options, Mapping):
            raise ValueError(
                f"options must be a dict (keys 'grid', 'starts') or None, got "
                f"{type(options).__name__} {_describe(options)}"
            )
        if seed is not None or self.rngs[copy] is None:
            self.rngs[copy], _ = seeding.np_random(seed)
        options = options or {}
        walls = self._episode_grid(copy, options.get("grid"))
        h, w = walls.shape
        observer, frontier = self._observer_for(copy, h, w)
        starts = self._episode_starts(copy, walls, options.get("starts"))
        p, b = self.pad, copy
        self.cells[b] = CELL_WALL
        self.cells[b, p : p + h, p : p + w] = np.where(walls, CELL_WALL, CELL_UNVISITED)
        self.credited_by[b] = -1
        self.positions[b] = starts
        # Start cells are visited at reset (not credited as new ground); the lowest index owns a
        # shared start cell, as it would when entering it.
        sl = slice(b, b + 1)
        visit_cells(self.cells[sl], p, self.positions[sl], self.credited_by[sl], self._credited[sl])
        self.n_visited[b] = int(self._credited[b].sum())
        self.n_free[b] = int((~walls).sum())
        self.steps[b] = 0
        self.new_cells[b] = 0
        self.wall_hits[b] = 0
        self.scale[b] = getattr(observer, "_scale", 1.0)
        self.walls[b] = walls
        self.observers[b], self.frontiers[b] = observer, frontier
        state = GridState(
            cells=self.cells[b, : h + 2 * p, : w + 2 * p],
            pad=p,
            positions=self.positions[b],
            credited_by=self.credited_by[b, :h, :w],
        )
        self.states[b] = state
        observer.reset(state)

    def step(self, actions: np.ndarray | Sequence[Any]) -> tuple[np.ndarray, np.ndarray]:
        """Step every copy with ``actions`` ``(B, N)`` (an integer array, or any array or sequence
        of ``B * N`` values in copy-major order); planner-backed actions are replaced by their
        moves first.

        Returns:
            ``(rewards, done)``: float64 ``(B, N)`` and bool ``(B,)`` (the copies whose episode
            reached ``max_steps``: all their agents are truncated).

        Raises:
            ValueError: for an action that is not an integer of the action space (a float, a
                string, ``None``, NaN, an array, or out of range), naming the agent, the value
                and what is allowed; nothing is stepped.
        """
        acts = self._checked_actions(actions)
        if self.spec.frontier is not None and self.spec.frontier.action is not None:
            for b in range(self.copies):
                acts[b] = self.frontiers[b].resolve(acts[b].tolist(), self.rng(b))
        rewards = np.empty((self.copies, self.n_agents), dtype=np.float64)
        step_batch(
            self.cells,
            self.pad,
            self.positions,
            acts,
            self.credited_by,
            self.steps,
            self.n_visited,
            self.new_cells,
            self.wall_hits,
            self._weights,
            self._hit,
            self._credited,
            rewards,
        )
        if not self.batched_observation:
            for b, state in enumerate(self.states):
                state.steps = int(self.steps[b])
        return rewards, self.steps >= self.max_steps

    def _checked_actions(self, actions: np.ndarray | Sequence[Any]) -> np.ndarray:
        """``actions`` as int64 ``(B, N)``, after the one check of what an action may be: an
        integer of ``0..n-1`` (Python's or numpy's, a 0-d integer array too: what Gymnasium's
        ``Discrete.contains`` takes; a bool or a float, even ``2.0``, is not one).

        An integer array (SB3's, the evaluation's) is checked by its dtype and two reductions,
        once per step for the whole batch; anything else (the PettingZoo env's per-agent values)
        value by value, so the message can name the offending agent.
        """
        n = self.copies * self.n_agents
        last = int(self.action_space.n) - 1
        if isinstance(actions, np.ndarray) and actions.dtype.kind in "iu":
            if actions.size != n:
                raise ValueError(
                    f"expected {n} actions ({self.copies} copies x {self.n_agents} agents), "
                    f"got an array of shape {actions.shape}"
                )
            acts = actions.astype(np.int64).reshape(self.copies, self.n_agents)
            if acts.min() >= 0 and acts.max() <= last:
                return acts
            values: list[Any] = acts.ravel().tolist()
        else:
            if isinstance(actions, (list, tuple)):
                values = list(actions)
            else:  # another array, or a lone value: its elements as they are
                values = list(np.asarray(actions, dtype=object).ravel())
            if len(values) != n:
                raise ValueError(
                    f"expected {n} actions ({self.copies} copies x {self.n_agents} agents), "
                    f"got {len(values)}"
                )
        for k, value in enumerate(values):
            if not _is_action(value, last):
                b, i = divmod(k, self.n_agents)
                who = agent_name(i) if self.copies == 1 else f"{agent_name(i)} of copy {b}"
                raise ValueError(
                    f"actions must be in 0..{last} (integers), got {_describe(value)} for {who}"
                )
        return np.array([int(v) for v in values], dtype=np.int64).reshape(
            self.copies, self.n_agents
        )

    # ------------------------------------------------------------------ observations
    def observe(self, copies: slice | None = None) -> np.ndarray | dict[str, np.ndarray]:
        """Every agent's observation of ``copies`` (default all), agents second:
        ``(B', N, *shape)`` (per key for a ``Dict`` space), fresh arrays. Call it once after each
        reset and step: the team map is built incrementally."""
        sl = copies if copies is not None else slice(0, self.copies)
        if self.batched_observation:
            out = np.empty((len(self.cells[sl]), self.n_agents, 13), dtype=np.float32)
            thesis_observation(self.cells[sl], self.pad, self.positions[sl], self.scale[sl], out)
            return add_agent_id(out, self.n_agents) if self.spec.agent_id else out
        # Other kinds: each copy's builder writes into its part of fresh batch arrays.
        indices = range(*sl.indices(self.copies))
        out = _zeros(self._space, (len(indices), self.n_agents))
        for j, b in enumerate(indices):
            part = {key: a[j] for key, a in out.items()} if isinstance(out, dict) else out[j]
            self.observers[b].build_into(self.states[b], part)
        return add_agent_id(out, self.n_agents, (len(indices),)) if self.spec.agent_id else out

    @staticmethod
    def flat(obs: np.ndarray | dict[str, np.ndarray]) -> np.ndarray | dict[str, np.ndarray]:
        """:meth:`observe`'s ``(copies, n_agents, ...)`` as one copy-major batch of agents
        ``(copies * n_agents, ...)`` (views): slot ``k`` is agent ``k % n_agents`` of copy
        ``k // n_agents``, the layout of SB3's slots and of a batched policy's input."""
        if isinstance(obs, dict):
            return {key: value.reshape(-1, *value.shape[2:]) for key, value in obs.items()}
        return obs.reshape(-1, *obs.shape[2:])

    # ------------------------------------------------------------------ infos
    def infos(self, copy: int) -> list[dict[str, Any]]:
        """Each agent's info after a step of copy ``copy``: ``coverage`` (the team's),
        ``new_cells``, ``wall_hits`` (this agent's so far), ``steps``, and on the last step
        ``"TimeLimit.truncated": True`` (SuperSuit and the core's VecEnv report truncation as a
        plain ``done``; this key makes SB3 store the transition as a time-out)."""
        steps = int(self.steps[copy])
        coverage = int(self.n_visited[copy]) / int(self.n_free[copy])
        done = steps >= self.max_steps
        out = []
        for new, hits in zip(self.new_cells[copy].tolist(), self.wall_hits[copy].tolist()):
            info = {"coverage": coverage, "new_cells": new, "wall_hits": hits, "steps": steps}
            if done:
                info["TimeLimit.truncated"] = True
            out.append(info)
        return out

    # ------------------------------------------------------------------ helpers
    def _observer_for(
        self, copy: int, height: int, width: int
    ) -> tuple[ObservationBuilder, Frontier | None]:
        key = (height, width)
        built = self._observers[copy]
        if key not in built:
            spec = self.spec
            ext = Frontier(spec.frontier, height, width) if spec.frontier is not None else None
            observer = spec.observation.make(height, width, spec.coords, spec.max_steps, ext)
            built[key] = (observer, ext)
        return built[key]

    def _episode_grid(self, copy: int, grid: Any) -> np.ndarray:
        source, n_agents, starts = self.spec.source, self.n_agents, self.spec.starts
        if grid is not None:
            walls = np.asarray(grid)
            if walls.ndim != 2:
                raise ValueError(f"options['grid'] must be a 2D array, got shape {walls.shape}")
            if walls.shape not in source.shapes:
                made_for = " or ".join(str(s) for s in sorted(source.shapes))
                raise ValueError(
                    f"options['grid'] has shape {walls.shape} but the env was made for "
                    f"{made_for}; pass height= and width= to match"
                )
            walls = walls.astype(bool)
            n_free = int((~walls).sum())
            if n_free == 0:
                raise ValueError("options['grid'] has no free cell")
            if n_free < n_agents:
                raise ValueError(
                    f"options['grid'] has {n_free} free cell(s), fewer than n_agents={n_agents}"
                )
            maps.warn_if_unreachable(walls, "options['grid']")
            return walls.copy()
        rng = self.rng(copy)
        for _ in range(_MAX_MAP_DRAWS):
            walls = source(rng, keep_free=starts)
            if starts is not None:
                if not walls[starts[:, 0], starts[:, 1]].any():
                    return walls  # fixed start cells all in the reachable area
            elif int((~walls).sum()) >= n_agents:
                return walls
        need = (
            "keeps the fixed start cells connected"
            if starts is not None
            else f"has at least n_agents={n_agents} free cells"
        )
        h, w = walls.shape
        raise ValueError(
            f"could not draw a {h}x{w} map ({source.name}, wall_fraction="
            f"{getattr(source, 'wall_fraction', (0.0, 0.0))}) that {need} ({_MAX_MAP_DRAWS} tries)"
        )

    def _episode_starts(self, copy: int, walls: np.ndarray, starts: Any) -> np.ndarray:
        if starts is not None:
            chosen = _as_starts(starts, "options['starts']")
        elif self.spec.starts is not None:
            chosen = self.spec.starts
        else:
            free = np.flatnonzero(~walls)
            picked = self.rng(copy).choice(free, size=self.n_agents, replace=False)
            return np.stack(np.divmod(picked, walls.shape[1]), axis=1).astype(np.int64)
        _check_starts(chosen, self.n_agents, *walls.shape, walls)
        return chosen

    # ------------------------------------------------------------------ read-only views
    def visited(self, copy: int) -> np.ndarray:
        """``bool (h, w)``: cells the team of copy ``copy`` has visited (a fresh array)."""
        return self.states[copy].interior == CELL_VISITED

    def coverage(self, copy: int) -> float:
        n_free = int(self.n_free[copy])
        return int(self.n_visited[copy]) / n_free if n_free else 0.0


def _zeros(space: spaces.Space, lead: tuple[int, ...]) -> np.ndarray | dict[str, np.ndarray]:
    """Zeroed arrays of ``space`` (per key for a ``Dict``) with the leading axes ``lead``."""
    if isinstance(space, spaces.Dict):
        return {key: _zeros(sub, lead) for key, sub in space.spaces.items()}  # type: ignore[misc]
    return np.zeros((*lead, *space.shape), dtype=space.dtype)


# ---------------------------------------------------------------------- validation
def agent_name(i: int) -> str:
    """The name of agent ``i`` (PettingZoo's ``possible_agents`` of the env)."""
    return f"agent_{i}"


def _is_action(value: Any, last: int) -> bool:
    """Whether ``value`` is an action of ``Discrete(last + 1)``: a Python or numpy integer (a
    0-d integer array too), not a bool, in ``0..last``."""
    if isinstance(value, np.ndarray):
        if value.shape != () or value.dtype.kind not in "iu":
            return False
        value = value.item()
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        return False
    return 0 <= value <= last


def _describe(value: Any) -> str:
    """``value`` for a one-line message: an array by its shape and dtype, anything else by its
    ``repr`` (a numpy scalar as the Python number it holds), cut to 60 characters."""
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape} ({value.dtype})"
    text = repr(value.item() if isinstance(value, np.generic) else value)
    text = " ".join(text.split())
    return text if len(text) <= 60 else text[:57] + "..."


def _check_int(name: str, value: Any, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


def _check_map_size(height: int, width: int) -> None:
    if height * width > MAX_MAP_CELLS:
        raise ValueError(
            f"a {height}x{width} map has {height * width:,} cells, more than the "
            f"{MAX_MAP_CELLS:,} the core handles"
        )


def _check_bool(name: str, value: Any) -> None:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")


def _check_rewards(rewards: Mapping[str, float] | None) -> dict[str, float]:
    merged = dict(DEFAULT_REWARDS)
    if rewards is not None:
        unknown = set(rewards) - set(DEFAULT_REWARDS)
        if unknown:
            raise ValueError(
                f"unknown reward key(s) {sorted(unknown)}; known: {sorted(DEFAULT_REWARDS)}"
            )
        for key, value in rewards.items():
            # A NaN or infinite weight would only show as a NaN loss once training has started.
            real = isinstance(value, (int, float, np.integer, np.floating))
            if isinstance(value, bool) or not real or not math.isfinite(value):
                raise ValueError(f"rewards.{key} must be a finite number, got {value!r}")
        merged.update({k: float(v) for k, v in rewards.items()})
    if not 0.0 <= merged["team"] <= 1.0:
        raise ValueError(f"rewards.team must be in [0, 1], got {merged['team']}")
    return merged


def _as_starts(starts: Any, name: str = "starts") -> np.ndarray:
    arr = np.asarray(starts)
    if arr.ndim != 2 or arr.shape[1] != 2 or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must be a list of integer (row, col) pairs, got {starts!r}")
    return arr.astype(np.int64)


def _check_starts(
    starts: np.ndarray, n_agents: int, height: int, width: int, walls: np.ndarray | None
) -> None:
    if len(starts) != n_agents:
        raise ValueError(f"{len(starts)} start cell(s) given for n_agents={n_agents}")
    for r, c in starts.tolist():
        if not (0 <= r < height and 0 <= c < width):
            raise ValueError(f"start cell {(r, c)} is off the {height}x{width} map")
        if walls is not None and walls[r, c]:
            raise ValueError(f"start cell {(r, c)} is on a wall")
    if len({tuple(s) for s in starts.tolist()}) != len(starts):
        raise ValueError(f"start cells must be distinct, got {starts.tolist()}")
