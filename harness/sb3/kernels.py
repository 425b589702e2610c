"""The numbers behind replay (:mod:`harness.sb3.replay`): the sum tree of proportional prioritized
replay (Schaul et al., 2015), its IS weights, n-step returns as SB3's ``NStepReplayBuffer``
computes them (on the host and on the device), the sampled batch's type and the replay memory's
size. SB3 ships no prioritized buffer (DLR-RM/stable-baselines3#1242) and none that handles
several envs.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from numba import njit

__all__ = [
    "PrioritizedReplayBufferSamples",
    "SumTree",
    "check_n_step_returns",
    "importance_weights",
    "n_step_returns",
    "n_step_returns_on_device",
    "replay_memory_bytes",
]


# Codes the kernels below return for bad input (0: none); the caller raises the message.
_BAD_INDEX = 1
_BAD_VALUE = 2


@njit(cache=True, nogil=True)
def _tree_set(
    nodes: np.ndarray,
    size: int,
    capacity: int,
    indices: np.ndarray,
    values: np.ndarray,
    min_leaf: float,
) -> tuple[int, float]:
    """Check, then write ``values`` into the leaves ``indices`` in order (the last write of an
    index wins) and recompute their ancestors; :class:`SumTree.update`'s kernel.

    Each leaf's ancestors are recomputed bottom-up as ``left + right`` after its own write. A
    node shared by several leaves' paths is written last by the last of them, when every node
    below it is final, so each ends as the sum of its final children: the same floats as a
    level-by-level pass after all the writes.

    ``min_leaf`` (the smallest positive leaf, ``inf``: none, NaN: unknown) follows the writes:
    a write can only lower it, unless it replaces a leaf equal to it by a larger value or a
    zero; then it becomes unknown (NaN) and the next read scans the leaves.

    Returns:
        0, or :data:`_BAD_INDEX` / :data:`_BAD_VALUE` (then nothing is written); and the new
        ``min_leaf``.
    """
    for k in range(indices.size):
        if indices[k] < 0 or indices[k] >= capacity:
            return _BAD_INDEX, min_leaf
    for k in range(values.size):
        # NaN fails both comparisons: not finite.
        if not (0.0 <= values[k] < np.inf):
            return _BAD_VALUE, min_leaf
    for k in range(indices.size):
        node = size + indices[k]
        value = values[k]
        if min_leaf == min_leaf:  # known
            if nodes[node] == min_leaf and (value > min_leaf or value == 0.0):
                min_leaf = np.nan
            elif 0.0 < value < min_leaf:
                min_leaf = value
        nodes[node] = value
        node >>= 1
        while node >= 1:
            nodes[node] = nodes[2 * node] + nodes[2 * node + 1]
            node >>= 1
    return 0, min_leaf


@njit(cache=True, nogil=True)
def _tree_descend(nodes: np.ndarray, size: int, queries: np.ndarray, out: np.ndarray) -> None:
    """:meth:`SumTree.find_prefixsum` of each of ``queries`` into ``out`` (a query at a time,
    the same comparisons and subtractions as a descent of all queries together)."""
    for k in range(queries.size):
        query = queries[k]
        if query < 0.0:  # np.maximum(query, 0): a NaN stays NaN and always goes left
            query = 0.0
        node = 1
        while node < size:
            left = 2 * node
            left_sum = nodes[left]
            if query >= left_sum and nodes[left + 1] > 0.0:
                query = query - left_sum
                node = left + 1
            else:
                node = left
        out[k] = node - size


@njit(cache=True, nogil=True)
def _stratified_queries(total: float, offsets: np.ndarray) -> np.ndarray:
    """``(k + offsets[k]) * total / n`` for ``k < n = len(offsets)``: one query per stratum."""
    n = offsets.size
    segment = total / n
    queries = np.empty(n, dtype=np.float64)
    for k in range(n):
        queries[k] = (k + offsets[k]) * segment
    return queries


@njit(cache=True, nogil=True)
def _min_positive(values: np.ndarray) -> float:
    """The smallest positive entry of ``values``, ``inf`` when there is none."""
    smallest = np.inf
    for k in range(values.size):
        if 0.0 < values[k] < smallest:
            smallest = values[k]
    return smallest


@njit(cache=True, nogil=True)
def _last_occurrences(
    indices: np.ndarray, errors: np.ndarray, capacity: int
) -> tuple[int, np.ndarray, np.ndarray]:
    """:meth:`PrioritizedReplayBuffer.update_priorities`'s checks and dedupe in one pass: the
    distinct ``indices`` in increasing order and, for each, the position of its last occurrence
    (what ``np.unique`` of the reversed array gives), after checking that ``errors`` are finite
    (:data:`_BAD_VALUE`) and ``indices`` lie in ``[0, capacity)`` (:data:`_BAD_INDEX`)."""
    empty = np.empty(0, dtype=np.int64)
    for k in range(errors.size):
        if not np.isfinite(errors[k]):
            return _BAD_VALUE, empty, empty
    for k in range(indices.size):
        if indices[k] < 0 or indices[k] >= capacity:
            return _BAD_INDEX, empty, empty
    # A stable sort keeps equal indices in their order: the last of a run is the last occurrence.
    order = np.argsort(indices, kind="mergesort")
    n = indices.size
    unique = np.empty(n, dtype=np.int64)
    last = np.empty(n, dtype=np.int64)
    count = 0
    for k in range(n):
        position = order[k]
        if k + 1 < n and indices[order[k + 1]] == indices[position]:
            continue
        unique[count] = indices[position]
        last[count] = position
        count += 1
    return 0, unique[:count], last[:count]


class SumTree:
    """Binary sum tree over ``capacity`` non-negative leaves, in float64.

    Node ``1`` is the root, node ``i`` has children ``2i`` and ``2i + 1`` and the leaves live at
    ``[size, 2 * size)`` where ``size`` is the smallest power of two ``>= capacity``; padding
    leaves stay zero. Updates and searches are numba-compiled loops over the items and their
    ``log2(size)`` ancestors (a NumPy pass per tree level cost more in call overhead, for a
    batch of 32, than the arithmetic); the smallest positive leaf (:attr:`min_leaf`) is kept
    up to date by the updates, so that reading it costs no pass over the leaves.

    Args:
        capacity: Number of leaves.
    """

    # The smallest positive leaf (inf: none) or NaN when an update may have raised it (the next
    # read scans the leaves). A class default, so that a tree pickled without it scans once.
    _min_leaf: float = float("nan")

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"SumTree capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.size = 1 << (self.capacity - 1).bit_length()
        # Number of levels below the root; a query descends exactly this many times.
        self.depth = self.size.bit_length() - 1
        self.nodes = np.zeros(2 * self.size, dtype=np.float64)
        self._min_leaf = float("inf")

    @property
    def total(self) -> float:
        """Sum of all leaves."""
        return float(self.nodes[1])

    @property
    def leaves(self) -> np.ndarray:
        """View of the ``capacity`` leaf values."""
        return self.nodes[self.size : self.size + self.capacity]

    @property
    def min_leaf(self) -> float:
        """The smallest positive leaf, ``inf`` when every leaf is zero."""
        if self._min_leaf != self._min_leaf:  # NaN: an update may have raised the minimum
            self._min_leaf = float(_min_positive(self.leaves))
        return self._min_leaf

    def get(self, indices: np.ndarray) -> np.ndarray:
        """Leaf values at ``indices``."""
        return self.nodes[self.size + np.asarray(indices, dtype=np.int64)]

    @staticmethod
    def _check_values(values: np.ndarray) -> None:
        if values.size and (not np.all(np.isfinite(values)) or values.min() < 0):
            raise ValueError("SumTree values must be finite and non-negative")

    def update(self, indices: np.ndarray, values: np.ndarray | float) -> None:
        """Set leaves ``indices`` to ``values`` and refresh their ancestors.

        Duplicate indices are allowed: the last occurrence wins. Parents are recomputed as
        ``left + right`` rather than shifted by a delta, so no rounding error accumulates.

        Args:
            indices: Leaf indices, any integer array.
            values: One value per index, or a scalar for all of them.
        """
        indices = np.ascontiguousarray(indices, dtype=np.int64).ravel()
        values = np.asarray(values, dtype=np.float64)
        if values.shape != indices.shape:  # a scalar, or a shape that broadcasts (or raises)
            values = np.broadcast_to(values, indices.shape)
        values = np.ascontiguousarray(values).ravel()
        code, self._min_leaf = _tree_set(
            self.nodes, self.size, self.capacity, indices, values, self._min_leaf
        )
        if code == _BAD_INDEX:
            raise IndexError(f"SumTree indices must lie in [0, {self.capacity})")
        if code == _BAD_VALUE:
            raise ValueError("SumTree values must be finite and non-negative")

    def rebuild(self, values: np.ndarray) -> None:
        """Replace all ``capacity`` leaves and recompute every internal node, level by level.

        Args:
            values: The new leaf values, shape ``(capacity,)``.
        """
        values = np.asarray(values, dtype=np.float64)
        if values.shape != (self.capacity,):
            raise ValueError(f"expected {self.capacity} values, got shape {values.shape}")
        self._check_values(values)
        self.nodes[:] = 0.0
        self.nodes[self.size : self.size + self.capacity] = values
        for level in reversed(range(self.depth)):
            start, end = 1 << level, 2 << level
            self.nodes[start:end] = (
                self.nodes[2 * start : 2 * end : 2] + self.nodes[2 * start + 1 : 2 * end : 2]
            )
        self._min_leaf = float("nan")

    def find_prefixsum(self, values: np.ndarray) -> np.ndarray:
        """For each query ``v``, the leaf ``i`` with ``sum(leaves[:i]) <= v < sum(leaves[:i + 1])``.

        Queries are clipped to ``>= 0``; a query ``>= total`` (e.g. rounding at the upper edge)
        returns the last non-zero leaf. A zero leaf is never returned, because the descent only
        goes right into a subtree with a positive sum.

        Args:
            values: Prefix-sum queries, any float array.

        Returns:
            Leaf indices (int64), same shape as ``values``.
        """
        if self.total <= 0.0:
            raise ValueError("cannot search an empty SumTree (total is 0)")
        queries = np.asarray(values, dtype=np.float64)
        out = np.empty(queries.shape, dtype=np.int64)
        _tree_descend(self.nodes, self.size, np.ascontiguousarray(queries).ravel(), out.ravel())
        return out

    def stratified(self, offsets: np.ndarray) -> np.ndarray:
        """Stratified search: ``[0, total)`` split into ``n = len(offsets)`` equal strata, and in
        stratum ``k`` the leaf at ``(k + offsets[k]) * total / n`` (:meth:`find_prefixsum`).

        Args:
            offsets: One position in ``[0, 1)`` per stratum, float64 ``(n,)``.

        Returns:
            Leaf indices (int64), ``(n,)``.
        """
        if self.total <= 0.0:
            raise ValueError("cannot search an empty SumTree (total is 0)")
        offsets = np.ascontiguousarray(offsets, dtype=np.float64)
        out = np.empty(offsets.shape, dtype=np.int64)
        _tree_descend(self.nodes, self.size, _stratified_queries(self.total, offsets), out)
        return out


def replay_memory_bytes(
    observation_space: spaces.Space,
    action_space: spaces.Space,
    buffer_size: int,
    n_envs: int,
    prioritized: bool = True,
) -> int:
    """Bytes the replay buffer will hold once full, from the spaces (nothing is allocated).

    As SB3's ``ReplayBuffer``/``DictReplayBuffer`` store them: ``buffer_size // n_envs`` rows of
    ``n_envs`` transitions, each with the observation and the next observation (every key of a
    ``Dict``), the action (one per ``Discrete``, in its dtype), and float32 reward, done and
    timeout. The prioritized buffer adds a float64 raw priority per transition and a float64 sum
    tree of ``2 * next_power_of_two(transitions)`` nodes.

    Args:
        observation_space: One slot's observation space (``Box`` or ``Dict`` of ``Box``).
        action_space: One slot's action space.
        buffer_size: Transitions over all envs, as in SB3.
        n_envs: VecEnv slots.
        prioritized: Add the prioritized buffer's bookkeeping.
    """
    boxes = (
        list(observation_space.spaces.values())
        if isinstance(observation_space, spaces.Dict)
        else [observation_space]
    )
    obs = sum(int(np.prod(b.shape)) * np.dtype(b.dtype).itemsize for b in boxes)
    action_dtype = np.dtype(action_space.dtype if action_space.dtype is not None else np.float32)
    if action_dtype == np.float64:  # SB3 stores float64 actions as float32
        action_dtype = np.dtype(np.float32)
    action_dim = (
        1 if isinstance(action_space, spaces.Discrete) else int(np.prod(action_space.shape))
    )
    per_transition = 2 * obs + action_dim * action_dtype.itemsize + 3 * 4
    transitions = max(buffer_size // n_envs, 1) * n_envs
    total = per_transition * transitions
    if prioritized:
        tree_leaves = 1 << (transitions - 1).bit_length()
        total += 8 * transitions + 8 * 2 * tree_leaves
    return int(total)


def importance_weights(
    probabilities: np.ndarray, min_probability: float, beta: float
) -> np.ndarray:
    """Normalised importance-sampling weights ``(N * P(i)) ** -beta / max_j w_j``.

    ``max_j w_j = (N * min_probability) ** -beta`` is the weight of the least likely stored
    transition, so every weight lies in ``(0, 1]`` and depends only on its own probability.
    ``N`` (the number of stored transitions) cancels: ``w_i = (min_probability / P(i)) ** beta``.

    Args:
        probabilities: ``P(i)`` of the sampled transitions.
        min_probability: The smallest ``P(j)`` over the stored transitions.
        beta: Importance-sampling exponent.

    Returns:
        float64 weights, same shape as ``probabilities``.
    """
    probabilities = np.asarray(probabilities, dtype=np.float64)
    return (min_probability / probabilities) ** beta


def check_n_step_returns(n_steps: int, gamma: float) -> None:
    """The n-step settings every buffer of this package takes (:func:`n_step_returns`).

    Raises:
        ValueError: for an ``n_steps`` that is no integer >= 1, or a ``gamma`` outside
            ``(0, 1]``.
    """
    if isinstance(n_steps, bool) or not isinstance(n_steps, int) or n_steps < 1:
        raise ValueError(f"n_steps must be an integer >= 1, got {n_steps!r}")
    if not 0.0 < gamma <= 1.0:
        raise ValueError(f"gamma must lie in (0, 1], got {gamma}")


def n_step_returns(
    rewards: np.ndarray,
    dones: np.ndarray,
    timeouts: np.ndarray,
    rows: np.ndarray,
    envs: np.ndarray,
    n_steps: int,
    gamma: float,
    newest_row: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """n-step returns of the transitions at ``(rows, envs)`` of SB3's ``[rows, n_envs]`` storage.

    The arithmetic of SB3's ``NStepReplayBuffer`` (Sutton and Barto 2018, §7.1), for given env
    columns: a transition's sequence runs over the next ``n_steps`` rows of its column and stops
    at the first episode end (done or timeout, inclusive) or at ``newest_row``, whose successor
    is not stored yet (on a full buffer, the next row is the oldest transition, of another
    episode). With ``k`` the sequence's length and ``last`` its final row:

    ``R = sum_{i<k} gamma**i * r_i``, target ``R + gamma**k * (1 - terminal) * max Q(s_last')``,
    where ``terminal`` is the final row's done unless it was a timeout (a timeout bootstraps).

    Args:
        rewards, dones, timeouts: The buffer's ``(rows, n_envs)`` arrays.
        rows, envs: The sampled transitions, ``(batch,)`` each.
        n_steps: Longest sequence (1 gives the one-step transition).
        gamma: Discount factor.
        newest_row: The row written last (``(pos - 1) % rows``).

    Returns:
        float32 returns ``R``, float32 discounts ``gamma**k``, the final rows ``last`` (their
        next observations are the bootstrap states) and float32 ``terminal``, each ``(batch,)``.
    """
    steps = np.arange(n_steps)
    seq_rows = (rows[:, None] + steps) % rewards.shape[0]  # (batch, n_steps)
    column = envs[:, None]
    ends = (dones[seq_rows, column] > 0) | (timeouts[seq_rows, column] > 0)
    ends |= seq_rows == newest_row
    first_end = np.where(ends.any(axis=1), ends.argmax(axis=1), n_steps - 1)
    inside = steps[None, :] <= first_end[:, None]
    returns = (rewards[seq_rows, column] * gamma**steps * inside).sum(axis=1)
    last = seq_rows[np.arange(len(rows)), first_end]
    terminal = dones[last, envs] * (1 - timeouts[last, envs])
    discounts = gamma ** (first_end + 1)
    return (
        returns.astype(np.float32),
        discounts.astype(np.float32),
        last,
        terminal.astype(np.float32),
    )


def n_step_returns_on_device(
    rewards: th.Tensor,
    dones: th.Tensor,
    timeouts: th.Tensor,
    rows: th.Tensor,
    envs: th.Tensor,
    n_steps: int,
    gamma: float,
    newest_row: int | th.Tensor,
) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
    """:func:`n_step_returns` on tensors: the same arithmetic (a sum in
    float64 of float32 rewards), the same results, where the tensors are."""
    steps = th.arange(n_steps, device=rows.device)
    seq_rows = (rows[:, None] + steps) % rewards.shape[0]  # (batch, n_steps)
    column = envs[:, None]
    ends = (dones[seq_rows, column] > 0) | (timeouts[seq_rows, column] > 0)
    ends |= seq_rows == newest_row
    # argmax gives the first largest entry: the first episode end.
    first = ends.to(th.uint8).argmax(dim=1)
    first_end = th.where(ends.any(dim=1), first, n_steps - 1)
    inside = steps[None, :] <= first_end[:, None]
    # gamma as a Python number: a tensor made from it would be a copy to the device.
    powers = gamma ** steps.to(th.float64)
    returns = (rewards[seq_rows, column] * powers * inside).sum(dim=1)
    last = seq_rows[th.arange(len(rows), device=rows.device), first_end]
    terminal = dones[last, envs] * (1 - timeouts[last, envs])
    discounts = gamma ** (first_end + 1).to(th.float64)
    return returns.float(), discounts.float(), last, terminal.float()


class PrioritizedReplayBufferSamples(NamedTuple):
    """``ReplayBufferSamples`` (same fields, same order) plus the PER fields.

    ``weights`` are the normalised importance-sampling weights, float32 ``(batch, 1)`` like
    ``rewards`` so they multiply a per-sample loss directly. ``indices`` are the flat buffer
    indices ``pos * n_envs + env`` to pass back to ``update_priorities``.
    """

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor
    discounts: th.Tensor | None
    weights: th.Tensor
    indices: np.ndarray
