"""Non-learned reference policies: ``random``, the memoryless ``local`` rule and the classical
``frontier`` explorer.

All are :data:`harness.evaluation.episodes.BatchPolicy` callables, so ``run_episodes``
evaluates them on exactly the maps and start cells a trained model sees (``harness eval
--policy frontier``).

``local`` is a hand-written rule that sees exactly what a learned agent sees (its own 13-number
observation, no memory): step into an unvisited neighbour if there is one; otherwise towards an
unvisited diagonal cell of the 3x3 window (a free neighbour beside it); otherwise into any free
neighbour; ties broken at random, ``stay`` only when boxed in. It never hits a wall. It answers
"what does this observation allow without learning?", the fair bar for a learned policy, where
the frontier explorer is the bar for any policy. Its random draws come from each env copy's
``np_random`` (seeded by the episode's reset), like the Boltzmann test policy, so an episode
repeats whatever the number of copies.

``frontier_step`` (only on an env with ``frontier: {action: step}``) always takes the env's
frontier step: without a planner the frontier explorer without claims, each agent heading for
its own nearest unvisited known cell; with one, that planner itself.

``rollout`` (only on an env with the goal action, ``frontier: {action: {goal: ...}}``) chooses
the goal action's candidate slots by rollouts on maps sampled for the cells nobody has seen,
from 80 % coverage on by default (:class:`RolloutPolicy`; its parameters are the config's
``eval.rollout``): a search that sees only the team's map, the
strongest non-learned policy with 4 agents on 50x50 maps (docs/planners.md, "The rollout
chooser"), and about a thousand times slower than the planners.

``frontier`` is the classical frontier-based explorer (Yamauchi 1997) on the team's shared map
(``envs.coverage.frontier``, where its search is described): every agent walks, by a shortest
path through free cells the team has seen, to the nearest seen free cell nobody has visited yet,
skipping the cells lower-index teammates claimed this step; equally near cells are chosen in a
fixed neighbour order. ``frontier_pocket`` and ``frontier_random`` are the same explorer with
other tie-breaks. Every planner of the registry ``envs.coverage.frontier.PLANNERS`` is a baseline
under its entry's ``baseline`` name: the target with the fewest open neighbours
(finish a pocket before leaving it), or a random one (from each episode's generator). The
frontier agent knows the whole team's map, which a learned agent (13 numbers of local view) does
not: it is a strong reference, not a fair opponent. It only ever steps into seen free cells, so
it never hits a wall. Its speed, and every planner's, is ``harness bench eval``'s
(docs/performance.md: on the 2-core machine 50-75 episodes per CPU second on 50x50 maps with 4
agents and 1000 steps).
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.coverage import CoverageEnv
from envs.coverage.frontier import PLANNERS, FrontierOptions
from envs.coverage.observations import observation_options
from envs.coverage.planners import FrontierPlanner
from envs.coverage.rollouts import MapPriorFn, SampledChooser, in_threads
from envs.coverage.types import CELL_UNVISITED, CELL_WALL
from harness.config.schema import EvalConfig, RolloutConfig
from harness.evaluation.episodes import BatchPolicy, batch_len, episode_draws, sample_categorical
from harness.processes import available_cores


@dataclass(frozen=True)
class BaselineEntry:
    """A baseline of the registry :data:`BASELINES`."""

    make: Callable[[int, EvalConfig], BatchPolicy]
    """Builds it from the evaluation's seed (only ``random`` uses it: the others draw from each
    episode's generator or none) and the config's ``eval`` section (only ``rollout`` reads it:
    its ``rollout`` parameters)."""
    summary: str
    """One line on what it plays (``harness eval --help``)."""
    needs_action: bool = False
    """It plays the env's planner-backed action, so it runs only on a config with
    ``env.frontier.action`` (:meth:`check`); without: on any config."""

    any_env: bool = False
    """It plays a PettingZoo env of one's own too (``env: {pettingzoo: ...}``): it reads
    nothing of the coverage env."""

    plays_moves: bool = True
    """It acts with the five moves (0-3 up, down, left, right; 4 stay). Where the config's
    planner-backed action replaces them (the goal action: an action is a candidate slot), it
    plays the same episodes with that action off (:meth:`env_config`)."""

    holds_goals: bool = False
    """It chooses the goal action's slots and keeps a chosen target until it is reached: it
    runs only on a config with the goal action (``env.frontier.action: {goal: ...}``), whose
    ``hold`` :meth:`env_config` turns on (slot 0 is never held, so the episodes are the
    same)."""

    reads_prior: bool = False
    """It can plan with a map prior (``eval.rollout.prior``): :func:`make_baseline` hands it
    the loaded prior (``make(seed, options, prior)``)."""

    def env_config(self, env: Any) -> Any:
        """The env config it plays for ``env`` (an ``EnvConfig``, or a PettingZoo env's, which
        is kept): ``env`` itself, or, for a baseline that plays the moves on an env whose
        actions are the goal action's slots, ``env`` with ``frontier`` (and ``prior``) off.
        The maps and start cells come from each episode's seed alone, so it plays the same
        episodes as a model on ``env`` does; its moves read the env's state, not the
        observation, so what the extension would add to the observation does not matter to
        it."""
        options = env.frontier_options
        if self.holds_goals and _holdable(options):
            held = dataclasses.replace(
                options, action=dataclasses.replace(options.action, hold=True)
            )
            return env.model_copy(update={"frontier": held.config()})
        if (
            self.plays_moves
            and options is not None
            and options.action is not None
            and options.action.replaces_moves
        ):
            # env.prior feeds the goal action's candidates (and the team map's predicted
            # views) alone: it goes with them
            update: dict[str, Any] = {"frontier": None, "prior": None}
            observation = observation_options(env.observation)
            if getattr(observation, "predicted", False):
                plain = dataclasses.replace(observation, predicted=False)
                update["observation"] = {plain.name: dataclasses.asdict(plain)}
            return env.model_copy(update=update)
        return env

    def check(self, options: FrontierOptions | None) -> None:
        """``ValueError`` (one line, saying what to set) unless it can play an env with the
        planner extension's ``options`` (``None``: off)."""
        if self.holds_goals and not _holdable(options):
            raise ValueError(
                "this baseline chooses the goal action's slots: it needs env.frontier.action "
                "{goal: {k: K}} (with a planner; the teammap observation)"
            )
        if self.needs_action:
            FrontierStepPolicy.check(options)


def _holdable(options: FrontierOptions | None) -> bool:
    """Whether the planner extension's action kind keeps chosen targets (its ``holdable``)."""
    return options is not None and options.action is not None and options.action.holdable


#: The baselines by the name ``--policy`` takes (the one list of them).
BASELINES: dict[str, BaselineEntry] = {
    "random": BaselineEntry(
        lambda seed, _: RandomPolicy(seed), "uniformly random actions (any env)", any_env=True
    ),
    "local": BaselineEntry(
        lambda seed, _: LocalPolicy(), "the thesis's memoryless rule on each agent's 3x3 window"
    ),
    # One per planner of the registry: frontier, frontier_pocket, frontier_random, ...
    **{
        entry.baseline: BaselineEntry(
            lambda seed, _, name=name: FrontierPolicy(name), entry.summary
        )
        for name, entry in PLANNERS.items()
    },
    "frontier_step": BaselineEntry(
        lambda seed, _: FrontierStepPolicy(),
        "always the env's planner-backed action (configs with env.frontier.action)",
        needs_action=True,
        plays_moves=False,
    ),
    "rollout": BaselineEntry(
        lambda seed, options, prior=None: RolloutPolicy.from_config(options.rollout, prior),
        "the goal action's slots chosen by rollouts on sampled maps (goal configs; eval.rollout)",
        needs_action=True,
        plays_moves=False,
        holds_goals=True,
        reads_prior=True,
    ),
}


def make_baseline(
    name: str, seed: int, options: EvalConfig | None = None, prior: MapPriorFn | None = None
) -> BatchPolicy:
    """Make a baseline batched policy.

    Args:
        name: One of :data:`BASELINES`.
        seed: Seeds the random policy's generator (``local`` draws from each episode's own
            generator, ``frontier`` is deterministic).
        options: The config's ``eval`` section (``rollout`` reads its parameters there);
            default: the defaults.
        prior: The loaded map prior of ``eval.rollout.prior``, for a baseline that
            :attr:`~BaselineEntry.reads_prior`.

    Returns:
        A ``policy(obs, envs) -> actions`` callable (``harness.evaluation.episodes.BatchPolicy``).

    Raises:
        ValueError: For an unknown name.
    """
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}; known: {', '.join(BASELINES)}")
    entry, options = BASELINES[name], EvalConfig() if options is None else options
    return entry.make(seed, options, prior) if entry.reads_prior else entry.make(seed, options)


class FrontierStepPolicy:
    """Every agent always takes the env's frontier step (``env.frontier.action: step``): one step
    along a shortest way to its nearest unvisited known cell, ties drawn from the episode's
    generator, no coordination; with ``env.frontier.planner`` that planner's move (this policy is
    then the planner's baseline, move for move). The bar a learned policy with that action
    must beat to show it learned more than "always take it"."""

    @staticmethod
    def check(options: FrontierOptions | None) -> int:
        """The action that follows the planner (the frontier step; the goal action's slot 0,
        the planner's own choice); ``ValueError`` unless the env has a planner-backed action."""
        if options is None or options.expert_action is None:
            raise ValueError(
                "the frontier_step baseline needs env.frontier.action (step, or goal with a "
                "planner; with the teammap observation)"
            )
        return options.expert_action

    def __call__(self, obs: Any, envs: Sequence[CoverageEnv]) -> np.ndarray:
        """The planner-backed action for every agent of every env copy."""
        actions = {self.check(env.frontier) for env in envs}
        return np.full(batch_len(obs), actions.pop(), dtype=np.int64)


class RolloutPolicy:
    """The rollout chooser (``--policy rollout``; docs/planners.md, "The rollout chooser"): a
    policy over the goal action's slots that sees only the team's map. Slot 0 (the env's
    planner) until the team's map says it has covered :attr:`SampledChooser.after
    <envs.coverage.rollouts.SampledChooser>` of the map, then, for every agent that is not
    walking to a chosen target, each candidate slot rolled out to the episode's end on a few
    maps its unseen cells are sampled for (:class:`envs.coverage.rollouts.SampledChooser`); a
    slot that beats slot 0 by more than the maps' noise is taken and held (the env's goal
    action with ``hold``). The maps are drawn from each episode's generator (``np_random``,
    seeded by its reset), so an episode repeats from its seed alone.

    The copies of an evaluation decide side by side on ``threads`` threads, and each decision
    scores its maps side by side (``SampledChooser.threads``): the compiled rollouts release
    the GIL, and every copy draws from its own generator, so the choices are those of one
    thread (docs/performance.md, "The rollout chooser on every core").

    Args:
        chooser: Its rule and parameters; the default is the one measured on the test
            episodes (4 maps, 4 standard errors, from 80 %, scored by the steps to 99 %),
            with ``threads`` threads for its maps.
        threads: Threads for the copies (default: every core this process may use).
    """

    def __init__(self, chooser: SampledChooser | None = None, threads: int | None = None) -> None:
        threads = available_cores() if threads is None else threads
        self.chooser = chooser if chooser is not None else SampledChooser(threads=threads)
        self._map = in_threads(threads)

    @classmethod
    def from_config(cls, config: RolloutConfig, prior: MapPriorFn | None = None) -> RolloutPolicy:
        """The policy with a config's ``eval.rollout`` parameters, on every core this process
        may use (for the copies and for each decision's maps), drawing its maps from ``prior``
        (the loaded ``eval.rollout.prior``: the harness's commands load it)."""
        threads = available_cores()
        if config.prior is not None and prior is None:
            raise ValueError(
                "eval.rollout.prior names a map prior: load it (harness.prior.model.load_prior) "
                "and hand it in"
            )
        return cls(config.chooser(threads=threads, prior=prior), threads=threads)

    def _decide(self, env: CoverageEnv) -> np.ndarray:
        frontier = env.frontier_state
        return self.chooser.decide(
            frontier.planner,
            frontier.candidates,
            env.max_steps - env.steps,
            env.np_random,
            frontier.held,
        )

    def __call__(self, obs: Any, envs: Sequence[CoverageEnv]) -> np.ndarray:
        """A slot for every agent of every env copy, copy-major like ``obs``."""
        slots = self._map(self._decide, envs)
        return np.concatenate([np.zeros(0, dtype=np.int64), *slots]).astype(np.int64)


class RandomPolicy:
    """Uniform random actions 0..4 from a seeded generator (repeatable for a given seed); of a
    PettingZoo env of one's own, uniform over its actions (over the allowed ones where its
    observations carry an action mask; the coverage env's goal action keeps its 0..4 draws)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs: np.ndarray, envs: Sequence[CoverageEnv]) -> np.ndarray:
        """One uniform action per agent in the batch."""
        from harness.config.pettingzoo import ACTION_MASK_KEY
        from harness.tasks.pettingzoo import EpisodeView

        view = envs[0] if envs else None
        if isinstance(view, EpisodeView) and isinstance(obs, dict) and ACTION_MASK_KEY in obs:
            rows = np.asarray(obs[ACTION_MASK_KEY])
            return np.array([self.rng.choice(np.flatnonzero(row)) for row in rows], np.int64)
        n_actions = view.n_actions if isinstance(view, EpisodeView) else 5
        return self.rng.integers(0, n_actions, size=batch_len(obs))


#: Window index (row-major 3x3, agent in the centre, 4) of the cell that each move
#: (0 up, 1 down, 2 left, 3 right) enters, and of the two diagonal cells beside that cell.
_MOVE_CELL = np.array([1, 7, 3, 5])
_MOVE_DIAGONALS = np.array([[0, 2], [6, 8], [0, 6], [2, 8]])


def local_actions(obs: np.ndarray, uniform: np.ndarray) -> np.ndarray:
    """The ``local`` rule for a batch of thesis observations (see the module docstring).

    Args:
        obs: ``(batch, >= 9)``: the 3x3 windows of thesis observations (-1 unvisited,
            0 visited, 1 wall) in their first 9 columns.
        uniform: ``(batch,)`` draws from U[0, 1), one per row, that break ties.

    Returns:
        ``(batch,)`` actions: a move among the rule's best candidates, ``stay`` (4) when no
        neighbour is free.
    """
    window = obs[:, :9]
    entered = window[:, _MOVE_CELL]
    free = entered != CELL_WALL
    unvisited = entered == CELL_UNVISITED
    toward = free & (window[:, _MOVE_DIAGONALS] == CELL_UNVISITED).any(axis=2)
    # The first non-empty class of candidates, per row: unvisited, then towards, then free.
    candidates = np.where(
        unvisited.any(axis=1, keepdims=True),
        unvisited,
        np.where(toward.any(axis=1, keepdims=True), toward, free),
    )
    boxed_in = ~candidates.any(axis=1, keepdims=True)  # then stay (action 4) is the candidate
    return sample_categorical(np.concatenate([candidates, boxed_in], axis=1).astype(float), uniform)


def thesis_windows(env: CoverageEnv) -> np.ndarray:
    """``(n_agents, 9)``: each agent's 3x3 window as the thesis observation shows it (-1
    unvisited free, 0 visited, 1 wall or outside), read from the env's state, so the local rule
    runs whatever observation the env gives its agents."""
    cells = np.where(env.walls, CELL_WALL, np.where(env.visited, 0.0, CELL_UNVISITED))
    padded = np.pad(cells, 1, constant_values=CELL_WALL)
    rows, cols = env.positions[:, 0], env.positions[:, 1]
    dr, dc = np.divmod(np.arange(9), 3)
    return padded[rows[:, None] + dr[None, :], cols[:, None] + dc[None, :]]


class LocalPolicy:
    """The memoryless ``local`` rule on each agent's 3x3 window (see the module docstring)."""

    def __call__(self, obs: np.ndarray, envs: Sequence[CoverageEnv]) -> np.ndarray:
        """Actions for every agent of every env copy, copy-major like ``obs``."""
        windows = np.concatenate([thesis_windows(env) for env in envs])
        return local_actions(windows, episode_draws(envs, len(windows) // len(envs)))


class FrontierPolicy:
    """Nearest-unclaimed-frontier explorer on the team's known map (see the module docstring).

    Args:
        planner: A planner of ``envs.coverage.frontier.PLANNERS`` (``"order"`` the classical
            explorer; ``"random"`` draws from each episode's generator, so an episode repeats
            from its seed), or a ``(height, width) -> planner`` factory, e.g. a coordinated
            planner with other parameters (``lambda h, w: UtilityPlanner(h, w, beta=0.1)``).
    """

    def __init__(self, planner: str | Callable[[int, int], FrontierPlanner] = "order") -> None:
        if isinstance(planner, str):
            if planner not in PLANNERS:
                raise ValueError(f"unknown planner {planner!r}; known: {', '.join(PLANNERS)}")
            self._make = PLANNERS[planner].make
        else:
            self._make = planner
        self.planner = planner
        # One team map per env copy; weak keys so finished envs do not pile up.
        self._maps: weakref.WeakKeyDictionary[CoverageEnv, FrontierPlanner] = (
            weakref.WeakKeyDictionary()
        )

    def __call__(self, obs: np.ndarray, envs: Sequence[CoverageEnv]) -> np.ndarray:
        """Actions for every agent of every env copy, copy-major like ``obs``."""
        actions: list[int] = []
        for env in envs:
            team = self._maps.get(env)
            if team is None or team.shape != (env.height, env.width):
                team = self._maps[env] = self._make(env.height, env.width)
            read_map = lambda env=env: (env.walls, env.visited)  # noqa: E731
            actions.extend(team.step(env.steps, env.positions, read_map, env.np_random))
        return np.asarray(actions, dtype=np.int64)
