"""Data types shared by the coverage environment's pieces (state, observations, rendering)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

# Cell codes of GridState.cells; they are also the observation's window values (§2.4), which is
# why the grid stores them directly: building an observation is a plain read.
CELL_UNVISITED = -1.0
CELL_VISITED = 0.0
CELL_WALL = 1.0

#: Action index -> (d_row, d_col): 0 up, 1 down, 2 left, 3 right, 4 stay.
MOVES = np.array([[-1, 0], [1, 0], [0, -1], [0, 1], [0, 0]], dtype=np.int64)
#: The stay action.
STAY = 4
#: With ``frontier={"action": "step"}``: one step along a shortest path to the nearest known free
#: cell not yet visited (the frontier compass's move), stay when there is none.
FRONTIER_STEP = 5


@dataclass
class GridState:
    """Mutable state of one episode.

    Attributes:
        cells: float32 ``(H + 2*pad, W + 2*pad)``: the map padded with wall, each cell
            ``CELL_WALL``, ``CELL_VISITED`` or ``CELL_UNVISITED``.
        pad: Width of the wall border around the map in ``cells``.
        positions: int64 ``(n_agents, 2)``: (row, col) of each agent in map coordinates.
        credited_by: int16 ``(H, W)``: the agent credited with each visited cell (start cells go
            to the agent that starts there), -1 elsewhere. Used to draw per-agent paths.
        steps: Steps taken this episode.
    """

    cells: np.ndarray
    pad: int
    positions: np.ndarray
    credited_by: np.ndarray
    steps: int = 0

    @property
    def interior(self) -> np.ndarray:
        """View of ``cells`` without the padding."""
        p = self.pad
        return self.cells[p:-p, p:-p]


def kind_options(value: str | Mapping[str, Any], registry: Mapping[str, type], what: str) -> Any:
    """The options object of a registry's kind from its config form: the kind's name (its
    defaults) or ``{name: {option: value, ...}}`` (the form of ``observation`` and
    ``frontier.action``).

    Args:
        value: The config form.
        registry: Kind names to their options classes (dataclasses).
        what: The option's name in messages (``"observation"``, ``"frontier.action"``).

    Raises:
        ValueError: naming ``what``, the kind or the option that is wrong.
    """
    if isinstance(value, str):
        name, given = value, {}
    elif isinstance(value, Mapping) and len(value) == 1:
        name, given = next(iter(value.items()))
        given = {} if given is None else given
        if not isinstance(given, Mapping):
            raise ValueError(f"{what} {name!r}: options must be a mapping, got {given!r}")
    else:
        raise ValueError(f"{what} must be a kind's name or {{name: {{options}}}}, got {value!r}")
    if name not in registry:
        raise ValueError(f"unknown {what} {name!r}; known: {', '.join(registry)}")
    cls = registry[name]
    known = [f.name for f in fields(cls)]
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise ValueError(
            f"{what} {name!r}: unknown option(s) {unknown}; known: {', '.join(known) or 'none'}"
        )
    return cls(**given)
