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
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from envs.coverage.planners import (
    FrontierPlanner,
    HungarianPlanner,
    MinPosPlanner,
    UtilityPlanner,
)
from envs.coverage.types import CELL_VISITED, CELL_WALL, FRONTIER_STEP, STAY, GridState

__all__ = [
    "ACTIONS",
    "PLANNERS",
    "ActionKind",
    "Frontier",
    "FrontierOptions",
    "PlannerEntry",
]


# ---------------------------------------------------------------------- the extension
@dataclass(frozen=True)
class PlannerEntry:
    """A planner of the registry :data:`PLANNERS`."""

    make: Callable[[int, int], FrontierPlanner]
    """Builds the planner for a map of ``(height, width)``."""
    baseline: str
    """Its baseline's name (``harness eval --policy NAME``)."""
    in_env: bool = True
    """Whether the env's compass and planner-backed actions can follow it: its move must be a
    function of the team's map (a planner that draws from a generator is a baseline only)."""


#: Planners by the name ``frontier.planner`` (and the baselines) take.
PLANNERS: dict[str, PlannerEntry] = {
    "order": PlannerEntry(lambda h, w: FrontierPlanner(h, w, "order"), "frontier"),
    "pocket": PlannerEntry(lambda h, w: FrontierPlanner(h, w, "pocket"), "frontier_pocket"),
    "random": PlannerEntry(
        lambda h, w: FrontierPlanner(h, w, "random"), "frontier_random", in_env=False
    ),
    # Coordinated planners, with the defaults chosen on validation episodes (docs/planners.md).
    "utility": PlannerEntry(lambda h, w: UtilityPlanner(h, w), "frontier_utility"),
    "minpos": PlannerEntry(lambda h, w: MinPosPlanner(h, w), "frontier_minpos"),
    "hungarian": PlannerEntry(lambda h, w: HungarianPlanner(h, w), "frontier_hungarian"),
}


@dataclass(frozen=True)
class ActionKind:
    """A planner-backed action kind of the registry :data:`ACTIONS`: actions numbered from
    ``FRONTIER_STEP`` (after the five moves) that the env turns into moves by asking
    :class:`Frontier`."""

    n_actions: int
    """Actions it adds to the five moves."""
    resolve: Callable[[Frontier, list[int], np.random.Generator], list[int]]
    """``(frontier, actions, rng) -> moves``: every action of this kind replaced by a move."""


def _step_moves(frontier: Frontier, actions: list[int], rng: np.random.Generator) -> list[int]:
    """The frontier step: one of the moves the current compass marks (drawn from ``rng`` when
    several tie, so teammates at one spot may part), stay when it marks none."""
    compass = frontier.compass
    out = list(actions)
    for i, a in enumerate(actions):
        if a == FRONTIER_STEP:
            moves = np.flatnonzero(compass[i, :4])
            if moves.size == 0:
                out[i] = STAY
            elif moves.size == 1:
                out[i] = int(moves[0])
            else:
                out[i] = int(moves[rng.integers(moves.size)])
    return out


#: Planner-backed action kinds by the name ``frontier.action`` takes.
ACTIONS: dict[str, ActionKind] = {"step": ActionKind(1, _step_moves)}


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
    """

    action: str | None = None
    planner: str | None = None

    def __post_init__(self) -> None:
        _choice(self.action, ACTIONS, "action")
        _choice(self.planner, PLANNERS, "planner")
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
        (``observation.check(frontier=True)``: the crop's channels).

        Args:
            observation: An observation's options (``envs.coverage.observations.TeamMap``,
                ``Thesis``), read by duck typing: ``name``, ``takes_frontier``, ``check``.
            options: The extension's options, ``None`` when off.

        Raises:
            ValueError: when they do not fit.
        """
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
        """The first planner-backed action (the planner's own move, which imitation learns
        from), ``None`` without one."""
        return FRONTIER_STEP if self.action is not None else None

    @property
    def extra_actions(self) -> int:
        """Actions added to the five moves."""
        return ACTIONS[self.action].n_actions if self.action is not None else 0


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
        self.planner = (
            PLANNERS[options.planner].make(height, width) if options.planner is not None else None
        )
        #: ``(agents, 5)``: the compass of the last observation (see the team-map observation).
        self.compass = np.zeros((0, 5), dtype=np.float32)

    def planned_moves(self, state: GridState) -> list[int]:
        """Each agent's move by the planner on the team's map of ``state`` (needs a planner)."""
        assert self.planner is not None
        interior = state.interior
        self.planner.sync(
            state.steps,
            state.positions,
            lambda: (interior == CELL_WALL, interior == CELL_VISITED),
        )
        return self.planner.act()

    def resolve(self, actions: Sequence[int], rng: np.random.Generator) -> list[int]:
        """``actions`` with every planner-backed action replaced by its move (rules: the kind's
        :attr:`ActionKind.resolve`)."""
        acts = list(actions)
        if self.options.action is None:
            return acts
        return ACTIONS[self.options.action].resolve(self, acts, rng)
