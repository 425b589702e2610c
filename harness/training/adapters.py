"""PettingZoo → SB3 VecEnv, through SuperSuit. The one module that calls SuperSuit.

Parameter sharing: every agent of every env copy is one slot of one SB3 VecEnv, so one Q-network
acts for all of them. Slot ``k`` is agent ``k % n_agents`` of copy ``k // n_agents``.

Seeding: SuperSuit's SB3 VecEnv has no ``seed()`` and its multi-process reset hands out seeds
``seed + process + copy``, which collide across processes. So each copy is built by its own
function that seeds its env once (``seed + copy``) before SuperSuit sees it; later resets continue
that copy's generator, and a run with the same seed repeats, whatever ``num_cpus`` is.
"""

from __future__ import annotations

import functools
import os
import signal
import warnings
from collections.abc import Mapping
from typing import Any

import supersuit as ss
from stable_baselines3.common.vec_env import VecEnv, VecMonitor
from supersuit.vector import MakeCPUAsyncConstructor
from supersuit.vector.sb3_vector_wrapper import SB3VecEnvWrapper

from harness.config.schema import EnvConfig
from harness.factory import make_env

#: Env info keys that VecMonitor copies into each finished episode's ``info["episode"]``.
EPISODE_INFO_KEYS = ("coverage", "new_cells", "wall_hits")


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
    vec = ss.pettingzoo_env_to_vec_env_v1(make_env(env))
    if seed is not None:
        vec.reset(seed=seed)
    return vec


def make_vec_env(
    env: EnvConfig | Mapping[str, Any],
    copies: int = 1,
    num_cpus: int = 0,
    seed: int | None = None,
    monitor: bool = True,
) -> VecEnv:
    """Build the SB3 VecEnv of ``copies × n_agents`` slots.

    Args:
        env: The env section of a config, or ``parallel_env`` keyword arguments (built by
            :func:`harness.factory.make_env`).
        copies: Env copies.
        num_cpus: Processes stepping the copies (0 or 1: in this process).
        seed: Copy ``i`` is seeded with ``seed + i``; ``None`` leaves them unseeded.
        monitor: Wrap in ``VecMonitor`` so finished episodes carry return, length and the
            coverage keys of :data:`EPISODE_INFO_KEYS` (SB3's ``ep_info_buffer`` then holds them).

    Returns:
        The VecEnv. Its ``num_envs`` is ``copies * n_agents``.
    """
    fns = [
        functools.partial(_make_copy, env, None if seed is None else seed + i, os.getpid())
        for i in range(copies)
    ]
    probe = make_env(env)
    # The same constructor concat_vec_envs_v1 uses, given one seeded function per copy.
    inner = MakeCPUAsyncConstructor(min(num_cpus, copies))(
        fns, probe.observation_space("agent_0"), probe.action_space("agent_0")
    )
    with warnings.catch_warnings():
        # SuperSuit's inner VecEnv has no get_attr("render_mode"); SB3 warns and uses None,
        # which is right: training never renders.
        warnings.filterwarnings("ignore", message="The `render_mode` attribute is not defined")
        venv: VecEnv = SB3VecEnvWrapper(inner)
        if monitor:
            venv = VecMonitor(venv, info_keywords=EPISODE_INFO_KEYS)
    return venv
