"""The rules of a PettingZoo env source (``env: {pettingzoo: {make: "module:attribute", kwargs:
{...}}}``): the import path's form and its import, and the contract on the env's spaces.

One owner for each rule: :class:`harness.config.schema.PettingZooEnvConfig` calls
:func:`resolve_constructor` and :func:`probe` when a config is validated, and
:func:`harness.factory.make_env` builds every env of such a config with :func:`build`.

An import path is code: importing the module runs it, and so does calling the constructor. A
config that names one is as trusted as the code it names (``docs/reliability.md``).
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

#: ``package.module:attribute`` (the attribute may be dotted: ``module:Class.method``).
_MAKE_RE = re.compile(r"[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*:[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*")


def resolve_constructor(make: str) -> Callable[..., Any]:
    """The callable named by ``make`` (``module:attribute``), imported.

    Raises:
        ValueError: one line naming the path's form, or the module and the import's error.
    """
    if not _MAKE_RE.fullmatch(make):
        raise ValueError(
            f"make: {make!r} is not an import path 'package.module:constructor' "
            "(e.g. 'mpe2.simple_spread_v3:parallel_env')"
        )
    module_name, _, attribute = make.partition(":")
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # any error of the imported code: ImportError, SyntaxError, ...
        raise ValueError(
            f"make: cannot import module {module_name!r} ({type(exc).__name__}: {exc})"
        ) from None
    target: Any = module
    for part in attribute.split("."):
        try:
            target = getattr(target, part)
        except AttributeError:
            raise ValueError(f"make: module {module_name!r} has no {attribute!r}") from None
    if not callable(target):
        raise ValueError(f"make: {make!r} is not callable")
    return target


def build(constructor: Callable[..., Any], kwargs: Mapping[str, Any], **extra: Any) -> Any:
    """The ``ParallelEnv`` that ``constructor(**kwargs, **extra)`` makes; an AEC env (one with
    ``agent_iter``) is converted by PettingZoo's ``aec_to_parallel``, which is valid for envs
    whose agents all act once per cycle (PettingZoo's own caveat).

    Raises:
        ValueError: the constructor's error, or an object that is neither kind of env, in one line.
    """
    try:
        env = constructor(**dict(kwargs), **extra)
    except Exception as exc:  # the env's own code: any error is the config's
        raise ValueError(
            f"kwargs: the constructor failed ({type(exc).__name__}: {str(exc)[:200]})"
        ) from None
    from pettingzoo import AECEnv

    if isinstance(env, AECEnv):
        from pettingzoo.utils.conversions import aec_to_parallel

        try:
            env = aec_to_parallel(env)
        except Exception as exc:
            raise ValueError(
                f"make: cannot convert the AEC env to a parallel one ({type(exc).__name__}: {exc})"
            ) from None
    if not all(hasattr(env, name) for name in ("possible_agents", "reset", "step")):
        raise ValueError(
            f"make: the constructor returned {type(env).__name__}, not a PettingZoo env "
            "(ParallelEnv or AEC env)"
        )
    return env


@dataclass(frozen=True)
class EnvSpaces:
    """What the harness reads of a PettingZoo env before it trains on it."""

    agents: tuple[str, ...]
    observation_space: Any
    action_space: Any

    @property
    def n_agents(self) -> int:
        """Agents of the team (``possible_agents``)."""
        return len(self.agents)


def check_spaces(env: Any) -> EnvSpaces:
    """The contract on an env's spaces: at least one agent, every agent with one ``Discrete``
    action space and one ``Box`` observation space, the same for all (one Q-network acts for
    every agent: parameter sharing).

    Raises:
        ValueError: one line naming the agent and the space that break it.
    """
    from gymnasium import spaces

    agents = tuple(env.possible_agents)
    if not agents:
        raise ValueError("the env has no agents (possible_agents is empty)")
    first = agents[0]
    observation, action = env.observation_space(first), env.action_space(first)
    if not isinstance(action, spaces.Discrete):
        raise ValueError(
            f"agent {first!r}: action space {action} is not Discrete (DQN picks one of n "
            "actions; for MPE envs set continuous_actions: false)"
        )
    if not isinstance(observation, spaces.Box):
        raise ValueError(
            f"agent {first!r}: observation space {observation} is not a Box (flatten it, e.g. "
            "with gymnasium's spaces.flatten_space and spaces.flatten)"
        )
    for agent in agents[1:]:
        for what, mine, shared in (
            ("action", env.action_space(agent), action),
            ("observation", env.observation_space(agent), observation),
        ):
            if mine != shared:
                raise ValueError(
                    f"agent {agent!r}: {what} space {mine} differs from {first!r}'s {shared} "
                    "(agents share one network: pad them to one space, e.g. SuperSuit's "
                    "pad_observations_v0 and pad_action_space_v0)"
                )
    return EnvSpaces(agents, observation, action)


def probe(make: str, kwargs: Mapping[str, Any]) -> EnvSpaces:
    """Import ``make``, build its env once and check its spaces (:func:`check_spaces`).

    Raises:
        ValueError: one line (see :func:`resolve_constructor`, :func:`build`, :func:`check_spaces`).
    """
    env = build(resolve_constructor(make), kwargs)
    try:
        return check_spaces(env)
    finally:
        close = getattr(env, "close", None)
        if close is not None:
            close()
