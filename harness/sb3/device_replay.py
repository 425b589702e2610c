"""Prioritized replay on the model's device: the storage, the proportional sampler and the priority
updates as tensor operations, so that a training call on an accelerator never waits for the host.

:class:`~harness.sb3.buffers.PrioritizedReplayBuffer` keeps its transitions and its sum tree in
host memory: every gradient step copies a batch to the device, and the next sample needs the
step's TD errors back on the host (a synchronisation per step). Here everything a training call
touches stays where the network is:

* the transitions are tensors on ``device`` (an env step's transitions are copied there when
  they are added, during collection, where the policy already reads its actions back);
* sampling is Schaul et al.'s stratified proportional sampling, as the host buffer's: ``[0,
  total)`` split into ``batch_size`` equal segments, one uniform draw in each, the transition
  whose cumulative priority interval holds the draw (``searchsorted`` over the cumulative sum of
  the priorities, the same interval the sum tree's descent finds), with the IS weights normalised
  by the largest weight of any stored transition;
* the priorities of a step's samples are written from its TD errors on the device, before the
  next sample, as the host buffer's are;
* the uniform draws come from the buffer's own generator on the device, saved with the buffer,
  so a resumed run draws what the uninterrupted one drew;
* what a sample reads besides the transitions and the priorities (the number stored, the newest
  row, beta) is on the device too, and every write is in place, so that a sample can be part of
  a captured CUDA graph (:class:`harness.sb3.graphs.GraphedStep`): :meth:`sample_at` draws at
  given offsets, and :meth:`graph_key` changes when a graph of it must be captured again.

The host path stays the one for the CPU (a sum tree costs ``log N`` per sample; a cumulative sum
over every stored priority costs ``N``, which an accelerator does in parallel): see
:func:`prioritized_buffer_class`.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, ReplayBufferSamples
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import VecNormalize

from harness.sb3.buffers import (
    PrioritizedDictReplayBuffer,
    PrioritizedReplayBuffer,
    PrioritizedReplayBufferSamples,
    check_n_step_returns,
)

__all__ = [
    "DeviceDictReplayBuffer",
    "DevicePrioritizedDictReplayBuffer",
    "DevicePrioritizedReplayBuffer",
    "DeviceReplayBuffer",
    "DeviceStorage",
    "buffer_on_device",
    "n_step_returns_on_device",
    "prioritized_buffer_class",
    "uniform_buffer_class",
]

#: The transitions' tensors of every device buffer.
_STORAGE = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
#: The prioritized one's priorities (and its scratch), tensors too.
_PRIORITIES = ("_raw_priorities", "_leaves", "_max_priority", "_last_use")


def buffer_on_device(device: th.device | str) -> bool:
    """Whether a model on ``device`` keeps its replay buffer there: on CUDA (where a training
    call then never waits for the host), not on the CPU nor on Apple's MPS (no float64 there
    for the priorities' sums)."""
    return get_device(device).type == "cuda"


def prioritized_buffer_class(
    device: th.device | str, dict_observations: bool
) -> type[PrioritizedReplayBuffer]:
    """The prioritized buffer for a model on ``device``: the device buffer on CUDA, the host
    buffer (its sum tree) elsewhere: on the CPU, and on Apple's MPS, which has no float64 for the
    priorities' sums.

    Args:
        device: The model's device (``"auto"`` as SB3 resolves it).
        dict_observations: Whether the observations are a ``Dict``.
    """
    on_device = buffer_on_device(device)
    if dict_observations:
        return DevicePrioritizedDictReplayBuffer if on_device else PrioritizedDictReplayBuffer
    return DevicePrioritizedReplayBuffer if on_device else PrioritizedReplayBuffer


def uniform_buffer_class(
    device: th.device | str, dict_observations: bool
) -> type[DeviceReplayBuffer] | None:
    """The uniform buffer for a model on ``device``: the device buffer on CUDA (its sample can
    be part of a recorded gradient step, :mod:`harness.sb3.graphs`), ``None`` elsewhere (SB3
    chooses its own: ``ReplayBuffer``, ``DictReplayBuffer`` or ``NStepReplayBuffer``).

    Args:
        device: The model's device (``"auto"`` as SB3 resolves it).
        dict_observations: Whether the observations are a ``Dict``.
    """
    if not buffer_on_device(device):
        return None
    return DeviceDictReplayBuffer if dict_observations else DeviceReplayBuffer


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
    """:func:`harness.sb3.buffers.n_step_returns` on tensors: the same arithmetic (a sum in
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


def _torch_dtype(dtype: Any) -> th.dtype:
    """The torch dtype of a numpy dtype, as ``th.as_tensor`` maps it."""
    return th.from_numpy(np.zeros(0, dtype=dtype)).dtype


class DeviceStorage:
    """The transitions of an SB3 buffer as tensors on its ``device`` (mixed in before the
    buffer's class): what the device buffers share. An env step's transitions are copied there
    when added, a batch is gathered there, n-step targets are computed there
    (:func:`n_step_returns_on_device`), and the buffer's own numbers a sample reads (the stored
    count, the newest row) are kept there too, so that :meth:`sample_at` can be part of a
    recorded CUDA graph (:mod:`harness.sb3.graphs`). The uniform draws come from the buffer's
    own generator on the device, saved with it."""

    #: The attributes that hold tensors (moved with :attr:`device`, pickled as host tensors).
    _tensors: ClassVar[tuple[str, ...]] = _STORAGE
    #: Device copies of the buffer's own numbers (made again, not pickled).
    _scalars: ClassVar[tuple[str, ...]] = ("_cursor",)

    buffer_size: int
    n_envs: int
    pos: int
    full: bool
    n_steps: int
    gamma: float
    action_dim: int
    handle_timeout_termination: bool
    observations: Any
    next_observations: Any

    def _storage_to_device(self) -> None:
        """Turn the host storage SB3 allocated (untouched zeros: no memory is used) into tensors
        on the device, and make the generator (seeded from numpy's global state, which SB3
        seeds: a seeded run repeats)."""
        self.observations = self._empty_like(self.observations)
        self.next_observations = self._empty_like(self.next_observations)
        for name in ("actions", "rewards", "dones", "timeouts"):
            setattr(self, name, self._empty_like(getattr(self, name)))
        self._generator = th.Generator(device=self.device)
        self._generator.manual_seed(int(np.random.randint(2**62)))  # noqa: NPY002

    def _empty_like(self, array: np.ndarray | dict[str, np.ndarray]) -> Any:
        if isinstance(array, dict):
            return {key: self._empty_like(value) for key, value in array.items()}
        return th.zeros(array.shape, dtype=_torch_dtype(array.dtype), device=self.device)

    @property
    def n_transitions(self) -> int:
        """Number of stored transitions over all envs."""
        return self.size() * self.n_envs  # type: ignore[attr-defined]

    # ------------------------------------------------------------------ device and pickling
    @property
    def device(self) -> th.device:
        """Where the storage is; assigning moves it (SB3 assigns the model's device to a loaded
        buffer)."""
        return self._device

    @device.setter
    def device(self, value: th.device | str) -> None:
        new = get_device(value)
        old = getattr(self, "_device", None)
        self._device = new
        if not getattr(self, "_storage_ready", False) or old == new:
            return
        for name in self._tensors:
            setattr(self, name, _to(getattr(self, name), new))
        self._make_scalars()
        if old is None or old.type != new.type:
            # A generator's state is the device kind's own: continue from a seed drawn from it.
            seed = int(th.randint(2**62, (), generator=self._generator, device=old).item())
            self._generator = th.Generator(device=new)
            self._generator.manual_seed(seed)

    def __getstate__(self) -> dict[str, Any]:
        return self.host_state(self.stored_state())

    def stored_state(self) -> dict[str, Any]:
        """What pickling writes, the tensors still where they are: a checkpoint cuts the rows
        not yet filled there (``harness.training.checkpoints``) before :meth:`host_state`
        copies only the rest to the host."""
        state = self.__dict__.copy()
        for name in self._scalars:
            state.pop(name, None)
        state["_generator"] = (str(self._device), self._generator.get_state())
        return state

    def host_state(self, state: dict[str, Any]) -> dict[str, Any]:
        """``state`` (:meth:`stored_state`) with its tensors on the host, as they are pickled:
        a buffer saved from a GPU loads on a machine without one."""
        return {
            name: _to(value, th.device("cpu")) if name in self._tensors else value
            for name, value in state.items()
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        device, generator_state = state.pop("_generator")
        self.__dict__.update(state)
        self._device = th.device("cpu")  # where the tensors were pickled
        self._generator = th.Generator(device=device)
        self._generator.set_state(generator_state)
        # Back where they were saved from (SB3 then assigns the model's device).
        saved = th.device(device)
        for name in self._tensors:
            setattr(self, name, _to(getattr(self, name), saved))
        self._device = saved
        self._make_scalars()

    def _make_scalars(self) -> None:
        """Make the device's copies of the stored count and the newest row."""
        self._cursor = th.zeros(2, dtype=th.int64, device=self.device)
        self._cursor_at: tuple[int, bool] | None = None  # (pos, full) the cursor holds

    def _sync_cursor(self) -> None:
        """Bring the device's copy of the stored count and the newest row up to date (kernels,
        no wait), before a sample reads it: once per training call, not per env step."""
        at = (self.pos, self.full)
        if at != self._cursor_at:
            self._cursor[0].fill_(self.n_transitions)
            self._cursor[1].fill_((self.pos - 1) % self.buffer_size)
            self._cursor_at = at

    # ------------------------------------------------------------------ storage
    def add(
        self,
        obs: np.ndarray | dict[str, np.ndarray],
        next_obs: np.ndarray | dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Store one step of all ``n_envs`` envs on the device, as SB3's ``add`` (then
        :meth:`_added` with the row written)."""
        row = self.pos
        self._write(self.observations, obs, row)
        self._write(self.next_observations, next_obs, row)
        self.actions[row] = self._tensor(np.asarray(action).reshape(self.n_envs, self.action_dim))
        self.rewards[row] = self._tensor(np.asarray(reward, dtype=np.float32))
        self.dones[row] = self._tensor(np.asarray(done, dtype=np.float32))
        if self.handle_timeout_termination:
            timeouts = [info.get("TimeLimit.truncated", False) for info in infos]
            self.timeouts[row] = self._tensor(np.asarray(timeouts, dtype=np.float32))
        self.pos += 1
        if self.pos == self.buffer_size:
            self.full = True
            self.pos = 0
        self._added(row)

    def _added(self, row: int) -> None:
        """What a buffer keeps beside the transitions of a step stored at ``row`` (nothing
        here; the prioritized one gives them the max priority)."""

    def _tensor(self, array: np.ndarray) -> th.Tensor:
        # (A read-only array, a broadcast view say, is copied first: torch wants writable ones.)
        return th.as_tensor(np.require(array, requirements="W")).to(self.device)

    def _write(self, storage: Any, values: Any, row: int) -> None:
        if isinstance(storage, dict):
            for key, column in storage.items():
                self._write(column, values[key], row)
            return
        storage[row] = self._tensor(np.asarray(values).reshape(storage.shape[1:]))

    def sample_at(self, draws: th.Tensor) -> ReplayBufferSamples:
        """The batch at the uniform ``draws`` (``(batch,)`` in ``[0, 1)``, float64, as
        ``sample`` draws them from the buffer's generator), reading nothing from the host: the
        part of a sample a recorded step holds (each buffer says how draws become samples)."""
        raise NotImplementedError

    def _check_sampleable(self, env: VecNormalize | None) -> None:
        if env is not None:
            raise ValueError("the device replay buffer does not support VecNormalize")
        if self.n_transitions == 0:
            raise ValueError(f"cannot sample from an empty {type(self).__name__}")

    def _get_samples_at(  # type: ignore[override]
        self, batch_inds: Any, env_indices: Any, env: VecNormalize | None = None
    ) -> ReplayBufferSamples:
        """The transitions at ``(batch_inds, env_indices)`` (arrays or tensors), as
        :meth:`PrioritizedReplayBuffer._get_samples_at` gives them."""
        if env is not None:
            raise ValueError("the device replay buffer does not support VecNormalize")
        rows = th.as_tensor(batch_inds, device=self.device).long()
        self._sync_cursor()  # n-step returns read the newest row
        return self._samples_at(rows, th.as_tensor(env_indices, device=self.device).long())

    def draw(self, n: int, out: th.Tensor | None = None) -> th.Tensor:
        """The draws of one sample of ``n`` (:meth:`_uniform`), the cursor that sample reads
        brought up to date first (:meth:`_sync_cursor`): what ``sample`` and a recorded step
        (before each launch) call."""
        self._sync_cursor()
        return self._uniform(n) if out is None else self._uniform(n, out)

    def _uniform(self, n: int, out: th.Tensor | None = None) -> th.Tensor:
        """``n`` uniform draws in ``[0, 1)``, float64, from the buffer's generator (into
        ``out`` when given)."""
        if out is not None:
            return th.rand(n, generator=self._generator, out=out)
        return th.rand(n, generator=self._generator, device=self.device, dtype=th.float64)

    def graph_key(self) -> tuple[Any, ...]:
        """What a recorded sample (or priority update) holds fixed: where each tensor lives and
        the constants it reads (n-step's length and gamma, the envs per row). A graph recorded
        under another key is stale."""
        pointers = tuple(
            tensor.data_ptr()
            for name in (*self._tensors, *self._scalars)
            for tensor in _flat(getattr(self, name))
        )
        return (pointers, self.n_steps, self.gamma, self.n_envs)

    def _samples_at(self, rows: th.Tensor, columns: th.Tensor) -> ReplayBufferSamples:
        next_rows, dones, rewards, discounts = self._device_targets_at(rows, columns)
        return ReplayBufferSamples(
            self._gather(self.observations, rows, columns),
            self.actions[rows, columns],
            self._gather(self.next_observations, next_rows, columns),
            dones,
            rewards,
            discounts=discounts,
        )

    @staticmethod
    def _gather(storage: Any, rows: th.Tensor, columns: th.Tensor) -> Any:
        if isinstance(storage, dict):
            return {key: column[rows, columns] for key, column in storage.items()}
        return storage[rows, columns]

    def _device_targets_at(
        self, rows: th.Tensor, columns: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor | None]:
        """:meth:`PrioritizedReplayBuffer._targets_at` on the device."""
        if self.n_steps == 1:
            done = self.dones[rows, columns] * (1 - self.timeouts[rows, columns])
            return rows, done.reshape(-1, 1), self.rewards[rows, columns].reshape(-1, 1), None
        returns, discounts, last, terminal = n_step_returns_on_device(
            self.rewards,
            self.dones,
            self.timeouts,
            rows,
            columns,
            self.n_steps,
            self.gamma,
            newest_row=self._cursor[1],
        )
        return last, terminal.reshape(-1, 1), returns.reshape(-1, 1), discounts.reshape(-1, 1)


class DeviceReplayBuffer(DeviceStorage, ReplayBuffer):
    """SB3's ``ReplayBuffer`` on the device: uniform sampling with replacement over the stored
    transitions (each stored transition equally likely, as SB3 draws a row and an env), with
    n-step returns as SB3's ``NStepReplayBuffer`` computes them (``n_steps``, ``gamma``), the
    storage and the draws on ``device`` (:class:`DeviceStorage`). ``VecNormalize`` is not
    supported. ``device="cpu"`` gives the same buffer on CPU tensors (the tests).

    Raises:
        ValueError: for ``optimize_memory_usage``, an ``n_steps`` that is no integer >= 1 or a
            ``gamma`` outside ``(0, 1]``.
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        n_steps: int = 1,
        gamma: float = 0.99,
    ) -> None:
        if optimize_memory_usage:
            raise ValueError("the device replay buffer does not support optimize_memory_usage")
        check_n_step_returns(n_steps, gamma)
        self._storage_ready = False
        super().__init__(
            buffer_size,
            observation_space,
            action_space,
            device=device,
            n_envs=n_envs,
            handle_timeout_termination=handle_timeout_termination,
        )
        self.n_steps = n_steps
        self.gamma = float(gamma)
        self._storage_to_device()
        self._make_scalars()
        self._storage_ready = True

    def sample(  # type: ignore[override]
        self, batch_size: int, env: VecNormalize | None = None
    ) -> ReplayBufferSamples:
        """Draw ``batch_size`` stored transitions uniformly, with replacement, on the device."""
        self._check_sampleable(env)
        return self.sample_at(self.draw(batch_size))

    def sample_at(self, draws: th.Tensor) -> ReplayBufferSamples:
        """The batch at the uniform ``draws`` (``(batch,)`` in ``[0, 1)``, float64, as
        :meth:`sample` draws them): draw ``u`` takes the stored transition ``floor(u * N)`` of
        the ``N`` stored ones (flat index ``row * n_envs + env``), reading nothing from the
        host."""
        stored = self._cursor[0]
        flat = th.minimum((draws * stored).long(), stored - 1)
        return self._samples_at(flat // self.n_envs, flat % self.n_envs)


class DeviceDictReplayBuffer(DeviceReplayBuffer, DictReplayBuffer):
    """:class:`DeviceReplayBuffer` for ``Dict`` observations (one tensor per key)."""

    def _samples_at(  # type: ignore[override]
        self, rows: th.Tensor, columns: th.Tensor
    ) -> DictReplayBufferSamples:
        return DictReplayBufferSamples(*super()._samples_at(rows, columns))


class DevicePrioritizedReplayBuffer(DeviceStorage, PrioritizedReplayBuffer):
    """:class:`~harness.sb3.buffers.PrioritizedReplayBuffer` whose transitions, priorities and
    sampler are tensors on ``device`` (see the module docstring): the same arguments, the same
    sampling distribution and IS weights, the same priority updates; ``sample`` returns the flat
    ``indices`` as a tensor on the device and ``update_priorities`` takes them with the TD errors
    there, reading nothing back.

    What the host buffer checks per step and this one cannot without waiting for the device: a
    non-finite TD error is written as it is (its loss is not finite either, and
    :class:`~harness.sb3.dqn.DoubleDQN` stops the run at the end of the call, naming the update).
    ``VecNormalize`` (which normalises numpy arrays) is not supported.

    ``device="cpu"`` gives the same buffer on CPU tensors: what the tests compare with the host
    path, and not faster than it there.
    """

    _tensors: ClassVar[tuple[str, ...]] = (*_STORAGE, *_PRIORITIES)
    _scalars: ClassVar[tuple[str, ...]] = ("_cursor", "_beta_tensor")

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._storage_ready = False
        super().__init__(*args, **kwargs)
        self._storage_to_device()
        capacity = self.buffer_size * self.n_envs
        self._tree = None  # the sum tree is the host path's
        self._raw_priorities = th.zeros(capacity, dtype=th.float64, device=self.device)
        self._leaves = th.zeros(capacity, dtype=th.float64, device=self.device)
        self._max_priority = th.ones((), dtype=th.float64, device=self.device)
        self._make_scalars()
        # Scratch for update_priorities (the last position of each index in a batch).
        self._last_use = th.empty(capacity, dtype=th.int64, device=self.device)
        self._storage_ready = True

    def _make_scalars(self) -> None:
        """Make the device's copies of the stored count, the newest row and beta."""
        super()._make_scalars()
        self._beta_tensor = th.tensor(self._beta, dtype=th.float64, device=self.device)

    def graph_key(self) -> tuple[Any, ...]:
        """:meth:`DeviceStorage.graph_key` and the priorities' constants (alpha, eps)."""
        return (*super().graph_key(), self._alpha, self.eps)

    # ------------------------------------------------------------------ priorities
    @property
    def alpha(self) -> float:
        """Priority exponent; setting it recomputes every stored transition's priority."""
        return self._alpha

    @alpha.setter
    def alpha(self, value: float) -> None:
        self._alpha = self._check_exponent("alpha", value)
        raw = self._raw_priorities
        # Empty slots stay zero: 0 ** 0 == 1 would make them sampleable when alpha == 0.
        # In place: a captured graph reads the leaves where they are.
        self._leaves.copy_(th.where(raw > 0, raw**self._alpha, th.zeros_like(raw)))

    @PrioritizedReplayBuffer.beta.setter
    def beta(self, value: float) -> None:
        PrioritizedReplayBuffer.beta.fset(self, value)  # type: ignore[attr-defined]
        if getattr(self, "_storage_ready", False):  # the copy a sample reads
            self._beta_tensor.fill_(self._beta)

    @property
    def max_priority(self) -> float:  # type: ignore[override]
        """The largest raw priority so far (new transitions get it); reading it waits for the
        device, which only inspection does."""
        return float(self._max_priority)

    @max_priority.setter
    def max_priority(self, value: float) -> None:
        if getattr(self, "_storage_ready", False):
            self._max_priority.fill_(float(value))

    @property
    def priorities(self) -> np.ndarray:
        """Copy of the sampling priorities by flat index (read from the device)."""
        return self._leaves.cpu().numpy().copy()

    @property
    def raw_priorities(self) -> np.ndarray:
        """Copy of the raw priorities by flat index, 0 for empty slots (read from the device)."""
        return self._raw_priorities.cpu().numpy().copy()

    @property
    def min_probability(self) -> float:
        """Sampling probability of the lowest-priority stored transition (read from the
        device)."""
        if self.n_transitions == 0:
            raise ValueError("the buffer holds no transition")
        return float(self._min_probability(self._leaves.sum()))

    def _min_probability(self, total: th.Tensor) -> th.Tensor:
        # Every stored transition has a positive priority (raw >= eps > 0) and every empty slot
        # a zero one (as the host tree's smallest positive leaf): no count, no sync, no shape
        # that depends on the data.
        leaves = self._leaves
        return th.where(leaves > 0, leaves, th.inf).amin() / total

    def _set_raw_priorities(self, flat_indices: th.Tensor, raw: th.Tensor) -> None:  # type: ignore[override]
        self._raw_priorities[flat_indices] = raw
        self._leaves[flat_indices] = raw**self._alpha

    def update_priorities(self, indices: Any, td_errors: Any) -> None:
        """Set the priorities of the transitions at flat ``indices`` from their TD errors, on the
        device, reading nothing back.

        Args:
            indices: Flat indices, as ``sample`` returns them (a tensor, or an array).
                Duplicates are allowed; the last occurrence wins.
            td_errors: TD errors (sign ignored), one per index.
        """
        indices = th.as_tensor(indices, device=self.device).reshape(-1).long()
        errors = th.as_tensor(td_errors, device=self.device).detach().reshape(-1)
        if errors.shape != indices.shape:
            raise ValueError(f"got {indices.numel()} indices but {errors.numel()} TD errors")
        if indices.numel() == 0:
            return
        raw = errors.to(th.float64).abs() + self.eps
        # Last occurrence wins: every copy of an index writes its last copy's value (the same
        # value, so the order of the writes does not matter), as the host buffer's dedupe does.
        positions = th.arange(indices.numel(), device=self.device)
        last = self._last_use.fill_(-1).scatter_reduce_(0, indices, positions, reduce="amax")
        raw = raw[last[indices]]
        self._set_raw_priorities(indices, raw)
        self._max_priority.copy_(th.maximum(self._max_priority, raw.max()))

    # ------------------------------------------------------------------ storage
    def _added(self, row: int) -> None:
        """Give the transitions just stored at ``row`` the max priority."""
        flat = row * self.n_envs + th.arange(self.n_envs, device=self.device)
        # On wrap-around this overwrites the priorities of the replaced transitions too.
        self._set_raw_priorities(flat, self._max_priority.expand(self.n_envs))

    def sample(  # type: ignore[override]
        self, batch_size: int, env: VecNormalize | None = None
    ) -> PrioritizedReplayBufferSamples:
        """Draw a stratified prioritized batch on the device (see the module docstring).

        Returns:
            The batch, with IS ``weights`` and flat ``indices`` (a tensor on the device).
        """
        self._check_sampleable(env)
        return self.sample_at(self.draw(batch_size))

    def sample_at(self, offsets: th.Tensor) -> PrioritizedReplayBufferSamples:
        """The stratified batch at the draws ``offsets`` (``(batch,)`` in ``[0, 1)``, float64,
        as :meth:`sample` draws them): the work of a sample without the draws, reading nothing
        from the host that a captured graph would keep (no count, no shape from the data)."""
        batch_size = offsets.shape[0]
        leaves = self._leaves
        cumulative = th.cumsum(leaves, dim=0)
        total = cumulative[-1]
        queries = (th.arange(batch_size, device=self.device) + offsets) * (total / batch_size)
        # The slot whose interval [cumulative[i-1], cumulative[i]) holds the query: never an
        # empty (zero) slot; a query at the top edge (rounding) takes the last stored slot.
        flat = th.minimum(th.searchsorted(cumulative, queries, right=True), self._cursor[0] - 1)
        probabilities = leaves[flat] / total
        weights = (self._min_probability(total) / probabilities) ** self._beta_tensor
        rows, columns = flat // self.n_envs, flat % self.n_envs
        samples = self._samples_at(rows, columns)
        return PrioritizedReplayBufferSamples(
            *samples, weights=weights.float().reshape(-1, 1), indices=flat
        )

    def reset(self) -> None:
        """Empty the buffer, its priorities and the max-priority tracker."""
        self.pos = 0
        self.full = False
        self._raw_priorities.zero_()
        self._leaves.zero_()
        self._max_priority.fill_(1.0)


class DevicePrioritizedDictReplayBuffer(DevicePrioritizedReplayBuffer, PrioritizedDictReplayBuffer):
    """:class:`DevicePrioritizedReplayBuffer` for ``Dict`` observations (one tensor per key)."""

    def _samples_at(  # type: ignore[override]
        self, rows: th.Tensor, columns: th.Tensor
    ) -> DictReplayBufferSamples:
        samples = super()._samples_at(rows, columns)
        return DictReplayBufferSamples(*samples)


def _flat(value: Any) -> list[th.Tensor]:
    """The tensors of a storage (a tensor, or a dict of them)."""
    return list(value.values()) if isinstance(value, dict) else [value]


def _to(value: Any, device: th.device) -> Any:
    if isinstance(value, dict):
        return {key: _to(v, device) for key, v in value.items()}
    return value.to(device) if isinstance(value, th.Tensor) else value
