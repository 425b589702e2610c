"""Config checks that need torch or an env: is the optimizer usable, is the device there, do
the networks and the replay buffer fit in memory, can the env place the team on its maps.

Training and sweeps run :func:`checked_config` once a config has passed its schema (which
imports neither torch nor builds an env), so that a config error never pays for importing
torch, and a config that passes both never fails later for one of these reasons (an
allocation error hours into a run, an optimizer that cannot step, a map too small).
"""

from __future__ import annotations

import inspect
import os
from typing import TYPE_CHECKING, Any

import torch as th
from stable_baselines3.common.utils import get_device

from envs.coverage.goals import GOALS_KEY
from harness.config.schema import ConfigError
from harness.sb3.buffers import replay_memory_bytes
from harness.sb3.dqn import resolve_optimizer_class
from harness.sb3.registry import POLICIES
from harness.sb3.replay import buffer_on_device
from harness.sb3.schedules import linear

if TYPE_CHECKING:
    from harness.config.schema import ExperimentConfig

#: Device types a DQN can train on.
TRAINING_DEVICE_TYPES = ("cpu", "cuda", "mps")


def policy_class_name(algo: Any) -> str:
    """The policy ``DoubleDQN`` is built with: ``algo.policy``, or its per-agent version
    (``PerAgentMlpPolicy``, ...) for ``algo.sharing: per_agent`` and ``per_group``."""
    entry = POLICIES[algo.policy]
    return entry.per_agent_name if per_network(algo) else algo.policy


def per_network(algo: Any) -> bool:
    """Whether the policy has one parameter set per one-hot index (``per_agent``: per agent;
    ``per_group``: per group, the index being the agent's group's)."""
    return algo.sharing in ("per_agent", "per_group")


def network_groups(config: Any) -> dict[str, tuple[str, ...]] | None:
    """The groups a ``per_group`` model's parameter sets play for (``env.groups``, in index
    order); ``None`` for the other kinds of sharing."""
    return config.env.groups if config.algo.sharing == "per_group" else None


def network_kwargs(
    algo: Any, n_agents: int, groups: dict[str, tuple[str, ...]] | None = None
) -> dict[str, Any]:
    """The policy's network settings from ``config.algo`` (the one place they are read):
    hidden layers, the dueling aggregator, the team-map extractor's sizes, and the number of
    parameter sets for ``algo.sharing: per_agent`` and ``per_group`` (``n_agents``: the one-hot
    index's width, ``env.id_width``: the team size, or the groups), with ``per_group`` the
    ``groups`` (``env.groups``) they play for, saved with the model to be checked where it
    plays."""
    entry = POLICIES[algo.policy]
    kwargs: dict[str, Any] = {"net_arch": list(algo.net_arch)}
    if per_network(algo):
        kwargs["n_agents"] = n_agents
    if groups is not None:  # (per_group's: network_groups)
        kwargs["groups"] = {name: list(members) for name, members in groups.items()}
    if entry.dueling:
        kwargs["aggregator"] = algo.dueling_aggregator
    if entry.team_map:
        kwargs["features_extractor_kwargs"] = {
            "features_dim": algo.features_dim,
            "channels": list(algo.cnn_channels),
        }
    if entry.slots:
        kwargs["slots_key"] = GOALS_KEY
    return kwargs


def policy_kwargs(
    algo: Any, n_agents: int, device: str, groups: dict[str, tuple[str, ...]] | None = None
) -> dict[str, Any]:
    """The policy's keyword arguments as ``harness run`` builds them from ``config.algo``: the
    network (:func:`network_kwargs`), the optimizer class and its fastest step on ``device``
    (:func:`fast_optimizer_kwargs`)."""
    optimizer_class = resolve_optimizer_class(algo.optimizer)
    return {
        **network_kwargs(algo, n_agents, groups),
        "optimizer_class": optimizer_class,
        "optimizer_kwargs": fast_optimizer_kwargs(optimizer_class, algo.optimizer_kwargs, device),
    }


def checked_config(config: ExperimentConfig, source: str) -> ExperimentConfig:
    """``config`` once :func:`check_runtime` passes.

    Raises:
        ConfigError: one line naming ``source`` and the key.
    """
    try:
        check_runtime(config)
    except ValueError as exc:
        message = str(exc)
        raise ConfigError(message if message.startswith(source) else f"{source}: {exc}") from None
    return config


def check_runtime(config: ExperimentConfig) -> None:
    """Check what the schema cannot: the optimizer, the device, the networks' and the replay
    buffer's memory.

    Raises:
        ValueError: one line naming the key (``algo.optimizer: ...``).
    """
    check_device(config.algo.device)
    # On the device the model will use: some settings (capturable) work on a GPU alone.
    device = str(get_device(config.algo.device))
    check_optimizer(config.algo.optimizer, config.algo.optimizer_kwargs, device)
    check_network_memory(config)
    check_replay_memory(config)


def schedule_warnings(config: ExperimentConfig) -> list[str]:
    """One line per phase schedule (ε, and β with prioritized replay) whose ``steps`` exceed the
    phase's ``timesteps``: it stops part-way at the phase's end (a phase shortened with ``--set
    phases.0.timesteps=...`` keeps the file's schedule, so ε may never leave ~1 and the whole
    phase acts at random). Each names the phase, both numbers, the value reached and the
    ``--set`` that fits the schedule to the phase; the schedule itself is left as written."""
    lines = []
    for i, phase in enumerate(config.phases):
        schedules = [("exploration", phase.exploration)]
        if config.algo.prioritized:  # β is read by the prioritized buffer alone
            schedules.append(("beta", phase.beta))
        for key, schedule in schedules:
            if schedule.steps <= phase.timesteps or schedule.start == schedule.end:
                continue
            reached = linear(schedule.start, schedule.end, schedule.steps, phase.timesteps)
            lines.append(
                f"phases.{i} ({phase.name}): {key}.steps is {schedule.steps:,}, more than the "
                f"phase's {phase.timesteps:,} timesteps: {key} goes {schedule.start:g} -> "
                f"{reached:.3g} and never reaches {schedule.end:g} in it (to fit: --set "
                f"phases.{i}.{key}.steps={phase.timesteps})"
            )
    return lines


def fast_optimizer_kwargs(
    optimizer_class: type[th.optim.Optimizer], kwargs: dict[str, Any], device: str = "cpu"
) -> dict[str, Any]:
    """``kwargs`` plus torch's fastest implementation of the step where the optimizer has one
    and ``kwargs`` names none: ``fused=True`` (one kernel for all parameters: Adam, AdamW, SGD,
    Adagrad, where torch has it on ``device``), else ``foreach=True`` (the multi-tensor step).

    Both are the same update as torch's default loop, not another optimizer (the fused step
    rounds some weights one unit in the last place differently). Measured on the 2-core
    machine (docs/performance.md): foreach gives ~20 % more gradient steps/s for the thesis's
    3x512 net with RMSprop (``harness bench``); fused Adam took 7-15 % off the CPU time of a
    short ``goals_2agents`` run against foreach ("The learner's optimizer step"). torch enables
    either by itself only on a GPU.
    """
    if "fused" in kwargs or "foreach" in kwargs:
        return dict(kwargs)
    # capturable (CUDA graphs) and differentiable (autograd through the step) ask for features
    # of torch's loops: the step keeps the implementation it had before the fused one was used.
    wants_loop = "capturable" in kwargs or "differentiable" in kwargs
    if not wants_loop and _fused_runs(optimizer_class, kwargs, str(get_device(device))):
        return {"fused": True, **kwargs}
    if "foreach" in inspect.signature(optimizer_class.__init__).parameters:
        return {"foreach": True, **kwargs}
    return dict(kwargs)


def _fused_runs(
    optimizer_class: type[th.optim.Optimizer], kwargs: dict[str, Any], device: str
) -> bool:
    """Whether ``optimizer_class`` takes ``fused=True`` beside ``kwargs`` and steps with it on
    ``device`` (a torch without the fused kernel for that device, or a setting the fused step
    lacks, is refused when the optimizer is built or stepped)."""
    if "fused" not in inspect.signature(optimizer_class.__init__).parameters:
        return False
    try:
        optimizer, _ = _throwaway(optimizer_class, {"fused": True, **kwargs}, device)
        optimizer.step()
    except Exception:  # torch says no with several exception types: all of them mean no
        return False
    return True


def _throwaway(
    optimizer_class: type[th.optim.Optimizer], kwargs: dict[str, Any], device: str
) -> tuple[th.optim.Optimizer, th.nn.Parameter]:
    """``optimizer_class`` over a throw-away parameter on ``device`` with a dense gradient,
    built as SB3's DQNPolicy builds it (lr from the schedule, then ``kwargs``): the probes of
    :func:`fast_optimizer_kwargs` and :func:`check_optimizer` step it. Raises what torch
    raises."""
    param = th.nn.Parameter(th.zeros(2, device=device))
    optimizer = optimizer_class([param], lr=1e-3, **kwargs)
    param.grad = th.ones(2, device=device)
    return optimizer, param


def check_optimizer(name: str, kwargs: dict[str, Any], device: str = "cpu") -> None:
    """The optimizer exists in ``torch.optim``, accepts ``kwargs`` and can take a plain step on
    ``device`` (the model's).

    One step on a throw-away parameter with a dense gradient catches what torch accepts by name
    but DQN cannot use: the abstract ``Optimizer``, ``LBFGS`` (needs a closure), ``SparseAdam``
    (sparse gradients only), and bad or unknown ``optimizer_kwargs``.
    """
    try:
        optimizer_class = resolve_optimizer_class(name)
    except ValueError:
        raise ValueError(
            f"algo.optimizer: unknown torch optimizer {name!r} (e.g. RMSprop, Adam, SGD)"
        ) from None
    if optimizer_class is th.optim.Optimizer:
        raise ValueError("algo.optimizer: 'Optimizer' is torch's base class; name a real one")
    if "lr" in kwargs:
        raise ValueError(
            "algo.optimizer_kwargs: lr is set by each phase's learning_rate; remove it here"
        )
    # torch reports unusable settings with any of several exception types (TypeError,
    # ValueError, RuntimeError, AssertionError for capturable/differentiable on CPU): all of
    # them mean no.
    try:
        optimizer, param = _throwaway(
            optimizer_class, fast_optimizer_kwargs(optimizer_class, kwargs, device), device
        )
    except MemoryError:  # no word on the settings: the process is short of memory
        raise ValueError(
            f"out of memory building the optimizer {name} (a memory limit, ulimit -v?)"
        ) from None
    except Exception as exc:
        raise ValueError(f"algo.optimizer_kwargs: {name} does not take {kwargs} ({exc})") from None
    try:
        optimizer.step()
    except Exception as exc:
        raise ValueError(
            f"algo.optimizer: torch.optim.{name} cannot train a DQN here "
            f"({str(exc).splitlines()[0]})"
        ) from None
    if not bool(th.isfinite(param).all()):
        raise ValueError(f"algo.optimizer_kwargs: {kwargs} make {name}'s first step non-finite")


def check_device(device: str) -> None:
    """``auto``, or a torch device this machine has and a DQN can train on."""
    if device == "auto":
        return
    try:
        dev = th.device(device)
    except (RuntimeError, ValueError):
        raise ValueError(
            f"algo.device: unknown device {device!r} (auto, cpu, cuda, cuda:N, mps)"
        ) from None
    if dev.type not in TRAINING_DEVICE_TYPES:
        kinds = ", ".join(TRAINING_DEVICE_TYPES)
        raise ValueError(f"algo.device: cannot train on {device!r} (one of auto, {kinds})")
    if dev.type == "cuda":
        if not th.cuda.is_available():
            raise ValueError(f"algo.device: {device!r} asked for, but this machine has no CUDA GPU")
        if dev.index is not None and dev.index >= th.cuda.device_count():
            raise ValueError(
                f"algo.device: {device!r} asked for, but this machine has "
                f"{th.cuda.device_count()} CUDA GPU(s)"
            )
    if dev.type == "mps" and not th.backends.mps.is_available():
        raise ValueError(f"algo.device: {device!r} asked for, but MPS is not available here")


def available_memory_bytes() -> int | None:
    """Memory available to new allocations, ``None`` when unknown.

    Linux's ``MemAvailable`` (free memory plus what the page cache can give back); where there is
    no ``/proc/meminfo``, the free physical pages ``os.sysconf`` reports (an underestimate).
    """
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None


def _slot_spaces(config: ExperimentConfig) -> tuple[Any, Any]:
    """One VecEnv slot's observation and action spaces, as the model sees them: the task's
    start (:meth:`harness.tasks.base.Task.start`: the env built once, a user's constructor
    run here, and what its spaces decide of the config checked)."""
    from harness.tasks import task_of

    return task_of(config.env).start(config)


def network_parameters(config: ExperimentConfig) -> int:
    """Weights of the policy of ``config.algo`` (online and target network), counted on torch's
    ``meta`` device: the policy is built as ``DoubleDQN`` builds it, without allocating memory."""
    algo = config.algo
    entry = POLICIES[algo.policy]
    kwargs = network_kwargs(algo, config.env.id_width, network_groups(config))
    policy_class = entry.load(per_agent=per_network(algo))
    # SB3 moves each new Q-network to ``policy.device`` (the CPU until it has weights); pointing
    # that hook at ``meta`` keeps every tensor on the meta device.
    sizing_class = type(
        f"_Sizing{policy_class.__name__}",
        (policy_class,),
        {"device": property(lambda self: th.device("meta"))},
    )
    observation_space, action_space = _slot_spaces(config)
    with th.device("meta"):
        policy = sizing_class(observation_space, action_space, lambda _: 1e-3, **kwargs)
    return sum(p.numel() for p in policy.parameters())


def check_network_memory(config: ExperimentConfig, available: int | None = None) -> int:
    """Refuse networks larger than the memory available now; return their estimated bytes.

    The estimate is float32 weights of the online and target network, plus as much again for the
    online network's gradients and optimizer state (RMSprop keeps one value per weight).
    """
    n = network_parameters(config)
    need = 4 * n * 2
    available = available_memory_bytes() if available is None else available
    if available is not None and need > available:
        keys = "algo.net_arch"
        if POLICIES[config.algo.policy].team_map:
            keys += ", algo.features_dim, algo.cnn_channels"
        raise ValueError(
            f"{keys}: a policy of {n:,} weights (online and target network) needs about "
            f"{format_bytes(need)} to train, more than the {format_bytes(available)} available"
        )
    return need


def check_replay_memory(config: ExperimentConfig, available: int | None = None) -> int:
    """Refuse a replay buffer larger than the memory available now; return its size in bytes.

    numpy reserves the buffer lazily, so without this check an oversized buffer would fail (or
    push the machine into swap) only once it fills, hours into the run.
    """
    observation_space, action_space = _slot_spaces(config)
    need = replay_memory_bytes(
        observation_space,
        action_space,
        config.algo.buffer_size,
        config.n_slots,
        prioritized=config.algo.prioritized,
    )
    where = "available"
    if available is None and buffer_on_device(config.algo.device) and not config.algo.per_decision:
        # The buffer is allocated on the GPU (harness.sb3.replay), all at once.
        available, where = (
            int(th.cuda.mem_get_info(get_device(config.algo.device))[0]),
            "free on the GPU",
        )
    available = available_memory_bytes() if available is None else available
    if available is not None and need > available:
        raise ValueError(
            f"algo.buffer_size: a replay buffer of {config.algo.buffer_size:,} transitions needs "
            f"about {format_bytes(need)}, more than the {format_bytes(available)} {where}"
        )
    limit = address_space_limit()
    if limit is not None and where == "available":  # (a GPU's buffer maps no host memory)
        left = limit[0] - limit[1]
        if need <= left < need + ADDRESS_SPACE_MARGIN:  # the limit, not the buffer, is short
            raise ValueError(
                f"the address-space limit of {format_bytes(limit[0])} (ulimit -v) leaves this "
                f"process {format_bytes(left)}, too little to train (about "
                f"{format_bytes(ADDRESS_SPACE_MARGIN)} and the replay buffer's "
                f"{format_bytes(need)}): raise the limit"
            )
        if need + ADDRESS_SPACE_MARGIN > left:
            raise ValueError(
                f"algo.buffer_size: a replay buffer of {config.algo.buffer_size:,} transitions "
                f"needs about {format_bytes(need)} (and training about "
                f"{format_bytes(ADDRESS_SPACE_MARGIN)} more), more than the "
                f"{format_bytes(left)} this process may still map under its address-space "
                f"limit of {format_bytes(limit[0])} (ulimit -v)"
            )
    return need


#: What training maps beyond the replay buffer once the config is checked (the modules it
#: still loads, the env's copies, thread stacks): kept free under an address-space limit. The
#: smoke config trains with 142 MiB left here and fails loading scipy with 43 MiB.
ADDRESS_SPACE_MARGIN = 128 << 20


def address_space_limit() -> tuple[int, int] | None:
    """This process's address-space limit (``RLIMIT_AS``, ``ulimit -v``) and what it maps now
    (``VmSize``), in bytes; ``None`` without a limit, or where either is unknown. numpy maps a
    replay buffer at once, so a buffer that fits the free memory can still exceed the limit."""
    try:
        import resource
    except ImportError:  # not POSIX
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    return soft, int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def format_bytes(n: float) -> str:
    """``1536`` → ``'1.5 KiB'``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    raise AssertionError("unreachable")
