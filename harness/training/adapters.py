"""The coverage env → SB3 VecEnv: the batched core's own VecEnv (the default), or SuperSuit over
the PettingZoo env (``vec.backend: supersuit``, the path for PettingZoo envs in general and the
check on the core's). The one module that calls SuperSuit.

Parameter sharing: every agent of every env copy is one slot of one SB3 VecEnv, so one Q-network
acts for all of them. Slot ``k`` is agent ``k % n_agents`` of copy ``k // n_agents``. Both
backends give the same observations, rewards, dones and infos for the same seeds and actions
(``tests/test_core_equality.py``).

Seeding: SuperSuit's SB3 VecEnv has no ``seed()`` and its multi-process reset hands out seeds
``seed + process + copy``, which collide across processes. So each copy is built by its own
function that seeds its env once (``seed + copy``) before SuperSuit sees it; later resets continue
that copy's generator, and a run with the same seed repeats, whatever ``num_cpus`` is.
"""

from __future__ import annotations

import atexit
import functools
import os
import signal
import sys
import types
import warnings
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import supersuit as ss
from pettingzoo.utils.wrappers import BaseParallelWrapper
from stable_baselines3.common.vec_env import VecEnv, VecMonitor
from stable_baselines3.common.vec_env.base_vec_env import (
    VecEnvIndices,
    VecEnvStepReturn,
)
from supersuit.vector import MakeCPUAsyncConstructor
from supersuit.vector.multiproc_vec import ProcConcatVec
from supersuit.vector.sb3_vector_wrapper import SB3VecEnvWrapper

from envs.coverage.core import CoverageCore
from harness.config.pettingzoo import EnvFailed, blank_observation
from harness.config.schema import VEC_BACKENDS, EnvConfig
from harness.factory import make_core_spec, make_env
from harness.sb3.decisions import EXPERT_KEY
from harness.tasks import task_of
from harness.tasks.coverage import EPISODE_INFO_KEYS
from harness.tasks.pettingzoo import TIME_LIMIT_KEY

__all__ = ["EPISODE_INFO_KEYS", "TIME_LIMIT_KEY"]


def _make_copy(
    env: EnvConfig | Mapping[str, Any], seed: int | None, owner: int | None = None
) -> Any:
    """One env copy as a SuperSuit Markov VecEnv (one slot per agent), seeded once.

    Built in a worker process (``vec.num_cpus > 1``: the pid is not ``owner``'s), it makes the
    worker ignore SIGINT and SIGTERM: a Ctrl-C in a terminal reaches the whole process group, and
    a worker that died of it would break the training process's clean stop (a checkpoint at the
    end of the round). The training process closes its workers when it ends.

    A worker also ends quietly when the training process is gone (a SIGKILL): its next write to
    the closed pipe ends it by SIGPIPE (the signal's default action), where Python would raise
    ``BrokenPipeError`` and SuperSuit's worker loop would print two tracebacks.
    """
    if owner is not None and os.getpid() != owner:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if hasattr(signal, "SIGPIPE"):  # POSIX
            signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    built = make_env(env)
    if task_of(env).leaving_agents:
        built = LeavingAgents(TimeLimitInfos(built))
    vec = ss.pettingzoo_env_to_vec_env_v1(built)
    if seed is not None:
        vec.reset(seed=seed)
    return vec


class TimeLimitInfos(BaseParallelWrapper):
    """A PettingZoo env of one's own whose truncated agents (a time limit: truncated, not
    terminated) carry ``"TimeLimit.truncated": True`` in their infos, as the coverage env's do:
    SuperSuit's VecEnv says only "done", and SB3's replay buffers read this key to bootstrap a
    time-out's last transition rather than treat it as the episode's true end."""

    def step(self, actions: dict[Any, Any]) -> tuple[dict[Any, Any], ...]:
        obs, rewards, terms, truncs, infos = self.env.step(actions)
        infos = dict(infos)
        for agent, truncated in truncs.items():
            if truncated and not terms.get(agent, False):
                infos[agent] = {**infos.get(agent, {}), TIME_LIMIT_KEY: True}
        return obs, rewards, terms, truncs, infos


class LeavingAgents(BaseParallelWrapper):
    """A PettingZoo env of one's own whose agents may leave mid-episode (a termination before
    the others', after which ``agents`` no longer holds the agent: PettingZoo's
    knights_archers_zombies), as SuperSuit's VecEnv can step it: every agent of
    ``possible_agents`` keeps its slot until the episode ends. An agent that has left gets a
    zero observation, reward 0 and empty infos (at the episode's end, those of its own last
    step, as evaluation reports them), its action is dropped, and it is done when the
    episode ends, with the others (SuperSuit's ``black_death_v3``, whose released version ends
    an episode only when its agents are terminated *and* truncated at once). Its slot so earns
    nothing after its last step, and its transitions after it (zero observations, reward 0)
    teach only the value of the zero observation, which is 0.

    The episode ends when the env's ``agents`` is empty or every agent of the step is terminated
    or truncated; agents that left before are then terminated. Over an env whose agents never
    leave, it changes nothing.
    """

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[Any, Any], dict[Any, Any]]:
        obs, infos = self.env.reset(seed=seed, options=options)
        self.agents = list(self.env.possible_agents)
        self._last_infos: dict[Any, dict[Any, Any]] = {}  # each agent's, of its own last step
        return self._filled(obs), infos

    def step(self, actions: dict[Any, Any]) -> tuple[dict[Any, Any], ...]:
        live = set(self.env.live_agents())
        obs, rewards, terms, truncs, infos = self.env.step(
            {agent: action for agent, action in actions.items() if agent in live}
        )
        over = not self.env.live_agents() or all(
            terms.get(agent, False) or truncs.get(agent, False) for agent in terms
        )
        agents = self.env.possible_agents
        rewards = {agent: rewards.get(agent, 0.0) for agent in agents}
        self._last_infos.update(infos)
        infos = {agent: infos.get(agent, {}) for agent in agents}
        if over:  # (an agent that left before: terminated, with the others' end)
            terms = {agent: terms.get(agent, agent not in truncs) for agent in agents}
            truncs = {agent: truncs.get(agent, False) for agent in agents}
            self.agents = []
            # The episode's last infos of an agent that left: those of its own last step (as
            # evaluation reports them), less a time limit's flag (it ends terminated here).
            for agent in agents:
                if agent not in live and agent in self._last_infos:
                    last = self._last_infos[agent]
                    infos[agent] = {k: v for k, v in last.items() if k != TIME_LIMIT_KEY}
        else:  # one end for every slot: the episode's
            terms = truncs = dict.fromkeys(agents, False)
        return self._filled(obs), rewards, terms, truncs, infos

    def _filled(self, obs: dict[Any, Any]) -> dict[Any, Any]:
        """``obs`` with a zero observation for each agent it lacks (every action allowed by
        an action mask: :func:`~harness.config.pettingzoo.blank_observation`)."""
        missing = [agent for agent in self.env.possible_agents if agent not in obs]
        if not missing:
            return obs
        space = self.env.observation_space(missing[0])  # (one space for all: the contract)
        return {**{agent: blank_observation(space) for agent in missing}, **obs}


class CoreVecEnv(VecEnv):
    """SB3's VecEnv over the batched core (:mod:`envs.coverage.core`): ``copies`` copies stepped
    by one call, every agent of every copy one slot (slot ``k`` is agent ``k % n_agents`` of copy
    ``k // n_agents``). A copy whose episode ends is reset on its own, from its own generator,
    and its slots' infos hold ``terminal_observation`` and ``TimeLimit.truncated``, as
    SuperSuit's Markov VecEnv does.

    Args:
        core: The core to step (its ``copies`` make ``copies * n_agents`` slots).
        seed: Copy ``i`` is seeded with ``seed + i`` at once, as
            :func:`make_vec_env`'s SuperSuit copies are, so that both backends draw the same
            episodes; later resets continue each copy's generator.
        labeller: Called with the core before each step (on the state the actions were chosen
            in): ``(copies, agents)`` expert labels, -1 for none; each label >= 0 is put in its
            slot's info of the step under :data:`~harness.sb3.decisions.EXPERT_KEY` (the
            teacher, :mod:`harness.training.teacher`). ``None``: no labels.
    """

    def __init__(
        self,
        core: CoverageCore,
        seed: int | None = None,
        labeller: Callable[[CoverageCore], np.ndarray] | None = None,
    ) -> None:
        self.core = core
        self.labeller = labeller
        self.n_agents = core.n_agents
        if seed is not None:
            for copy in range(core.copies):
                core.reset(copy, seed + copy)
        self._actions: np.ndarray | None = None
        super().__init__(core.copies * core.n_agents, core.observation_space, core.action_space)

    # ------------------------------------------------------------------ SB3 API
    def seed(self, seed: int | None = None) -> list[int | None]:
        """Seeds each copy's next reset with ``seed + copy`` (a copy's agents share a map)."""
        if seed is None:
            return [None] * self.num_envs
        self._seeds = [seed + k // self.n_agents for k in range(self.num_envs)]
        return list(self._seeds)

    def reset(self) -> np.ndarray | dict[str, np.ndarray]:
        core = self.core
        for copy in range(core.copies):
            slot = copy * self.n_agents
            core.reset(copy, self._seeds[slot], self._options[slot] or None)
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return CoverageCore.flat(core.observe())

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        core, n = self.core, self.n_agents
        actions = self._actions
        if actions is None:
            raise RuntimeError("step_wait() without step_async()")
        self._actions = None
        labels = None if self.labeller is None else self.labeller(core).reshape(-1)
        rewards, done = core.step(actions)
        obs = core.observe()
        infos = [info for copy in range(core.copies) for info in core.infos(copy)]
        if labels is not None:
            for k in np.flatnonzero(labels >= 0).tolist():
                infos[k][EXPERT_KEY] = int(labels[k])
        for copy in np.flatnonzero(done).tolist():
            for i in range(n):  # the slot's own last observation, as SuperSuit gives it
                infos[copy * n + i]["terminal_observation"] = _row(obs, copy, i)
            core.reset(copy)
            fresh = core.observe(slice(copy, copy + 1))
            if isinstance(obs, dict):
                for key, value in obs.items():
                    value[copy] = fresh[key][0]
            else:
                obs[copy] = fresh[0]
        dones = np.repeat(done, n)
        return CoverageCore.flat(obs), rewards.reshape(-1).astype(np.float32), dones, infos

    def close(self) -> None:
        pass

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        if attr_name == "render_mode":  # training never renders
            return [None] * len(self._get_indices(indices))
        raise AttributeError(f"CoreVecEnv has no per-slot attribute {attr_name!r}")

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise AttributeError(f"CoreVecEnv has no per-slot attribute {attr_name!r}")

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **kwargs: Any
    ) -> list[Any]:
        raise AttributeError(f"CoreVecEnv has no per-slot method {method_name!r}")

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False] * len(self._get_indices(indices))


def _row(obs: np.ndarray | dict[str, np.ndarray], copy: int, agent: int) -> Any:
    """One agent's observation (a fresh array, or a dict of them) from a batch."""
    if isinstance(obs, dict):
        return {key: value[copy, agent].copy() for key, value in obs.items()}
    return obs[copy, agent].copy()


def make_vec_env(
    env: EnvConfig | Mapping[str, Any],
    copies: int = 1,
    num_cpus: int = 0,
    seed: int | None = None,
    monitor: bool = True,
    backend: str = "core",
    labeller: Callable[[CoverageCore], np.ndarray] | None = None,
) -> VecEnv:
    """Build the SB3 VecEnv of ``copies × n_agents`` slots.

    Args:
        env: The env section of a config, or ``parallel_env`` keyword arguments (built by
            :func:`harness.factory.make_env`).
        copies: Env copies.
        num_cpus: Processes stepping the copies (SuperSuit only; 0 or 1: in this process).
        seed: Copy ``i`` is seeded with ``seed + i``; ``None`` leaves them unseeded.
        monitor: Wrap in ``VecMonitor`` so finished episodes carry return, length and the
            coverage keys of :data:`EPISODE_INFO_KEYS` (SB3's ``ep_info_buffer`` then holds them).
        backend: One of :data:`harness.config.schema.VEC_BACKENDS`: ``"core"`` (the batched
            core, one call steps every copy) or ``"supersuit"`` (SuperSuit over the PettingZoo
            env, one copy at a time, in ``num_cpus`` processes).
        labeller: The core's expert labels before each step (:class:`CoreVecEnv`; the core
            backend only).

    Returns:
        The VecEnv. Its ``num_envs`` is ``copies * n_agents``.
    """
    if backend not in VEC_BACKENDS:
        raise ValueError(f"unknown vec backend {backend!r}; known: {', '.join(VEC_BACKENDS)}")
    if backend == "core" and not task_of(env).batched_core:
        # (the config picks supersuit for such an env: harness.config.schema)
        raise ValueError("the batched core is the coverage env's: a pettingzoo env needs supersuit")
    if labeller is not None and backend != "core":
        raise ValueError("expert labels come from the batched core's copies: backend 'core'")
    if backend == "core":
        venv: VecEnv = CoreVecEnv(CoverageCore(make_core_spec(env), copies), seed, labeller)
        return VecMonitor(venv, info_keywords=EPISODE_INFO_KEYS) if monitor else venv
    return _supersuit_vec_env(env, copies, num_cpus, seed, monitor)


def _supersuit_vec_env(
    env: EnvConfig | Mapping[str, Any], copies: int, num_cpus: int, seed: int | None, monitor: bool
) -> VecEnv:
    """SuperSuit's VecEnv: one seeded function per copy (see the module docstring)."""
    fns = [
        functools.partial(_make_copy, env, None if seed is None else seed + i, os.getpid())
        for i in range(copies)
    ]
    probe = make_env(env)
    agent = probe.possible_agents[0]  # (all agents share their spaces: the config checks it)
    # The same constructor concat_vec_envs_v1 uses, given one seeded function per copy.
    inner = MakeCPUAsyncConstructor(min(num_cpus, copies))(
        fns, probe.observation_space(agent), probe.action_space(agent)
    )
    probe.close()
    if isinstance(inner, ProcConcatVec):
        inner._receive_info = types.MethodType(_receive_quietly, inner)  # type: ignore[method-assign]
        _end_workers_at_exit(inner)
    with warnings.catch_warnings():
        # SuperSuit's inner VecEnv has no get_attr("render_mode"); SB3 warns and uses None,
        # which is right: training never renders.
        warnings.filterwarnings("ignore", message="The `render_mode` attribute is not defined")
        venv = SB3VecEnvWrapper(inner)
        if monitor:
            # The task's info keys (a PettingZoo env: none; its infos are read from the last
            # step's infos by the episode log, harness.training.callbacks).
            venv = VecMonitor(venv, info_keywords=task_of(env).monitor_keys)
    return venv


def _end_workers_at_exit(vec: ProcConcatVec) -> None:
    """Kill ``vec``'s env workers that are still alive when this process exits.

    Training closes its workers as it ends (``venv.close()``, in a ``finally``), but a second
    Ctrl-C can land in that cleanup, where it is a ``KeyboardInterrupt`` again (the first one's
    clean stop is over), and skip or cut the close. Those workers would wait for their next
    instruction for ever (they ignore SIGINT and SIGTERM: :func:`_make_copy`), and
    multiprocessing's exit handler waits for every child that is not a daemon: the command
    printed its last line and never ended. This exit handler, registered after
    multiprocessing's (its workers are started), runs before it and kills them; a close that
    ended takes it off again.
    """
    kill = functools.partial(_kill_alive, list(vec.procs))
    atexit.register(kill)

    def close() -> None:
        ProcConcatVec.close(vec)
        atexit.unregister(kill)

    vec.close = close  # type: ignore[method-assign]


def _kill_alive(procs: list[Any]) -> None:
    for proc in procs:
        if proc.is_alive():
            proc.kill()


def _receive_quietly(vec: ProcConcatVec) -> list[Any]:
    """SuperSuit's ``ProcConcatVec._receive_info`` (each worker's answer; a worker's error raised
    here), without printing a worker's traceback when the error is the env's
    :class:`~harness.config.pettingzoo.EnvFailed`: its one line says it all (the training's
    error line). Another error's traceback is still printed, on stderr."""
    answers = []
    for pipe in vec.pipes:
        data = pipe.recv()
        if isinstance(data, tuple):
            error, trace = data
            if not isinstance(error, EnvFailed):
                print(trace, file=sys.stderr)
            raise error
        answers.append(data)
    return answers
