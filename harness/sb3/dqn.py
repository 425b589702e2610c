"""Double DQN with prioritized replay and per-slot epsilon-greedy, on top of SB3's DQN."""

from __future__ import annotations

import io
import json
import warnings
import zipfile
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, PyTorchObs, Schedule
from stable_baselines3.common.utils import ConstantSchedule
from stable_baselines3.dqn import DQN
from stable_baselines3.dqn.policies import DQNPolicy
from torch.nn import functional as F

from harness.sb3.buffers import PrioritizedReplayBuffer
from harness.sb3.device_replay import DevicePrioritizedReplayBuffer, DeviceStorage
from harness.sb3.graphs import GraphedStep, side_stream
from harness.sb3.policies import ACTION_MASK_KEY, MultiInputPolicy, PerAgentQNetwork
from harness.sb3.registry import POLICIES
from harness.sb3.targets import double_q_target, large_margin_loss, max_q_target

#: The layout of the models :class:`DoubleDQN` saves, stored in each (``harness_model_format`` in
#: its ``data``). Increased when a saved model's layout changes; an older model is refused, not
#: read through shims. 2: the classes under
#: ``harness.sb3``, the target network always stored (a compact export stores it as the online
#: network's tensors, once), an action mask in the env's dtype, no retired settings.
MODEL_FORMAT = 2
#: The ``data`` key that holds a saved model's :data:`MODEL_FORMAT`.
FORMAT_KEY = "harness_model_format"


class OldModelError(ValueError):
    """A saved model in another layout than :data:`MODEL_FORMAT` (one line)."""


def saved_model_format(path: str | Path | io.BufferedIOBase) -> int | None:
    """The :data:`MODEL_FORMAT` a saved model zip states, 1 for a DQN model saved before
    formats were stated, ``None`` for anything else: not a model zip, or another algorithm's
    (left to SB3 to report)."""
    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data"))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return None
    finally:
        if isinstance(path, io.BufferedIOBase):
            path.seek(0)
    if not isinstance(data, dict):
        return None
    if FORMAT_KEY in data:
        return int(data[FORMAT_KEY])
    # Only a DQN model (SB3's or this harness's) can be an older harness model.
    return 1 if "target_update_interval" in data else None


def target_as_online(policy_state: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
    """A DQN policy's ``state_dict`` whose target network entries (``q_net_target.*``) are the
    online network's tensors (``q_net.*``), the same objects, so that ``torch.save`` stores them
    once: the compact form of a model kept only to be played (``harness export``)."""
    online = {k: v for k, v in policy_state.items() if not k.startswith("q_net_target.")}
    target = {
        "q_net_target." + k.removeprefix("q_net."): v
        for k, v in online.items()
        if k.startswith("q_net.")
    }
    return {**online, **target}


__all__ = [
    "ACTION_MASK_KEY",
    "MODEL_FORMAT",
    "DoubleDQN",
    "OldModelError",
    "StepStats",
    "allowed_actions",
    "per_agent_loss",
    "resolve_optimizer_class",
    "target_as_online",
]


def allowed_actions(
    obs: PyTorchObs | np.ndarray | dict[str, np.ndarray], n_actions: int
) -> th.Tensor | np.ndarray | None:
    """The actions the observations' :data:`ACTION_MASK_KEY` entry allows, ``(batch, n_actions)``
    bool (a torch tensor for tensors, a numpy array for arrays), or ``None`` when the
    observations carry no mask.

    Any nonzero entry counts as allowed. A row that allows nothing allows every action instead:
    the terminal observation of a PettingZoo env often has an all-zero mask, and a choice among
    no actions has no value (its bootstrap would be ``-inf``, and ``0 * -inf`` a NaN target).
    """
    if not isinstance(obs, dict) or ACTION_MASK_KEY not in obs:
        return None
    mask = obs[ACTION_MASK_KEY]
    if isinstance(mask, th.Tensor):
        allowed = mask.reshape(-1, n_actions) != 0
        return allowed | ~allowed.any(dim=1, keepdim=True)
    allowed = np.asarray(mask).reshape(-1, n_actions) != 0
    return allowed | ~allowed.any(axis=1, keepdims=True)


def resolve_optimizer_class(optimizer: str | type[th.optim.Optimizer]) -> type[th.optim.Optimizer]:
    """Turn the name of a ``torch.optim`` class (``"RMSprop"``, ``"Adam"``, ...) into the class.

    Classes pass through unchanged, so config files can use names and code can use classes.

    Args:
        optimizer: A ``torch.optim.Optimizer`` subclass or its name in ``torch.optim``.

    Returns:
        The optimizer class.
    """
    if isinstance(optimizer, str):
        candidate = getattr(th.optim, optimizer, None)
        if not (isinstance(candidate, type) and issubclass(candidate, th.optim.Optimizer)):
            raise ValueError(f"unknown torch optimizer {optimizer!r}: not a class in torch.optim")
        return candidate
    if isinstance(optimizer, type) and issubclass(optimizer, th.optim.Optimizer):
        return optimizer
    raise ValueError(f"optimizer_class must be a torch.optim.Optimizer subclass, got {optimizer!r}")


def per_agent_loss(
    per_sample_loss: th.Tensor,
    agent: th.Tensor,
    n_agents: int,
    weights: th.Tensor | None = None,
) -> th.Tensor:
    """The loss of N independent learners in one batch: the sum over agents of each agent's
    (IS-weighted) mean loss over its own samples.

    Why weighting rather than stratified sampling: the replay buffer (and PER's sum tree) stays
    one, unchanged, over all slots. Conditional on being agent ``i``'s, a prioritized sample is
    drawn with probability ``p_j / sum_i(p)``, exactly what agent ``i``'s own prioritized buffer
    would draw; only the number of agent ``i``'s samples in a batch varies (``N * batch_size``
    are drawn: ``batch_size`` per agent in expectation with uniform replay, as every slot holds
    as many transitions; under PER in proportion to each agent's share of the priorities).
    Dividing each agent's terms by its own count gives each set the gradient of a
    batch mean over its own transitions, as a separate learner with its own batch would get;
    a plain mean over the whole batch would instead scale each set's step by its share of the
    batch. Gradients reach a set only from its own samples (:class:`PerAgentQNetwork` routes
    them), and the IS weights are normalised by each agent's own largest weight in the batch (a
    separate buffer's normalisation), so no agent's transitions change another's step.

    Args:
        per_sample_loss: ``(batch, 1)`` or ``(batch,)`` losses.
        agent: ``(batch,)`` agent index of each sample.
        n_agents: Number of agents (parameter sets).
        weights: IS weights ``(batch, 1)`` from a prioritized buffer, or ``None``.

    Returns:
        The scalar loss to minimise.
    """
    losses = per_sample_loss.reshape(-1)
    if weights is not None:
        w = weights.reshape(-1).to(losses.dtype)
        largest = th.zeros(n_agents, dtype=w.dtype, device=w.device).scatter_reduce(
            0, agent, w, reduce="amax", include_self=False
        )
        losses = losses * (w / largest[agent])
    # Counted by a scatter, not th.bincount: on CUDA bincount reads the indices' range back
    # to the host (a synchronisation per gradient step). The counts are the same integers.
    ones = th.ones_like(losses)
    counts = th.zeros(n_agents, dtype=losses.dtype, device=losses.device)
    counts = counts.index_add(0, agent, ones).clamp(min=1)
    return (losses / counts[agent]).sum()


def _to_host(tensor: th.Tensor) -> np.ndarray:
    """``tensor``'s values as a numpy array: the one way :meth:`DoubleDQN.train` reads the
    device (a host synchronisation on an accelerator), so that the reads can be counted."""
    return tensor.detach().cpu().numpy()


class StepStats:
    """Scalars of each gradient step of a training call (the loss, the mean TD error, ...),
    kept on the device where they were computed until :meth:`read` brings all of them to the
    host in one transfer: a read per step would make the host wait for every step's kernels."""

    def __init__(self) -> None:
        self._values: dict[str, list[th.Tensor]] = {}

    def add(self, name: str, value: th.Tensor) -> None:
        """Record one step's ``value`` (a one-element tensor) under ``name``; reads nothing."""
        self._values.setdefault(name, []).append(value.detach().reshape(()))

    def extend(self, values: dict[str, th.Tensor]) -> None:
        """:meth:`add` each of ``values`` (one step's, by name)."""
        for name, value in values.items():
            self.add(name, value)

    def latest(self) -> dict[str, th.Tensor]:
        """Every name's last value, in the order the names were first added."""
        return {name: values[-1] for name, values in self._values.items()}

    def read(self) -> dict[str, np.ndarray]:
        """Every name's values in the order added, float64, in one transfer; then forgets them.

        Empty (and no transfer) when nothing was added.
        """
        if not self._values:
            return {}
        names = list(self._values)
        # One concatenation (promoted to a common dtype) and one copy to the host.
        host = _to_host(th.cat([th.stack(self._values[name]) for name in names]))
        out: dict[str, np.ndarray] = {}
        start = 0
        for name in names:
            n = len(self._values[name])
            out[name] = host[start : start + n].astype(np.float64)
            start += n
        self._values.clear()
        return out


class NonFiniteLossError(FloatingPointError):
    """The training loss became NaN or infinite; the weights are no longer trustworthy."""


class DoubleDQN(DQN):
    """SB3 DQN with Double-Q targets, prioritized replay and per-slot epsilon-greedy.

    Differences from ``stable_baselines3.DQN`` (everything else, including the arguments, is
    SB3's):

    * ``double_q=True`` (default) bootstraps with ``Q_target(s', argmax_a Q_online(s', a))``;
      ``double_q=False`` gives SB3's ``max_a Q_target(s', a)``. Per-sample ``discounts`` from
      SB3's n-step buffer are honoured.
    * With ``replay_buffer_class=PrioritizedReplayBuffer`` the per-sample Huber loss is
      weighted by the importance-sampling weights and the priorities are updated with
      ``|TD error|`` after every gradient step. Any other ``ReplayBuffer`` trains as in SB3.
    * The default optimizer is ``torch.optim.RMSprop`` (set in ``policy_kwargs`` when it has no
      ``"optimizer_class"``). ``policy_kwargs["optimizer_class"]`` may also be the name of a
      ``torch.optim`` class, e.g. ``"Adam"``.
    * ``predict(deterministic=False)`` draws one exploration coin per observation (per VecEnv
      slot / agent), instead of SB3's single coin for the whole batch.
    * Invalid-action masking (Huang & Ontañón 2022), PettingZoo's convention: when the
      observation space is a ``Dict`` with an :data:`ACTION_MASK_KEY` (``"action_mask"``) entry,
      a ``MultiBinary(n)`` or a ``Box`` of shape ``(n,)`` with 1 where an action is allowed,
      only allowed actions are chosen: the greedy action and the ε-random one (uniform over the
      allowed actions) in :meth:`predict`, the random actions before ``learning_starts``, and
      the next-state max (or the online argmax of the double-Q target) of the TD target, over
      the next observation's mask. A row that allows nothing counts as allowing every action
      (:func:`allowed_actions`). The harness's policies and ``"MultiInputPolicy"`` keep the mask
      out of the network's input (:mod:`harness.sb3.policies`). Without such an entry nothing
      is masked.
    * ``expert_action=a`` adds DQfD's large-margin loss (Hester et al. 2018;
      :func:`harness.sb3.targets.large_margin_loss`) towards action ``a`` to every sample's TD loss,
      ``margin_weight * max_a [Q(s, a) + margin * (a != a_E)] - Q(s, a_E)``: the greedy policy
      follows the expert's action (for the coverage env, its frontier step) unless the TD targets
      hold another action's value higher (how strongly depends on ``margin_weight``:
      docs/training.md). The priorities stay ``|TD error|``.
    * The names of :data:`harness.sb3.registry.POLICIES` select the harness's policies
      (``"DuelingMlpPolicy"``, ``"TeamMapPolicy"``, ``"DuelingTeamMapPolicy"``), and
      ``"MultiInputPolicy"`` is SB3's with the mask left out of the network's input.

    Schedules. SB3 overwrites ``exploration_rate`` in ``_on_step`` from
    ``exploration_schedule(progress_remaining)``, so assigning ``exploration_rate`` from a
    callback has no lasting effect; replace the schedule instead. Likewise ``beta_schedule``
    (``progress_remaining -> float``, default: constant at the buffer's initial ``beta``) is
    written to ``replay_buffer.beta`` at every env step. Both are rebuilt by ``_setup_model``
    (so also by ``load``) and are not saved. ``alpha`` is changed directly:
    ``model.replay_buffer.alpha = 0.5``.

    Phases. SB3's ``progress_remaining`` counts over the whole run once ``learn`` is called with
    ``reset_num_timesteps=False`` (``1 - num_timesteps / (steps before + steps asked)``), so a
    schedule meant for the second ``learn()`` call would start part-way. After
    :meth:`start_phase`, ``progress_remaining`` is ``1 - (num_timesteps - phase_start) /
    phase_timesteps`` instead: every schedule (learning rate, ε, β) then follows the transition
    count within the phase, taken from the model's own counter, the same in a fresh run, in a later
    phase and in a resumed run. Without :meth:`start_phase` the progress is SB3's.

    Args:
        policy: Policy class or alias (``"MlpPolicy"``, ``"DuelingMlpPolicy"``, ...).
        env: Environment (a VecEnv with several slots is fine).
        learning_rate: Learning rate, constant or schedule.
        buffer_size: Replay buffer size, over all envs.
        learning_starts: Env steps before learning starts.
        batch_size: Minibatch size.
        tau: Soft update coefficient (1 = hard target update).
        gamma: Discount factor.
        train_freq: Train every ``train_freq`` steps, or ``(n, "step" | "episode")``.
        gradient_steps: Gradient steps per rollout; ``-1`` = as many as env steps collected.
        replay_buffer_class: Replay buffer class, e.g. :class:`PrioritizedReplayBuffer`.
        replay_buffer_kwargs: Its keyword arguments, e.g. ``dict(alpha=0.6, beta=0.4)``.
        optimize_memory_usage: As SB3 (not supported by the prioritized buffer).
        n_steps: n-step returns with SB3's buffer (only when ``replay_buffer_class`` is None;
            the prioritized buffers take ``n_steps`` and ``gamma`` in ``replay_buffer_kwargs``).
        target_update_interval: Env steps between target network updates.
        exploration_fraction: Fraction of training over which epsilon decays.
        exploration_initial_eps: Initial epsilon.
        exploration_final_eps: Final epsilon.
        max_grad_norm: Gradient clipping norm.
        stats_window_size: Episodes averaged in the rollout logs.
        tensorboard_log: Tensorboard log directory.
        policy_kwargs: Policy keyword arguments (``net_arch``, ``aggregator``,
            ``optimizer_class``, ``optimizer_kwargs``, ...).
        verbose: Verbosity level.
        seed: Random seed.
        device: Torch device.
        double_q: Use the Double-DQN target.
        expert_action: The action DQfD's large-margin loss favours; ``None``: no such loss.
        margin: The lead over every other action's value the loss asks of ``expert_action``.
        margin_weight: The loss's weight beside the TD loss (DQfD's lambda_2).
        cuda_graph: On CUDA with a device replay buffer (prioritized or uniform,
            :class:`~harness.sb3.device_replay.DeviceStorage`), record a gradient step once as
            a CUDA graph and launch it again for every later step (:mod:`harness.sb3.graphs`):
            the same results, several times the gradient steps/s. Without effect elsewhere;
            a step that cannot be recorded warns once and trains without a graph.
        _init_setup_model: Build the networks now (``False`` is used by ``load``).
    """

    # Every name of the harness's policy registry (MlpPolicy, DuelingMlpPolicy, TeamMapPolicy,
    # DuelingTeamMapPolicy, SlotTeamMapPolicy), beside SB3's own aliases.
    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        **DQN.policy_aliases,
        **{name: entry.load() for name, entry in POLICIES.items()},
        **{
            entry.per_agent_name: entry.load(per_agent=True)
            for entry in POLICIES.values()
            if entry.per_agent
        },
        "MultiInputPolicy": MultiInputPolicy,
    }
    beta_schedule: Schedule
    #: Transition count (``num_timesteps``) at which the current phase started.
    phase_start: int = 0
    #: Transitions in the current phase; ``None``: SB3's own progress (no phases).
    phase_timesteps: int | None = None
    expert_action: int | None
    margin: float
    margin_weight: float

    def __init__(
        self,
        policy: str | type[DQNPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 32,
        tau: float = 1.0,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 4,
        gradient_steps: int = 1,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        target_update_interval: int = 10000,
        exploration_fraction: float = 0.1,
        exploration_initial_eps: float = 1.0,
        exploration_final_eps: float = 0.05,
        max_grad_norm: float = 10,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        double_q: bool = True,
        expert_action: int | None = None,
        margin: float = 0.8,
        margin_weight: float = 1.0,
        cuda_graph: bool = True,
        _init_setup_model: bool = True,
    ) -> None:
        # Copy: the caller's dict must not change, and the resolved class (not a string) is
        # what gets saved with the model.
        policy_kwargs = dict(policy_kwargs or {})
        policy_kwargs["optimizer_class"] = resolve_optimizer_class(
            policy_kwargs.get("optimizer_class", th.optim.RMSprop)
        )
        super().__init__(
            policy,
            env,
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            target_update_interval=target_update_interval,
            exploration_fraction=exploration_fraction,
            exploration_initial_eps=exploration_initial_eps,
            exploration_final_eps=exploration_final_eps,
            max_grad_norm=max_grad_norm,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
        )
        self.double_q = double_q
        if expert_action is not None and not 0 <= expert_action < self.action_space.n:  # type: ignore[attr-defined]
            raise ValueError(
                f"expert_action {expert_action} is not an action of {self.action_space}"
            )
        if margin < 0 or margin_weight < 0:
            raise ValueError(
                f"margin and margin_weight must be >= 0, got {margin} and {margin_weight}"
            )
        self.expert_action = expert_action
        self.margin = float(margin)
        self.margin_weight = float(margin_weight)
        self.cuda_graph = bool(cuda_graph)
        # The recorded step (rebuilt, never saved), whether recording failed in this process,
        # and the gradient steps this process has taken (a loaded model warms up again).
        self._graph: GraphedStep | None = None
        self._graph_failed = False
        self._steps_here = 0
        # Saved with the model (SB3 saves the instance's attributes): load checks it.
        setattr(self, FORMAT_KEY, MODEL_FORMAT)
        if _init_setup_model:
            self._setup_model()

    @property
    def prioritized(self) -> bool:
        """Whether the replay buffer is a :class:`PrioritizedReplayBuffer`."""
        return isinstance(self.replay_buffer, PrioritizedReplayBuffer)

    @property
    def masked(self) -> bool:
        """Whether the observations carry an action mask (:data:`ACTION_MASK_KEY`)."""
        space = self.observation_space
        return isinstance(space, spaces.Dict) and ACTION_MASK_KEY in space.spaces

    def _check_action_mask_space(self) -> None:
        if not self.masked:
            return
        mask_space = self.observation_space[ACTION_MASK_KEY]  # type: ignore[index]
        n_actions = int(self.action_space.n)  # type: ignore[attr-defined]
        shape_ok = mask_space.shape == (n_actions,)
        if not (isinstance(mask_space, (spaces.MultiBinary, spaces.Box)) and shape_ok):
            raise ValueError(
                f"the {ACTION_MASK_KEY!r} observation must be a MultiBinary({n_actions}) or a Box "
                f"of shape ({n_actions},), one entry per action, got {mask_space}"
            )

    def _setup_model(self) -> None:
        self._check_action_mask_space()
        super()._setup_model()
        initial_beta = self.replay_buffer.beta if self.prioritized else 0.0  # type: ignore[union-attr]
        self.beta_schedule = ConstantSchedule(initial_beta)

    def start_phase(self, timesteps: int, start: int | None = None) -> None:
        """Make ``progress_remaining`` run from 1 to 0 over a phase of ``timesteps`` transitions.

        Args:
            timesteps: Transitions in the phase (> 0).
            start: The ``num_timesteps`` at which the phase started; default now. A resumed run
                passes the phase's original start, so its schedules continue where they were.
        """
        if timesteps <= 0:
            raise ValueError(f"a phase needs timesteps > 0, got {timesteps}")
        self.phase_timesteps = int(timesteps)
        self.phase_start = int(self.num_timesteps if start is None else start)
        self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)

    def at_round_boundary(self) -> bool:
        """Whether the phase so far is a whole number of collection rounds of ``train_freq`` env
        steps (each followed by a training call).

        SB3 collects in rounds that start with each ``learn()`` call. A checkpoint written at a
        round boundary is resumed on the same rounds as the uninterrupted run, so training calls
        (and the schedule values they use) fall on the same transitions, and the phase ends on the
        same transition.
        """
        steps = (self.num_timesteps - self.phase_start) // self.n_envs
        return steps % self.train_freq.frequency == 0

    def _update_current_progress_remaining(self, num_timesteps: int, total_timesteps: int) -> None:
        if self.phase_timesteps is None:
            super()._update_current_progress_remaining(num_timesteps, total_timesteps)
            return
        done = num_timesteps - self.phase_start
        self._current_progress_remaining = 1.0 - done / self.phase_timesteps

    def _on_step(self) -> None:
        super()._on_step()
        if self.prioritized:
            self.replay_buffer.beta = self.beta_schedule(self._current_progress_remaining)  # type: ignore[union-attr]

    @classmethod
    def load(  # type: ignore[override]
        cls,
        path: str | Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> DoubleDQN:
        """SB3's ``load``, of a model in today's :data:`MODEL_FORMAT` only.

        Raises:
            OldModelError: The model was saved in an older or newer layout (one line).
        """
        found = saved_model_format(path)
        where = path if isinstance(path, (str, Path)) else "the model"
        if found is not None and found < MODEL_FORMAT:
            raise OldModelError(
                f"{where}: saved by an older version of the harness (model format {found}, this "
                f"version reads {MODEL_FORMAT}); retrain it with this version"
            )
        if found is not None and found > MODEL_FORMAT:
            raise OldModelError(
                f"{where}: saved by a newer version of the harness (model format {found}, this "
                f"version reads {MODEL_FORMAT}); update the harness to load it"
            )
        return super().load(path, env=env, device=device, custom_objects=custom_objects, **kwargs)

    def _excluded_save_params(self) -> list[str]:
        # Both schedules are rebuilt by _setup_model on load; saving them would only pickle
        # whatever closure a callback installed (possibly holding the callback or the model).
        return [
            *super()._excluded_save_params(),
            "exploration_schedule",
            "beta_schedule",
            "_graph",
            "_graph_failed",
            "_steps_here",
        ]

    @property
    def agent_sets(self) -> int:
        """Parameter sets of the Q-network: ``n_agents`` for a per-agent policy, else 1."""
        return self.q_net.n_agents if isinstance(self.q_net, PerAgentQNetwork) else 1

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """SB3's DQN update with Double-Q targets and prioritized replay when configured.

        Each gradient step is :meth:`_gradient_step`, built from the hooks :meth:`_td_target`,
        :meth:`_loss_terms` and :meth:`_weighted_loss`. The losses, the TD-error means and the
        imitation statistics stay on the device (:class:`StepStats`) and are read once, at the end
        of the call, where the non-finite check runs too. With prioritized replay each step's
        new priorities are written before the next sample: on the device with
        :class:`~harness.sb3.device_replay.DevicePrioritizedReplayBuffer` (the call then reads
        the device once), or copied to the host buffer after every step, where a non-finite one
        stops the call at once.

        With a per-agent policy (:attr:`agent_sets` = N > 1) each gradient step samples
        ``N * batch_size`` transitions, ``batch_size`` per agent's set on average (see
        :func:`per_agent_loss` for why the loss is weighted rather than the batch stratified).

        Raises:
            NonFiniteLossError: A step's loss (or TD error) was NaN or infinite; the message
                names the first such update.
        """
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        buffer = self.replay_buffer
        assert buffer is not None
        prioritized = isinstance(buffer, PrioritizedReplayBuffer)
        batch = batch_size * self.agent_sets

        stats = StepStats()
        graphs = self._graphs_wanted()
        # Nothing a step does changes the key: one look per call.
        graph = self._graphed_step(batch) if graphs else None
        for step in range(gradient_steps):
            if graph is not None:
                # The sample, the loss, the gradients and the new priorities in one launch.
                stats.extend(graph.replay())
                self.policy.optimizer.step()
                continue
            with side_stream(graphs):  # the steps before a recording, as torch asks
                abs_td, indices = self._sampled_step(batch, stats)
            if prioritized and not isinstance(buffer, DevicePrioritizedReplayBuffer):
                # The host buffer's next sample needs the new priorities: a transfer a step.
                priorities = _to_host(abs_td)
                if not np.isfinite(priorities).all():
                    self._check_finite(stats.read())  # raises, naming the loss when it is bad
                    bad = priorities[~np.isfinite(priorities)][0]
                    raise self._non_finite("TD error", float(bad), step)
                buffer.update_priorities(indices, priorities)  # type: ignore[union-attr]

        values = stats.read()  # the call's one read of the device
        self._check_finite(values)
        self._n_updates += gradient_steps
        self._steps_here += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", np.mean(self._reported_losses(values)))
        self.logger.record("train/mean_td_error", np.mean(values.get("td_error", [])))
        if "margin_loss" in values:
            self.logger.record("train/margin_loss", np.mean(values["margin_loss"]))
            self.logger.record("train/expert_agreement", np.mean(values["expert_agreement"]))
        if prioritized:
            self.logger.record("train/beta", buffer.beta)  # type: ignore[union-attr]
            self.logger.record("train/alpha", buffer.alpha)  # type: ignore[union-attr]

    def _sampled_step(self, batch: int, stats: StepStats) -> tuple[th.Tensor, Any]:
        """Sample ``batch`` transitions and take :meth:`_gradient_step` on them, recording the
        loss and the mean TD error; with the device buffer also write the new priorities.

        Returns the samples' ``|TD error|`` and their buffer indices (``None`` for a buffer
        without priorities): what the host buffer's priority update needs.
        """
        buffer = self.replay_buffer
        assert buffer is not None
        replay_data = buffer.sample(batch, env=self._vec_normalize_env)
        loss, abs_td = self._gradient_step(replay_data, stats)
        stats.add("loss", loss)
        stats.add("td_error", abs_td.mean())
        if isinstance(buffer, DevicePrioritizedReplayBuffer):
            # Errors from before this step's update, as in Schaul et al. (Algorithm 1), written
            # where the buffer is: nothing is read (a non-finite one makes this step's loss
            # non-finite, which the call's one read reports).
            buffer.update_priorities(replay_data.indices, abs_td)
        return abs_td, getattr(replay_data, "indices", None)

    # ------------------------------------------------------------------ CUDA graphs
    #: Gradient steps taken without a graph before one is recorded, in each process (the first
    #: steps set up the optimizer's state and cuBLAS's work spaces, not to be done in a recording).
    GRAPH_WARMUP_STEPS: ClassVar[int] = 3

    def _graphs_wanted(self) -> bool:
        """Whether this call's steps go through a recorded graph (:mod:`harness.sb3.graphs`):
        ``cuda_graph``, a device buffer (prioritized or uniform), a CUDA device, and no failed
        recording so far."""
        return (
            self.cuda_graph
            and not self._graph_failed
            and isinstance(self.replay_buffer, DeviceStorage)
            and self.device.type == "cuda"
        )

    def _graph_key(self, batch: int) -> tuple[Any, ...]:
        """What a recorded step of ``batch`` samples holds fixed (see :mod:`harness.sb3.graphs`):
        a step recorded under another key is recorded again."""
        buffer = self.replay_buffer
        assert isinstance(buffer, DeviceStorage)
        return (
            batch,
            buffer.graph_key(),
            self.gamma,
            self.double_q,
            self.expert_action,
            self.margin,
            self.margin_weight,
            self.max_grad_norm,
            tuple(p.data_ptr() for p in self.policy.parameters()),
        )

    def _graphed_step(self, batch: int) -> GraphedStep | None:
        """The recorded step for ``batch`` samples, recorded now when there is none under
        today's key; ``None`` while warming up or after a recording failed (with a warning)."""
        if self._steps_here < self.GRAPH_WARMUP_STEPS:
            # A call warms up whole; a resumed run warms up too (its steps so far were another
            # process's).
            return None
        key = self._graph_key(batch)
        if self._graph is not None and self._graph.key == key:
            return self._graph
        buffer = self.replay_buffer
        assert isinstance(buffer, DeviceStorage)
        self._graph = None  # free the stale graph's memory first

        def step(draws: th.Tensor) -> dict[str, th.Tensor]:
            recorded = StepStats()
            replay_data = buffer.sample_at(draws)
            loss, abs_td = self._backward(replay_data, recorded)
            recorded.add("loss", loss)
            recorded.add("td_error", abs_td.mean())
            if isinstance(buffer, DevicePrioritizedReplayBuffer):
                buffer.update_priorities(replay_data.indices, abs_td)
            return recorded.latest()

        try:
            self._graph = GraphedStep(
                key,
                step,
                batch,
                buffer.draw,
                list(self.policy.parameters()),
                self.device,
            )
        except RuntimeError as error:
            self._graph_failed = True
            warnings.warn(
                f"DoubleDQN: the gradient step could not be recorded as a CUDA graph "
                f"({str(error).splitlines()[0]}); training goes on without one",
                RuntimeWarning,
                stacklevel=3,
            )
            self.policy.optimizer.zero_grad()
        return self._graph

    def _reported_losses(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """The logged loss of each step: per agent set, the mean over the sets (the minimised
        loss is their sum, :func:`per_agent_loss`), divided on the host in float64."""
        return values.get("loss", np.empty(0)) / self.agent_sets

    def _non_finite(self, what: str, value: float, step: int) -> NonFiniteLossError:
        return NonFiniteLossError(
            f"the {what} became {value} at step {self.num_timesteps} "
            f"(update {self._n_updates + step})"
        )

    def _check_finite(self, values: dict[str, np.ndarray]) -> None:
        """Raise :class:`NonFiniteLossError` naming the first update whose loss is not finite."""
        losses = self._reported_losses(values)
        bad = np.flatnonzero(~np.isfinite(losses))
        if bad.size:
            raise self._non_finite("loss", float(losses[bad[0]]), int(bad[0]))

    def _gradient_step(
        self, replay_data: Any, stats: StepStats | None = None
    ) -> tuple[th.Tensor, th.Tensor]:
        """One optimizer step on a sampled batch, from the hooks; reads nothing from the device.

        Returns the minimised loss (detached; with per-agent sets their sum) and the samples'
        ``|TD error|`` before the step, ``(batch,)``, both where they were computed.
        ``replay_data`` carries ``weights`` (IS weights) when it comes from a prioritized
        buffer, and ``discounts`` from SB3's n-step buffer. ``stats`` collects what the loss
        terms log (:meth:`_margin_loss`).
        """
        loss, abs_td = self._backward(replay_data, stats)
        self.policy.optimizer.step()
        return loss, abs_td

    def _backward(
        self, replay_data: Any, stats: StepStats | None = None
    ) -> tuple[th.Tensor, th.Tensor]:
        """:meth:`_gradient_step` up to the optimizer's step: the loss from the hooks, its
        gradients, clipped, in the parameters' ``grad`` (what a CUDA graph records); the same
        returns."""
        target_q = self._td_target(replay_data)
        q_values = self.q_net(replay_data.observations)
        current_q = th.gather(q_values, dim=1, index=replay_data.actions.long())
        terms = self._loss_terms(replay_data, q_values, current_q, target_q, stats)
        per_sample_loss = terms[0]
        for term in terms[1:]:
            per_sample_loss = per_sample_loss + term
        loss = self._weighted_loss(per_sample_loss, replay_data)

        self.policy.optimizer.zero_grad()
        loss.backward()
        if isinstance(self.q_net, PerAgentQNetwork):
            self.q_net.clip_grad_norm_(self.max_grad_norm)
        else:
            th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
        return loss.detach(), (current_q.detach() - target_q).abs().reshape(-1)

    # ------------------------------------------------------------------ the update's hooks
    def _td_target(self, replay_data: Any) -> th.Tensor:
        """The TD target of each sample, ``(batch, 1)``, without gradient: Double-Q's
        (:func:`~harness.sb3.targets.double_q_target`) or the plain max
        (:func:`~harness.sb3.targets.max_q_target`), over the actions the next observation
        allows, with the n-step ``discounts`` when the samples carry them."""
        # n-step samples carry gamma**k per sample; plain/prioritized samples do not.
        discounts = getattr(replay_data, "discounts", None)
        if discounts is None:
            discounts = self.gamma
        n_actions = int(self.action_space.n)  # type: ignore[attr-defined]
        with th.no_grad():
            next_q_target = self.q_net_target(replay_data.next_observations)
            allowed = allowed_actions(replay_data.next_observations, n_actions)
            blocked = None if allowed is None else ~allowed
            if self.double_q:
                next_q_online = self.q_net(replay_data.next_observations)
                return double_q_target(
                    replay_data.rewards,
                    replay_data.dones,
                    discounts,
                    next_q_online,
                    next_q_target,
                    blocked,
                )
            return max_q_target(
                replay_data.rewards, replay_data.dones, discounts, next_q_target, blocked
            )

    def _loss_terms(
        self,
        replay_data: Any,
        q_values: th.Tensor,
        current_q: th.Tensor,
        target_q: th.Tensor,
        stats: StepStats | None = None,
    ) -> list[th.Tensor]:
        """The per-sample loss terms, ``(batch, 1)`` each, summed in this order into the loss
        that :meth:`_weighted_loss` weights: the TD loss (:meth:`_td_loss`), then DQfD's margin
        (:meth:`_margin_loss`) with ``expert_action`` or the samples' own ``experts`` labels.
        A new term is one more method, added here.

        Args:
            replay_data: The sampled batch.
            q_values: Online Q-values of its observations, ``(batch, n_actions)``.
            current_q: Those of the taken actions, ``(batch, 1)``.
            target_q: The TD targets, ``(batch, 1)`` (:meth:`_td_target`).
            stats: Where the terms record what they log, or ``None``.
        """
        terms = [self._td_loss(current_q, target_q)]
        if self.expert_action is not None or getattr(replay_data, "experts", None) is not None:
            terms.append(self._margin_loss(replay_data, q_values, stats))
        return terms

    def _td_loss(self, current_q: th.Tensor, target_q: th.Tensor) -> th.Tensor:
        """The Huber loss of each sample's TD error, ``(batch, 1)``: per sample, so that the
        IS weights can scale each term."""
        return F.smooth_l1_loss(current_q, target_q, reduction="none")

    def _margin_loss(
        self, replay_data: Any, q_values: th.Tensor, stats: StepStats | None = None
    ) -> th.Tensor:
        """DQfD's large-margin term towards the expert's action, times ``margin_weight``,
        ``(batch, 1)`` (:func:`~harness.sb3.targets.large_margin_loss`): towards each sample's
        own label when the samples carry ``experts`` (a teacher's labels,
        :mod:`harness.sb3.decisions`; 0 on the samples labelled -1, none), else towards
        ``expert_action``. Records the unweighted margin loss and the expert agreement of the
        greedy actions (over the labelled samples) as ``margin_loss`` and
        ``expert_agreement``."""
        experts = getattr(replay_data, "experts", None)
        if experts is not None:
            labelled = experts >= 0
            expert: th.Tensor | int = th.where(labelled, experts, th.zeros_like(experts))
            # The labels' range was checked as they entered the buffer: no device read here.
            margin_loss = large_margin_loss(q_values, expert, self.margin, check_range=False)
            margin_loss = margin_loss * labelled
        else:
            assert self.expert_action is not None
            labelled, expert = None, self.expert_action
            margin_loss = large_margin_loss(q_values, expert, self.margin)
        term = self.margin_weight * margin_loss
        if stats is not None:
            # The agreement of the action the policy would take: the greedy one among the
            # allowed actions when the observations carry a mask.
            allowed_now = allowed_actions(replay_data.observations, int(self.action_space.n))  # type: ignore[attr-defined]
            greedy = _masked(q_values, allowed_now).argmax(dim=1, keepdim=True)  # type: ignore[arg-type]
            agree = (greedy == expert).float()
            if labelled is None:
                stats.add("margin_loss", margin_loss.mean())
                stats.add("expert_agreement", agree.mean())
            else:  # over the labelled samples (none labelled: 0)
                count = labelled.sum().clamp(min=1)
                stats.add("margin_loss", margin_loss.sum() / count)
                stats.add("expert_agreement", (agree * labelled).sum() / count)
        return term

    def _weighted_loss(self, per_sample_loss: th.Tensor, replay_data: Any) -> th.Tensor:
        """The scalar loss to minimise from the per-sample losses: the mean, each sample scaled
        by its IS weight when the batch carries ``weights`` (prioritized replay); with per-agent
        sets the sum of each set's mean over its own samples (:func:`per_agent_loss`)."""
        weights = getattr(replay_data, "weights", None)
        sets = self.agent_sets
        if sets > 1:
            agent = self.q_net.agents_of(replay_data.observations)  # type: ignore[operator]
            return per_agent_loss(per_sample_loss, agent, sets, weights)
        weighted = per_sample_loss if weights is None else weights * per_sample_loss
        return weighted.mean()

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """Epsilon-greedy with an independent coin per observation in the batch.

        SB3's ``DQN.predict`` draws one coin for the whole batch, so all VecEnv slots (all
        agents of a SuperSuit-vectorised PettingZoo env) explore or exploit together. Here
        each slot explores with probability ``exploration_rate`` on its own, vectorised.
        With an :data:`ACTION_MASK_KEY` entry in the observations, the greedy action and the
        random one are both chosen among the allowed actions (:func:`allowed_actions`).

        Args:
            observation: One observation or a batch (one per VecEnv slot).
            state: Unused (no recurrent policies), passed through.
            episode_start: Unused, passed through.
            deterministic: Greedy actions only.

        Returns:
            The actions (shape as SB3's: ``(n,)`` for a batch, ``()`` for one observation)
            and the state.
        """
        allowed = None
        if self.masked:
            action, allowed = self._masked_greedy(observation)  # type: ignore[arg-type]
        else:
            action, state = self.policy.predict(observation, state, episode_start, deterministic)
        if deterministic or self.exploration_rate <= 0.0:
            return action, state
        greedy = np.asarray(action)
        flat = greedy.reshape(-1)
        n_actions = int(self.action_space.n)  # type: ignore[attr-defined]
        # The global np.random is what SB3 seeds in set_random_seed (and uses itself), so runs
        # stay reproducible with `seed=`. Random actions are in [0, n) like the greedy argmax
        # (SB3's Q-network ignores Discrete.start).
        explore = np.random.random_sample(flat.shape[0]) < self.exploration_rate  # noqa: NPY002
        if allowed is None:
            random_actions = np.random.randint(n_actions, size=flat.shape[0])  # noqa: NPY002
        else:  # uniform over the allowed actions: the largest of iid keys, the others below all
            keys = np.random.random_sample((flat.shape[0], n_actions))  # noqa: NPY002
            random_actions = np.where(allowed, keys, -1.0).argmax(axis=1)
        mixed = np.where(explore, random_actions, flat).astype(flat.dtype, copy=False)
        return mixed.reshape(greedy.shape), state

    def _masked_greedy(self, observation: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The greedy action among the actions the observation's mask allows, shaped as SB3's
        ``policy.predict`` shapes it, and the ``(batch, n_actions)`` allowed mask."""
        self.policy.set_training_mode(False)
        obs, vectorized = self.policy.obs_to_tensor(observation)
        with th.no_grad():
            allowed = allowed_actions(obs, int(self.action_space.n))  # type: ignore[attr-defined]
            assert isinstance(allowed, th.Tensor)
            action = self._masked_argmax(obs, allowed).cpu().numpy()  # type: ignore[arg-type]
        action = action if vectorized else action.squeeze(axis=0)
        return action, allowed.cpu().numpy()

    def _masked_argmax(self, obs: dict[str, th.Tensor], allowed: th.Tensor) -> th.Tensor:
        """The best allowed action of each row (:meth:`_masked_greedy`), the network run on the
        rows with a choice only: a row whose mask allows one action (a forced step: a held goal)
        takes it without a pass of the network (the same action: the masked argmax of a row
        with one allowed action is that action)."""
        deciding = allowed.sum(dim=1) > 1
        n_deciding = int(deciding.sum())  # one read of the device for both cases below
        if n_deciding == deciding.numel():
            return _masked(self.q_net(obs), allowed).argmax(dim=1)
        action = allowed.to(th.int8).argmax(dim=1)  # a forced row's one action
        if n_deciding > 0:
            rows = {key: value[deciding] for key, value in obs.items()}
            action[deciding] = _masked(self.q_net(rows), allowed[deciding]).argmax(dim=1)
        return action

    def _sample_action(
        self,
        learning_starts: int,
        action_noise: ActionNoise | None = None,
        n_envs: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """SB3's action choice during ``learn``; the uniformly random actions before
        ``learning_starts`` are drawn among the allowed actions when the observations carry a
        mask (from the action space's own generator, as SB3's are)."""
        allowed = None
        if self.masked and self.num_timesteps < learning_starts:
            assert self._last_obs is not None, "self._last_obs was not set"
            allowed = allowed_actions(self._last_obs, int(self.action_space.n))  # type: ignore[attr-defined]
        if allowed is None:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        action = np.array(
            [self.action_space.sample(mask=row.astype(np.int8)) for row in allowed]  # type: ignore[call-arg]
        )
        return action, action


def _masked(q: th.Tensor, allowed: th.Tensor | None) -> th.Tensor:
    """``q`` with the actions ``allowed`` leaves out at ``-inf``, so that argmax skips them."""
    return q if allowed is None else q.masked_fill(~allowed, float("-inf"))
