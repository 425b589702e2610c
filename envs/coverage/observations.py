"""Observation kinds of the coverage environment.

An observation kind turns the environment's state into every agent's observation (an array, or
a dict of arrays for a ``Dict`` space). It is a small class with a ``space()``, a ``reset(state)``
called at the start of each episode and a ``build(state)`` called after the reset and after every
step, so that new kinds can be added without touching the step logic: register its options class
(a frozen dataclass with a ``make`` method, e.g. :class:`TeamMap`) in :data:`OBSERVATIONS` and
pass ``observation="<name>"`` or an options object to the env (as Jumanji passes its observation
in). Kinds that keep per-episode arrays (the team map) start them in ``reset`` and bring them up
to date in ``build``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces

from envs.coverage.frontier import Frontier, FrontierOptions
from envs.coverage.goals import ACTION_MASK_KEY, GOALS_KEY
from envs.coverage.step import thesis_observation
from envs.coverage.teammap_kernels import ego_counts, teammap_views
from envs.coverage.types import CELL_UNVISITED, CELL_WALL, GridState, kind_options

COORD_MODES = ("normalized", "raw")


class ObservationBuilder(ABC):
    """Builds every agent's observation from a :class:`GridState` in one vectorised call.

    Args:
        height: Rows of the map.
        width: Columns of the map.
        coords: ``"normalized"`` (row/(H-1), col/(W-1)) or ``"raw"`` (row, col).
        max_steps: Episode length (for kinds that show the time elapsed).
    """

    name: ClassVar[str]
    #: Cells of padding around the grid that :meth:`build` reads (``state.cells`` is padded by
    #: the largest padding of the builder in use, so windows never need bounds checks).
    padding: int = 1

    def __init__(
        self, height: int, width: int, coords: str = "normalized", max_steps: int = 1000
    ) -> None:
        if coords not in COORD_MODES:
            raise ValueError(f"coords must be one of {COORD_MODES}, got {coords!r}")
        self.height, self.width, self.coords = height, width, coords
        self.max_steps = max_steps
        if coords == "normalized":
            # max(.., 1) keeps a one-row or one-column map finite (its coordinate is always 0).
            self._scale = np.array(
                [1.0 / max(height - 1, 1), 1.0 / max(width - 1, 1)], dtype=np.float32
            )
        else:
            self._scale = np.ones(2, dtype=np.float32)

    @abstractmethod
    def space(self) -> spaces.Space:
        """The observation space of one agent."""

    def reset(self, state: GridState) -> None:  # noqa: B027 (an optional hook)
        """Called once per episode, after ``state`` is made and before the first :meth:`build`.
        Incremental kinds start their per-episode arrays here."""

    @abstractmethod
    def build(self, state: GridState) -> np.ndarray | dict[str, np.ndarray]:
        """Every agent's observation, a fresh array (or a dict of fresh arrays) with the agents on
        the first axis: ``(n_agents, *space().shape)`` (per key for a ``Dict`` space)."""

    def build_into(self, state: GridState, out: np.ndarray | dict[str, np.ndarray]) -> None:
        """:meth:`build` written into ``out`` (zeroed arrays of that shape, views of a batch's
        arrays: the core builds every copy's part in place). Kinds that can write there
        directly override it."""
        obs = self.build(state)
        if isinstance(out, dict):
            for key, value in out.items():
                value[...] = obs[key]
        else:
            out[...] = obs

    def _coords_high(self) -> np.ndarray:
        if self.coords == "normalized":
            return np.ones(2, dtype=np.float32)
        return np.array([self.height - 1, self.width - 1], dtype=np.float32)


class ThesisObservation(ObservationBuilder):
    """The thesis's 13-element observation (§3.2).

    * 0-8: the 3x3 window around the agent, row-major from the top-left: -1 unvisited free,
      0 visited free, 1 wall or outside the grid. Element 4 is the agent's own cell (0).
    * 9-10: the agent's own (row, col).
    * 11-12: (row, col) of the nearest other agent (Euclidean, ties to the lower index); a lone
      agent sees its own position again.
    """

    name = "thesis"
    padding = 1
    #: Built for a whole batch of copies at once by the core (:mod:`envs.coverage.core`).
    batched = True

    def space(self) -> spaces.Box:
        high_xy = self._coords_high()
        low = np.concatenate([np.full(9, CELL_UNVISITED), np.zeros(4)]).astype(np.float32)
        high = np.concatenate([np.full(9, CELL_WALL), high_xy, high_xy]).astype(np.float32)
        return spaces.Box(low=low, high=high, shape=(13,), dtype=np.float32)

    def build(self, state: GridState) -> np.ndarray:
        # The batched core's compiled kernel on a batch of one: one implementation of the rule.
        obs = np.empty((1, state.positions.shape[0], 13), dtype=np.float32)
        thesis_observation(
            state.cells[None], state.pad, state.positions[None], self._scale[None], obs
        )
        return obs[0]


def _is_int(value: object) -> bool:
    """An integer (numpy's included), not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


# Categories of a cell in the team's knowledge (the team-map observation's first channels).
KNOWN_WALL, VISITED, KNOWN_FREE, UNKNOWN = 0, 1, 2, 3


class TeamMapObservation(ObservationBuilder):
    """The team's knowledge of the map, as images (a ``Dict`` of uint8 arrays, channel-first).

    A cell is *known* once it has been inside any agent's 3x3 window (start windows included);
    outside the grid is known wall. Every known cell is a wall, visited, or free and not yet
    visited; the others are unknown. Per agent:

    * ``"local"`` ``(5, crop, crop)``: the crop centred on the agent; channels known wall,
      visited, known free not visited, unknown, teammates present (0 or 255). With the planner
      extension (``frontier``) one more channel (the last), the *frontier field*: how much
      nearer each cell of the crop is to the nearest known free cell not yet visited than the
      agent's own cell is, along a shortest path through known free cells,
      ``clip(128 + 16 * (d(agent) - d(cell)), 1, 255)`` (brighter is nearer; 0 on walls,
      unknown cells and cells from which no such cell can be reached).
    * ``"global"`` ``(6, G, G)``: the whole map cut into a G x G grid of blocks (block ``i`` holds
      rows ``floor(i*H/G) .. floor((i+1)*H/G) - 1``, likewise columns, so any size or aspect
      fits); channels the share of the block visited, known free not visited, unknown and known
      wall (``round(255 * share)``; a block with no cell, on a map smaller than G, counts as
      wall), this agent's block and the teammates' blocks (255).
    * ``"ego"`` ``(5, E, E)``, only with ``ego_size=E > 0``: a coarse map centred on the agent,
      E x E blocks of ``ego_block`` x ``ego_block`` cells (the centre block is centred on the
      agent's cell), so it reaches ``(E * ego_block) // 2`` cells each way; channels the share of
      the block visited, known free not visited, unknown and known wall (outside the grid counts
      as wall), and teammates present (255). Where the absolute ``"global"`` view tells where
      the agent is on the map, this one makes "which way is unexplored ground, which way are my
      teammates" the same pattern wherever the agent stands (translation-equivariant).
    * ``"predicted_local"`` ``(1, crop, crop)``, ``"predicted_global"`` ``(1, G, G)`` and, with
      the ego view, ``"predicted_ego"`` ``(1, E, E)``, only with ``predicted=True``: a map
      prior's prediction beside the views of the same name (MapExRL's recipe, Ho et al. 2025),
      the free floor it expects where the team has not looked: each unseen cell
      ``round(255 * (1 - p_wall))``, seen cells and outside the grid 0, and the blocks of the
      coarse views the share of their cells so expected free (like the share channels). The
      prior is the goal action's (:attr:`envs.coverage.frontier.Frontier.p_wall`, asked every
      :data:`~envs.coverage.goals.PRIOR_EVERY` steps); cells seen since count as seen.
    * ``"vector"`` ``(3,)`` float32: own row / (H-1), own col / (W-1), steps / max_steps.
    * ``"frontier"`` ``(5,)`` float32, only with ``frontier``: the frontier compass. For
      each move (up, down, left, right) 1 if it takes the agent one step nearer the nearest
      known free cell not yet visited (it starts a shortest path there), else 0; then the
      distance to that cell over ``H + W`` (at most 1; 1 when none is reachable). A shortest
      path to the nearest unvisited known cell is what the frontier planner walks; the
      compass shows it beyond the crop, the field shows the other frontiers nearby. When the
      frontier options name a planner the four moves mark instead that planner's move
      (:attr:`envs.coverage.frontier.Frontier.planned_moves`: the first step towards the
      nearest such cell that no lower-index teammate claimed this step), none when it would
      stay; the distance stays the nearest cell's. The compass is written to the
      :class:`~envs.coverage.frontier.Frontier`, whose planner-backed actions follow it.

    The frontier distances ``d`` are one multi-source breadth-first search per step from every
    known free unvisited cell through *all* free cells (compiled:
    :func:`envs.coverage.teammap_kernels.frontier_views`). Going through unknown cells never
    shortens a path, so this equals the search through known cells only: a known free cell next
    to an unknown one is never visited (a visited cell's 3x3 window is known), so a path that
    crosses unknown ground reaches a source before it leaves it.

    Built incrementally: each step only the cells of the agents' new 3x3 windows are looked at,
    and only those whose category changed update the images, the per-block counts and, with
    the ego view, the counts of every ``ego_block`` x ``ego_block`` window around them, so a
    step costs ``O(agents * (crop^2 + G^2 + E^2))`` besides the frontier search, whatever the
    map's size. One compiled call per step builds every agent's views
    (:func:`envs.coverage.teammap_kernels.teammap_views`); the core calls it for each copy
    with views of the batch's arrays (:meth:`build_into`).

    Args:
        height, width, coords, max_steps: As :class:`ObservationBuilder`.
        crop: Side of the local crop (odd, >= :attr:`MIN_CROP`).
        global_size: G, blocks per side of the global view (>= :attr:`MIN_GLOBAL_SIZE`).
        ego_size: E, blocks per side of the ego view (0: no ego view; else odd and
            >= :attr:`MIN_EGO_SIZE`).
        ego_block: Cells per side of an ego block (odd, >= 1).
        frontier: The planner extension's state (:class:`envs.coverage.frontier.Frontier`):
            adds the frontier field (a crop channel) and the frontier compass; ``None``: off.
        predicted: Add the prior's views (``"predicted_*"``); needs ``frontier`` with a map
            prior (:meth:`envs.coverage.frontier.FrontierOptions.check_fits`).

    Raises:
        ValueError: For a crop or global size out of range, or views the options cannot fill.
    """

    name = "teammap"
    LOCAL_CHANNELS = 5
    GLOBAL_CHANNELS = 6
    EGO_CHANNELS = 5
    # Stable-Baselines3 reads a uint8 image as channel-first only when its first axis is (one of)
    # the smallest (``is_image_space_channels_first``; otherwise it wraps the env in
    # ``VecTransposeImage`` and swaps the axes), so no spatial side may be below the channels.
    #: Smallest crop: odd and at least the local view's 5 channels (7 with the frontier field,
    #: :meth:`min_crop`).
    MIN_CROP = 5
    #: Smallest global size: the global view's 6 channels.
    MIN_GLOBAL_SIZE = 6
    #: Smallest ego view (when on): odd and at least its 5 channels.
    MIN_EGO_SIZE = 5
    # Categories in the order of the global view's share channels.
    _SHARE_ORDER = (VISITED, KNOWN_FREE, UNKNOWN, KNOWN_WALL)

    def __init__(
        self,
        height: int,
        width: int,
        coords: str = "normalized",
        max_steps: int = 1000,
        crop: int = 15,
        global_size: int = 13,
        ego_size: int = 0,
        ego_block: int = 5,
        frontier: Frontier | None = None,
        predicted: bool = False,
    ) -> None:
        super().__init__(height, width, coords, max_steps)
        options = TeamMap(crop, global_size, ego_size, ego_block, predicted)
        FrontierOptions.check_fits(options, None if frontier is None else frontier.options)
        self.predicted = bool(predicted)
        crop, global_size = int(crop), int(global_size)
        self.crop, self.global_size = crop, global_size
        self.ego_size, self.ego_block = int(ego_size), int(ego_block)
        self.frontier = frontier is not None
        self._frontier_ext = frontier
        self.local_channels = self.LOCAL_CHANNELS + self.frontier
        #: Index of the frontier field in ``"local"`` (with ``frontier``): the last channel.
        self.frontier_channel = self.local_channels - 1
        self._frontier_scale = 1.0 / (height + width)
        # Ego block edges relative to the agent's cell: block k spans rows
        # offsets[k] .. offsets[k+1]-1, and block E//2 is centred on the agent.
        self._ego_edges = (np.arange(self.ego_size + 1) - self.ego_size // 2) * self.ego_block - (
            self.ego_block // 2
        )
        self.padding = crop // 2
        g = global_size
        # Block of each row and column: the last block whose first row is <= r.
        starts_r = (np.arange(g) * height) // g
        starts_c = (np.arange(g) * width) // g
        self._row_block = np.searchsorted(starts_r, np.arange(height), side="right") - 1
        self._col_block = np.searchsorted(starts_c, np.arange(width), side="right") - 1
        block_cells = np.zeros(g * g, dtype=np.int64)
        flat = (self._row_block[:, None] * g + self._col_block[None, :]).ravel()
        np.add.at(block_cells, flat, 1)
        self._block_cells = block_cells
        # Block index of every padded cell (-1 on the padding: outside counts in no block).
        p = self.padding
        self._block_of = np.full((height + 2 * p, width + 2 * p), -1, dtype=np.int64)
        self._block_of[p : p + height, p : p + width] = flat.reshape(height, width)
        self._block_of = self._block_of.ravel()
        self._in_map = self._block_of >= 0  # the padded cells inside the map (the prior's views)
        self._scale3 = np.array(
            [1.0 / max(height - 1, 1), 1.0 / max(width - 1, 1)], dtype=np.float32
        )

    @classmethod
    def min_crop(cls, frontier: bool = False) -> int:
        """Smallest crop: odd and at least the local view's channel count."""
        channels = cls.LOCAL_CHANNELS + bool(frontier)
        return channels + 1 - channels % 2

    def space(self) -> spaces.Dict:
        c, g, e = self.crop, self.global_size, self.ego_size
        views = {
            "local": spaces.Box(0, 255, (self.local_channels, c, c), np.uint8),
            "global": spaces.Box(0, 255, (self.GLOBAL_CHANNELS, g, g), np.uint8),
        }
        if e:
            views["ego"] = spaces.Box(0, 255, (self.EGO_CHANNELS, e, e), np.uint8)
        if self.predicted:
            views["predicted_local"] = spaces.Box(0, 255, (1, c, c), np.uint8)
            views["predicted_global"] = spaces.Box(0, 255, (1, g, g), np.uint8)
            if e:
                views["predicted_ego"] = spaces.Box(0, 255, (1, e, e), np.uint8)
        views["vector"] = spaces.Box(0.0, 1.0, (3,), np.float32)
        if self.frontier:
            views["frontier"] = spaces.Box(0.0, 1.0, (5,), np.float32)
        goal = self._frontier_ext.goal if self._frontier_ext is not None else None
        if goal is not None:
            width = self._frontier_ext.n_goal_features
            views[GOALS_KEY] = spaces.Box(-1.0, 1.0, (goal.k, width), np.float32)
            # int8, PettingZoo's and Gymnasium's convention (Discrete.sample(mask) takes it).
            views[ACTION_MASK_KEY] = spaces.Box(0, 1, (goal.k,), np.int8)
        return spaces.Dict(views)

    # ------------------------------------------------------------------ per-episode arrays
    def reset(self, state: GridState) -> None:
        p, (hp, wp) = state.pad, state.cells.shape
        if p != self.padding:
            raise ValueError(f"the grid is padded by {p}, the team map needs {self.padding}")
        # Category of every padded cell; the padding (outside the grid) is known wall.
        self._cat = np.full(hp * wp, KNOWN_WALL, dtype=np.int8)
        interior = np.zeros((hp, wp), dtype=bool)
        interior[p:-p, p:-p] = True
        self._cat[interior.ravel()] = UNKNOWN
        # One 0/255 plane per category, for the local crops.
        self._planes = np.zeros((4, hp * wp), dtype=np.uint8)
        self._planes[self._cat, np.arange(hp * wp)] = 255
        self._planes_2d = self._planes.reshape(4, hp, wp)
        # Cells per block and category; all interior cells start unknown.
        self._counts = np.zeros((self.global_size**2, 4), dtype=np.int64)
        self._counts[:, UNKNOWN] = self._block_cells
        # The global view's four share channels, kept up to date block by block.
        self._shares = np.zeros((4, self.global_size**2), dtype=np.uint8)
        self._update_shares(np.arange(self.global_size**2))
        self._wp = wp
        if self.frontier:
            # Free cells of the padded grid, flat: walls never change within an episode, so the
            # frontier field's search reads this copy instead of the (maybe strided) grid; and
            # the search's scratch arrays.
            self._free = np.ascontiguousarray(state.cells != CELL_WALL).ravel()
            self._dist = np.empty(hp * wp, dtype=np.float64)
            self._queue = np.empty(hp * wp, dtype=np.int64)
            self._needed = np.zeros(hp * wp, dtype=bool)
        else:
            self._free, self._needed = _NO_CELLS, _NO_CELLS
            self._dist, self._queue = _NO_CELLS.astype(np.float64), _NO_CELLS.astype(np.int64)
        if self.ego_size:
            self._ego_counts = ego_counts(self.height, self.width, self.ego_block)
        else:
            self._ego_counts = _NO_EGO_COUNTS

    def _update_shares(self, blocks: np.ndarray) -> None:
        """Recompute the share channels of ``blocks`` (repeats allowed) from the counts."""
        cells = self._block_cells[blocks]
        empty = cells == 0
        shares = self._counts[blocks][:, self._SHARE_ORDER] / np.maximum(cells, 1)[:, None]
        shares[empty] = (0.0, 0.0, 0.0, 1.0)  # a block with no cell counts as wall
        self._shares[:, blocks] = np.rint(255.0 * shares.T)

    def build(self, state: GridState) -> dict[str, np.ndarray]:
        n = state.positions.shape[0]
        out = {
            key: np.zeros((n, *space.shape), dtype=space.dtype)
            for key, space in self.space().spaces.items()
        }
        self.build_into(state, out)
        return out

    def build_into(self, state: GridState, out: dict[str, np.ndarray]) -> None:
        """:meth:`build` into ``out``: arrays of the space's keys, zeroed, agents first (views
        of a batch's arrays: the core builds every copy's observation in place)."""
        n = state.positions.shape[0]
        glob = out["global"].reshape(n, self.GLOBAL_CHANNELS, -1)
        compass = out["frontier"] if self.frontier else _NO_COMPASS
        teammap_views(
            state.cells, state.pad, state.positions, min(state.steps / self.max_steps, 1.0),
            self._cat, self._planes, self._counts, self._block_of, self._block_cells,
            self._shares, self._row_block, self._col_block, self.global_size, self._scale3,
            self._free, self._frontier_scale, self._dist, self._queue, self._needed,
            self._ego_counts, self.ego_block,
            out["local"], glob, out.get("ego", _NO_EGO), out["vector"], compass,
        )  # fmt: skip
        ext = self._frontier_ext
        if ext is None:
            return
        if ext.planner is not None:
            # The compass marks the planner's move instead (STAY, 4, marks none).
            compass[:, :4] = 0.0
            for i, move in enumerate(ext.planned_moves(state)):
                if move < 4:
                    compass[i, move] = 1.0
        ext.compass = compass  # what planner-backed actions of the next env step follow
        if ext.candidates is not None:  # the goal action's (made by planned_moves above)
            out[GOALS_KEY][:] = ext.candidates.features
            out[ACTION_MASK_KEY][:] = ext.candidates.mask
        if self.predicted:  # after planned_moves, which asks the prior when it is time
            self._predicted_views(state, ext.p_wall, out)

    def _predicted_views(
        self, state: GridState, p_wall: np.ndarray, out: dict[str, np.ndarray]
    ) -> None:
        """The ``"predicted_*"`` views of the wall probabilities ``p_wall`` ``(H, W)``."""
        p, (hp, wp) = self.padding, state.cells.shape
        # Expected free floor on the team's unknown cells, padded like the grid (padding: 0).
        free = np.zeros((hp, wp))
        free[p : hp - p, p : wp - p] = 1.0 - np.clip(p_wall, 0.0, 1.0)
        free *= self._cat.reshape(hp, wp) == UNKNOWN
        rows, cols = state.positions[:, 0], state.positions[:, 1]
        c = self.crop  # the crop centred on (row + p, col + p) starts at (row, col)
        windows = np.lib.stride_tricks.sliding_window_view(free, (c, c))
        out["predicted_local"][:, 0] = np.rint(255.0 * windows[rows, cols])
        g = self.global_size
        inside = self._in_map
        sums = np.bincount(self._block_of[inside], weights=free.ravel()[inside], minlength=g * g)
        share = np.where(self._block_cells > 0, sums / np.maximum(self._block_cells, 1), 0.0)
        out["predicted_global"][:, 0] = np.rint(255.0 * share).reshape(g, g)
        if self.ego_size:
            # Block sums from an integral image of the map (rows and columns clipped to it).
            h, w = self.height, self.width
            ii = np.zeros((h + 1, w + 1))
            ii[1:, 1:] = free[p : hp - p, p : wp - p].cumsum(0).cumsum(1)
            r = np.clip(rows[:, None] + self._ego_edges[None, :], 0, h)
            k = np.clip(cols[:, None] + self._ego_edges[None, :], 0, w)
            r0, r1 = r[:, :-1, None], r[:, 1:, None]
            k0, k1 = k[:, None, :-1], k[:, None, 1:]
            sums = ii[r1, k1] - ii[r0, k1] - ii[r1, k0] + ii[r0, k0]
            out["predicted_ego"][:, 0] = np.rint(255.0 * sums / self.ego_block**2)


# Empty arrays for the views that are off (the compiled call takes every array).
_NO_CELLS = np.zeros(0, dtype=bool)
_NO_COMPASS = np.zeros((0, 5), dtype=np.float32)
_NO_EGO_COUNTS = np.zeros((4, 0, 0), dtype=np.uint8)
_NO_EGO = np.zeros((0, 5, 0, 0), dtype=np.uint8)


#: Key of the agent's one-hot index in a ``Dict`` observation (``agent_id=True``).
AGENT_ID_KEY = "agent_id"


def agent_id_space(space: spaces.Space, n_agents: int) -> spaces.Space:
    """``space`` with the agent's one-hot index (``n_agents`` floats in [0, 1]) added.

    The one layout of agent indication (Terry et al. 2020), read back by the per-agent policy:
    a ``Box`` vector gets the one-hot appended at its end; a ``Dict`` gets an
    :data:`AGENT_ID_KEY` entry (a float32 vector, which every ``Dict`` policy reads as a vector).
    """
    if isinstance(space, spaces.Dict):
        if AGENT_ID_KEY in space.spaces:
            raise ValueError(f"the observation already has a {AGENT_ID_KEY!r} key")
        return spaces.Dict(
            {**space.spaces, AGENT_ID_KEY: spaces.Box(0.0, 1.0, (n_agents,), np.float32)}
        )
    if isinstance(space, spaces.Box) and len(space.shape) == 1:
        low = np.concatenate([space.low, np.zeros(n_agents, dtype=space.dtype)])
        high = np.concatenate([space.high, np.ones(n_agents, dtype=space.dtype)])
        return spaces.Box(low=low, high=high, dtype=space.dtype)  # type: ignore[arg-type]
    raise ValueError(f"agent indication needs a 1-D Box or a Dict observation, not {space}")


def add_agent_id(
    obs: np.ndarray | dict[str, np.ndarray], n_agents: int, lead: tuple[int, ...] = ()
) -> np.ndarray | dict[str, np.ndarray]:
    """Every agent's observation (agents on the first axis after the leading axes ``lead``, as
    :meth:`ObservationBuilder.build` makes them, or the core for a batch of copies) with its
    one-hot index added, in the layout of :func:`agent_id_space`."""
    if isinstance(obs, dict):
        eye = np.eye(n_agents, dtype=np.float32)
        return {**obs, AGENT_ID_KEY: np.broadcast_to(eye, (*lead, n_agents, n_agents)).copy()}
    eye = np.eye(n_agents, dtype=obs.dtype)  # leading batch axes get the same one-hot
    return np.concatenate([obs, np.broadcast_to(eye, (*obs.shape[:-2], n_agents, n_agents))], -1)


def blocked_moves(obs: np.ndarray | dict[str, np.ndarray], n_actions: int = 5) -> np.ndarray:
    """Which moves each observation shows to be blocked: ``(batch, n_actions)`` bool in action
    order (up, down, left, right, stay, then the frontier step when the env has it), True where
    the neighbouring cell in that direction is a wall or outside the grid. ``stay`` and the
    frontier step (which only walks through free cells) are never blocked.

    Read from the observation alone (what the agent itself sees), for any observation kind:
    the thesis window's elements 1, 7, 3 and 5 (value 1: wall or outside), or the team map
    crop's known-wall channel next to its centre. Used by the test policy's wall shield.

    Args:
        obs: A batch of observations: ``(batch, 13 + ...)`` thesis vectors, or a dict of stacked
            team-map arrays (``"local"`` of shape ``(batch, 5, crop, crop)``).
        n_actions: Columns of the result (5, or 6 with the frontier step).
    """
    if isinstance(obs, dict) and GOALS_KEY in obs:  # the goal action: slots, no moves
        return np.zeros((len(obs[GOALS_KEY]), n_actions), dtype=bool)
    if isinstance(obs, dict):
        local = np.asarray(obs["local"])
        c = local.shape[-1] // 2
        walls = local[:, KNOWN_WALL] > 0
        neighbours = [
            walls[:, c - 1, c],
            walls[:, c + 1, c],
            walls[:, c, c - 1],
            walls[:, c, c + 1],
        ]
    else:
        window = np.asarray(obs)[:, :9]
        neighbours = [window[:, 1] == CELL_WALL, window[:, 7] == CELL_WALL]
        neighbours += [window[:, 3] == CELL_WALL, window[:, 5] == CELL_WALL]
    blocked = np.zeros((len(neighbours[0]), n_actions), dtype=bool)
    blocked[:, :4] = np.stack(neighbours, axis=1)
    return blocked


# ---------------------------------------------------------------------- options (user-facing)
@dataclass(frozen=True)
class Thesis:
    """Options of the thesis observation (:class:`ThesisObservation`): none."""

    name: ClassVar[str] = ThesisObservation.name
    #: Whether the planner extension's field and compass fit in this observation.
    takes_frontier: ClassVar[bool] = False

    def make(
        self, height: int, width: int, coords: str, max_steps: int, frontier: Frontier | None
    ) -> ThesisObservation:
        """The builder for one map size."""
        return ThesisObservation(height, width, coords, max_steps)


@dataclass(frozen=True)
class TeamMap:
    """Options of the team-map observation (:class:`TeamMapObservation`), checked here once.

    Attributes:
        crop: Side of the local crop (odd, >= 5; >= 7 with the frontier field).
        global_size: G, blocks per side of the global view (>= 6).
        ego_size: E, blocks per side of the ego view (0: none; else odd and >= 5).
        ego_block: Cells per side of an ego block (odd).
        predicted: Add a map prior's views (``"predicted_*"``, :class:`TeamMapObservation`);
            needs the goal action with a prior (``frontier.prior``; the harness's ``env.prior``).
    """

    crop: int = 15
    global_size: int = 13
    ego_size: int = 0
    ego_block: int = 5
    predicted: bool = False
    name: ClassVar[str] = TeamMapObservation.name
    takes_frontier: ClassVar[bool] = True
    #: Largest side of an image (the cell count of the largest map the harness takes): larger
    #: sides would fail only when the env allocates its arrays.
    MAX_SIDE: ClassVar[int] = 2_000

    def __post_init__(self) -> None:
        self.check(frontier=False)

    def check(self, frontier: bool) -> None:
        """Raise ``ValueError`` naming the option that is out of range (with the frontier field
        when ``frontier``)."""
        top = self.MAX_SIDE
        least = TeamMapObservation.min_crop(frontier)
        c = self.crop
        if not (_is_int(c) and least <= c <= top and c % 2 == 1):
            with_field = " with the frontier field" if frontier else ""
            raise ValueError(
                f"crop must be an odd integer in {least}..{top}{with_field}, got {c!r}"
            )
        least = TeamMapObservation.MIN_GLOBAL_SIZE
        g = self.global_size
        if not (_is_int(g) and least <= g <= top):
            raise ValueError(f"global_size must be an integer in {least}..{top}, got {g!r}")
        least = TeamMapObservation.MIN_EGO_SIZE
        e = self.ego_size
        if not (_is_int(e) and (e == 0 or (least <= e <= top and e % 2 == 1))):
            raise ValueError(
                f"ego_size must be 0 (off) or an odd integer in {least}..{top}, got {e!r}"
            )
        b = self.ego_block
        if not (_is_int(b) and 1 <= b <= top and b % 2 == 1):
            raise ValueError(f"ego_block must be an odd integer in 1..{top}, got {b!r}")
        if not isinstance(self.predicted, bool):
            raise ValueError(f"predicted must be true or false, got {self.predicted!r}")

    def make(
        self, height: int, width: int, coords: str, max_steps: int, frontier: Frontier | None
    ) -> TeamMapObservation:
        """The builder for one map size."""
        return TeamMapObservation(
            height,
            width,
            coords,
            max_steps,
            self.crop,
            self.global_size,
            self.ego_size,
            self.ego_block,
            frontier,
            self.predicted,
        )


ObservationOptions = Thesis | TeamMap

#: Observation kinds by name: their options classes (the env's ``observation=`` argument).
OBSERVATIONS: dict[str, type[Thesis] | type[TeamMap]] = {"thesis": Thesis, "teammap": TeamMap}


def observation_options(value: str | Mapping[str, Any] | ObservationOptions) -> ObservationOptions:
    """The options object of ``value``: a kind's name (its defaults), ``{name: {option:
    value, ...}}``, or options already made.

    Raises:
        ValueError: naming the kind or option that is wrong.
    """
    if isinstance(value, (Thesis, TeamMap)):
        return value
    return kind_options(value, OBSERVATIONS, "observation")
