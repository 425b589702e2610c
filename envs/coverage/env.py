"""The coverage environment: a PettingZoo ``ParallelEnv`` (see ``envs/coverage_v0.py`` for the
documentation page)."""

from __future__ import annotations

import functools
import inspect
from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from envs.coverage import render
from envs.coverage.core import DEFAULT_REWARDS, CoreSpec, CoverageCore, agent_name
from envs.coverage.frontier import Frontier
from envs.coverage.types import CELL_VISITED, GridState

__all__ = ["DEFAULT_REWARDS", "CoverageEnv"]


class CoverageEnv(ParallelEnv):
    """N agents cover an unknown grid map together. See the module ``envs.coverage_v0``."""

    metadata: dict[str, Any] = {  # noqa: RUF012 (PettingZoo convention: a class attribute)
        "name": "coverage_v0",
        "render_modes": ["rgb_array", "ansi"],
        "is_parallelizable": True,
        "render_fps": 10,
    }

    def __init__(self, render_mode: str | None = None, **kwargs: Any) -> None:
        # The arguments (``envs/coverage_v0.py``) have one owner, CoreSpec.parse, which turns
        # them into the objects the core is built from; the signature below shows them.
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be one of {self.metadata['render_modes']} or None, "
                f"got {render_mode!r}"
            )
        # The batched core holds the episode (one copy): the rules are written once, there.
        self._attach(CoverageCore(CoreSpec.parse(**kwargs), copies=1), 0, render_mode)

    @classmethod
    def copy_of(cls, core: CoverageCore, copy: int, render_mode: str | None = None) -> CoverageEnv:
        """A view of copy ``copy`` of a batched core, for code that plays a batch of episodes
        and hands each copy to readers of an env (the baselines, rendering): its read-only state,
        ``np_random``, ``render()`` and ``reset()`` are the copy's. Its ``step()`` refuses: the
        core steps every copy at once (``harness.evaluation.episodes.run_episodes``)."""
        env = cls.__new__(cls)
        env._attach(core, copy, render_mode)
        return env

    def _attach(self, core: CoverageCore, copy: int, render_mode: str | None) -> None:
        spec = core.spec
        self._core, self._copy = core, copy
        self.map_name = spec.map_name
        self.wall_fraction = getattr(spec.source, "wall_fraction", (0.0, 0.0))
        self.rewards = dict(spec.rewards)
        self.frontier = spec.frontier
        self.observation, self.coords = spec.observation, spec.coords
        self.observation_kind = spec.observation.name
        self.agent_id = spec.agent_id
        # The current episode's map size (a mix may draw several); the largest until the first
        # reset, which is the size the observation space is made for.
        self.height, self.width = core.max_shape
        self.n_agents, self.max_steps = spec.n_agents, spec.max_steps
        self.render_mode = render_mode
        self.possible_agents = [agent_name(i) for i in range(self.n_agents)]
        self.agents: list[str] = []
        self._obs_space = core.observation_space
        self._act_space = core.action_space

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
        view = self._core.walls[self._copy].view()
        view.flags.writeable = False
        return view

    @property
    def np_random(self) -> np.random.Generator:
        """The episode's random generator, seeded by ``reset(seed=...)`` (Gymnasium's name).

        The env draws from it only at reset (and for the frontier step's ties); a stochastic test
        policy may draw its action noise from it, so an episode's actions depend on its seed alone.
        """
        return self._core.rng(self._copy)

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
        return int(self._core.n_free[self._copy])

    @property
    def coverage(self) -> float:
        """The team's coverage: visited free cells / free cells."""
        return self._core.coverage(self._copy)

    @property
    def steps(self) -> int:
        """Steps taken in the current episode."""
        self._require_state()
        return int(self._core.steps[self._copy])

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

    @property
    def core(self) -> CoverageCore:
        """The batched core this env is the batch-of-one view of."""
        return self._core

    @property
    def frontier_state(self) -> Frontier | None:
        """The episode's planner extension (``None`` without ``frontier``): its planner on the
        team's map (whose ``free`` row is the true map: read it only where the team has seen),
        the goal action's candidates and held targets, as of the last observation."""
        return self._core.frontiers[self._copy]

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
                Other keys are ignored (PettingZoo's API test passes one of its own).

        Returns:
            Observations and infos. The infos are empty dicts: SuperSuit merges reset infos over
            the last step's infos at an automatic reset, so metrics in them would hide the
            episode's final coverage.
        """
        core, copy = self._core, self._copy
        core.reset(copy, seed, options)
        self.height, self.width = core.walls[copy].shape
        self.agents = self.possible_agents[:]
        obs = self._per_agent(core.observe(slice(copy, copy + 1)))
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
        """Move every agent at once (rules: ``envs/coverage_v0.py``); PettingZoo's five dicts.

        Raises:
            ValueError: for actions that are not a dict, a live agent without an action, an
                action for a name that is no live agent, or an action that is not an integer of
                the action space (the core's check names the agent, the value and the range);
                nothing is stepped.
        """
        self._require_state()
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        if self._core.copies != 1:
            raise RuntimeError("a copy of a batched core is stepped by its core, not by step()")
        if not isinstance(actions, Mapping):
            raise ValueError(
                f"actions must be a dict of agent name to action, got {type(actions).__name__}"
            )
        try:
            acts = [actions[a] for a in self.agents]
        except KeyError as exc:
            raise ValueError(f"no action given for {exc.args[0]}") from exc
        if len(actions) != len(acts):  # a misspelt name would be an action nobody takes
            extra = next(str(a) for a in actions if a not in self.agents)
            raise ValueError(f"an action for {extra!r}, which is no agent of this episode")
        core = self._core
        # The values as given: the core's one check of what an action may be names the agent.
        reward, done = core.step(acts)
        agents = self.agents
        finished = bool(done[0])
        infos = dict(zip(agents, core.infos(0)))
        observations = self._per_agent(core.observe())
        rewards = dict(zip(agents, reward[0].tolist()))
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, finished)
        if finished:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | str | None:
        """``rgb_array``: an ``(H*k, W*k, 3)`` uint8 image; ``ansi``: a text picture."""
        if self.render_mode is None:
            return None
        state = self._require_state()
        walls = self._core.walls[self._copy]
        if self.render_mode == "ansi":
            return render.ansi(walls, state.interior == CELL_VISITED, state.positions)
        return render.rgb_array(walls, state.credited_by, state.positions)

    def close(self) -> None:
        pass

    # ------------------------------------------------------------------ helpers
    def _per_agent(self, obs: np.ndarray | dict[str, np.ndarray]) -> dict[str, Any]:
        """One observation per agent from the core's batch of one (an array, or a dict)."""
        if isinstance(obs, dict):
            return {
                a: {key: value[0, i] for key, value in obs.items()}
                for i, a in enumerate(self.agents)
            }
        return dict(zip(self.agents, obs[0]))

    def _require_state(self) -> GridState:
        state = self._core.states[self._copy]
        if state is None:
            raise RuntimeError("call reset() before using the environment")
        return state


def _constructor_signature() -> inspect.Signature:
    """``CoverageEnv(...)``'s signature as ``help()`` and editors show it: the arguments of
    :meth:`CoreSpec.parse` (their one owner) and ``render_mode``."""
    parse = inspect.signature(CoreSpec.parse)
    render_mode = inspect.Parameter(
        "render_mode", inspect.Parameter.KEYWORD_ONLY, default=None, annotation="str | None"
    )
    params = [inspect.Parameter("self", inspect.Parameter.POSITIONAL_OR_KEYWORD)]
    params += [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in parse.parameters.values()]
    return parse.replace(parameters=[*params, render_mode], return_annotation=None)


CoverageEnv.__init__.__signature__ = _constructor_signature()  # type: ignore[attr-defined]
