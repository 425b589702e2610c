"""The coverage environment: a PettingZoo ``ParallelEnv`` (see ``envs/coverage_v0.py`` for the
documentation page)."""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from envs.coverage import generators, maps, render
from envs.coverage.frontier import Frontier, FrontierOptions
from envs.coverage.observations import (
    ObservationBuilder,
    ObservationOptions,
    add_agent_id,
    agent_id_space,
    observation_options,
)
from envs.coverage.step import credit_new_cells, resolve_moves, thesis_reward
from envs.coverage.types import (
    CELL_UNVISITED,
    CELL_VISITED,
    CELL_WALL,
    GridState,
)

DEFAULT_REWARDS: dict[str, float] = {
    "new_cell": 2.0,
    "wall_hit": -10.0,
    "step": -1.0,
    "team": 0.0,
}
#: Attempts at drawing a random map with at least ``n_agents`` free cells before giving up.
_MAX_MAP_DRAWS = 100


class CoverageEnv(ParallelEnv):
    """N agents cover an unknown grid map together. See the module ``envs.coverage_v0``."""

    metadata: dict[str, Any] = {  # noqa: RUF012 (PettingZoo convention: a class attribute)
        "name": "coverage_v0",
        "render_modes": ["rgb_array", "ansi"],
        "is_parallelizable": True,
        "render_fps": 10,
    }

    def __init__(
        self,
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
        render_mode: str | None = None,
        frontier: FrontierOptions | Mapping[str, Any] | None = None,
        agent_id: bool = False,
    ) -> None:
        _check_int("n_agents", n_agents, 1)
        _check_bool("agent_id", agent_id)
        _check_int("max_steps", max_steps, 1)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']} or None, "
                f"got {render_mode!r}"
            )
        observation = observation_options(observation)
        self.frontier = FrontierOptions.parse(frontier)
        FrontierOptions.check_fits(observation, self.frontier)
        self.rewards = _check_rewards(rewards)

        # The map source (envs/coverage/generators.py): a generator object, or built from the
        # name: "random", a shipped map or a map file.
        self.map_name = map.name if isinstance(map, generators.MapGenerator) else str(map)
        if not isinstance(map, generators.MapGenerator):
            if str(map) == "random":
                _check_int("height", height, 1)
                _check_int("width", width, 1)
                wall_fraction = maps.check_wall_fraction(wall_fraction)
            map = generators.from_name(map, height, width, wall_fraction)
        self._generator: generators.MapGenerator = map
        self.wall_fraction = getattr(map, "wall_fraction", (0.0, 0.0))
        self._map_spec = map.fixed
        if self._map_spec is not None:
            n_free = int((~self._map_spec.grid).sum())
            if n_free < n_agents:
                raise ValueError(
                    f"{self._map_spec.source} has {n_free} free cell(s), fewer than "
                    f"n_agents={n_agents}"
                )
        elif map.min_shape[0] * map.min_shape[1] < n_agents:
            height, width = map.min_shape
            raise ValueError(f"a {height}x{width} map has fewer cells than n_agents={n_agents}")
        # The current episode's map size (a mix may draw several); the largest until the first
        # reset, which is the size the observation space is made for.
        height, width = map.max_shape
        self.height, self.width = int(height), int(width)
        self.n_agents, self.max_steps = int(n_agents), int(max_steps)
        self.render_mode = render_mode

        # Fixed start cells: the constructor's, else the map file's S marks, else random each reset.
        if starts is not None:
            self._starts: np.ndarray | None = _as_starts(starts)
        elif self._map_spec is not None and self._map_spec.starts is not None:
            self._starts = _as_starts(self._map_spec.starts)
        else:
            self._starts = None
        if self._starts is not None:
            # Fixed start cells must lie on every map size the source makes.
            grid = self._map_spec.grid if self._map_spec is not None else None
            _check_starts(self._starts, self.n_agents, *self._generator.min_shape, grid)

        # One builder (and planner extension) per map size: a mix may draw maps of several sizes.
        # The space is the largest size's (with raw coordinates its bounds hold every smaller
        # map's positions).
        self.observation, self.coords = observation, coords
        self._observers: dict[tuple[int, int], tuple[ObservationBuilder, Frontier | None]] = {}
        self._observer, self._frontier = self._observer_for(self.height, self.width)
        self.observation_kind = observation.name
        self.possible_agents = [f"agent_{i}" for i in range(self.n_agents)]
        self.agents: list[str] = []
        # Agent indication: each agent's one-hot index is part of its observation (so of the
        # observation space a model is saved with); the per-agent policy routes by it.
        self.agent_id = bool(agent_id)
        space = self._observer.space()
        self._obs_space = agent_id_space(space, self.n_agents) if self.agent_id else space
        # Actions 0..4 move (up, down, left, right, stay); a planner-backed action kind of the
        # frontier option adds its actions after them (the frontier step: 5), or replaces them
        # (the goal action: one action per candidate slot).
        self._act_space = spaces.Discrete(self.frontier.n_actions if self.frontier else 5)
        self._np_random: np.random.Generator | None = None
        self._state: GridState | None = None
        self._walls = np.zeros((self.height, self.width), dtype=bool)
        self._n_free = 0
        self._n_visited = 0
        # Per-agent counters and positions as Python lists: the step works agent by agent.
        self._positions: list[tuple[int, int]] = []
        self._new_cells: list[int] = [0] * self.n_agents
        self._wall_hits: list[int] = [0] * self.n_agents

    # ------------------------------------------------------------------ spaces
    @functools.cache  # noqa: B019 (PettingZoo wants the same object per agent)
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Discrete:
        return self._act_space

    # ------------------------------------------------------------------ read-only state
    @property
    def walls(self) -> np.ndarray:
        """``bool (H, W)``, True = wall (read-only view)."""
        view = self._walls.view()
        view.flags.writeable = False
        return view

    @property
    def np_random(self) -> np.random.Generator:
        """The episode's random generator, seeded by ``reset(seed=...)`` (Gymnasium's name).

        The env draws from it only at reset; a stochastic test policy may draw its action noise
        from it, so an episode's actions depend on its seed alone.
        """
        if self._np_random is None:
            self._np_random, _ = seeding.np_random(None)
        return self._np_random

    @property
    def visited(self) -> np.ndarray:
        """``bool (H, W)``: cells the team has visited (a fresh array)."""
        return self._require_state().interior == CELL_VISITED

    @property
    def positions(self) -> np.ndarray:
        """``int (n_agents, 2)``: each agent's (row, col) (a copy)."""
        return self._require_state().positions.copy()

    @property
    def credited_by(self) -> np.ndarray:
        """``int16 (H, W)``: the agent credited with each visited cell, -1 elsewhere (a copy)."""
        return self._require_state().credited_by.copy()

    @property
    def free_cells(self) -> int:
        """Number of free cells of the current map."""
        return self._n_free

    @property
    def coverage(self) -> float:
        """The team's coverage: visited free cells / free cells."""
        return self._n_visited / self._n_free if self._n_free else 0.0

    @property
    def steps(self) -> int:
        """Steps taken in the current episode."""
        return self._require_state().steps

    # ------------------------------------------------------------------ API
    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """Start an episode.

        Args:
            seed: Seeds the env's generator (maps and start cells); later resets without a seed
                continue that generator, so a seeded env gives a repeatable sequence of episodes.
            options: ``"grid"`` (2D bool array, True = wall, same shape as the env) and/or
                ``"starts"`` (``[(row, col), ...]``) fix this episode's map and start cells.
                Other keys are ignored.

        Returns:
            Observations and infos. The infos are empty dicts: SuperSuit merges reset infos over
            the last step's infos at an automatic reset, so metrics in them would hide the
            episode's final coverage.
        """
        if seed is not None or self._np_random is None:
            self._np_random, _ = seeding.np_random(seed)
        options = options or {}
        walls = self._episode_grid(options.get("grid"))
        self.height, self.width = walls.shape
        self._observer, self._frontier = self._observer_for(self.height, self.width)
        starts = self._episode_starts(walls, options.get("starts"))

        pad = self._observer.padding
        cells = np.full((self.height + 2 * pad, self.width + 2 * pad), CELL_WALL, dtype=np.float32)
        cells[pad:-pad, pad:-pad] = np.where(walls, CELL_WALL, CELL_UNVISITED)
        credited_by = np.full((self.height, self.width), -1, dtype=np.int16)
        self._state = GridState(
            cells=cells, pad=pad, positions=starts.copy(), credited_by=credited_by
        )
        self._walls = walls
        self._n_free = int((~walls).sum())
        # Start cells are visited at reset (not credited as new ground); the lowest index owns a
        # shared start cell, as it would when entering it.
        self._positions = [tuple(p) for p in starts.tolist()]
        credit_new_cells(cells, pad, self._positions, credited_by)
        self._n_visited = int((cells == CELL_VISITED).sum())
        self._new_cells = [0] * self.n_agents
        self._wall_hits = [0] * self.n_agents
        self.agents = self.possible_agents[:]
        self._observer.reset(self._state)
        obs = self._per_agent(self._observe(self._state))
        return obs, {a: {} for a in self.agents}

    def step(
        self, actions: Mapping[str, int]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Move every agent at once (rules: ``envs/coverage_v0.py``); PettingZoo's five dicts."""
        state = self._require_state()
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        try:
            acts = [actions[a] for a in self.agents]
        except KeyError as exc:
            raise ValueError(f"no action given for {exc.args[0]}") from exc
        last = int(self._act_space.n) - 1
        if not all(0 <= a <= last for a in acts):
            raise ValueError(f"actions must be in 0..{last}, got {[int(a) for a in acts]}")
        if self._frontier is not None:
            acts = self._frontier.resolve(acts, self.np_random)

        positions, hit = resolve_moves(state.cells, state.pad, self._positions, acts)
        credited = credit_new_cells(state.cells, state.pad, positions, state.credited_by)
        self._positions = positions
        state.positions = np.array(positions, dtype=np.int64)
        state.steps += 1
        self._n_visited += sum(credited)
        new_cells = self._new_cells = [a + b for a, b in zip(self._new_cells, credited)]
        wall_hits = self._wall_hits = [a + b for a, b in zip(self._wall_hits, hit)]
        reward = thesis_reward(credited, hit, **self.rewards)

        agents = self.agents
        done = state.steps >= self.max_steps
        coverage = self._n_visited / self._n_free
        infos: dict[str, dict[str, Any]] = {}
        for i, a in enumerate(agents):
            info = {
                "coverage": coverage,
                "new_cells": new_cells[i],
                "wall_hits": wall_hits[i],
                "steps": state.steps,
            }
            if done:
                # SuperSuit turns truncation into a plain `done`; this key makes SB3 store the
                # transition as a time-out (bootstrapped), not as a terminal state.
                info["TimeLimit.truncated"] = True
            infos[a] = info
        observations = self._per_agent(self._observe(state))
        rewards = dict(zip(agents, reward))
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, done)
        if done:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | str | None:
        """``rgb_array``: an ``(H*k, W*k, 3)`` uint8 image; ``ansi``: a text picture."""
        if self.render_mode is None:
            return None
        state = self._require_state()
        if self.render_mode == "ansi":
            return render.ansi(self._walls, state.interior == CELL_VISITED, state.positions)
        return render.rgb_array(self._walls, state.credited_by, state.positions)

    def close(self) -> None:
        pass

    # ------------------------------------------------------------------ helpers
    def _observe(self, state: GridState) -> np.ndarray | dict[str, np.ndarray]:
        obs = self._observer.build(state)
        return add_agent_id(obs, self.n_agents) if self.agent_id else obs

    def _per_agent(self, obs: np.ndarray | dict[str, np.ndarray]) -> dict[str, Any]:
        """One observation per agent from a builder's batch (an array, or a dict of arrays)."""
        if isinstance(obs, dict):
            return {
                a: {key: value[i] for key, value in obs.items()} for i, a in enumerate(self.agents)
            }
        return dict(zip(self.agents, obs))

    @property
    def known(self) -> np.ndarray:
        """``bool (H, W)``: cells the team has seen, i.e. that were inside some agent's 3x3 window
        (a fresh array). Every position an agent has held is visited, so this is the visited map
        grown by one cell in every direction (diagonals included)."""
        visited = np.pad(self.visited, 1)
        height, width = self.height, self.width
        seen = np.zeros((height, width), dtype=bool)
        for dr in range(3):
            for dc in range(3):
                seen |= visited[dr : dr + height, dc : dc + width]
        return seen

    def _observer_for(self, height: int, width: int) -> tuple[ObservationBuilder, Frontier | None]:
        key = (height, width)
        if key not in self._observers:
            ext = Frontier(self.frontier, height, width) if self.frontier is not None else None
            observer = self.observation.make(height, width, self.coords, self.max_steps, ext)
            self._observers[key] = (observer, ext)
        return self._observers[key]

    def _require_state(self) -> GridState:
        if self._state is None:
            raise RuntimeError("call reset() before using the environment")
        return self._state

    def _episode_grid(self, grid: Any) -> np.ndarray:
        if grid is not None:
            walls = np.asarray(grid)
            if walls.ndim != 2:
                raise ValueError(f"options['grid'] must be a 2D array, got shape {walls.shape}")
            if walls.shape not in self._generator.shapes:
                made_for = " or ".join(str(s) for s in sorted(self._generator.shapes))
                raise ValueError(
                    f"options['grid'] has shape {walls.shape} but the env was made for "
                    f"{made_for}; pass height= and width= to match"
                )
            walls = walls.astype(bool)
            n_free = int((~walls).sum())
            if n_free == 0:
                raise ValueError("options['grid'] has no free cell")
            if n_free < self.n_agents:
                raise ValueError(
                    f"options['grid'] has {n_free} free cell(s), fewer than "
                    f"n_agents={self.n_agents}"
                )
            maps.warn_if_unreachable(walls, "options['grid']")
            return walls.copy()
        assert self._np_random is not None
        for _ in range(_MAX_MAP_DRAWS):
            walls = self._generator(self._np_random, keep_free=self._starts)
            if self._starts is not None:
                if not walls[self._starts[:, 0], self._starts[:, 1]].any():
                    return walls  # fixed start cells all in the reachable area
            elif int((~walls).sum()) >= self.n_agents:
                return walls
        need = (
            "keeps the fixed start cells connected"
            if self._starts is not None
            else (f"has at least n_agents={self.n_agents} free cells")
        )
        height, width = walls.shape
        raise ValueError(
            f"could not draw a {height}x{width} map ({self.map_name}, wall_fraction="
            f"{self.wall_fraction}) that {need} ({_MAX_MAP_DRAWS} tries)"
        )

    def _episode_starts(self, walls: np.ndarray, starts: Any) -> np.ndarray:
        if starts is not None:
            chosen = _as_starts(starts, "options['starts']")
        elif self._starts is not None:
            chosen = self._starts
        else:
            assert self._np_random is not None
            free = np.flatnonzero(~walls)
            picked = self._np_random.choice(free, size=self.n_agents, replace=False)
            return np.stack(np.divmod(picked, walls.shape[1]), axis=1).astype(np.int64)
        _check_starts(chosen, self.n_agents, *walls.shape, walls)
        return chosen


# ---------------------------------------------------------------------- validation
def _check_int(name: str, value: Any, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


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
