"""The planner extension of the coverage env, its one owner.

It holds the option ``frontier=`` of the env
(:class:`FrontierOptions`: which planner-backed action kind, which planner), the registries of
planners (:data:`PLANNERS`) and of planner-backed action kinds (:data:`ACTIONS`), and
:class:`Frontier`, the extension's state during an episode, which the env asks for the moves of
planner-backed actions. A new planner or action kind is an entry of a registry, not a flag.
The ``frontier*`` baselines (``harness.evaluation.baselines``) play the planners' moves; the
team-map observation shows them in its frontier compass.

The planners themselves are in :mod:`envs.coverage.planners`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import numpy as np

from envs.coverage.goals import (
    GOAL_FEATURES,
    PRIOR_EVERY,
    PRIOR_FEATURES,
    Candidates,
    Goal,
    gather_candidates,
    predicted_features,
)
from envs.coverage.planners import (
    FrontierPlanner,
    HungarianPlanner,
    MinPosPlanner,
    UtilityPlanner,
)
from envs.coverage.rollouts import MapPriorFn, prior_wall_probability
from envs.coverage.types import (
    CELL_VISITED,
    CELL_WALL,
    FRONTIER_STEP,
    STAY,
    GridState,
    kind_options,
)

__all__ = [
    "ACTIONS",
    "PLANNERS",
    "ActionKind",
    "Frontier",
    "FrontierOptions",
    "Goal",
    "PlannerEntry",
    "Step",
]


# ---------------------------------------------------------------------- the extension
@dataclass(frozen=True)
class PlannerEntry:
    """A planner of the registry :data:`PLANNERS`."""

    make: Callable[[int, int], FrontierPlanner]
    """Builds the planner for a map of ``(height, width)``."""
    baseline: str
    """Its baseline's name (``harness eval --policy NAME``)."""
    summary: str
    """One line on what it plays (``harness eval --help``)."""
    in_env: bool = True
    """Whether the env's compass and planner-backed actions can follow it: its move must be a
    function of the team's map (a planner that draws from a generator is a baseline only)."""


#: Planners by the name ``frontier.planner`` (and the baselines) take.
PLANNERS: dict[str, PlannerEntry] = {
    "order": PlannerEntry(
        lambda h, w: FrontierPlanner(h, w, "order"),
        "frontier",
        "the frontier explorer with claims, order tie-break",
    ),
    "pocket": PlannerEntry(
        lambda h, w: FrontierPlanner(h, w, "pocket"),
        "frontier_pocket",
        "the frontier explorer with claims, pocket-first tie-break",
    ),
    "random": PlannerEntry(
        lambda h, w: FrontierPlanner(h, w, "random"),
        "frontier_random",
        "the frontier explorer with claims, random tie-break",
        in_env=False,
    ),
    # Coordinated planners, with the defaults chosen on validation episodes (docs/planners.md).
    "utility": PlannerEntry(
        lambda h, w: UtilityPlanner(h, w),
        "frontier_utility",
        "coordinated by utility (Burgard et al. 2005)",
    ),
    "minpos": PlannerEntry(
        lambda h, w: MinPosPlanner(h, w), "frontier_minpos", "MinPos (Bautin et al. 2012)"
    ),
    "hungarian": PlannerEntry(
        lambda h, w: HungarianPlanner(h, w),
        "frontier_hungarian",
        "the optimal assignment of distinct targets (Hungarian method)",
    ),
}


@dataclass(frozen=True)
class Step:
    """Options of the frontier step (``frontier: {action: step}``): a sixth action after the
    five moves, one step along the compass (the planner's move when the options name one).
    None to set."""

    name: ClassVar[str] = "step"
    #: The step is added after the five moves.
    replaces_moves: ClassVar[bool] = False
    #: The action a policy that follows the planner takes.
    expert_action: ClassVar[int] = FRONTIER_STEP
    needs_planner: ClassVar[bool] = False
    #: Its actions are no candidate slots (no feature block for a slot-scoring policy).
    slots: ClassVar[bool] = False
    #: Its observation carries no action mask.
    masked: ClassVar[bool] = False
    #: It has no target to keep: each step is chosen anew.
    holdable: ClassVar[bool] = False
    n_actions: ClassVar[int] = 1

    def config(self) -> str:
        """The config form of these options."""
        return self.name

    def resolve(
        self, frontier: Frontier, actions: list[int], rng: np.random.Generator
    ) -> list[int]:
        """The frontier step: one of the moves the current compass marks (drawn from ``rng``
        when several tie, so teammates at one spot may part), stay when it marks none."""
        out = list(actions)
        marks = None
        for i, a in enumerate(actions):
            if a == FRONTIER_STEP:
                if marks is None:  # the compass's four moves, read once a step
                    marks = frontier.compass[:, :4].tolist()
                moves = [m for m, marked in enumerate(marks[i]) if marked]
                if not moves:
                    out[i] = STAY
                elif len(moves) == 1:
                    out[i] = moves[0]
                else:
                    out[i] = moves[int(rng.integers(len(moves)))]
        return out


#: A planner-backed action kind's options.
ActionKind = Step | Goal

#: Planner-backed action kinds by the name ``frontier.action`` takes: their options classes
#: (``action: NAME`` or ``action: {NAME: {option: value}}``).
ACTIONS: dict[str, type[Step] | type[Goal]] = {"step": Step, "goal": Goal}


def _action(value: Any) -> ActionKind | None:
    """The action kind's options from their config form (a name, ``{name: {options}}``, or
    options already made)."""
    if value is None or isinstance(value, (Step, Goal)):
        return value
    return kind_options(value, ACTIONS, "frontier.action")


def _choice(value: Any, registry: Mapping[str, Any], key: str) -> None:
    if value is not None and value not in registry:
        known = ", ".join(registry)
        raise ValueError(f"frontier.{key}: unknown {key} {value!r}; known: {known} (or null)")


@dataclass(frozen=True)
class FrontierOptions:
    """The env's ``frontier=`` option: the frontier field and compass in the team-map
    observation, and what is built on them.

    Attributes:
        action: A planner-backed action kind of :data:`ACTIONS` (``"step"``: a sixth action,
            one step along the compass), or ``None``: the five moves only.
        planner: A planner of :data:`PLANNERS` whose move the compass marks (targets claimed in
            agent index order), or ``None``: the compass marks every move that starts a
            shortest path to the nearest known unvisited cell (and the step draws among them).
        prior: A map prior (:data:`envs.coverage.rollouts.MapPriorFn`: the team's map to each
            cell's wall probability) whose prediction the goal action's candidates carry
            (:data:`envs.coverage.goals.PRIOR_FEATURES`), or ``None``. An object, not a
            setting: it is no part of :meth:`config` (the harness names it ``env.prior``).
    """

    action: ActionKind | None = None
    planner: str | None = None
    # An object the env is handed, no config option (``metadata``: the docs' key list skips it).
    prior: MapPriorFn | None = field(default=None, metadata={"config": False})

    def __post_init__(self) -> None:
        object.__setattr__(self, "action", _action(self.action))
        _choice(self.planner, PLANNERS, "planner")
        if self.prior is not None:
            if not callable(self.prior):
                raise ValueError(
                    f"frontier.prior must be a map prior function, got "
                    f"{type(self.prior).__name__} (in a harness config: env.prior: RUN)"
                )
            if not isinstance(self.action, Goal):
                raise ValueError(
                    "frontier.prior feeds the goal action's candidates: it needs "
                    "action {'goal': {...}}"
                )
        if self.action is not None and self.action.needs_planner and self.planner is None:
            raise ValueError(
                f"frontier.action: {self.action.name!r} needs frontier.planner (the planner's "
                f"choice is its first candidate); known: "
                f"{', '.join(n for n, p in PLANNERS.items() if p.in_env)}"
            )
        if self.planner is not None and not PLANNERS[self.planner].in_env:
            raise ValueError(
                f"frontier.planner: {self.planner!r} draws its ties from a generator: it is a "
                f"baseline only (--policy {PLANNERS[self.planner].baseline}); in the env use one "
                f"of {', '.join(n for n, p in PLANNERS.items() if p.in_env)}"
            )

    @classmethod
    def parse(cls, value: FrontierOptions | Mapping[str, Any] | None) -> FrontierOptions | None:
        """The options from their config form: ``None`` (off), a mapping of
        ``action``/``planner``, or options already made.

        Raises:
            ValueError: naming the key, for an unknown key or choice.
        """
        if value is None or isinstance(value, FrontierOptions):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(
                f"frontier must be null or a mapping with action and planner, got {value!r}"
            )
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(value) - set(names))
        if unknown:
            raise ValueError(f"frontier: unknown key(s) {unknown}; known: {', '.join(names)}")
        return cls(**value)

    @staticmethod
    def check_fits(observation: Any, options: FrontierOptions | None) -> None:
        """The rule between the observation and the extension: its field and compass live in
        an observation that takes them (the team map), whose options must hold the field
        (``observation.check(frontier=True)``: the crop's channels). An observation that shows
        a map prior's prediction (the team map's ``predicted``) needs the prior, which the goal
        action's candidates ask (:attr:`prior`).

        Args:
            observation: An observation's options (``envs.coverage.observations.TeamMap``,
                ``Thesis``), read by duck typing: ``name``, ``takes_frontier``, ``check``.
            options: The extension's options, ``None`` when off.

        Raises:
            ValueError: when they do not fit.
        """
        if getattr(observation, "predicted", False) and (options is None or options.prior is None):
            raise ValueError(
                "observation predicted: true shows a map prior's prediction: it needs one "
                "(frontier.prior; in a harness config env.prior: RUN)"
            )
        if options is None:
            return
        if not observation.takes_frontier:
            raise ValueError(
                "frontier needs the teammap observation (its field and compass are part of it), "
                f"not {observation.name!r}"
            )
        observation.check(frontier=True)

    @property
    def expert_action(self) -> int | None:
        """The action that follows the planner (the frontier step; the goal action's slot 0),
        which imitation learns from; ``None`` without a planner-backed action."""
        return self.action.expert_action if self.action is not None else None

    @property
    def n_actions(self) -> int:
        """Size of the env's action space: the five moves and the kind's actions after them,
        or the kind's actions alone when it replaces the moves (the goal action)."""
        if self.action is None:
            return 5
        return self.action.n_actions + (0 if self.action.replaces_moves else 5)

    def config(self) -> dict[str, Any]:
        """These options in their config form (``{"action": ..., "planner": ...}``)."""
        action = self.action.config() if self.action is not None else None
        return {"action": action, "planner": self.planner}


class Frontier:
    """The planner extension during an episode, for one map size: the planner (when the options
    name one) and the frontier compass of the last observation, which the team-map observation
    writes and planner-backed actions follow.

    Args:
        options: What is on.
        height: Rows of the map.
        width: Columns of the map.
    """

    def __init__(self, options: FrontierOptions, height: int, width: int) -> None:
        self.options = options
        #: The prior's last wall probabilities and the step it gave them (asked every
        #: :data:`~envs.coverage.goals.PRIOR_EVERY` steps).
        self._p_wall = np.zeros((height, width))
        self._prior_step = 0
        self.planner = (
            PLANNERS[options.planner].make(height, width) if options.planner is not None else None
        )
        #: ``(agents, 5)``: the compass of the last observation (see the team-map observation).
        self.compass = np.zeros((0, 5), dtype=np.float32)
        self.height, self.width = height, width
        #: The goal action's candidates of the last observation (``None`` without it).
        self.candidates: Candidates | None = None
        #: ``(agents,)`` each agent's held target (padded flat cell, -1: none), with the goal
        #: action's ``hold`` (set by :meth:`Goal.resolve`, let go by :func:`gather_candidates`).
        self.held = np.full(0, -1, dtype=np.int64)

    @property
    def goal(self) -> Goal | None:
        """The goal action's options, when that is the action kind."""
        action = self.options.action
        return action if isinstance(action, Goal) else None

    @property
    def p_wall(self) -> np.ndarray:
        """``(H, W)``: the prior's wall probabilities of the team's map as it last asked
        (:meth:`planned_moves`, every :data:`~envs.coverage.goals.PRIOR_EVERY` steps); zeros
        before that or without a prior."""
        return self._p_wall

    @property
    def n_goal_features(self) -> int:
        """Columns of the goal action's candidate features (with a prior, its columns too)."""
        return len(GOAL_FEATURES) + (len(PRIOR_FEATURES) if self.options.prior is not None else 0)

    def planned_moves(self, state: GridState) -> list[int]:
        """Each agent's move by the planner on the team's map of ``state`` (needs a planner)."""
        assert self.planner is not None
        interior = state.interior
        moves = self.planner.step(
            state.steps, state.positions, lambda: (interior == CELL_WALL, interior == CELL_VISITED)
        )
        goal = self.goal
        if goal is not None:
            held = None
            if goal.hold:
                n = len(moves)
                if state.steps == 0 or self.held.size != n:  # an episode starts: nothing held
                    self.held = np.full(n, -1, dtype=np.int64)
                held = self.held
            candidates = gather_candidates(
                self.planner, moves, goal.k, self.height, self.width, held
            )
            prior = self.options.prior  # the goal action's candidates then carry its features
            if prior is not None:
                if state.steps == 0 or state.steps - self._prior_step >= PRIOR_EVERY:
                    self._p_wall = prior_wall_probability(self.planner, prior)
                    self._prior_step = state.steps
                extra = predicted_features(self._p_wall, self.planner.seen, candidates.cells)
                candidates.features = np.concatenate([candidates.features, extra], axis=2)
            self.candidates = candidates
        return moves

    def resolve(self, actions: Sequence[int], rng: np.random.Generator) -> list[int]:
        """``actions`` with every planner-backed action replaced by its move (rules: the kind's
        :attr:`ActionKind.resolve`)."""
        acts = list(actions)
        if self.options.action is None:
            return acts
        return self.options.action.resolve(self, acts, rng)
