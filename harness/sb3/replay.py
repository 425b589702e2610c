"""Replay for :class:`~harness.sb3.dqn.DoubleDQN`, composed: a storage (:mod:`harness.sb3.storage`:
the host's numpy arrays or the device's tensors, array or ``Dict`` observations, optionally one
transition per decision, :mod:`harness.sb3.decisions`) × a sampler (:mod:`harness.sb3.samplers`:
uniform or prioritized, on the storage's placement), held by one SB3 buffer class, :class:`Replay`.

:class:`PrioritizedReplayBuffer` is :class:`Replay` with the prioritized sampler by default (the
name saved models hold); :func:`replay_for` gives ``harness run``'s choice for a device. SB3
ships no prioritized buffer (DLR-RM/stable-baselines3#1242) and none that handles several envs;
these keep SB3's ``[buffer_size // n_envs, n_envs]`` layout, any ``n_envs``, and SB3's n-step
returns (``n_steps``, ``gamma``: the arguments SB3 asks a custom buffer to take).

On the device (``placement="device"``, :func:`replay_for` on CUDA) a training call never waits
for the host: transitions are copied there as they are added, a sample and its priority update
are tensor operations there, and what a sample reads (the stored count, the newest row, beta)
is on the device too, so that a sample can be part of a recorded CUDA graph
(:mod:`harness.sb3.graphs`: :meth:`Replay.sample_at` draws at given uniform numbers,
:meth:`Replay.graph_key` changes when a graph of it must be recorded again). The host keeps its
sum tree (``log N`` a sample; a cumulative sum costs ``N``, which an accelerator does in
parallel). ``device="cpu"`` with ``placement="device"`` runs the device path on CPU tensors (the
tests compare the two).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import BaseBuffer, ReplayBuffer
from stable_baselines3.common.type_aliases import DictReplayBufferSamples, ReplayBufferSamples
from stable_baselines3.common.utils import get_device
from stable_baselines3.common.vec_env import VecNormalize

from harness.sb3.decisions import Decisions, LabelledSamples
from harness.sb3.kernels import PrioritizedReplayBufferSamples, check_n_step_returns
from harness.sb3.samplers import (
    DevicePrioritizedSampler,
    DeviceUniformSampler,
    PrioritizedSampler,
    UniformSampler,
)
from harness.sb3.storage import DeviceStorage, HostStorage

__all__ = [
    "PrioritizedReplayBuffer",
    "Replay",
    "buffer_on_device",
    "graphable",
    "priorities_on_device",
    "prioritized",
    "replay_for",
]

#: The parts a buffer holds (pickled flat: their fields beside the buffer's own).
_PARTS = ("storage", "sampler", "decisions")


def buffer_on_device(device: th.device | str) -> bool:
    """Whether a model on ``device`` keeps its replay buffer there: on CUDA, not on the CPU nor
    on Apple's MPS (no float64 there for the priorities' sums)."""
    return get_device(device).type == "cuda"


def replay_for(
    device: th.device | str,
    prioritized: bool,
    per_decision: bool = False,
) -> tuple[type[Replay] | None, dict[str, Any]]:
    """``harness run``'s buffer for a model on ``device``: the class and the keyword arguments
    that select its sampler and placement (the caller adds ``alpha``, ``n_steps``, ...). On the
    device on CUDA (per-decision replay stays on the host); ``(None, {})`` for uniform replay on
    the host, where SB3 chooses its own buffer (``ReplayBuffer``, ``DictReplayBuffer`` or
    ``NStepReplayBuffer``)."""
    placement = "device" if buffer_on_device(device) and not per_decision else "host"
    if per_decision:
        sampler = "prioritized" if prioritized else "uniform"
        return Replay, {"sampler": sampler, "per_decision": True}
    if prioritized:
        return PrioritizedReplayBuffer, {"placement": placement}
    if placement == "device":
        return Replay, {"placement": placement}
    return None, {}


def prioritized(buffer: Any) -> bool:
    """Whether ``buffer`` samples by priority (it has ``alpha``, ``beta``, priorities)."""
    return isinstance(buffer, Replay) and buffer.sampler.prioritized


def priorities_on_device(buffer: Any) -> bool:
    """Whether ``buffer``'s priorities are updated where its samples are (no host read)."""
    return prioritized(buffer) and buffer.sampler.on_device


def graphable(buffer: Any) -> bool:
    """Whether ``buffer`` samples on the device from given draws (``draw``, ``sample_at``,
    ``graph_key``): a sample a recorded CUDA graph can hold."""
    return isinstance(buffer, Replay) and buffer.sampler.on_device


class Replay(ReplayBuffer):
    """A replay buffer composed of a storage and a sampler (module docstring).

    Args:
        buffer_size: Most transitions, over all envs (as in SB3).
        observation_space: The observation space (a ``Dict`` is stored one array per key).
        action_space: The action space.
        device: Where the samples go (and, ``placement="device"``, the transitions).
        n_envs: VecEnv slots.
        optimize_memory_usage: Must be ``False``.
        handle_timeout_termination: As in SB3: a timeout is not a terminal state.
        sampler: ``"uniform"`` or ``"prioritized"`` (proportional, ``alpha``, ``beta``, ``eps``).
        placement: ``"host"`` (numpy) or ``"device"`` (tensors on ``device``).
        n_steps: Length of the n-step returns (1: one-step transitions, ``discounts`` None).
        gamma: Discount factor of the n-step or per-decision returns (the algorithm's).
        alpha: Priority exponent; 0 is uniform sampling, 1 fully proportional.
        beta: Importance-sampling exponent; 1 fully corrects the sampling bias.
        eps: Added to ``|delta|`` so that no transition gets a zero probability.
        per_decision: One transition per decision (:mod:`harness.sb3.decisions`; a ``Dict``
            observation with an action mask, ``n_steps`` 1, on the host).
        labels: With ``per_decision``, keep each decision's expert label, sampled as
            ``experts``.

    Raises:
        ValueError: for ``optimize_memory_usage``, an unknown sampler or placement, bad n-step
            settings, or per-decision replay that cannot be (above).
    """

    # Class defaults: a buffer pickled without n-step settings loads as one-step.
    n_steps: int = 1
    gamma: float = 0.99

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        sampler: str = "uniform",
        placement: str = "host",
        n_steps: int = 1,
        gamma: float = 0.99,
        alpha: float = 0.6,
        beta: float = 0.4,
        eps: float = 1e-6,
        per_decision: bool = False,
        labels: bool = False,
    ) -> None:
        if optimize_memory_usage:
            raise ValueError(f"{type(self).__name__} does not support optimize_memory_usage=True")
        if sampler not in ("uniform", "prioritized") or placement not in ("host", "device"):
            raise ValueError(f"unknown sampler {sampler!r} or placement {placement!r}")
        if per_decision and n_steps != 1:
            raise ValueError(
                f"a per-decision buffer stores one transition per decision; n_steps must be 1, "
                f"got {n_steps!r}"
            )
        check_n_step_returns(n_steps, gamma)
        columns = 1 if per_decision else n_envs  # per decision: one flat column
        BaseBuffer.__init__(
            self, buffer_size, observation_space, action_space, device=device, n_envs=columns
        )
        self.buffer_size = max(buffer_size // columns, 1)
        self.optimize_memory_usage = False
        self.handle_timeout_termination = handle_timeout_termination
        self.n_steps, self.gamma = n_steps, float(gamma)
        capacity = self.buffer_size * self.n_envs
        self.decisions = None
        if per_decision:
            if placement == "device":
                raise ValueError("a per-decision buffer keeps its transitions on the host")
            self.decisions = Decisions(
                n_envs, observation_space, action_space, self.action_dim, gamma, labels
            )
        if placement == "device":
            self.storage: HostStorage | DeviceStorage = DeviceStorage(
                self.buffer_size, self.n_envs, observation_space, action_space, self.device
            )
            self.sampler: Any = (
                DevicePrioritizedSampler(capacity, self.device, alpha, beta, eps)
                if sampler == "prioritized"
                else DeviceUniformSampler(capacity, self.device)
            )
        else:
            self.storage = HostStorage(
                self.buffer_size, self.n_envs, observation_space, action_space, per_decision
            )
            self.sampler = (
                PrioritizedSampler(capacity, alpha, beta, eps)
                if sampler == "prioritized"
                else UniformSampler(capacity)
            )

    # ------------------------------------------------------------------ what tests and logs read
    @property
    def n_transitions(self) -> int:
        """Number of stored transitions over all envs (``N`` in the IS weights)."""
        return self.size() * self.n_envs

    def __getattr__(self, name: str) -> Any:
        # The sampler's and the storage's public fields read through (``alpha``, ``beta``,
        # ``priorities``, ``rewards``, ``step_discounts``, ...); only reached for names the
        # buffer lacks (a missing part while unpickling is just missing).
        if name.startswith("__") or name in _PARTS:
            raise AttributeError(name)
        for part in _PARTS:
            holder = self.__dict__.get(part)
            if holder is not None and hasattr(holder, name):
                return getattr(holder, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __setattr__(self, name: str, value: Any) -> None:
        # alpha, beta and max_priority are the sampler's (a schedule writes beta every step).
        if name in ("alpha", "beta", "max_priority") and "sampler" in self.__dict__:
            if not self.sampler.prioritized:
                raise AttributeError(f"a uniform buffer has no {name}")
            setattr(self.sampler, name, value)
            return
        if name == "device" and "storage" in self.__dict__:
            self._move(get_device(value))
            return
        super().__setattr__(name, value)

    @property
    def slots(self) -> int:
        """VecEnv slots (``n_envs`` as SB3 passed it; per decision, one column holds them)."""
        return self.decisions.slots if self.decisions is not None else self.n_envs

    @property
    def labels(self) -> bool:
        return self.decisions is not None and self.decisions.labels

    # ------------------------------------------------------------------ storing
    def add(
        self,
        obs: Any,
        next_obs: Any,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Store one step of all envs as SB3 does (per decision: the transitions it completes),
        each at the max priority with a prioritized sampler."""
        if self.decisions is not None:
            n_actions = int(self.action_space.n)  # type: ignore[attr-defined]
            self.decisions.step(obs, next_obs, action, reward, done, infos, n_actions, self._add)
            return
        self._add(obs, next_obs, action, reward, done, infos)

    def _add(
        self,
        obs: Any,
        next_obs: Any,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
        discount: float | None = None,
        label: int = -1,
    ) -> None:
        row = self.pos
        timeouts = None
        if self.handle_timeout_termination:
            truncated = [info.get("TimeLimit.truncated", False) for info in infos]
            timeouts = np.asarray(truncated, dtype=np.float32)
        self.storage.write(row, obs, next_obs, action, reward, done, timeouts)
        if discount is not None:  # per decision: its gamma ** tau and label
            self.storage.step_discounts[row, 0] = discount  # type: ignore[index]
            self.storage.expert_actions[row, 0] = label  # type: ignore[index]
        self.pos += 1
        if self.pos == self.buffer_size:
            self.full = True
            self.pos = 0
        if self.sampler.prioritized:
            if self.sampler.on_device:
                flat: Any = row * self.n_envs + th.arange(self.n_envs, device=self.device)
            else:
                flat = row * self.n_envs + np.arange(self.n_envs, dtype=np.int64)
            self.sampler.added(flat)

    def update_priorities(self, indices: Any, td_errors: Any) -> None:
        """Set the priorities of the transitions at flat ``indices`` (as sampled) from their TD
        errors (sign ignored; duplicates allowed, the last wins); on the device where they are,
        reading nothing back."""
        if not self.sampler.prioritized:
            raise AttributeError("a uniform buffer has no priorities")
        self.sampler.update(indices, td_errors)

    def reset(self) -> None:
        """Empty the buffer, its priorities and its pending decisions."""
        self.pos, self.full = 0, False
        self.storage.clear()
        self.sampler.reset()
        if self.decisions is not None:
            self.decisions.reset()

    # ------------------------------------------------------------------ sampling
    def sample(self, batch_size: int, env: VecNormalize | None = None) -> Any:  # type: ignore[override]
        """A batch of ``batch_size`` transitions; a prioritized one carries IS ``weights`` and
        flat ``indices`` (``row * n_envs + env``; a device tensor on the device), a per-decision
        one its ``discounts`` (and ``experts`` with labels)."""
        if self.n_transitions == 0:
            raise ValueError(f"cannot sample from an empty {type(self).__name__}")
        if self.sampler.on_device:
            if env is not None:
                raise ValueError("the device replay buffer does not support VecNormalize")
            return self.sample_at(self.draw(batch_size))
        if not self.sampler.prioritized:
            upper = self.buffer_size if self.full else self.pos
            rows, columns = self.sampler.rows_and_columns(batch_size, upper, self.n_envs)
            return self._labelled(self._samples(rows, columns, env), rows, columns)
        flat, weights = self.sampler.draw(batch_size)
        rows, columns = np.divmod(flat, self.n_envs)
        samples = PrioritizedReplayBufferSamples(
            *self._samples(rows, columns, env),
            weights=self._batch_tensor(weights.astype(np.float32).reshape(-1, 1)),
            indices=flat,
        )
        return self._labelled(samples, rows, columns)

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> Any:  # type: ignore[override]
        """SB3's ``_get_samples`` on the host: the rows given, a column drawn for each."""
        columns = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))  # noqa: NPY002
        return self._labelled(self._samples(batch_inds, columns, env), batch_inds, columns)

    def _samples(self, rows: np.ndarray, columns: np.ndarray, env: VecNormalize | None) -> Any:
        """The host storage's transitions at ``(rows, columns)`` as tensors."""
        obs, actions, next_obs, dones, rewards, discounts = self.storage.gather(  # type: ignore[call-arg]
            rows,
            columns,
            self.n_steps,
            self.gamma,
            (self.pos - 1) % self.buffer_size,
            lambda o: self._normalize_obs(o, env),
            lambda r: self._normalize_reward(r, env),
        )
        return self._as_samples(
            _map(self._batch_tensor, obs),
            self._batch_tensor(actions),
            _map(self._batch_tensor, next_obs),
            self._batch_tensor(dones),
            self._batch_tensor(rewards),
            None if discounts is None else self._batch_tensor(discounts),
        )

    def _as_samples(self, *fields: Any) -> Any:
        if isinstance(fields[0], dict):
            return DictReplayBufferSamples(*fields)
        return ReplayBufferSamples(*fields)

    def _labelled(self, samples: Any, rows: np.ndarray, columns: np.ndarray) -> Any:
        if not self.labels:
            return samples
        return LabelledSamples(samples, self.to_torch(self.storage.experts(rows, columns)))  # type: ignore[union-attr]

    def _batch_tensor(self, array: np.ndarray) -> th.Tensor:
        """A sampled array (made afresh, never a view of the storage) as a tensor: shared on the
        CPU rather than copied as SB3's ``to_torch`` copies it."""
        if self.device.type == "cpu":
            return th.from_numpy(array)
        return self.to_torch(array)

    # ------------------------------------------------------------------ on the device
    def _sync_cursor(self) -> None:
        self.sampler.sync_cursor(self.pos, self.full, self.n_transitions, self.buffer_size)

    def draw(self, n: int, out: th.Tensor | None = None) -> th.Tensor:
        """The uniform draws of one sample of ``n`` (into ``out``), the cursor that sample reads
        brought up to date first: what ``sample`` and a recorded step (before each launch)
        call."""
        self._sync_cursor()
        return self._uniform(n) if out is None else self._uniform(n, out)

    def _uniform(self, n: int, out: th.Tensor | None = None) -> th.Tensor:
        """``n`` uniform draws in ``[0, 1)``, float64, from the sampler's generator."""
        return self.sampler.uniform(n, out)

    def sample_at(self, draws: th.Tensor) -> Any:
        """The batch at the uniform ``draws`` (``(batch,)`` in ``[0, 1)``, float64), reading
        nothing from the host: the part of a sample a recorded step holds."""
        flat, weights = self.sampler.flat_at(draws)
        rows, columns = flat // self.n_envs, flat % self.n_envs
        fields = self._gather_on_device(rows, columns)
        samples = self._as_samples(*fields)
        if weights is None:
            return samples
        return PrioritizedReplayBufferSamples(*samples, weights=weights, indices=flat)

    def _get_samples_at(self, rows: Any, columns: Any, env: VecNormalize | None = None) -> Any:
        """The transitions at given ``(rows, columns)`` (without weights)."""
        if not self.sampler.on_device:
            return self._samples(np.asarray(rows), np.asarray(columns), env)
        if env is not None:
            raise ValueError("the device replay buffer does not support VecNormalize")
        self._sync_cursor()  # n-step returns read the newest row
        rows = th.as_tensor(rows, device=self.device).long()
        columns = th.as_tensor(columns, device=self.device).long()
        fields = self._gather_on_device(rows, columns)
        return self._as_samples(*fields)

    def _gather_on_device(self, rows: th.Tensor, columns: th.Tensor) -> Any:
        newest = self.sampler.newest_row
        return self.storage.gather(rows, columns, self.n_steps, self.gamma, newest)  # type: ignore[call-arg]

    def graph_key(self) -> tuple[Any, ...]:
        """What a recorded sample (or priority update) holds fixed: where each tensor lives and
        the constants it reads. A graph recorded under another key is stale."""
        assert isinstance(self.storage, DeviceStorage)
        tensors = [*self.storage.tensors(), *self.sampler.tensors()]
        key = (tuple(t.data_ptr() for t in tensors), self.n_steps, self.gamma, self.n_envs)
        if self.sampler.prioritized:
            key = (*key, self.sampler.alpha, self.sampler.eps)
        return key

    def _move(self, device: th.device) -> None:
        """Assigning ``device`` (SB3 assigns the model's to a loaded buffer) moves a device
        storage and its sampler there."""
        old = self.__dict__["device"]
        self.__dict__["device"] = device
        if isinstance(self.storage, DeviceStorage) and old != device:
            self.storage.to(device)
            self.sampler.to(old, device)

    # ------------------------------------------------------------------ pickling
    def stored_state(self) -> dict[str, Any]:
        """What pickling writes, flat (each part's fields beside the buffer's own, as
        ``"storage.observations"``, ..., so that a checkpoint cuts the rows not yet filled:
        ``harness.training.checkpoints``), tensors still where they are (:meth:`host_state`
        copies the rest to the host)."""
        state = {k: v for k, v in self.__dict__.items() if k not in _PARTS}
        for part in _PARTS:
            holder = self.__dict__[part]
            state[part] = None if holder is None else type(holder)
            if holder is None:
                continue
            if isinstance(holder, DeviceUniformSampler):
                fields = holder.state()
            else:
                fields = {name: getattr(holder, name) for name in type(holder).FIELDS}
            state.update({f"{part}.{name}": value for name, value in fields.items()})
        return state

    def host_state(self, state: dict[str, Any]) -> dict[str, Any]:
        """``state`` with its tensors on the host: a buffer saved from a GPU loads without one."""
        return {name: _to(value, th.device("cpu")) for name, value in state.items()}

    def __getstate__(self) -> dict[str, Any]:
        return self.host_state(self.stored_state())

    def __setstate__(self, state: dict[str, Any]) -> None:
        state = dict(state)
        device = state["device"]  # back where it was saved from (SB3 then assigns the model's)
        for part in _PARTS:
            cls = state.pop(part)
            prefix = part + "."
            fields = {k[len(prefix) :]: state.pop(k) for k in list(state) if k.startswith(prefix)}
            holder = None
            if cls is not None:
                holder = cls.__new__(cls)
                if issubclass(cls, (DeviceStorage, DeviceUniformSampler)):
                    fields = {name: _to(value, device) for name, value in fields.items()}
                if issubclass(cls, DeviceUniformSampler):
                    holder.restore(fields, device)
                else:
                    holder.__dict__.update(fields)
            object.__setattr__(self, part, holder)
        self.__dict__.update(state)


def _map(fn: Any, value: Any) -> Any:
    if isinstance(value, dict):
        return {key: fn(v) for key, v in value.items()}
    return fn(value)


def _to(value: Any, device: th.device) -> Any:
    if isinstance(value, dict):
        return {key: _to(v, device) for key, v in value.items()}
    return value.to(device) if isinstance(value, th.Tensor) else value


class PrioritizedReplayBuffer(Replay):
    """Proportional prioritized replay (Schaul et al., 2015): :class:`Replay` whose sampler is
    prioritized by default (the class saved models name; ``placement="device"`` keeps it on the
    model's device)."""

    def __init__(self, *args: Any, sampler: str = "prioritized", **kwargs: Any) -> None:
        super().__init__(*args, sampler=sampler, **kwargs)
