"""Experiment configuration: typed schema, YAML loading and ``--set`` overrides.

This is the one place that turns a YAML file into objects. Every section is a pydantic model that
rejects unknown keys, and every default is the thesis's (Table 4.1). A config looks like::

    name: ddqn_4agents
    seed: 0
    env: {n_agents: 4, max_steps: 1000}        # arguments of coverage_v0
    vec: {copies: 4}                            # env copies; VecEnv slots = copies * n_agents
    algo: {policy: MlpPolicy, net_arch: [512, 512, 512]}
    phases:                                     # run in order on one model and one buffer
      - {name: initial, timesteps: 2000000, ...}
      - {name: optimizing, timesteps: 1000000, ...}
    eval: {every: 100000, episodes: 20}
    checkpoint: {every: 100000}

Step counts (``timesteps``, schedule ``steps``, ``eval.every``, ``checkpoint.every``,
``target_update_interval``, ``learning_starts``) count transitions, i.e. agent-steps, as SB3's
``num_timesteps`` does for a VecEnv; ``train_freq`` counts env steps (one step of every slot).
"""

from __future__ import annotations

import dataclasses
import hashlib
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, Union, get_args

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    PrivateAttr,
    Tag,
    ValidationInfo,
    field_validator,
    model_validator,
)

from envs.coverage import generators, maps
from envs.coverage.env import DEFAULT_REWARDS
from envs.coverage.frontier import PLANNERS, FrontierOptions
from envs.coverage.maps import check_wall_fraction, shipped_maps
from envs.coverage.observations import observation_options
from envs.coverage.rollouts import SampledChooser
from harness.config.maps import build_source, parse_source
from harness.config.pettingzoo import (
    DEFAULT_STEP_LIMIT,
    EnvSpaces,
    agent_groups,
    check_select,
    indicated_spaces,
    masked,
    probe,
)
from harness.sb3.registry import DEFAULT_POLICY, POLICIES


class ConfigError(ValueError):
    """A config problem, with a one-line message naming the file and key."""


class _Section(BaseModel):
    # No NaN or infinity anywhere: a NaN reward or an infinite learning rate would only show as a
    # NaN loss (or an error deep in the replay buffer) once training has started.
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


Fraction = Annotated[float, Field(ge=0.0, le=1.0)]

#: Largest seed: numpy and torch take seeds below 2**32, and episode ``k`` of an evaluation uses
#: ``seed + k`` (a resumed run ``seed + 100_000 * resumes``), so seeds stay below 2**31.
MAX_SEED = 2**31 - 1
Seed = Annotated[int, Field(ge=0, le=MAX_SEED)]

#: Largest map (cells): the env keeps several arrays of the map's size per env copy.
MAX_MAP_CELLS = 4_000_000

#: Largest config file: configs are a few KB; anything this large is not one.
MAX_CONFIG_BYTES = 1 << 20

#: Most replay-buffer transitions: more than any machine holds; the memory check says so with
#: an estimate below this, above it the numbers stop being numbers.
MAX_BUFFER_SIZE = 1 << 40

#: Most torch threads: far beyond any useful count, and below where torch fails to start them.
MAX_THREADS = 256

#: Most VecEnv slots (``vec.copies`` x the env's agents): 16 times the largest run measured (64
#: copies of 4 agents); beyond, the arrays of one step alone take minutes to fill, and a run
#: would neither train nor stop on a signal in any useful time.
MAX_SLOTS = 4096

#: Most maps ``eval.rollout.samples`` rolls out at each decision: 16 times the most measured
#: (docs/results.md); each costs a rollout of every slot, so more would take days an episode.
MAX_ROLLOUT_SAMPLES = 256


def _registered(name: str, registry: Mapping[str, Any], kind: str) -> str:
    """``name`` if the registry of its kind knows it, else a ValueError listing the known ones."""
    if name not in registry:
        raise ValueError(f"unknown {kind} {name!r}; known: {', '.join(registry)}")
    return name


class RewardsConfig(_Section):
    """Reward weights of eq. 3.1 (defaults: the env's ``DEFAULT_REWARDS``)."""

    new_cell: float = DEFAULT_REWARDS["new_cell"]
    wall_hit: float = DEFAULT_REWARDS["wall_hit"]
    step: float = DEFAULT_REWARDS["step"]
    team: Fraction = DEFAULT_REWARDS["team"]
    """Share of the team's new cells in each agent's ``new_cell`` reward (0: its own cells, the
    thesis's; 1: every cell the team finds)."""


def _check_map_file_size(path: Path) -> None:
    """Refuse a map file of more than :data:`MAX_MAP_CELLS` cells, the bound generated maps obey
    (counted line by line, stopping at the bound: no huge file is read whole)."""
    cells = 0
    try:
        with path.open("rb") as f:
            for line in f:
                cells += len(line.rstrip(b"\r\n"))
                if cells > MAX_MAP_CELLS:
                    raise ValueError(
                        f"map file {str(path)!r} has more than the {MAX_MAP_CELLS:,} cells this "
                        "harness handles"
                    )
    except OSError as exc:
        raise ValueError(f"cannot read map file {str(path)!r} ({exc.strerror})") from None


def _no_prior(seen: Any, free: Any) -> Any:
    """A stand-in map prior: what the config checks of ``env.prior`` before the factory loads
    the real one (:meth:`EnvConfig._frontier_fits_observation`)."""
    raise NotImplementedError


class EnvConfig(_Section):
    """Arguments of ``coverage_v0.parallel_env`` (see ``envs/coverage_v0.py``)."""

    map: str | dict[str, Any] = "random"
    """``random``, a shipped map's name, a map file, or a map source of the generator registry
    (``{cave: {...}}``, ``{maze: {...}}``, ``{random: {...}}``, ``{file: {path: ...}}``,
    ``{shipped: {name: ...}}`` or ``{mix: [{weight: w, <source>}, ...]}``; see
    ``harness/config/maps.py``); a source's size defaults to ``height`` x ``width``."""
    test_maps: list[str] = []
    """Shipped map names or map files kept for testing: a generated training map equal to one is
    drawn again, a mix may not contain one, and ``harness run`` refuses to train on one."""
    height: PositiveInt = 50
    width: PositiveInt = 50
    wall_fraction: tuple[float, float] = (0.15, 0.20)
    n_agents: PositiveInt = 4
    max_steps: PositiveInt = 1000
    observation: str | dict[str, dict[str, Any] | None] = "thesis"
    """An observation kind of the env's registry (``envs.coverage.observations.OBSERVATIONS``):
    ``thesis`` (13 numbers) or ``teammap`` (images of the team's knowledge), or ``{teammap:
    {crop: 15, global_size: 13, ego_size: 0, ego_block: 5, predicted: false}}`` with its options
    (checked by the env's ``TeamMap``; ``predicted`` shows ``prior``'s prediction as images)."""
    frontier: dict[str, Any] | None = None
    """The planner extension (``envs.coverage.frontier``, which checks it): ``null`` (off), or
    ``{action: step | {goal: {k: 8}} | null, planner: <a planner of the registry> | null}``: the
    field and compass in the team map, a planner-backed action (the frontier step, or the goal
    action's ``k`` candidate targets), and the planner the compass follows."""
    prior: str | None = None
    """A map prior (docs/prior.md): a prior run's folder or its ``model.zip``, relative to the
    current directory like ``runs/``, whose prediction the goal action's candidates carry as
    two more features (``envs.coverage.goals.PRIOR_FEATURES``) and, with the team map's
    ``predicted: true``, images; ``null``: none. Needs the goal action (``frontier: {action:
    {goal: ...}}``)."""
    coords: Literal["normalized", "raw"] = "normalized"
    rewards: RewardsConfig = RewardsConfig()
    starts: list[tuple[int, int]] | None = None
    _agent_id: bool = PrivateAttr(default=False)
    """Whether each observation holds the agent's one-hot index (the env's ``agent_id``): not a
    key of its own, derived from ``algo.sharing`` (its one owner) when :class:`ExperimentConfig`
    resolves its sections (:meth:`with_agent_id`)."""
    map_sha256: str | None = None
    """For a map file: SHA-256 of its content. Filled in when the config is loaded (with the
    file's absolute path in ``map``), so a run's ``config.yaml`` names exactly the map it was made
    with, from any directory; loading that config again checks the file is unchanged."""

    @model_validator(mode="before")
    @classmethod
    def _resolve_map_file(cls, data: Any) -> Any:
        # Once, when the config is loaded: a relative path is taken from the current directory,
        # then stored absolute with the content's hash (not re-resolved where it is read later).
        if not isinstance(data, dict):
            return data
        name = data.get("map", "random")
        if not isinstance(name, str) or name == "random" or name in shipped_maps():
            return data
        path = Path(name).expanduser()
        if not path.is_file():
            return data  # _map_exists names the problem
        try:
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
        except OSError as exc:
            raise ValueError(f"cannot read map file {name!r} ({exc.strerror})") from None
        given = data.get("map_sha256")
        if given is not None and given != digest:
            raise ValueError(
                f"map file {str(path)!r} has changed since this config was written "
                f"(sha256 {digest[:12]}..., the config says {str(given)[:12]}...)"
            )
        return {**data, "map": str(path.resolve()), "map_sha256": digest}

    @field_validator("observation")
    @classmethod
    def _known_observation(cls, v: str | dict[str, Any]) -> str | dict[str, Any]:
        observation_options(v)  # the env's options class checks the kind and its options
        return v

    @field_validator("frontier")
    @classmethod
    def _frontier_options(cls, v: dict[str, Any] | None) -> dict[str, Any] | None:
        options = FrontierOptions.parse(v)
        return None if options is None else options.config()

    @model_validator(mode="after")
    def _frontier_fits_observation(self) -> EnvConfig:
        options = self.frontier_options
        if self.prior is not None:
            # The env owns the rules (a prior needs the goal action; the team map's predicted
            # views need a prior): ask its options with a stand-in for the prior the factory
            # will load.
            try:
                options = dataclasses.replace(options or FrontierOptions(), prior=_no_prior)
            except ValueError as exc:
                raise ValueError(f"prior: {exc} (or drop env.prior)") from None
            if not Path(self.prior).exists():
                raise ValueError(f"prior: {self.prior!r} is no prior run folder or prior file")
        FrontierOptions.check_fits(observation_options(self.observation), options)
        return self

    @property
    def observation_kind(self) -> str:
        """The observation kind's name (``thesis``, ``teammap``)."""
        return observation_options(self.observation).name

    @property
    def frontier_options(self) -> FrontierOptions | None:
        """``frontier`` as the env's options object."""
        return FrontierOptions.parse(self.frontier)

    @field_validator("wall_fraction")
    @classmethod
    def _fraction_range(cls, v: tuple[float, float]) -> tuple[float, float]:
        return check_wall_fraction(v)

    @field_validator("map")
    @classmethod
    def _map_exists(cls, v: str | dict[str, Any]) -> str | dict[str, Any]:
        if isinstance(v, dict):
            return parse_source(v)
        if v != "random" and v not in shipped_maps() and not Path(v).is_file():
            raise ValueError(
                f"{v!r} is not 'random', a shipped map ({', '.join(shipped_maps())}) "
                "or an existing map file"
            )
        if Path(v).is_file() and v not in shipped_maps():
            _check_map_file_size(Path(v))
        return v

    @field_validator("test_maps")
    @classmethod
    def _test_maps_exist(cls, v: list[str]) -> list[str]:
        for name in v:
            if name not in shipped_maps() and not Path(name).is_file():
                raise ValueError(f"{name!r} is neither a shipped map nor an existing map file")
        return [name if name in shipped_maps() else str(Path(name).resolve()) for name in v]

    @model_validator(mode="after")
    def _enough_cells(self) -> EnvConfig:
        if self.map == "random" or isinstance(self.map, dict):
            if isinstance(self.map, dict):
                try:  # at env.height x env.width where the source names no size: name the key
                    source = build_source(self.map, self.height, self.width)
                except ValueError as exc:
                    raise ValueError(f"map: {exc}") from None
                largest, smallest = source.max_shape, source.min_shape
                if self.test_maps:
                    # A mix that names a test map: the generators' own refusal, no env built.
                    try:
                        generators.WithoutMaps(source, self.test_grids())
                    except ValueError as exc:
                        raise ValueError(f"map: {exc} (it is in env.test_maps)") from None
            else:
                largest = smallest = (self.height, self.width)
            cells = largest[0] * largest[1]
            if cells > MAX_MAP_CELLS:
                raise ValueError(
                    f"a {largest[0]}x{largest[1]} map has {cells:,} cells, more than the "
                    f"{MAX_MAP_CELLS:,} this harness handles"
                )
            if self.n_agents > smallest[0] * smallest[1]:
                raise ValueError(
                    f"n_agents={self.n_agents} is more than the {smallest[0]}x{smallest[1]} "
                    "map's cells"
                )
        if self.starts is not None and len(self.starts) != self.n_agents:
            raise ValueError(f"starts has {len(self.starts)} cells for n_agents={self.n_agents}")
        # The env checks the rest (map file contents, start cells on walls, maps that cannot
        # place the team) where it is built: harness.factory.check_env.
        return self

    @property
    def agent_id(self) -> bool:
        """Whether each observation holds the agent's one-hot index (set from ``algo.sharing``)."""
        return self._agent_id

    def with_agent_id(self, on: bool, by_group: bool = False) -> EnvConfig:
        """This section with agent indication ``on``: itself when it has it already, else a
        copy (a section may be shared by several configs; none of them changes it). The
        coverage env's agents are one group: ``by_group`` is refused before it gets here."""
        if self._agent_id == on:
            return self
        env = self.model_copy()
        env._agent_id = on
        return env

    @property
    def groups(self) -> dict[str, tuple[str, ...]]:
        """The agents' groups: one (``agent_0``, ``agent_1``, ...)."""
        return agent_groups(tuple(f"agent_{k}" for k in range(self.n_agents)))

    @property
    def id_width(self) -> int:
        """Entries of the one-hot index that agent indication appends: one per agent."""
        return self.n_agents

    def test_grids(self) -> list[Any]:
        """The grids of ``test_maps``."""
        return [maps.load_map(name).grid for name in self.test_maps]

    #: Whether the team's size is a key (checked with the config); else it is known once the
    #: env is built, where the run starts (:meth:`check_fits`).
    agents_known: ClassVar[bool] = True

    #: ``vec.backend`` when the config gives none (``None``: the vec section's default, the
    #: batched core).
    default_backend: ClassVar[VecBackend | None] = None

    def check_with(self, config: ExperimentConfig) -> None:
        """Nothing more to check of the other sections: their own validators know this env."""

    def check_fits(self, config: ExperimentConfig) -> None:
        """Nothing left to check where the run starts: the config's validation checked it."""

    def check_training_map(self) -> None:
        """Refuse a fixed ``map`` that is one of ``test_maps`` (training; evaluation may use it).

        Raises:
            ValueError: naming ``env.map``.
        """
        if isinstance(self.map, str) and self.map != "random" and self.test_maps:
            grid = maps.load_map(self.map).grid
            if any(t.shape == grid.shape and (t == grid).all() for t in self.test_grids()):
                raise ValueError(
                    f"env.map: {self.map!r} is a test-only map (env.test_maps): never trained on"
                )


class PettingZooSource(_Section):
    """A PettingZoo env of your own: its constructor by import path, and its keyword arguments
    (``docs/your-own-env.md``). Validating it runs none of that code: the run's start builds the
    env once (:meth:`probe`, :func:`harness.config.pettingzoo.probe`) to check its spaces, before
    the run folder is made; a config that names an import path runs that code then
    (``docs/reliability.md``)."""

    make: str
    """``package.module:constructor``, e.g. ``mpe2.simple_spread_v3:parallel_env``: a function
    or class that returns a PettingZoo ``ParallelEnv`` (an AEC env is converted)."""
    kwargs: dict[str, Any] = {}
    """Keyword arguments of the constructor (``render_mode`` is the harness's to give)."""
    step_limit: PositiveInt = DEFAULT_STEP_LIMIT
    """Most steps of an episode: one still going then stops training or evaluation in one line
    (an env that never ends its episodes; :class:`harness.config.pettingzoo.ContractGuard`)."""
    groups: dict[str, list[str]] | None = None
    """The agents' groups by name (``{predators: [adversary_0, adversary_1], prey: [agent_0]}``),
    every agent in one (:func:`harness.config.pettingzoo.agent_groups`); ``null``: by name
    prefix. An agent in two groups is refused with the config; one that is no agent of the env,
    or an agent in none, where the run starts (the env built)."""
    select: str | None = None
    """The group whose mean return the harness's choices on validation episodes maximise
    (``best_model.zip``, ``harness tune``'s temperature, a sweep's trial value): one of
    :attr:`groups` (or of the groups by name prefix), of two or more; ``null``: the team's return
    (a competitive env's sides cancel in it)."""
    _spaces: EnvSpaces | None = PrivateAttr(default=None)

    @field_validator("groups")
    @classmethod
    def _groups_apart(cls, v: dict[str, list[str]] | None) -> dict[str, list[str]] | None:
        if v is None:
            return v
        if not v:
            raise ValueError("{} names no group (leave it out: groups by name prefix)")
        seen: dict[str, str] = {}
        for name, members in v.items():
            if not members:
                raise ValueError(f"group {name!r} has no agent")
            for agent in members:
                if agent in seen:
                    raise ValueError(f"{agent!r} is in {seen[agent]!r} and {name!r}")
                seen[agent] = name
        return v

    @field_validator("select")
    @classmethod
    def _select_named(cls, v: str | None, info: ValidationInfo) -> str | None:
        # Named groups are known without the env: checked now (else where the run starts).
        named = info.data.get("groups")
        if v is not None and named is not None:
            check_select(v, named)
        return v

    @field_validator("kwargs")
    @classmethod
    def _no_render_mode(cls, v: dict[str, Any]) -> dict[str, Any]:
        # Training builds its envs without rendering, `harness render` with rgb_array.
        if "render_mode" in v:
            raise ValueError("render_mode is given by the harness (harness render), not here")
        return v

    def probe(self) -> EnvSpaces:
        """The env's agents and their (shared) spaces: the env built and stepped once
        (:func:`harness.config.pettingzoo.probe`) the first time they are asked for.

        Raises:
            ValueError: one line naming ``env.pettingzoo`` and the problem.
        """
        if self._spaces is None:
            try:
                self._spaces = probe(self.make, self.kwargs)
            except ValueError as exc:
                raise ValueError(f"env.pettingzoo: {exc}") from None
        return self._spaces

    @property
    def spaces(self) -> EnvSpaces:
        """The env's agents and their (shared) spaces (:meth:`probe`)."""
        return self.probe()

    def __eq__(self, other: object) -> bool:
        # The same source whether or not its env was built yet (the spaces are read of it).
        if not isinstance(other, PettingZooSource):
            return NotImplemented
        return self.model_dump() == other.model_dump()

    __hash__ = None  # type: ignore[assignment]  (as pydantic's models: mutable, unhashable)


class PettingZooEnvConfig(_Section):
    """The ``env`` section for a PettingZoo env of your own: ``{pettingzoo: {make, kwargs}}``.

    It answers what the rest of the harness asks of an ``env`` section (the team size, its
    agent indication, no planner); the coverage env's keys do not apply to it."""

    pettingzoo: PettingZooSource
    #: The team's size is the env's: known once it is built, where the run starts.
    agents_known: ClassVar[bool] = False
    #: SuperSuit steps it (the batched core is the coverage env's).
    default_backend: ClassVar[VecBackend | None] = "supersuit"
    _agent_id: bool = PrivateAttr(default=False)
    """Whether each observation ends in the agent's one-hot index (SuperSuit's agent indication,
    :class:`harness.config.pettingzoo.AgentIndicator`): not a key of its own, derived from
    ``algo.sharing`` when :class:`ExperimentConfig` resolves its sections."""
    _by_group: bool = PrivateAttr(default=False)
    """Whether that index is the agent's group's (``algo.sharing: per_group``)."""

    @property
    def n_agents(self) -> int:
        """Agents of the team (the env's ``possible_agents``)."""
        return self.pettingzoo.spaces.n_agents

    @property
    def agent_id(self) -> bool:
        """Whether each observation ends in the agent's one-hot index (set from
        ``algo.sharing``)."""
        return self._agent_id

    @property
    def by_group(self) -> bool:
        """Whether the one-hot index is the agent's group's (``algo.sharing: per_group``)."""
        return self._agent_id and self._by_group

    @property
    def groups(self) -> dict[str, tuple[str, ...]]:
        """The agents' groups: ``env.pettingzoo.groups``, else by name prefix
        (:func:`harness.config.pettingzoo.agent_groups`).

        Raises:
            ValueError: one line naming an agent that is not the env's, or in no group.
        """
        return agent_groups(self.pettingzoo.spaces.agents, self.pettingzoo.groups)

    @property
    def select(self) -> str | None:
        """``env.pettingzoo.select`` checked against the env's :attr:`groups` (the env built).

        Raises:
            ValueError: one line naming ``env.pettingzoo.select``.
        """
        select = self.pettingzoo.select
        if select is not None:
            try:
                check_select(select, self.groups)
            except ValueError as exc:
                raise ValueError(f"env.pettingzoo.select: {exc}") from None
        return select

    @property
    def id_width(self) -> int:
        """Entries of the one-hot index that agent indication appends: one per agent, or one per
        group (:attr:`by_group`)."""
        return len(self.groups) if self.by_group else self.n_agents

    @property
    def spaces(self) -> EnvSpaces:
        """The agents and spaces as the harness's networks see them: the env's, the observation
        with the one-hot index where :attr:`agent_id` is on."""
        spaces = self.pettingzoo.spaces
        return indicated_spaces(spaces, self.id_width) if self._agent_id else spaces

    def with_agent_id(self, on: bool, by_group: bool = False) -> PettingZooEnvConfig:
        """This section with agent indication ``on`` (the group's index where ``by_group``):
        itself when it has it already, else a copy (the env is not probed again)."""
        if self._agent_id == on and self._by_group == by_group:
            return self
        env = self.model_copy()
        env._agent_id, env._by_group = on, by_group
        return env

    @property
    def frontier_options(self) -> None:
        """No planner extension (the coverage env's)."""
        return None

    def check_training_map(self) -> None:
        """Nothing to refuse: test maps are the coverage env's."""

    def check_with(self, config: ExperimentConfig) -> None:
        """What a PettingZoo env can be trained with, as far as the config shows it: the
        SuperSuit VecEnv (the batched core is the coverage env's), networks over its own
        observations (not the coverage env's team map), no coverage-specific test-time shield.

        Raises:
            ValueError: one line naming the key.
        """
        if config.vec.backend == "core" and "backend" in config.vec.model_fields_set:
            raise ValueError(
                "vec.backend: core is the coverage env's batched core; a pettingzoo env "
                "runs on vec.backend: supersuit (the default for it)"
            )
        entry = POLICIES[config.algo.policy]
        if entry.team_map or entry.slots:
            vector = [
                name for name, p in POLICIES.items() if not (p.team_map or p.slots or p.masked)
            ]
            raise ValueError(
                f"algo.policy {config.algo.policy} reads the coverage env's team map; a "
                f"pettingzoo env's Box observation takes one of {', '.join(vector)}"
            )
        if config.eval.shield:
            raise ValueError(
                "eval.shield reads the coverage env's observation: not for a pettingzoo env"
            )

    def check_fits(self, config: ExperimentConfig) -> None:
        """What of ``config`` the env's spaces decide, checked where the run starts (the env
        built once, :meth:`PettingZooSource.probe`): the agent indication of ``algo.sharing``,
        a network that reads the observations as they are (an action mask or none), and the
        VecEnv's slots.

        Raises:
            ValueError: one line naming the key.
        """
        spaces = self.pettingzoo.spaces
        algo = config.algo
        groups = self.groups  # (the named groups against the env's agents: ValueError)
        _ = self.select  # (the selected group against them: ValueError)
        if algo.sharing == "per_group" and len(groups) < 2:
            config.check_groups()
        if algo.sharing != "shared":
            try:
                indicated_spaces(spaces)
            except ValueError as exc:
                raise ValueError(f"algo.sharing: {algo.sharing}: {exc}") from None
            shape = spaces.observation_space.shape
            if algo.sharing in ("per_agent", "per_group") and len(shape) != 1:
                raise ValueError(
                    f"algo.sharing: {algo.sharing} routes each observation by the one-hot index "
                    f"at its end: it needs vector observations, not of shape {shape} (flatten "
                    "them, e.g. with SuperSuit's flatten_v0, or use shared_id)"
                )
        entry = POLICIES[algo.policy]
        if config.prior is None and entry.masked != masked(spaces):
            fitting = [name for name, p in POLICIES.items() if p.masked and not p.team_map]
            if entry.masked:
                raise ValueError(
                    f"algo.policy {algo.policy} reads an action mask: the env's "
                    "observations are a Box without one (use MlpPolicy or DuelingMlpPolicy)"
                )
            raise ValueError(
                f"algo.policy {algo.policy} reads a Box, but the env's observations carry "
                f"an action mask (PettingZoo's Dict of observation and action_mask): use "
                f"algo.policy: {' or '.join(fitting)}"
            )
        config.check_slots()


#: The env sources an ``env`` section can be, by the section's tag: the coverage env's keys, or
#: ``{pettingzoo: ...}``.
ENV_SECTIONS: dict[str, type[_Section]] = {"coverage": EnvConfig, "pettingzoo": PettingZooEnvConfig}
ENV_SOURCES = tuple(ENV_SECTIONS)


def _env_source(value: Any) -> str:
    """Which env source an ``env`` section is (a mapping with a ``pettingzoo`` key, or not)."""
    if isinstance(value, PettingZooEnvConfig) or (
        isinstance(value, dict) and "pettingzoo" in value
    ):
        return "pettingzoo"
    return "coverage"


#: An ``env`` section of either source.
AnyEnvConfig = Annotated[
    Union[  # noqa: UP007 (the tagged members are Annotated: `|` does not take them)
        Annotated[EnvConfig, Tag("coverage")], Annotated[PettingZooEnvConfig, Tag("pettingzoo")]
    ],
    Discriminator(_env_source),
]


#: How the env is vectorised (``vec.backend``): the batched core's own VecEnv, or SuperSuit
#: over the PettingZoo env (the same episodes, one copy at a time; ``harness.training.adapters``).
VecBackend = Literal["core", "supersuit"]
VEC_BACKENDS: tuple[str, ...] = get_args(VecBackend)


class VecConfig(_Section):
    """How the env is vectorised: copies of the env, the VecEnv that steps them, and (SuperSuit)
    processes that run them."""

    # strict: ``true``, ``4.0`` or the text ``1e9`` (PyYAML's reading of 1e9) is not a count.
    copies: Annotated[int, Field(strict=True, gt=0, le=MAX_SLOTS)] = 4
    """Env copies; the VecEnv has ``copies`` x the env's agents slots, at most
    :data:`MAX_SLOTS`."""
    backend: VecBackend = "core"
    """``core``: the batched core steps every copy in one call (the default); ``supersuit``:
    SuperSuit over the PettingZoo env, copy by copy. Both give the same episodes."""
    num_cpus: NonNegativeInt = 0
    """Processes that step the copies (``backend: supersuit`` only); 0 steps them in the
    training process."""

    @model_validator(mode="after")
    def _processes_need_supersuit(self) -> VecConfig:
        if self.num_cpus > 1 and self.backend != "supersuit":
            raise ValueError(
                "vec.num_cpus > 1 needs vec.backend: supersuit (the core steps every copy in "
                "the training process)"
            )
        return self


class ImitationConfig(_Section):
    """DQfD's large-margin loss towards the frontier step (Hester et al. 2018, eq. 2).

    Every sampled transition adds ``weight * (max_a [Q(s, a) + margin * (a != step)] -
    Q(s, step))`` to its TD loss: the network's greedy policy is the step (with
    a planner in ``env.frontier``, the planner's move) unless the TD term holds another
    move's value higher. The weight decides how hard that is: a move becomes greedy only when
    its advantage exceeds about ``weight / (its share of the samples)``, never when the weight
    is above that share (docs/training.md). The step is computed by the env in
    every state, so the "demonstrations" are every transition the agents collect."""

    margin: Annotated[float, Field(ge=0.0)] = 0.8
    """The lead the step's Q-value must have over every other action's (reward units: a new
    cell is +2, a move -1)."""
    weight: Annotated[float, Field(ge=0.0)] = 1.0
    """The loss's weight beside the TD (Huber) loss: DQfD's lambda_2."""


class TeacherConfig(_Section):
    """A teacher that sees the true map, for training only (DAgger, docs/goals.md "The
    teacher"): at the decisions of a share of the copies' steps, the rollout teacher
    (``envs.coverage.teacher``: every candidate slot tried on a copy of the episode with the
    true walls, the best kept) labels the slot it would take; the label is stored with the
    decision's transition and DQfD's large-margin loss pulls the network's greedy choice
    towards it, beside the TD loss. The policy never sees the true map, and evaluation never
    builds the teacher."""

    share: Annotated[float, Field(gt=0.0, le=1.0)] = 1.0
    """Share of the copies' steps whose decisions are labelled (a copy's step is labelled or
    not as a whole, drawn from the run's own generator): the teacher's rollouts are the cost."""
    margin: Annotated[float, Field(ge=0.0)] = 0.8
    """The loss's margin: the lead the label's Q-value must have over every other slot's."""
    weight: Annotated[float, Field(ge=0.0)] = 1.0
    """The loss's weight beside the TD (Huber) loss (DQfD's lambda_2), on labelled samples."""
    reach: Annotated[float, Field(gt=0.0, le=1.0)] | None = None
    """Score the rollouts by the steps they take to this coverage (fewer is better; e.g. 0.99,
    the 4-agent settings' measure, where every rollout covers the whole map) instead of the
    cells found by the episode's end."""


class AlgoConfig(_Section):
    """The learner: ``DoubleDQN`` with its policy, buffer and optimizer (thesis §2.9-2.11, §3.4)."""

    sharing: Literal["shared", "shared_id", "per_agent", "per_group"] = "shared"
    """How the agents share the Q-network: ``shared``, one network for all (parameter sharing);
    ``shared_id``, one network that also reads the agent's one-hot index (agent indication);
    ``per_agent``, one set of parameters per agent (the thesis's independent learners), in one
    model that routes each agent to its set; ``per_group``, one set per agent group (a
    pettingzoo env's, ``env.pettingzoo.groups`` or by name prefix), shared by its agents: the
    group's one-hot index routes them. The non-shared modes add the one-hot index to the
    observation (``env.agent_id``), so they are tied to the team size (or groups) they were
    trained with."""
    policy: str = DEFAULT_POLICY
    """A policy of ``harness.sb3.registry.POLICIES``: ``MlpPolicy``, ``DuelingMlpPolicy`` (the
    thesis observation), ``TeamMapPolicy``, ``DuelingTeamMapPolicy``, ``SlotTeamMapPolicy``
    (``teammap``), ``MaskedMlpPolicy`` (a pettingzoo env's action-mask ``Dict``)."""
    net_arch: list[PositiveInt] = list(POLICIES[DEFAULT_POLICY].default_net_arch)
    """Hidden layers; for the dueling policy, each of the value and advantage streams. Not given:
    the policy's ``default_net_arch`` (the thesis's ``[512, 512, 512]``, ``[]`` (none) for the
    TeamMap policies, ``[128]`` for the slot scorer)."""
    dueling_aggregator: Literal["mean", "max"] = "mean"
    double_q: bool = True
    gamma: Annotated[float, Field(gt=0.0, le=1.0)] = 0.99
    buffer_size: Annotated[int, Field(ge=1, le=MAX_BUFFER_SIZE)] = 100_000
    learning_starts: NonNegativeInt = 1_000
    target_update_interval: PositiveInt = 10_000
    optimizer: str = "RMSprop"
    optimizer_kwargs: dict[str, float | int | bool] = {}
    max_grad_norm: PositiveFloat = 10.0
    prioritized: bool = True
    per_eps: PositiveFloat = 1e-6
    n_steps: Annotated[int, Field(ge=1, le=100)] = 1
    """n-step returns (Sutton and Barto 2018, §7.1): the TD target sums ``n_steps`` discounted
    rewards before it bootstraps, cut at an episode's end. 1: the one-step target (the thesis).
    In the prioritized buffers (any observation), or SB3's ``NStepReplayBuffer`` (thesis
    observation only) when ``prioritized`` is false."""
    per_decision: bool = False
    """One transition per decision (temporal abstraction, docs/goals.md): the steps of states
    whose action mask allows one action (the goal action's held targets, ``env.frontier.action:
    {goal: {hold: true}}``) are merged into the transition of the decision before them, with the
    discounted sum of their rewards and the discount ``gamma ** steps``
    (``harness.sb3.decisions``). Needs an observation with an action mask (the goal action) and
    ``n_steps: 1``; prioritized or not. The buffer stays on the host on an accelerator too."""
    device: str = "auto"
    cuda_graph: bool = True
    """On CUDA (the replay buffer then lives on the GPU, prioritized or uniform; not the
    per-decision one), record a gradient step once as a CUDA graph and launch it again for every
    later step (``harness.sb3.graphs``): the same updates, several times the gradient steps/s
    (docs/performance.md). Without effect on a CPU; ``false`` for debugging."""
    threads: Annotated[int, Field(ge=1, le=MAX_THREADS)] | None = 1
    """torch CPU threads (``torch.set_num_threads``); ``null`` keeps torch's default (one per
    core). One by default, from ``harness bench train`` (docs/performance.md): on a quiet 2-core
    machine 2 threads make 1.12-1.54 x the gradient steps of the 3x512 net and 0.75-0.99 x those
    of the small ones; on a busy one 0.18-0.85 x for every size. With ``teacher``, also the
    threads its labels are made on (``null``: every core)."""

    imitation: ImitationConfig | None = None
    """DQfD's large-margin loss towards the planner-backed action (needs ``env.frontier.action``);
    ``null``: none."""
    teacher: TeacherConfig | None = None
    """DQfD's large-margin loss towards a true-map teacher's labels of the policy's own
    decisions (needs the goal action, ``per_decision: true`` and the core backend); ``null``:
    none."""

    features_dim: PositiveInt = 256
    """TeamMap policies: width of the layer that joins the image branches and the vector."""
    cnn_channels: tuple[PositiveInt, PositiveInt] = (8, 16)
    """TeamMap policies: filters of the two 3x3 conv layers of each image branch."""

    @model_validator(mode="before")
    @classmethod
    def _policy_default_head(cls, data: Any) -> Any:
        # Each policy has its own default head (the registry says which and why); an unknown
        # policy is left to the field's check, which names it.
        if isinstance(data, dict) and "net_arch" not in data:
            entry = POLICIES.get(str(data.get("policy", DEFAULT_POLICY)))
            if entry is not None:
                return {**data, "net_arch": list(entry.default_net_arch)}
        return data

    @field_validator("policy")
    @classmethod
    def _known_policy(cls, v: str) -> str:
        return _registered(v, POLICIES, "policy")

    @field_validator("device")
    @classmethod
    def _device_kind(cls, v: str) -> str:
        # Whether torch knows it and this machine has it is checked once the config is complete
        # (harness.training.checks), so that a config error never has to import torch.
        if not v.strip():
            raise ValueError("must be 'auto', 'cpu', 'cuda', 'cuda:N' or 'mps'")
        return v


class LinearScheduleConfig(_Section):
    """A linear schedule (eq. 4.1): ``start`` → ``end`` over ``steps`` transitions, then ``end``."""

    start: Fraction
    end: Fraction
    steps: NonNegativeInt = 0


class PhaseConfig(_Section):
    """One training phase (thesis §3.7, Table 4.1): its length and every setting that changes
    between phases."""

    name: str
    timesteps: PositiveInt
    learning_rate: PositiveFloat | tuple[PositiveFloat, PositiveFloat] = 5e-5
    """A constant, or ``[start, end]`` going linearly over the phase."""
    batch_size: PositiveInt = 32
    train_freq: PositiveInt = 2
    alpha: Fraction = 0.55
    exploration: LinearScheduleConfig = LinearScheduleConfig(start=1.0, end=0.05, steps=0)
    beta: LinearScheduleConfig = LinearScheduleConfig(start=0.4, end=1.0, steps=0)
    epochs: list[tuple[Fraction, PositiveInt]] = [(0.0, 1), (0.40, 5), (0.60, 7)]
    """``(coverage threshold, epochs)`` rows; epochs = gradient steps per training call."""
    epochs_window: PositiveInt = 20
    """K: the epochs table follows the median coverage of the last K finished episodes."""

    @field_validator("epochs")
    @classmethod
    def _sorted_table(cls, v: list[tuple[float, int]]) -> list[tuple[float, int]]:
        if not v:
            raise ValueError("needs at least one (threshold, epochs) row")
        thresholds = [t for t, _ in v]
        if thresholds != sorted(thresholds) or len(set(thresholds)) != len(thresholds):
            raise ValueError("thresholds must be strictly increasing")
        return v


def thesis_phases(
    initial_steps: int = 1_000_000, optimizing_steps: int = 500_000
) -> list[PhaseConfig]:
    """The thesis's two phases (Table 4.1) with the given lengths."""
    return [
        PhaseConfig(
            name="initial",
            timesteps=initial_steps,
            exploration=LinearScheduleConfig(start=1.0, end=0.05, steps=initial_steps // 2),
            beta=LinearScheduleConfig(start=0.4, end=1.0, steps=initial_steps),
        ),
        PhaseConfig(
            name="optimizing",
            timesteps=optimizing_steps,
            learning_rate=(5e-6, 1e-6),
            batch_size=64,
            train_freq=4,
            alpha=0.75,
            exploration=LinearScheduleConfig(start=0.0, end=0.0),
            beta=LinearScheduleConfig(start=1.0, end=1.0),
            epochs=[(0.0, 1), (0.40, 3), (0.60, 5)],
        ),
    ]


#: Smallest distance between ``eval.seed`` and ``eval.validation_seed``.
SEED_GAP = 100_000


class RolloutConfig(_Section):
    """The rollout chooser that ``harness eval --policy rollout`` plays (docs/planners.md, "The
    rollout chooser"; :class:`envs.coverage.rollouts.SampledChooser`). The defaults were
    chosen first, on 4-agent validation episodes; from 60 % on, 8 maps with 4 agents (about 4
    times the cost) and 16 with 2 (about 30 times) gained more on validation and on the test
    episodes of 50x50 random maps (docs/results.md). They stay the defaults: the caves and
    mazes, where sampled cells mislead, were not validated with the others."""

    samples: Annotated[int, Field(strict=True, gt=0, le=MAX_ROLLOUT_SAMPLES)] = 4
    """Maps sampled for the unseen cells at each decision; every slot is rolled out on each (at
    most :data:`MAX_ROLLOUT_SAMPLES`)."""
    after: Annotated[float, Field(ge=0.0, le=1.0)] = 0.8
    """The team's coverage (as its map tells it) from which it decides; slot 0 before."""

    prior: str | None = None
    """A map prior to draw the unseen cells from (a prior run's folder or its ``model.zip``,
    docs/prior.md); ``None``: every unseen cell a wall with the seen cells' wall share."""

    @field_validator("samples")
    @classmethod
    def _noise_rule_has_maps(cls, v: int) -> int:
        # One map turns the rule against chance gains off (it compares gains over the maps):
        # measured, the team then chases noise (research/README.md, map priors).
        if v < 2:
            raise ValueError(
                "needs 2 maps or more: with 1 the rule against chance gains is off and every "
                "chance gain deviates (21 % coverage on a floor plan where the planner makes 89 %)"
            )
        return v

    def chooser(self, threads: int = 1, prior: Any = None) -> SampledChooser:
        """The chooser these parameters make (its noise rule the measured one, 4 standard
        errors: no result asked for another), scoring its maps on ``threads`` threads, drawing
        them from ``prior`` (the loaded :attr:`prior`, :class:`harness.prior.model.MapPrior`)."""
        return SampledChooser(samples=self.samples, after=self.after, threads=threads, prior=prior)


class EvalConfig(_Section):
    """Periodic evaluation during training, and the defaults of ``harness eval``."""

    every: NonNegativeInt = 100_000
    """Transitions between evaluations; 0 turns periodic evaluation off."""
    episodes: PositiveInt = 10
    seed: Seed = 1_000_003
    """Seed of the test episodes of ``harness eval`` (different from training seeds: unseen
    maps). Nothing is chosen on them: model and temperature choices use ``validation_seed``."""
    validation_seed: Seed = 2_000_003
    """Seed of the validation episodes: the in-training evaluations (``evaluations.csv``,
    ``best_model.zip``) and ``harness tune``. Runs made before this key existed evaluated on the
    first episodes of ``seed`` during training."""
    temperature: NonNegativeFloat = 0.0
    """Test-time action choice: 0 is greedy (ε = 0, the thesis's test); above 0 each agent samples
    from softmax(Q / temperature) (Boltzmann), which breaks the loops of a greedy policy."""
    shield: bool = False
    """Test-time wall shield: leave out the moves the agent's observation shows to be blocked
    (a wall or the edge next to it) before the choice, so the test policy never hits a wall.
    Applies to ``harness eval``/``tune``, the in-training evaluations and sweeps; training's
    own (ε-greedy) actions are unchanged."""
    rollout: RolloutConfig = RolloutConfig()
    """The parameters of the ``rollout`` baseline (``--policy rollout``, ``--against
    rollout``); nothing else reads them."""

    @model_validator(mode="after")
    def _separate_seeds(self) -> EvalConfig:
        # Episode k of an evaluation uses seed + k: keep the two ranges of maps apart.
        if abs(self.validation_seed - self.seed) < SEED_GAP:
            raise ValueError(
                f"validation_seed must be at least {SEED_GAP} away from seed (test episodes "
                "seed, seed+1, ... must not be validation episodes)"
            )
        return self


#: The written planners whose episodes a map prior learns from (``prior.planner``).
PRIOR_PLANNERS = tuple(entry.baseline for entry in PLANNERS.values())


class PriorConfig(_Section):
    """``prior:``: the run trains a map prior instead of a policy (docs/prior.md). The partial
    maps are the team's maps along episodes of ``planner`` on the env's maps; the phases'
    ``timesteps`` count gradient steps (each on ``batch_size`` partial maps, at the phase's
    ``learning_rate``), ``eval.every`` and ``checkpoint.every`` too, and ``eval.episodes``
    validation episodes (``eval.validation_seed``) score it during training."""

    channels: Annotated[list[PositiveInt], Field(min_length=1, max_length=5)] = [16, 32, 64]
    """Features of the U-Net's levels (each level halves the map)."""
    planner: str = "frontier_pocket"
    """The written planner (a ``--policy`` name) whose episodes give the partial maps."""
    episodes: Annotated[int, Field(ge=1, le=100_000)] = 200
    """Training episodes recorded (seeds apart from the test and validation ones)."""
    snapshots: Annotated[int, Field(ge=1, le=1_000)] = 10
    """Team maps kept an episode, at steps drawn uniformly from it."""

    @field_validator("planner")
    @classmethod
    def _known_planner(cls, v: str) -> str:
        return _registered(v, dict.fromkeys(PRIOR_PLANNERS), "prior.planner")


class CheckpointConfig(_Section):
    """Checkpoints (model, replay buffer and training state), written atomically."""

    every: NonNegativeInt = 100_000
    """Transitions between checkpoints; 0 writes one only at the end of each phase."""


_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def check_name(value: str) -> str:
    """``value`` if it is a name a folder can take (a run's, a study's): 1-64 letters, digits,
    ``_``, ``.`` or ``-``, starting with a letter or digit; no separators, no ``..``.

    Raises:
        ValueError: saying what a name may hold.
    """
    if not _NAME_RE.fullmatch(value):  # fullmatch: `$` would let a trailing newline through
        raise ValueError(
            "must be 1-64 characters of letters, digits, '_', '.', '-', starting with a "
            "letter or digit"
        )
    return value


class ExperimentConfig(_Section):
    """A whole experiment: everything ``harness run`` needs."""

    name: str = "experiment"
    seed: Seed = 0
    env: AnyEnvConfig = EnvConfig()
    vec: VecConfig = VecConfig()
    algo: AlgoConfig = AlgoConfig()
    phases: list[PhaseConfig] = Field(default_factory=thesis_phases)
    eval: EvalConfig = EvalConfig()
    checkpoint: CheckpointConfig = CheckpointConfig()
    prior: PriorConfig | None = None
    """Set: the run trains a map prior (docs/prior.md), not a policy; ``algo`` and ``vec`` are
    not used."""

    @field_validator("name", mode="before")
    @classmethod
    def _name_as_text(cls, v: Any) -> Any:
        # YAML reads `name: 2024` as a number (taken as its text, as --name 2024 is) and
        # `name: true` (yes, no, on, off) as a bool, which is no name anyone meant.
        if isinstance(v, bool):
            raise ValueError(f"a name is text; YAML read this one as {v} (a bool): quote it")
        return str(v) if isinstance(v, int) else v

    @field_validator("name")
    @classmethod
    def _safe_name(cls, v: str) -> str:
        # The name becomes a folder under runs/: no separators, no "..", no hidden names.
        return check_name(v)

    @model_validator(mode="after")
    def _env_section_fits(self) -> ExperimentConfig:
        # What the env section takes of the other sections, as far as the config shows it
        # (what the env's spaces decide is checked where the run starts: check_env_fits).
        self.env.check_with(self)
        return self

    @model_validator(mode="after")
    def _imitation_has_an_expert(self) -> ExperimentConfig:
        # The expert's action is the env's planner-backed action: without one there is nothing
        # to imitate.
        options = self.env.frontier_options
        if self.algo.imitation is not None and (options is None or options.expert_action is None):
            raise ValueError(
                "algo.imitation needs env.frontier.action (the planner-backed action is the "
                "expert's)"
            )
        return self

    @model_validator(mode="after")
    def _teacher_labels_decisions(self) -> ExperimentConfig:
        # The teacher labels decisions of the core's copies (it reads their planners and true
        # walls), stored by the per-decision buffer; its loss is the imitation loss's.
        if self.algo.teacher is None:
            return self
        if not self.algo.per_decision:
            raise ValueError(
                "algo.teacher labels decisions: it needs algo.per_decision: true (and the goal "
                "action, env.frontier.action: {goal: {k: K}})"
            )
        if self.algo.imitation is not None:
            raise ValueError(
                "algo.teacher and algo.imitation are two experts for one margin loss: set one"
            )
        if self._backend() != "core":
            raise ValueError(
                f"algo.teacher reads the batched core's copies: it needs vec.backend: core, got "
                f"{self._backend()!r}"
            )
        return self

    @model_validator(mode="after")
    def _n_step_buffer_exists(self) -> ExperimentConfig:
        # SB3's own Dict buffer has no n-step variant; the prioritized ones do.
        if (
            isinstance(self.env, EnvConfig)
            and self.algo.n_steps > 1
            and not self.algo.prioritized
            and self.env.observation_kind != "thesis"
        ):
            raise ValueError(
                f"algo.n_steps: {self.algo.n_steps} needs algo.prioritized: true with "
                f"env.observation {self.env.observation!r} (SB3 has no n-step Dict buffer; "
                "the prioritized one samples uniformly with alpha 0)"
            )
        return self

    @model_validator(mode="after")
    def _decisions_are_masked(self) -> ExperimentConfig:
        # A decision is a state whose action mask allows several actions: without a mask in the
        # observation there is nothing to merge (the goal action's env carries one).
        if not self.algo.per_decision:
            return self
        options = self.env.frontier_options
        if options is None or options.action is None or not options.action.masked:
            raise ValueError(
                "algo.per_decision reads the observation's action mask: it needs "
                "env.frontier.action: {goal: {k: K}} (with hold: true its held steps merge)"
            )
        if self.algo.n_steps > 1:
            raise ValueError(
                f"algo.per_decision stores one transition per decision: algo.n_steps must be 1, "
                f"got {self.algo.n_steps}"
            )
        return self

    @model_validator(mode="after")
    def _policy_fits_observation(self) -> ExperimentConfig:
        if not isinstance(self.env, EnvConfig) or self.prior is not None:  # no policy trains
            return self
        wanted = POLICIES[self.algo.policy].observation
        if wanted != self.env.observation_kind:
            fitting = [
                name for name, p in POLICIES.items() if p.observation == self.env.observation_kind
            ]
            raise ValueError(
                f"algo.policy {self.algo.policy} is for observation {wanted!r}, but "
                f"env.observation is {self.env.observation_kind!r} (use one of "
                f"{', '.join(fitting)})"
            )
        return self

    @model_validator(mode="after")
    def _policy_fits_actions(self) -> ExperimentConfig:
        if self.prior is not None:  # a prior's run trains no policy
            return self
        entry = POLICIES[self.algo.policy]
        options = self.env.frontier_options
        slotted = options is not None and options.action is not None and options.action.slots
        if entry.slots and not slotted:
            raise ValueError(
                f"algo.policy {self.algo.policy} scores the goal action's candidates: it needs "
                "env.frontier.action: {goal: {k: K}} (with a planner)"
            )
        if self.algo.sharing in ("per_agent", "per_group") and not entry.per_agent:
            raise ValueError(
                f"algo.sharing: {self.algo.sharing}: {self.algo.policy} has no per-agent version "
                "(use shared or shared_id)"
            )
        if self.algo.sharing == "per_group" and self.env.agents_known:
            self.check_groups()  # (else where the run starts: check_env_fits)
        return self

    def check_groups(self) -> None:
        """Refuse ``algo.sharing: per_group`` for a team of one group (one network would be
        ``shared_id`` without the agent's index).

        Raises:
            ValueError: naming ``algo.sharing``.
        """
        groups = self.env.groups
        if len(groups) < 2:
            (name, members), *_ = groups.items()
            raise ValueError(
                f"algo.sharing: per_group: the agents form one group ({name!r}: "
                f"{', '.join(members)}), so one network: use per_agent or shared_id, or name "
                "two groups or more in env.pettingzoo.groups"
            )

    @model_validator(mode="after")
    def _prior_reads_planned_maps(self) -> ExperimentConfig:
        # A prior learns from the team maps of a written planner's episodes: the planner plays
        # the moves, so the env is the coverage env with move actions.
        if self.prior is None:
            return self
        if not isinstance(self.env, EnvConfig):
            raise ValueError(
                "prior: a map prior learns the coverage env's maps, not a pettingzoo env"
            )
        options = self.env.frontier_options
        if options is not None and options.action is not None:
            raise ValueError(
                "prior: the partial maps are recorded along a planner's moves; drop "
                "env.frontier.action (the goal action) from a prior's config"
            )
        if self.prior.snapshots > self.env.max_steps:
            raise ValueError(
                f"prior.snapshots: {self.prior.snapshots} is more than the "
                f"{self.env.max_steps} steps of an episode"
            )
        return self

    @model_validator(mode="after")
    def _something_trains(self) -> ExperimentConfig:
        # Learning starts after learning_starts transitions: at or past the run's end nothing
        # would train, and the run would still say "done". (A prior's steps are gradient steps.)
        if self.prior is None and self.algo.learning_starts >= self.total_timesteps:
            raise ValueError(
                f"algo.learning_starts: {self.algo.learning_starts:,} is not below the run's "
                f"{self.total_timesteps:,} transitions (the phases' timesteps): nothing would train"
            )
        return self

    @model_validator(mode="after")
    def _slots_fit(self) -> ExperimentConfig:
        if self.env.agents_known:  # (else where the run starts: check_env_fits)
            self.check_slots()
        return self

    def check_slots(self) -> None:
        """Refuse more VecEnv slots than a run can step.

        Raises:
            ValueError: naming ``vec.copies``.
        """
        if self.prior is None and self.n_slots > MAX_SLOTS:
            raise ValueError(
                f"vec.copies: {self.vec.copies:,} copies of {self.env.n_agents} agents make "
                f"{self.n_slots:,} slots, more than the {MAX_SLOTS:,} a run can step"
            )

    def check_env_fits(self) -> None:
        """What the env's spaces decide, checked where the run starts, once the env is built
        (a user's constructor never runs while a config is validated): the env section's
        :meth:`~PettingZooEnvConfig.check_fits`.

        Raises:
            ValueError: one line naming the key.
        """
        self.env.check_fits(self)

    @model_validator(mode="after")
    def _batch_fits_buffer(self) -> ExperimentConfig:
        # A batch is drawn from the buffer: a larger one only repeats transitions, and a huge one
        # fails allocating its arrays at the first gradient step.
        for phase in self.phases:
            if phase.batch_size > self.algo.buffer_size:
                raise ValueError(
                    f"phases.{phase.name}.batch_size: {phase.batch_size:,} is larger than "
                    f"algo.buffer_size ({self.algo.buffer_size:,})"
                )
        return self

    def _backend(self) -> VecBackend:
        """``vec.backend`` as the run uses it: as given, else the env's own (the batched core for
        the coverage env, SuperSuit for a pettingzoo env, which the core cannot step)."""
        if "backend" in self.vec.model_fields_set or self.env.default_backend is None:
            return self.vec.backend
        return self.env.default_backend

    @model_validator(mode="after")
    def _resolved(self) -> ExperimentConfig:
        # The one step that fills in values that depend on other sections, after every check
        # above (which only check, reading them through _backend): the vec backend an env needs,
        # and the env's agent indication (algo.sharing owns it; the env carries it out).
        # Into copies: a section given to this config may be another config's too, and
        # validating one config must not change another. Kept last: validators run in order.
        backend = self._backend()
        if self.vec.backend != backend:  # an assignment checks the config again, once
            self.vec = self.vec.model_copy(update={"backend": backend})
        env = self.env.with_agent_id(
            self.algo.sharing != "shared", by_group=self.algo.sharing == "per_group"
        )
        if env is not self.env:
            self.env = env
        return self

    @field_validator("phases")
    @classmethod
    def _phases(cls, v: list[PhaseConfig]) -> list[PhaseConfig]:
        if not v:
            raise ValueError("needs at least one phase")
        names = [p.name for p in v]
        if len(set(names)) != len(names):
            raise ValueError(f"phase names must be unique, got {names}")
        return v

    @property
    def total_timesteps(self) -> int:
        """Transitions over all phases."""
        return sum(p.timesteps for p in self.phases)

    @property
    def n_slots(self) -> int:
        """VecEnv slots: one per agent per env copy."""
        return self.env.n_agents * self.vec.copies

    def to_yaml(self) -> str:
        """The fully resolved config as YAML (what a run directory keeps)."""
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)
