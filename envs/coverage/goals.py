"""The goal action of the planner extension: each agent chooses one of ``k`` candidate targets,
and the env walks it one step along a shortest path to the chosen one.

One network decision per env step (so SB3's DQN, double Q, dueling, prioritized replay and per-slot
ε work unchanged), the planner does the walking: the design that the multi-robot exploration
literature's wins over written planners share (ACE, Yu et al. 2023; ARiADNE, Cao et al. 2023).

**The candidates** of agent ``i`` at a step, in slot order:

* slot 0: the target the env's planner (``frontier.planner``) chose for the agent this step, and
  its move (the planner's own first step), so that a policy that always takes slot 0 *is* the
  planner, step for step (the imitation target, ``expert_action`` 0), with one exception: an
  agent the planner leaves without a target (once fewer targets are left than agents, the last
  in claim order stay in place) has no planner's choice, and its slots hold the clusters from
  slot 0 on, so that slot 0 walks it towards the nearest instead of staying;
* slots 1..k-1: one target per *frontier cluster* (a 4-connected group of known free unvisited
  cells), the cluster's cell nearest to the agent (ties: the lower row-major cell), clusters by
  their distance (ties: the lower cell), leaving out slot 0's cluster and clusters the agent
  cannot reach (the nearest other cells instead were tried and retired:
  research/experiment-log.md);
* fewer candidates than ``k``: the remaining slots are empty, shown by the ``action_mask`` (0)
  and by all-zero features; an empty slot the policy takes anyway keeps the agent in place.

**Holding a target** (``hold: true``, off by default): an agent that takes a slot >= 1 (a
deviation from the planner) keeps that target and walks a shortest path to it, a step per env
step, until the cell is visited (by it or a teammate) or no longer reachable through the seen
free cells. While it holds, its only candidate is the held target, in slot 0 (the mask allows
slot 0 alone; taking it walks on), and its teammates' ``heading`` feature reads the held target
instead of its planner's. Taking slot 0 is never held (the planner walks that step and the agent
chooses again at the next), so a policy that always takes slot 0 is still the planner. The rule
is the commitment ``research/experiments/goal_oracle.py`` measured; a learner stores each choice
as one transition over the steps it held (``algo.per_decision``, docs/goals.md).

Distances are shortest paths through the cells the team has seen (as the planners plan), from
one search per step for all agents
(:meth:`envs.coverage.planners.FrontierPlanner.distance_fields`).

**The features** of a candidate (a row of the observation's ``"goals"`` block, each in [-1, 1]),
in the order of :data:`GOAL_FEATURES`:

==============  ==========================================================================
``valid``       1 for a candidate, 0 for an empty slot
``planner``     1 for the planner's choice (slot 0)
``distance``    the agent's path length to it over ``H + W`` (at most 1)
``teammate``    the nearest teammate's path length to it over ``H + W`` (1: no teammate
                reaches it, or a lone agent)
``heading``     1 if a teammate's planner target lies in its cluster
``cluster``     ``log(1 + cells of its cluster) / log(1 + H * W)``
``unknown``     share of unknown cells in the 5x5 window around it
``open``        share of its 4 neighbours that are unseen or seen free and not visited (the
                pocket tie-break's count: a low value is a pocket's last cells)
``row``, ``col``  its offset from the agent over ``H`` and ``W``
==============  ==========================================================================

**With a map prior** (``frontier={..., "prior": f}``, a function from the team's map to each cell's
probability of being a wall, e.g. a prior run of the harness: ``env.prior``), two more columns
follow, in the order of :data:`PRIOR_FEATURES`: the free cells the prior expects among the unseen
ones in the 7x7 (``predicted_near``) and 15x15 (``predicted_far``) windows around the candidate,
over the window's cells: how much unexplored floor lies behind it (MapEx's predicted information
gain, Ho et al. 2025, as features a policy reads: MapExRL's recipe). The prior is asked every
:data:`PRIOR_EVERY` steps; the cells seen since count as seen. Without a prior the block
has the columns above alone, as the shipped goal models were trained.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from numba import njit

from envs.coverage.paths import distance_fields, first_step, move_towards
from envs.coverage.types import STAY

if TYPE_CHECKING:
    from envs.coverage.planners import FrontierPlanner

__all__ = [
    "ACTION_MASK_KEY",
    "GOALS_KEY",
    "GOAL_FEATURES",
    "PRIOR_FEATURES",
    "Candidates",
    "Goal",
    "gather_candidates",
    "predicted_features",
]

#: Key of the candidates' feature block in the observation (``(k, len(GOAL_FEATURES))``).
GOALS_KEY = "goals"
#: Key of the slots' mask in the observation (PettingZoo's convention, int8): 1 where a slot
#: holds a candidate.
ACTION_MASK_KEY = "action_mask"
#: Names of the candidate features, in column order (see the module docstring).
GOAL_FEATURES = (
    "valid",
    "planner",
    "distance",
    "teammate",
    "heading",
    "cluster",
    "unknown",
    "open",
    "row",
    "col",
)

#: Names of the columns a map prior adds after :data:`GOAL_FEATURES` (module docstring), and the
#: half-width of each one's window.
PRIOR_FEATURES = ("predicted_near", "predicted_far")
PRIOR_RADII = (3, 7)
#: The env asks its prior every this many steps (and at an episode's first) and reads the
#: prediction in between with the team's seen cells of the step: a network call costs far more
#: than the rest of a step (``harness bench env``, "... + map prior"), and the prediction of the
#: unseen part changes slowly (every step: 301 agent-steps/s on 50x50, every 5: 1,877, one run).
PRIOR_EVERY = 5

#: Most slots a goal action may have (the candidate block is an observation of this width).
MAX_K = 64


@dataclass(frozen=True)
class Goal:
    """Options of the goal action (``frontier: {action: {goal: {k: 8}}, planner: ...}``).

    Attributes:
        k: Candidate slots per agent (the action space is ``Discrete(k)``), 2..64.
        hold: Keep a target chosen in a slot >= 1 until it is visited or unreachable (module
            docstring); ``False``: choose again every step.
    """

    k: int = 8
    hold: bool = False
    name: ClassVar[str] = "goal"
    #: The action space is the slots alone: no primitive moves beside them.
    replaces_moves: ClassVar[bool] = True
    #: The slot a policy that follows the planner takes.
    expert_action: ClassVar[int] = 0
    #: The goal action needs a planner (its choice is slot 0).
    needs_planner: ClassVar[bool] = True
    #: Its actions are candidate slots, each with its features in the observation
    #: (:data:`GOALS_KEY`): a policy that scores slots can play it.
    slots: ClassVar[bool] = True
    #: Its observation carries an action mask (:data:`ACTION_MASK_KEY`: 1 where a slot holds a
    #: candidate), which a learner may read (masked actions, decisions per goal).
    masked: ClassVar[bool] = True
    #: A chosen target can be kept until it is reached (the ``hold`` option).
    holdable: ClassVar[bool] = True

    def __post_init__(self) -> None:
        k = self.k
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 2 <= k <= MAX_K:
            raise ValueError(f"frontier.action.goal.k must be an integer in 2..{MAX_K}, got {k!r}")
        if not isinstance(self.hold, (bool, np.bool_)):
            raise ValueError(f"frontier.action.goal.hold must be true or false, got {self.hold!r}")

    @property
    def n_actions(self) -> int:
        return int(self.k)

    def config(self) -> dict[str, Any]:
        """The config form of these options (``hold`` only when on: the form of the configs
        written before it existed stays as it was)."""
        options: dict[str, Any] = {"k": int(self.k)}
        if self.hold:
            options["hold"] = True
        return {self.name: options}

    def resolve(self, frontier: Any, actions: list[int], rng: np.random.Generator) -> list[int]:
        """Each agent's move: the first step towards its chosen slot's candidate (stay for an
        empty slot), from the candidates of the last observation (``frontier.candidates``).
        With :attr:`hold`, a candidate taken in a slot >= 1 becomes the agent's held target
        (``frontier.held``), which the next observation's candidates keep in slot 0."""
        candidates = frontier.candidates
        if self.hold:
            for i, a in enumerate(actions):
                if a >= 1 and candidates.cells[i, a] >= 0:
                    frontier.held[i] = candidates.cells[i, a]
        moves = candidates.moves
        return [int(moves[i, a]) for i, a in enumerate(actions)]


@dataclass
class Candidates:
    """The candidates of every agent at one step (see the module docstring)."""

    cells: np.ndarray
    """``(agents, k)`` padded flat cell of each slot's candidate (-1: empty)."""
    moves: np.ndarray
    """``(agents, k)`` the move (0-3) towards it, ``STAY`` for an empty slot."""
    features: np.ndarray
    """``(agents, k, len(GOAL_FEATURES))`` float32."""

    @property
    def mask(self) -> np.ndarray:
        """``(agents, k)`` int8 (PettingZoo's and Gymnasium's dtype of an action mask), 1 where
        a slot holds a candidate."""
        return (self.cells >= 0).astype(np.int8)

    @classmethod
    def empty(cls, n_agents: int, k: int) -> Candidates:
        return cls(
            np.full((n_agents, k), -1, dtype=np.int64),
            np.full((n_agents, k), STAY, dtype=np.int64),
            np.zeros((n_agents, k, len(GOAL_FEATURES)), dtype=np.float32),
        )


def gather_candidates(
    planner: FrontierPlanner,
    planned: Sequence[int],
    k: int,
    height: int,
    width: int,
    held: np.ndarray | None = None,
) -> Candidates:
    """The candidates of every agent (module docstring), for a planner that has just planned.

    Args:
        planner: The env's planner, synced to this step, after :meth:`act` (its ``goals``).
        planned: Its moves this step (one per agent), slot 0's moves.
        k: Slots per agent.
        height, width: The map's size (for the features' scales).
        held: ``(agents,)`` int64, each agent's held target (padded flat cell, -1: none), or
            ``None`` (no holding). Updated in place: a target that was visited or is no longer
            reachable is let go (-1); an agent that still holds one gets it as its only
            candidate.
    """
    n = len(planner.positions)
    out = Candidates.empty(n, k)
    if held is None:
        held = np.full(n, -1, dtype=np.int64)
    if planner.n_targets == 0:
        held[:] = -1  # every seen cell is visited: nothing is left to hold
        return out
    dist, scratch = planner.work_arrays()
    _gather_candidates(
        planner.passable, planner.target, planner.seen, planner.stride,
        np.asarray(planner.positions, dtype=np.int64), np.asarray(planner.goals, dtype=np.int64),
        np.asarray(planned, dtype=np.int64), held, _cluster_shares(height, width),
        1.0 / (height + width), height, width,
        dist, scratch, out.cells, out.moves, out.features,
    )  # fmt: skip
    return out


def predicted_features(p_wall: np.ndarray, seen: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The :data:`PRIOR_FEATURES` of candidate ``cells`` (padded flat, -1: an empty slot, whose
    features are 0) for wall probabilities ``p_wall`` ``(H, W)`` and the team's padded flat
    ``seen`` cells (a padding of one ring): ``float32 (*cells.shape, len(PRIOR_FEATURES))``.

    A window's value is the sum over its unseen cells inside the map of ``1 - p_wall``, over the
    window's cells (so in [0, 1])."""
    h, w = p_wall.shape
    unseen = ~np.asarray(seen, dtype=bool).reshape(h + 2, w + 2)[1:-1, 1:-1]
    expected_free = np.where(unseen, 1.0 - np.asarray(p_wall, dtype=np.float64), 0.0)
    out = np.zeros((*cells.shape, len(PRIOR_FEATURES)), dtype=np.float32)
    valid = cells >= 0
    rows, cols = np.divmod(cells[valid], w + 2)
    rows, cols = rows - 1, cols - 1  # the padded cell's place in the map
    for f, r in enumerate(PRIOR_RADII):
        # Window sums from an integral image with a margin of r zeros on every side.
        padded = np.zeros((h + 2 * r + 1, w + 2 * r + 1))
        padded[r + 1 : r + 1 + h, r + 1 : r + 1 + w] = expected_free
        ii = padded.cumsum(0).cumsum(1)
        side = 2 * r + 1
        total = (
            ii[rows + side, cols + side] - ii[rows, cols + side]
            - ii[rows + side, cols] + ii[rows, cols]
        )  # fmt: skip
        out[valid, f] = total / side**2
    return out


@lru_cache(maxsize=32)
def _cluster_shares(height: int, width: int) -> np.ndarray:
    """The ``cluster`` feature of a cluster of every size ``0 .. H * W``,
    ``log(1 + cells) / log(1 + H * W)``, by NumPy's ``log1p`` (the features were measured and
    the shipped models trained with it; a compiled ``log1p`` may differ in the last bit)."""
    return np.log1p(np.arange(height * width + 1)) / np.log1p(height * width)


@njit(cache=True, nogil=True)
def _gather_candidates(
    passable: np.ndarray,
    target: np.ndarray,
    seen: np.ndarray,
    stride: int,
    starts: np.ndarray,
    goals: np.ndarray,
    planned: np.ndarray,
    held: np.ndarray,
    cluster_shares: np.ndarray,
    scale: float,
    height: int,
    width: int,
    dist: np.ndarray,
    scratch: np.ndarray,
    cells: np.ndarray,
    moves: np.ndarray,
    features: np.ndarray,
) -> None:
    """:func:`gather_candidates` in one compiled call: every agent's distance field through the
    seen free cells (``dist`` ``(agents, cells)``), the held targets still held (the others set
    to -1 in ``held``), the frontier clusters, and the slots with their features
    (:func:`_fill_candidates`); ``scratch`` ``(>= 3, cells)`` int64."""
    size = target.size
    no_predecessors = np.empty((0, 0), dtype=np.int32)
    distance_fields(passable, stride, starts, np.inf, dist, no_predecessors, scratch[0])
    for i in range(starts.size):
        # Let go of a target once it is visited (no longer a target) or cannot be reached.
        if held[i] >= 0 and not (target[held[i]] and dist[i, held[i]] < np.inf):
            held[i] = -1
    n_targets = 0
    for c in range(size):
        if target[c]:
            scratch[0, n_targets] = c
            n_targets += 1
    if n_targets == 0:
        return
    targets = scratch[0, :n_targets].copy()
    labels = scratch[1]
    labels[:] = 0
    n_clusters = _label_clusters(target, targets, stride, labels, scratch[2])
    ids = np.empty(n_targets, dtype=np.int64)
    sizes = np.zeros(n_clusters + 1, dtype=np.int64)
    column = scratch[2]  # each target cell's column in costs (the stack is no longer needed)
    for j in range(n_targets):
        ids[j] = labels[targets[j]]
        sizes[ids[j]] += 1
        column[targets[j]] = j
    cluster_share = np.empty(n_clusters + 1)
    for c in range(n_clusters + 1):
        cluster_share[c] = cluster_shares[sizes[c]]
    n = starts.size
    costs = np.empty((n, n_targets))
    for i in range(n):
        for j in range(n_targets):
            costs[i, j] = dist[i, targets[j]]
    goal_cluster = np.zeros(n, dtype=np.int64)  # where each agent heads: held, else planned
    for i in range(n):
        if held[i] >= 0:
            goal_cluster[i] = labels[held[i]]
        elif goals[i] >= 0:
            goal_cluster[i] = labels[goals[i]]
    _fill_candidates(
        costs, targets, ids, n_clusters, goal_cluster, goals, planned, held, dist, starts, stride,
        column, labels, cluster_share, passable, target, seen, scale, height, width,
        cells, moves, features,
    )  # fmt: skip


@njit(cache=True, nogil=True)
def _unknown_share(seen: np.ndarray, stride: int, c: int) -> np.float32:
    """The ``unknown`` feature of padded cell ``c``: the share of unseen cells in the 5x5
    window around it (outside the padded grid counts as seen), as SciPy's
    ``uniform_filter(unseen, 5, mode="constant")`` on float32 computes it: a float32 mean
    down each column, then a float32 mean of five of them (both sums are exact in float64,
    so this equals SciPy's running sums value for value)."""
    rows = seen.size // stride
    row, col = c // stride, c % stride
    total = 0.0
    for cc in range(col - 2, col + 3):
        if 0 <= cc < stride:
            count = 0
            for rr in range(row - 2, row + 3):
                if 0 <= rr < rows and not seen[rr * stride + cc]:
                    count += 1
            total += np.float64(np.float32(count / 5.0))
    return np.float32(total / 5.0)


@njit(cache=True, nogil=True)
def _open_share(passable: np.ndarray, target: np.ndarray, seen: np.ndarray, stride: int, c: int):
    """The ``open`` feature of padded cell ``c``: the share of its 4 neighbours that are
    unseen, or seen free and not visited (a target)."""
    count = 0
    for v in (c - stride, c - 1, c + 1, c + stride):
        if not seen[v] or target[v]:
            count += 1
    return np.float32(count / 4.0)


# The per-step work of the candidates, compiled: it runs over every target cell once per agent.
@njit(cache=True, nogil=True)
def _label_clusters(
    target: np.ndarray, cells: np.ndarray, stride: int, labels: np.ndarray, stack: np.ndarray
) -> int:
    """Number the frontier clusters (4-connected groups of ``target`` cells, flat and padded)
    1, 2, ... into ``labels`` (0 elsewhere; ``labels`` starts zeroed) and return how many. Only
    the grouping is used, never the numbers."""
    n = 0
    for c in cells:
        if labels[c]:
            continue
        n += 1
        labels[c] = n
        top = 0
        stack[0] = c
        while top >= 0:
            v = stack[top]
            top -= 1
            for w in (v - stride, v - 1, v + 1, v + stride):
                if target[w] and not labels[w]:
                    labels[w] = n
                    top += 1
                    stack[top] = w
    return n


@njit(cache=True, nogil=True)
def _nearest_of_clusters(
    cost: np.ndarray,
    targets: np.ndarray,
    ids: np.ndarray,
    n_clusters: int,
    skip: int,
    dist: np.ndarray,
    start: int,
    stride: int,
    cells: np.ndarray,
    moves: np.ndarray,
) -> int:
    """One agent's cluster candidates (module docstring): of every cluster it reaches, other
    than ``skip``, the nearest cell (ties: the lower cell), nearest first (ties: the lower
    cell), as many as ``cells`` holds, with the first move of the path to each (walked back
    along the agent's distance field ``dist``). Returns how many were written."""
    best = np.full(n_clusters + 1, -1, dtype=np.int64)  # per cluster: its nearest target
    for j in range(targets.size):  # targets ascend: a strictly nearer cell replaces
        c = ids[j]
        if best[c] < 0 or cost[j] < cost[best[c]]:
            best[c] = j
    key = np.empty(n_clusters, dtype=np.float64)
    picks = np.empty(n_clusters, dtype=np.int64)
    m = 0
    for c in range(1, n_clusters + 1):
        j = best[c]
        if j >= 0 and c != skip and cost[j] < np.inf:
            picks[m] = j
            # path lengths are whole numbers: distance first, then the cell, in one exact key
            key[m] = cost[j] * dist.size + targets[j]
            m += 1
    order = np.argsort(key[:m])
    count = min(m, cells.size)
    for slot in range(count):
        goal = targets[picks[order[slot]]]
        cells[slot] = goal
        moves[slot] = move_towards(first_step(dist, goal, stride), start, stride)
    return count


@njit(cache=True, nogil=True)
def _fill_candidates(
    costs: np.ndarray,
    targets: np.ndarray,
    ids: np.ndarray,
    n_clusters: int,
    goal_cluster: np.ndarray,
    goals: np.ndarray,
    planned: np.ndarray,
    held: np.ndarray,
    dist: np.ndarray,
    starts: np.ndarray,
    stride: int,
    column: np.ndarray,
    labels: np.ndarray,
    cluster_share: np.ndarray,
    passable: np.ndarray,
    target: np.ndarray,
    seen: np.ndarray,
    scale: float,
    height: int,
    width: int,
    cells: np.ndarray,
    moves: np.ndarray,
    features: np.ndarray,
) -> None:
    """Every agent's slots (``cells``, ``moves``) and their features (module docstring), into
    the empty :class:`Candidates` arrays: slot 0 the planner's target and move, then
    :func:`_nearest_of_clusters`; for an agent that holds a target (``held``), that target and
    the first step towards it alone."""
    n = starts.size
    for i in range(n):
        m = 0
        if held[i] >= 0:  # the held target, its only candidate
            cells[i, 0] = held[i]
            moves[i, 0] = move_towards(first_step(dist[i], held[i], stride), starts[i], stride)
            m = 1
        else:
            if goals[i] >= 0:  # slot 0: the planner's choice and its own move
                cells[i, 0], moves[i, 0] = goals[i], planned[i]
                m = 1
            m += _nearest_of_clusters(
                costs[i], targets, ids, n_clusters, goal_cluster[i], dist[i], starts[i], stride,
                cells[i, m:], moves[i, m:],
            )  # fmt: skip
        if m == 0:
            continue
        row_i, col_i = starts[i] // stride, starts[i] % stride
        for slot in range(m):
            c = cells[i, slot]
            col = column[c]
            f = features[i, slot]
            f[0] = 1.0
            f[2] = min(costs[i, col] * scale, 1.0)
            mate, heading = np.inf, False
            for j in range(n):
                if j != i:
                    mate = min(mate, costs[j, col])
                    heading = heading or goal_cluster[j] == labels[c]
            f[3] = min(mate * scale, 1.0)
            f[4] = 1.0 if heading else 0.0
            f[5] = cluster_share[labels[c]]
            f[6] = _unknown_share(seen, stride, c)
            f[7] = _open_share(passable, target, seen, stride, c)
            f[8] = (c // stride - row_i) / height
            f[9] = (c % stride - col_i) / width
        f0 = features[i, 0]
        f0[1] = 1.0 if goals[i] >= 0 and cells[i, 0] == goals[i] else 0.0
