"""How a replay buffer (:mod:`harness.sb3.replay`) chooses the transitions of a sample: uniformly or
by priority (Schaul et al., 2015), on the host (numpy's global generator, which SB3 seeds; a sum
tree) or on the device (the buffer's own generator, saved with it; a cumulative sum).

A sampler addresses a transition by its flat index ``row * n_envs + column`` and draws exactly as
the buffers it replaces drew, so seeded runs repeat:

* :class:`UniformSampler`: SB3's draws, a row then a column per sample (``np.random.randint``);
* :class:`PrioritizedSampler`: one ``np.random.random_sample`` per stratum of ``[0, total)``,
  the leaf found by the sum tree's descent;
* :class:`DeviceUniformSampler`: ``floor(u * N)`` of one uniform draw ``u`` per sample;
* :class:`DevicePrioritizedSampler`: the stratified draws found by ``searchsorted`` over the
  cumulative priorities, the same intervals as the tree's.

Priorities are ``(|delta| + eps) ** alpha``; new transitions get the largest raw priority so far;
IS weights ``(p_min / p_i) ** beta`` are normalised by the least likely stored transition's, so a
transition's weight does not depend on the batch it was drawn in (``importance_weights``). On the
device, a sample reads nothing from the host that a recorded CUDA graph would keep: the stored
count, the newest row and beta are device tensors (the cursor), written in place.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th

from harness.sb3.kernels import (
    _BAD_INDEX,
    _BAD_VALUE,
    SumTree,
    _last_occurrences,
    importance_weights,
)

__all__ = [
    "DevicePrioritizedSampler",
    "DeviceUniformSampler",
    "PrioritizedSampler",
    "UniformSampler",
]


def _check_exponent(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value}")
    return value


class _PrioritySettings:
    """A prioritized sampler's ``eps`` and exponents ``alpha`` and ``beta``, checked when set;
    the sampler applies a new exponent in :meth:`_apply_alpha` (:meth:`_apply_beta`)."""

    eps: float
    _alpha: float
    _beta: float

    def _set_settings(self, alpha: float, beta: float, eps: float) -> None:
        if eps <= 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        self.eps = float(eps)
        self._alpha = _check_exponent("alpha", alpha)
        self._beta = _check_exponent("beta", beta)

    @property
    def alpha(self) -> float:
        return self._alpha

    @alpha.setter
    def alpha(self, value: float) -> None:
        self._alpha = _check_exponent("alpha", value)
        self._apply_alpha()

    @property
    def beta(self) -> float:
        return self._beta

    @beta.setter
    def beta(self, value: float) -> None:
        self._beta = _check_exponent("beta", value)
        self._apply_beta()

    def _apply_alpha(self) -> None:
        raise NotImplementedError

    def _apply_beta(self) -> None:
        """Nothing to apply: a draw reads ``beta`` where it is."""


class UniformSampler:
    """SB3's uniform draws on the host: a row among the stored ones, then a column."""

    prioritized = False
    on_device = False
    FIELDS: tuple[str, ...] = ()

    def __init__(self, capacity: int, device: th.device | None = None) -> None:
        del capacity, device

    def rows_and_columns(
        self, batch_size: int, stored_rows: int, n_envs: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """``batch_size`` rows in ``[0, stored_rows)`` and columns in ``[0, n_envs)``."""
        rows = np.random.randint(0, stored_rows, size=batch_size)  # noqa: NPY002
        columns = np.random.randint(0, high=n_envs, size=(len(rows),))  # noqa: NPY002
        return rows, columns

    def added(self, flat: Any) -> None:
        """Transitions were stored at ``flat``: nothing to keep."""

    def reset(self) -> None:
        """Nothing to forget."""


class PrioritizedSampler(_PrioritySettings):
    """Proportional prioritized sampling on the host, on a float64 :class:`SumTree`: stratified
    (``[0, total)`` split into ``batch_size`` equal segments, one uniform draw in each); raw
    priorities ``|delta| + eps`` are kept, so ``alpha`` can change (the tree is rebuilt).

    Args:
        capacity: Transitions (``rows * n_envs``).
        alpha: Priority exponent; 0 is uniform sampling, 1 fully proportional.
        beta: Importance-sampling exponent; 1 fully corrects the sampling bias.
        eps: Added to ``|delta|`` so that no transition gets a zero probability.
    """

    prioritized = True
    on_device = False
    FIELDS: tuple[str, ...] = ("eps", "_alpha", "_beta", "_tree", "_raw_priorities")
    FIELDS += ("max_priority",)

    def __init__(self, capacity: int, alpha: float, beta: float, eps: float) -> None:
        self._set_settings(alpha, beta, eps)
        self._tree = SumTree(capacity)
        # Raw priorities |delta| + eps (0 = empty slot), kept so that alpha can change later.
        self._raw_priorities = np.zeros(capacity, dtype=np.float64)
        self.max_priority = 1.0

    def _apply_alpha(self) -> None:
        stored = self._raw_priorities > 0.0
        # Mask empty slots explicitly: 0 ** 0 == 1 would make them sampleable when alpha == 0.
        leaves = np.zeros_like(self._raw_priorities)
        leaves[stored] = self._raw_priorities[stored] ** self._alpha
        self._tree.rebuild(leaves)

    @property
    def priorities(self) -> np.ndarray:
        return self._tree.leaves.copy()

    @property
    def raw_priorities(self) -> np.ndarray:
        return self._raw_priorities.copy()

    @property
    def min_probability(self) -> float:
        """Sampling probability of the lowest-priority stored transition (empty slots, zero
        leaves, skipped: the tree keeps the smallest positive leaf)."""
        smallest = self._tree.min_leaf
        if smallest == np.inf:
            raise ValueError("the buffer holds no transition")
        return smallest / self._tree.total

    def _set_raw(self, flat: np.ndarray, raw: np.ndarray) -> None:
        self._raw_priorities[flat] = raw
        self._tree.update(flat, raw**self._alpha)

    def added(self, flat: np.ndarray) -> None:
        """Give the transitions just stored at ``flat`` the max priority (on wrap-around this
        overwrites the replaced transitions' priorities too)."""
        self._set_raw(flat, np.full(flat.shape[0], self.max_priority))

    def update(self, indices: np.ndarray, td_errors: np.ndarray | th.Tensor) -> None:
        """Set the priorities at flat ``indices`` from their TD errors (sign ignored; the last
        occurrence of a duplicate wins)."""
        if isinstance(td_errors, th.Tensor):
            td_errors = td_errors.detach().cpu().numpy()
        indices = np.ascontiguousarray(indices, dtype=np.int64).ravel()
        errors = np.ascontiguousarray(td_errors, dtype=np.float64).ravel()
        if errors.shape != indices.shape:
            raise ValueError(f"got {indices.size} indices but {errors.size} TD errors")
        # The checks, then the dedupe (last wins, so that the raw array and the tree agree), in
        # one compiled pass: increasing distinct indices and their last positions.
        code, unique, last = _last_occurrences(indices, errors, self._raw_priorities.size)
        if code == _BAD_VALUE:
            raise ValueError("TD errors must be finite")
        if code == _BAD_INDEX:
            raise IndexError(f"flat indices must lie in [0, {self._raw_priorities.size})")
        if indices.size == 0:
            return
        raw = np.abs(errors[last]) + self.eps
        self._set_raw(unique, raw)
        self.max_priority = max(self.max_priority, float(raw.max()))

    def draw(self, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        """A stratified batch: flat indices and their IS weights (float64)."""
        total = self._tree.total
        # Global np.random, as SB3's own buffers: seeded by set_random_seed.
        offsets = np.random.random_sample(batch_size)  # noqa: NPY002
        # Only stored slots have non-zero leaves, and the search never returns a zero leaf.
        flat = self._tree.stratified(offsets)
        probabilities = self._tree.get(flat) / total
        return flat, importance_weights(probabilities, self.min_probability, self._beta)

    def reset(self) -> None:
        self._raw_priorities[:] = 0.0
        self._tree.rebuild(self._raw_priorities)
        self.max_priority = 1.0


class DeviceUniformSampler:
    """Uniform sampling with replacement on the device: draw ``u`` takes the stored transition
    ``floor(u * N)`` of the ``N`` stored ones, the draws from the sampler's own generator
    (seeded from numpy's global state, which SB3 seeds)."""

    prioritized = False
    on_device = True
    #: The tensors (moved with the device, pickled as host tensors) and the rest of the state.
    TENSORS: tuple[str, ...] = ()
    FIELDS: tuple[str, ...] = ()

    def __init__(self, capacity: int, device: th.device) -> None:
        del capacity
        self._generator = th.Generator(device=device)
        self._generator.manual_seed(int(np.random.randint(2**62)))  # noqa: NPY002
        self._make_scalars(device)

    def _make_scalars(self, device: th.device) -> None:
        """The device copies of the stored count and the newest row (the cursor)."""
        self._cursor = th.zeros(2, dtype=th.int64, device=device)
        self._cursor_at: tuple[int, bool] | None = None  # (pos, full) the cursor holds

    def sync_cursor(self, pos: int, full: bool, n_transitions: int, rows: int) -> None:
        """Bring the cursor up to date (kernels, no wait), once per training call."""
        if (pos, full) != self._cursor_at:
            self._cursor[0].fill_(n_transitions)
            self._cursor[1].fill_((pos - 1) % rows)
            self._cursor_at = (pos, full)

    @property
    def newest_row(self) -> th.Tensor:
        return self._cursor[1]

    def uniform(self, n: int, out: th.Tensor | None = None) -> th.Tensor:
        """``n`` uniform draws in ``[0, 1)``, float64, from the generator (into ``out``)."""
        if out is not None:
            return th.rand(n, generator=self._generator, out=out)
        device = self._cursor.device
        return th.rand(n, generator=self._generator, device=device, dtype=th.float64)

    def flat_at(self, draws: th.Tensor) -> tuple[th.Tensor, None]:
        """The flat indices at the uniform ``draws`` (no weights)."""
        stored = self._cursor[0]
        return th.minimum((draws * stored).long(), stored - 1), None

    def tensors(self) -> list[th.Tensor]:
        return [self._cursor, *(getattr(self, name) for name in self.TENSORS)]

    def to(self, old: th.device, new: th.device) -> None:
        """Move the tensors to ``new``; a generator of another device kind continues from a
        seed drawn from the old one."""
        for name in self.TENSORS:
            setattr(self, name, getattr(self, name).to(new))
        if old.type != new.type:
            seed = int(th.randint(2**62, (), generator=self._generator, device=old).item())
            self._generator = th.Generator(device=new)
            self._generator.manual_seed(seed)
        self._make_scalars(new)

    def state(self) -> dict[str, Any]:
        """What pickling keeps (the cursor is made again)."""
        names = (*self.TENSORS, *self.FIELDS)
        state = {name: getattr(self, name) for name in names}
        device = str(self._cursor.device)
        state["_generator"] = (device, self._generator.get_state())
        return state

    def restore(self, state: dict[str, Any], device: th.device) -> None:
        """The inverse of :meth:`state` (its tensors already on ``device``)."""
        saved, generator_state = state.pop("_generator")
        self._generator = th.Generator(device=saved)
        self._generator.set_state(generator_state)
        for name in (*self.TENSORS, *self.FIELDS):
            setattr(self, name, state.pop(name))
        self._make_scalars(device)

    def added(self, flat: Any) -> None:
        """Transitions were stored at ``flat``: nothing to keep."""

    def reset(self) -> None:
        """Nothing to forget."""


class DevicePrioritizedSampler(DeviceUniformSampler, _PrioritySettings):
    """:class:`PrioritizedSampler` on the device (the same distribution, IS weights and
    updates; see the module docstring): ``update`` takes the flat indices and TD errors where
    they are and reads nothing back, so a non-finite TD error is written as it is (its loss is
    not finite either, and ``DoubleDQN`` stops the run at the end of the call)."""

    prioritized = True
    TENSORS: tuple[str, ...] = ("_raw_priorities", "_leaves", "_max_priority", "_last_use")
    FIELDS: tuple[str, ...] = ("eps", "_alpha", "_beta")

    def __init__(
        self, capacity: int, device: th.device, alpha: float, beta: float, eps: float
    ) -> None:
        self._set_settings(alpha, beta, eps)
        self._raw_priorities = th.zeros(capacity, dtype=th.float64, device=device)
        self._leaves = th.zeros(capacity, dtype=th.float64, device=device)
        self._max_priority = th.ones((), dtype=th.float64, device=device)
        # Scratch for update (the last position of each index in a batch).
        self._last_use = th.empty(capacity, dtype=th.int64, device=device)
        super().__init__(capacity, device)

    def _make_scalars(self, device: th.device) -> None:
        super()._make_scalars(device)
        self._beta_tensor = th.tensor(self._beta, dtype=th.float64, device=device)

    def tensors(self) -> list[th.Tensor]:
        return [*super().tensors(), self._beta_tensor]

    def _apply_alpha(self) -> None:
        raw = self._raw_priorities
        # Empty slots stay zero: 0 ** 0 == 1 would make them sampleable when alpha == 0.
        # In place: a captured graph reads the leaves where they are.
        self._leaves.copy_(th.where(raw > 0, raw**self._alpha, th.zeros_like(raw)))

    def _apply_beta(self) -> None:
        self._beta_tensor.fill_(self._beta)  # the copy a sample reads

    @property
    def max_priority(self) -> float:
        """The largest raw priority so far (reading it waits for the device)."""
        return float(self._max_priority)

    @max_priority.setter
    def max_priority(self, value: float) -> None:
        self._max_priority.fill_(float(value))

    @property
    def priorities(self) -> np.ndarray:
        return self._leaves.cpu().numpy().copy()

    @property
    def raw_priorities(self) -> np.ndarray:
        return self._raw_priorities.cpu().numpy().copy()

    def min_probability_of(self, total: th.Tensor) -> th.Tensor:
        # Every stored transition has a positive priority (raw >= eps > 0) and every empty slot
        # a zero one: no count, no sync, no shape that depends on the data.
        leaves = self._leaves
        return th.where(leaves > 0, leaves, th.inf).amin() / total

    @property
    def min_probability(self) -> float:
        return float(self.min_probability_of(self._leaves.sum()))

    def _set_raw(self, flat: th.Tensor, raw: th.Tensor) -> None:
        self._raw_priorities[flat] = raw
        self._leaves[flat] = raw**self._alpha

    def added(self, flat: th.Tensor) -> None:
        """Give the transitions just stored at ``flat`` the max priority."""
        self._set_raw(flat, self._max_priority.expand(flat.shape[0]))

    def update(self, indices: Any, td_errors: Any) -> None:
        """Set the priorities at flat ``indices`` from their TD errors, on the device, reading
        nothing back (the last occurrence of a duplicate wins)."""
        device = self._leaves.device
        indices = th.as_tensor(indices, device=device).reshape(-1).long()
        errors = th.as_tensor(td_errors, device=device).detach().reshape(-1)
        if errors.shape != indices.shape:
            raise ValueError(f"got {indices.numel()} indices but {errors.numel()} TD errors")
        if indices.numel() == 0:
            return
        raw = errors.to(th.float64).abs() + self.eps
        # Every copy of an index writes its last copy's value (the order of the writes does
        # not matter), as the host sampler's dedupe does.
        positions = th.arange(indices.numel(), device=device)
        last = self._last_use.fill_(-1).scatter_reduce_(0, indices, positions, reduce="amax")
        raw = raw[last[indices]]
        self._set_raw(indices, raw)
        self._max_priority.copy_(th.maximum(self._max_priority, raw.max()))

    def flat_at(self, draws: th.Tensor) -> tuple[th.Tensor, th.Tensor]:  # type: ignore[override]
        """The stratified batch at the draws (``(batch,)`` in ``[0, 1)``): flat indices and IS
        weights ``(batch, 1)`` float32, reading nothing from the host."""
        batch_size = draws.shape[0]
        leaves = self._leaves
        cumulative = th.cumsum(leaves, dim=0)
        total = cumulative[-1]
        queries = (th.arange(batch_size, device=leaves.device) + draws) * (total / batch_size)
        # The slot whose interval [cumulative[i-1], cumulative[i]) holds the query: never an
        # empty (zero) slot; a query at the top edge (rounding) takes the last stored slot.
        flat = th.minimum(th.searchsorted(cumulative, queries, right=True), self._cursor[0] - 1)
        probabilities = leaves[flat] / total
        weights = (self.min_probability_of(total) / probabilities) ** self._beta_tensor
        return flat, weights.float().reshape(-1, 1)

    def reset(self) -> None:
        self._raw_priorities.zero_()
        self._leaves.zero_()
        self._max_priority.fill_(1.0)
