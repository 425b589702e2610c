"""Where a replay buffer's transitions live (:mod:`harness.sb3.replay`): SB3's ``[rows, n_envs]``
layout as numpy arrays on the host (:class:`HostStorage`) or as tensors on the model's device
(:class:`DeviceStorage`), observations an array or a ``Dict`` of them (one per key).

A storage writes a row of ``n_envs`` transitions as SB3's ``ReplayBuffer.add`` does and reads
what a sample needs of the transitions at given ``(rows, columns)``: the observations, actions,
bootstrap observations, ``dones`` (a timeout is no terminal state) and ``rewards``, with n-step
returns as SB3's ``NStepReplayBuffer`` computes them (:func:`~harness.sb3.kernels.n_step_returns`,
whose ``discounts`` ``gamma**k`` the TD target uses). Per-decision transitions
(:mod:`harness.sb3.decisions`) keep their ``discounts`` and expert labels beside
(``decisions=True``). The buffer keeps the cursor (``pos``, ``full``); a storage keeps arrays.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape

from harness.sb3.kernels import n_step_returns, n_step_returns_on_device

__all__ = ["DeviceStorage", "HostStorage"]


def _action_dtype(action_space: spaces.Space) -> Any:
    """SB3's dtype for stored actions (float64 is stored as float32)."""
    dtype = action_space.dtype
    return np.float32 if dtype == np.float64 else dtype


def _torch_dtype(dtype: Any) -> th.dtype:
    """The torch dtype of a numpy dtype, as ``th.as_tensor`` maps it."""
    return th.from_numpy(np.zeros(0, dtype=dtype)).dtype


class HostStorage:
    """SB3's replay arrays on the host.

    Args:
        rows: Rows (``buffer_size // n_envs``).
        n_envs: Columns (VecEnv slots; 1 for per-decision storage).
        observation_space: A ``Box`` (or any SB3 space) or a ``Dict`` of them.
        action_space: The action space.
        decisions: Keep a per-transition discount and expert label (per-decision replay).
    """

    #: The arrays (or dicts of arrays, rows first; the last two per decision only) and every
    #: attribute a buffer pickles.
    ARRAYS: tuple[str, ...] = ("observations", "next_observations", "actions", "rewards")
    ARRAYS += ("dones", "timeouts", "step_discounts", "expert_actions")
    FIELDS: tuple[str, ...] = (*ARRAYS, "space", "width")

    def __init__(
        self,
        rows: int,
        n_envs: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        decisions: bool = False,
    ) -> None:
        self.space = observation_space
        self.width = get_action_dim(action_space)  # of a stored action
        obs_shape = get_obs_shape(observation_space)
        if isinstance(observation_space, spaces.Dict):
            assert isinstance(obs_shape, dict)
            self.observations = {
                key: np.zeros((rows, n_envs, *shape), dtype=observation_space[key].dtype)
                for key, shape in obs_shape.items()
            }
            self.next_observations = {
                key: np.zeros((rows, n_envs, *shape), dtype=observation_space[key].dtype)
                for key, shape in obs_shape.items()
            }
        else:
            shape = (rows, n_envs, *obs_shape)  # type: ignore[misc]
            self.observations = np.zeros(shape, dtype=observation_space.dtype)
            self.next_observations = np.zeros(shape, dtype=observation_space.dtype)
        self.actions = np.zeros((rows, n_envs, self.width), dtype=_action_dtype(action_space))
        self.rewards = np.zeros((rows, n_envs), dtype=np.float32)
        self.dones = np.zeros((rows, n_envs), dtype=np.float32)
        self.timeouts = np.zeros((rows, n_envs), dtype=np.float32)
        self.step_discounts = np.zeros((rows, 1), dtype=np.float32) if decisions else None
        self.expert_actions = np.full((rows, 1), -1, dtype=np.int64) if decisions else None

    def write(
        self,
        row: int,
        obs: Any,
        next_obs: Any,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        timeouts: np.ndarray | None,
    ) -> None:
        """Write one step of every column at ``row``, converted as SB3's ``add`` converts."""
        n_envs = self.rewards.shape[1]
        self._write_obs(self.observations, obs, row, n_envs)
        self._write_obs(self.next_observations, next_obs, row, n_envs)
        self.actions[row] = np.array(np.asarray(action).reshape((n_envs, self.width)))
        self.rewards[row] = np.array(reward)
        self.dones[row] = np.array(done)
        if timeouts is not None:
            self.timeouts[row] = timeouts

    def _write_obs(self, storage: Any, values: Any, row: int, n_envs: int) -> None:
        space = self.space
        if isinstance(storage, dict):
            for key, column in storage.items():
                value = values[key]
                if isinstance(space.spaces[key], spaces.Discrete):  # type: ignore[attr-defined]
                    value = value.reshape((n_envs, *column.shape[2:]))
                column[row] = np.array(value)
            return
        if isinstance(space, spaces.Discrete):
            values = values.reshape((n_envs, *storage.shape[2:]))
        storage[row] = np.array(values)

    def gather(
        self,
        rows: np.ndarray,
        columns: np.ndarray,
        n_steps: int,
        gamma: float,
        newest_row: int,
        normalize_obs: Any,
        normalize_reward: Any,
    ) -> tuple[Any, np.ndarray, Any, np.ndarray, np.ndarray, np.ndarray | None]:
        """The transitions at ``(rows, columns)``: observations, actions, bootstrap observations,
        ``dones`` and ``rewards`` ``(batch, 1)`` and the n-step ``discounts`` ``(batch, 1)``
        (``None``: one step), as arrays made afresh (never views of the storage)."""
        if n_steps == 1:
            # As SB3: only dones that are not timeouts are terminal.
            done = self.dones[rows, columns] * (1 - self.timeouts[rows, columns])
            reward = normalize_reward(self.rewards[rows, columns])
            next_rows, dones, rewards, discounts = rows, done.reshape(-1, 1), reward, None
            rewards = rewards.reshape(-1, 1)
        else:
            returns, step_discounts, next_rows, terminal = n_step_returns(
                # With a VecNormalize (the harness has none) this normalises the whole reward
                # array per sample: correct, if wasteful; the scale is elementwise, as in SB3.
                normalize_reward(self.rewards),
                self.dones,
                self.timeouts,
                rows,
                columns,
                n_steps,
                gamma,
                newest_row=newest_row,
            )
            dones, rewards = terminal.reshape(-1, 1), returns.reshape(-1, 1)
            discounts = step_discounts.reshape(-1, 1)
        if self.step_discounts is not None:
            discounts = self.step_discounts[rows, columns].reshape(-1, 1)
        return (
            normalize_obs(_take(self.observations, rows, columns)),
            self.actions[rows, columns],
            normalize_obs(_take(self.next_observations, next_rows, columns)),
            dones,
            rewards,
            discounts,
        )

    def experts(self, rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """The expert labels of the transitions at ``(rows, columns)``, ``(batch, 1)``."""
        assert self.expert_actions is not None
        return self.expert_actions[rows, columns].reshape(-1, 1)

    def clear(self) -> None:
        """Forget the labels (the arrays themselves are overwritten as rows are reused)."""
        if self.expert_actions is not None:
            self.expert_actions[:] = -1


def _take(storage: Any, rows: Any, columns: Any) -> Any:
    if isinstance(storage, dict):
        return {key: column[rows, columns] for key, column in storage.items()}
    return storage[rows, columns]


class DeviceStorage:
    """SB3's replay arrays as tensors on ``device``: an env step's transitions are copied there
    when added (during collection, where the policy already reads its actions back), a batch is
    gathered there and n-step targets are computed there
    (:func:`~harness.sb3.kernels.n_step_returns_on_device`), reading nothing from the host: the
    newest row comes as a tensor (the buffer's cursor), so that a gather can be part of a
    recorded CUDA graph (:mod:`harness.sb3.graphs`)."""

    ARRAYS: tuple[str, ...] = HostStorage.ARRAYS[:6]
    FIELDS: tuple[str, ...] = (*ARRAYS, "width")

    def __init__(
        self,
        rows: int,
        n_envs: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device,
    ) -> None:
        # The host layout (untouched zeros: no memory is used), then the same on the device.
        host = HostStorage(rows, n_envs, observation_space, action_space)
        self.width = host.width
        for name in self.ARRAYS:
            setattr(self, name, _empty_like(getattr(host, name), device))

    @property
    def device(self) -> th.device:
        return self.rewards.device

    def to(self, device: th.device) -> None:
        """Move every tensor to ``device``."""
        for name in self.ARRAYS:
            setattr(self, name, _to(getattr(self, name), device))

    def tensors(self) -> list[th.Tensor]:
        """Every tensor, in a fixed order (a recorded graph reads them where they are)."""
        return [t for name in self.ARRAYS for t in _flat(getattr(self, name))]

    def _tensor(self, array: np.ndarray) -> th.Tensor:
        # (A read-only array, a broadcast view say, is copied first: torch wants writable ones.)
        return th.as_tensor(np.require(array, requirements="W")).to(self.device)

    def write(
        self,
        row: int,
        obs: Any,
        next_obs: Any,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        timeouts: np.ndarray | None,
    ) -> None:
        """Write one step of every column at ``row``, on the device."""
        n_envs = self.rewards.shape[1]
        self._write(self.observations, obs, row)
        self._write(self.next_observations, next_obs, row)
        self.actions[row] = self._tensor(np.asarray(action).reshape(n_envs, self.width))
        self.rewards[row] = self._tensor(np.asarray(reward, dtype=np.float32))
        self.dones[row] = self._tensor(np.asarray(done, dtype=np.float32))
        if timeouts is not None:
            self.timeouts[row] = self._tensor(timeouts)

    def _write(self, storage: Any, values: Any, row: int) -> None:
        if isinstance(storage, dict):
            for key, column in storage.items():
                self._write(column, values[key], row)
            return
        storage[row] = self._tensor(np.asarray(values).reshape(storage.shape[1:]))

    def gather(
        self, rows: th.Tensor, columns: th.Tensor, n_steps: int, gamma: float, newest_row: Any
    ) -> tuple[Any, th.Tensor, Any, th.Tensor, th.Tensor, th.Tensor | None]:
        """:meth:`HostStorage.gather` on the device (``newest_row`` a tensor or an int)."""
        if n_steps == 1:
            done = self.dones[rows, columns] * (1 - self.timeouts[rows, columns])
            next_rows, dones, discounts = rows, done.reshape(-1, 1), None
            rewards = self.rewards[rows, columns].reshape(-1, 1)
        else:
            returns, step_discounts, next_rows, terminal = n_step_returns_on_device(
                self.rewards,
                self.dones,
                self.timeouts,
                rows,
                columns,
                n_steps,
                gamma,
                newest_row=newest_row,
            )
            dones, rewards = terminal.reshape(-1, 1), returns.reshape(-1, 1)
            discounts = step_discounts.reshape(-1, 1)
        return (
            _take(self.observations, rows, columns),
            self.actions[rows, columns],
            _take(self.next_observations, next_rows, columns),
            dones,
            rewards,
            discounts,
        )

    def clear(self) -> None:
        """Nothing to forget: rows are overwritten as they are reused."""


def _empty_like(array: Any, device: th.device) -> Any:
    if array is None:
        return None
    if isinstance(array, dict):
        return {key: _empty_like(value, device) for key, value in array.items()}
    return th.zeros(array.shape, dtype=_torch_dtype(array.dtype), device=device)


def _flat(value: Any) -> list[th.Tensor]:
    """The tensors of a field (a tensor, or a dict of them)."""
    return list(value.values()) if isinstance(value, dict) else [value]


def _to(value: Any, device: th.device) -> Any:
    if isinstance(value, dict):
        return {key: _to(v, device) for key, v in value.items()}
    return value.to(device) if isinstance(value, th.Tensor) else value
