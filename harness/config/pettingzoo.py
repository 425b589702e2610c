"""The rules of a PettingZoo env source (``env: {pettingzoo: {make: "module:attribute", kwargs:
{...}}}``): the import path's form and its import, and the contract on the env's spaces.

One owner for each rule: :class:`harness.config.schema.PettingZooEnvConfig` calls
:func:`resolve_constructor` and :func:`probe` when a config is validated, and
:func:`harness.factory.make_env` builds every env of such a config with :func:`build`.

The env's own code runs in two places only, and each holds it to the contract: :func:`build`
(the import, the constructor, the spaces; a ``ValueError`` in one line, which a config check
turns into exit 2 before any run folder exists) and :class:`ContractGuard`, the wrapper every
built env is stepped through (reset, step, render: :class:`EnvFailed`, "the env failed at step
N: ...", which training turns into exit 1 with its newest checkpoint named). Whatever the env's
code raises, ``SystemExit`` included, is named in that one line; ``KeyboardInterrupt`` is left
to stop the harness as Ctrl-C does.

An import path is code: importing the module runs it, and so does calling the constructor. A
config that names one is as trusted as the code it names (``docs/reliability.md``).
"""

from __future__ import annotations

import contextlib
import importlib
import math
import numbers
import re
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

#: ``package.module:attribute`` (the attribute may be dotted: ``module:Class.method``).
_MAKE_RE = re.compile(r"[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*:[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*")

#: Most steps of an episode when ``env.pettingzoo.step_limit`` is not given: an episode still
#: going then is an env that never ends it, refused (training would log no episode, and an
#: evaluation would never end).
DEFAULT_STEP_LIMIT = 100_000

#: The ``metadata`` of an env that defines none (SuperSuit's VecEnv reads it).
DEFAULT_METADATA: dict[str, Any] = {"render_modes": [], "is_parallelizable": True}

#: The keys of PettingZoo's action-mask convention: an agent's ``Dict`` observation holds its
#: observation (a ``Box``) and its mask (1 where an action is allowed), as the coverage env's
#: (``harness.sb3.policies.ACTION_MASK_KEY``, which the learner honours in every choice).
OBSERVATION_KEY = "observation"
ACTION_MASK_KEY = "action_mask"

#: Characters of the env's own error message kept in the one line that names it.
_MESSAGE_CHARS = 200


class EnvFailed(Exception):
    """The env raised, or broke the contract, while the harness reset, stepped or rendered it
    (:class:`ContractGuard`). Its text is one line: "the env failed at step N: <its error>"
    (``during`` ``"reset"``: "at reset"; ``"render"``: "rendering at step N")."""

    def __init__(self, step: int, error: str, during: str = "step") -> None:
        # (the arguments as given: the exception is pickled back from a SuperSuit worker)
        super().__init__(step, error, during)
        self.step, self.error, self.during = step, error, during

    def __str__(self) -> str:
        where = {"reset": "at reset", "render": f"rendering at step {self.step:,}"}.get(
            self.during, f"at step {self.step:,}"
        )
        return f"the env failed {where}: {self.error}"


def describe(exc: BaseException) -> str:
    """One line naming an exception of the env's own code: its type and message (whitespace
    folded, shortened to :data:`_MESSAGE_CHARS`), or the code a ``sys.exit`` gave."""
    if isinstance(exc, SystemExit):
        return f"SystemExit({exc.code!r}): it called sys.exit"
    text = " ".join(str(exc).split())
    if len(text) > _MESSAGE_CHARS:
        text = text[: _MESSAGE_CHARS - 3] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


@contextlib.contextmanager
def users_code(fail: Callable[[str], Exception]) -> Iterator[None]:
    """Run the env's own code: whatever it raises becomes ``fail(describe(exc))``, raised in its
    place. ``SystemExit`` too: a library's ``sys.exit`` would otherwise end the harness with its
    code and no word. ``KeyboardInterrupt`` is left alone (Ctrl-C stops the harness cleanly)."""
    try:
        yield
    except KeyboardInterrupt:
        raise
    except BaseException as exc:
        raise fail(describe(exc)) from None


def close_quietly(env: Any) -> None:
    """Close an env; what its ``close`` raises changes nothing the harness has done (its results
    are in), so it is dropped rather than shown as a traceback at the end of the work."""
    with contextlib.suppress(Exception), users_code(RuntimeError):
        env.close()


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
    # Any error of the imported code: ImportError, SyntaxError, a sys.exit at its top level ...
    with users_code(
        lambda text: ValueError(f"make: cannot import module {module_name!r} ({text})")
    ):
        module = importlib.import_module(module_name)
    target: Any = module
    for part in attribute.split("."):
        try:
            target = getattr(target, part)
        except AttributeError:
            raise ValueError(f"make: module {module_name!r} has no {attribute!r}") from None
    if not callable(target):
        raise ValueError(f"make: {make!r} is not callable")
    return target


def build(
    constructor: Callable[..., Any],
    kwargs: Mapping[str, Any],
    step_limit: int = DEFAULT_STEP_LIMIT,
    **extra: Any,
) -> ContractGuard:
    """The ``ParallelEnv`` that ``constructor(**kwargs, **extra)`` makes, its spaces checked
    (:func:`check_spaces`), in the :class:`ContractGuard` that it is stepped through (episodes of
    at most ``step_limit`` steps). An AEC env is converted by PettingZoo's ``aec_to_parallel``,
    which is valid for envs whose agents all act once per cycle (PettingZoo's own caveat; one
    that does not fails the probe's step: :func:`probe`).

    Raises:
        ValueError: the constructor's error (``SystemExit`` included), an object that is neither
            kind of env, or spaces that break the contract, in one line.
    """
    with users_code(lambda text: ValueError(f"kwargs: the constructor failed ({text})")):
        env = constructor(**dict(kwargs), **extra)
    from pettingzoo import AECEnv, ParallelEnv

    if isinstance(env, AECEnv):
        from pettingzoo.utils.conversions import aec_to_parallel

        with users_code(
            lambda text: ValueError(f"make: cannot convert the AEC env to a parallel one ({text})")
        ):
            env = aec_to_parallel(env)
    if not isinstance(env, ParallelEnv):
        # An object with possible_agents, reset and step alone fails later, in SuperSuit (no
        # metadata, ...): the classes are PettingZoo's contract.
        raise ValueError(
            f"make: the constructor returned {type(env).__name__}, not a PettingZoo env (a "
            "subclass of pettingzoo.ParallelEnv or pettingzoo.AECEnv)"
        )
    try:
        spaces = check_spaces(env)
    except ValueError:
        close_quietly(env)
        raise
    return ContractGuard(env, spaces, step_limit, extra.get("render_mode"))


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

    with users_code(
        lambda text: ValueError(
            f"the env's possible_agents, observation_space() or action_space() failed ({text})"
        )
    ):
        agents = tuple(env.possible_agents)
        observations = {agent: env.observation_space(agent) for agent in agents}
        actions = {agent: env.action_space(agent) for agent in agents}
    if not agents:
        raise ValueError("the env has no agents (possible_agents is empty)")
    first = agents[0]
    observation, action = observations[first], actions[first]
    if not isinstance(action, spaces.Discrete):
        kind = "continuous: " if isinstance(action, spaces.Box) else ""
        raise ValueError(
            f"agent {first!r}: action space {action} is not Discrete ({kind}DQN picks one of n "
            "actions, and no SuperSuit wrapper makes such a space Discrete: discretise the "
            "actions in the env, e.g. for MPE envs set continuous_actions: false)"
        )
    if int(action.start) != 0 or int(action.n) < 1:
        # The network's outputs are actions 0 .. n-1: another start is an index error at the
        # first gradient step.
        raise ValueError(
            f"agent {first!r}: action space {action} is not Discrete(n) with n >= 1 starting "
            "at 0 (the network picks actions 0 .. n-1: shift the env's actions)"
        )
    if isinstance(observation, spaces.Dict):
        check_masked_space(first, observation, int(action.n))
        inner = observation[OBSERVATION_KEY]
    elif isinstance(observation, spaces.Box):
        inner = observation
    else:
        raise ValueError(
            f"agent {first!r}: observation space {observation} is not a Box (flatten it, e.g. "
            "with gymnasium's spaces.flatten_space and spaces.flatten)"
        )
    if not inner.shape or 0 in inner.shape:
        raise ValueError(
            f"agent {first!r}: observation space {inner} has shape {inner.shape}: "
            "the network needs at least one number (a shape such as (1,))"
        )
    for agent in agents[1:]:
        for what, mine, shared in (
            ("action", actions[agent], action),
            ("observation", observations[agent], observation),
        ):
            if mine != shared:
                wrapper = "pad_observations_v0" if what == "observation" else "pad_action_space_v0"
                raise ValueError(
                    f"agent {agent!r}: {what} space {mine} differs from {first!r}'s {shared} "
                    "(agents share one network: pad them to one space with SuperSuit's "
                    f"{wrapper} in your constructor)"
                )
    return EnvSpaces(agents, observation, action)


def check_masked_space(agent: Any, observation: Any, n_actions: int) -> None:
    """The contract on a ``Dict`` observation space: PettingZoo's action-mask convention, an
    :data:`OBSERVATION_KEY` ``Box`` and an ``int8`` :data:`ACTION_MASK_KEY` ``MultiBinary`` or
    ``Box`` of ``n_actions`` entries (1 where the action is allowed), and no other key.

    Raises:
        ValueError: one line naming the agent and what breaks it.
    """
    from gymnasium import spaces

    keys = set(observation.spaces)
    if keys != {OBSERVATION_KEY, ACTION_MASK_KEY}:
        raise ValueError(
            f"agent {agent!r}: observation space {observation} is a Dict with the keys "
            f"{sorted(keys)}: the harness reads PettingZoo's action-mask convention "
            f"({OBSERVATION_KEY!r}: a Box, {ACTION_MASK_KEY!r}: the mask) and no other "
            "(flatten the rest into the observation)"
        )
    inner, mask = observation[OBSERVATION_KEY], observation[ACTION_MASK_KEY]
    if not isinstance(inner, spaces.Box):
        raise ValueError(
            f"agent {agent!r}: the {OBSERVATION_KEY!r} space {inner} is not a Box (flatten it, "
            "e.g. with gymnasium's spaces.flatten_space and spaces.flatten)"
        )
    if not isinstance(mask, spaces.MultiBinary | spaces.Box) or tuple(mask.shape) != (n_actions,):
        raise ValueError(
            f"agent {agent!r}: the {ACTION_MASK_KEY!r} space {mask} is not a MultiBinary or "
            f"Box of the {n_actions} actions (one entry per action, 1 where it is allowed)"
        )


def masked(spaces: EnvSpaces) -> bool:
    """Whether the env's observations carry an action mask (PettingZoo's ``Dict`` convention,
    :func:`check_masked_space`)."""
    return hasattr(spaces.observation_space, "spaces")


def blank_observation(space: Any) -> Any:
    """The observation of an agent that is not in the episode: zeros, with every action allowed
    where the space carries an action mask (the slot's action is dropped anyway, and a row with
    nothing allowed would have no best action)."""
    if hasattr(space, "spaces"):
        inner, mask = space[OBSERVATION_KEY], space[ACTION_MASK_KEY]
        return {
            OBSERVATION_KEY: np.zeros(inner.shape, inner.dtype),
            ACTION_MASK_KEY: np.ones(mask.shape, mask.dtype),
        }
    return np.zeros(space.shape, space.dtype)


def stack_observations(observations: list[Any]) -> Any:
    """A batch of observations: one array, or a dict of stacked arrays for ``Dict`` ones."""
    if observations and isinstance(observations[0], dict):
        return {key: np.stack([o[key] for o in observations]) for key in observations[0]}
    return np.stack(observations)


def first_allowed(observation: Any) -> int:
    """Action 0, or the first action that the observation's action mask allows."""
    if isinstance(observation, dict) and ACTION_MASK_KEY in observation:
        allowed = np.flatnonzero(np.asarray(observation[ACTION_MASK_KEY]))
        return int(allowed[0]) if len(allowed) else 0
    return 0


def probe(make: str, kwargs: Mapping[str, Any]) -> EnvSpaces:
    """Import ``make``, build its env once (:func:`build`: the constructor and the spaces) and
    play its first step: ``reset(seed=0)`` and every agent's action 0 (its first allowed one
    where the observation carries an action mask), through the
    :class:`ContractGuard`, so that an env whose ``reset`` or ``step`` breaks the contract (the
    API's shape, observations of another shape than the space, a non-finite reward, an error of
    its own) is refused with the config, before any run folder exists.

    Raises:
        ValueError: one line (see :func:`resolve_constructor`, :func:`build`,
            :func:`check_spaces`, :class:`EnvFailed`).
    """
    env = build(resolve_constructor(make), kwargs)
    try:
        observations, _ = env.reset(seed=0)
        env.step({agent: first_allowed(observations.get(agent)) for agent in env.live_agents()})
    except EnvFailed as exc:
        raise ValueError(str(exc)) from None
    finally:
        env.close()
    return env.spaces


class ContractGuard(BaseParallelWrapper):
    """A PettingZoo env of one's own as the harness resets, steps and renders it (:func:`build`
    wraps every one: training's copies, evaluation's episodes, pictures): the one place where
    the env's code runs once it is built, and where its answers are held to the contract. What
    breaks it raises :class:`EnvFailed` naming the step of the episode and the fault:

    * an error of the env's code (``SystemExit`` included);
    * ``reset`` that returns no ``(observations, infos)`` pair, ``step`` that returns no five
      dicts (the old API's four values among them);
    * an observation of another shape than the observation space, or one holding NaN or inf;
      a reward that is not a finite number (replay would learn NaN);
    * an episode still going after ``step_limit`` steps (an env that never ends its episodes);
    * ``render()`` that returns no ``(H, W, 3)`` picture; float frames in [0, 1] are scaled to
      ``uint8`` (:func:`as_frame`).

    The checks cost a few microseconds a step, next to the env's own step.

    It also gives what SuperSuit's VecEnv reads of an env and many community envs do not define
    (PettingZoo's ``parallel_api_test`` asks neither): ``render_mode``, the one the harness built
    the env with (``None`` unless it renders), and ``metadata``, the env's own or
    :data:`DEFAULT_METADATA`. SuperSuit reads ``render_mode`` of ``unwrapped``: the guard is
    its own ``unwrapped`` (the env's code is reached through the guard only).
    """

    def __init__(
        self,
        env: Any,
        spaces: EnvSpaces,
        step_limit: int = DEFAULT_STEP_LIMIT,
        render_mode: str | None = None,
    ) -> None:
        super().__init__(env)
        self.spaces, self.step_limit = spaces, step_limit
        self.steps = 0  # of the episode under way
        self._known = set(spaces.agents)
        self.render_mode = render_mode
        with users_code(lambda text: ValueError(f"the env's metadata failed ({text})")):
            metadata = getattr(env, "metadata", None)
        #: whether the env declares a ``metadata`` of its own (:data:`DEFAULT_METADATA` if not)
        self.own_metadata = isinstance(metadata, Mapping)
        self.metadata = metadata if self.own_metadata else dict(DEFAULT_METADATA)

    @property
    def unwrapped(self) -> ContractGuard:  # type: ignore[override]
        """The guard itself: SuperSuit reads ``unwrapped.render_mode``, which the env need not
        define (the class docstring)."""
        return self

    def _failed(self, error: str, during: str = "step") -> EnvFailed:
        return EnvFailed(self.steps, error, during)

    def live_agents(self) -> list[Any]:
        """The env's ``agents`` (those still in the episode)."""
        with users_code(self._failed):
            return list(self.env.agents)

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[Any, Any], dict[Any, Any]]:
        self.steps = 0
        with users_code(lambda text: self._failed(text, "reset")):
            out = self.env.reset(seed=seed, options=options)
        if not (isinstance(out, tuple) and len(out) == 2 and all(isinstance(x, dict) for x in out)):
            raise self._failed(
                f"reset() returned {_kind(out)}, not the pair (observations, infos) of dicts "
                "that PettingZoo's API asks (since 1.22)",
                "reset",
            )
        self._check_observations(out[0], "reset")
        return out

    def step(self, actions: dict[Any, Any]) -> tuple[dict[Any, Any], ...]:
        self.steps += 1
        with users_code(self._failed):
            out = self.env.step(actions)
        if not (isinstance(out, tuple) and len(out) == 5 and all(isinstance(x, dict) for x in out)):
            old = (
                " (the old API's four values: dones are now terminations and truncations)"
                if isinstance(out, tuple) and len(out) == 4
                else ""
            )
            raise self._failed(
                f"step() returned {_kind(out)}, not five dicts (observations, rewards, "
                f"terminations, truncations, infos){old}"
            )
        observations, rewards, terminations, truncations, _ = out
        self._check_observations(observations)
        for agent, reward in rewards.items():
            if not _finite(reward):
                raise self._failed(f"the reward of {agent!r} is {reward!r}, not a finite number")
        if self.steps >= self.step_limit and not all(
            terminations.get(agent, False) or truncations.get(agent, False) for agent in actions
        ):
            raise self._failed(
                f"its episode has not ended in {self.step_limit:,} steps "
                "(env.pettingzoo.step_limit): end it with a truncation (a time limit), or raise "
                "the limit"
            )
        return out

    def _check_observations(self, observations: dict[Any, Any], during: str = "step") -> None:
        space = self.spaces.observation_space
        for agent, value in observations.items():
            if agent not in self._known:
                raise self._failed(
                    f"an observation for {agent!r}, not one of possible_agents", during
                )
            if not hasattr(space, "spaces"):
                self._check_array(agent, value, space.shape, during)
                continue
            if not isinstance(value, dict) or set(value) != set(space.spaces):
                raise self._failed(
                    f"the observation of {agent!r} is not a dict of {sorted(space.spaces)}",
                    during,
                )
            for key, part in space.spaces.items():
                self._check_array(agent, value[key], part.shape, during, key)
            if not np.asarray(value[ACTION_MASK_KEY]).any():
                raise self._failed(f"the action mask of {agent!r} allows no action", during)

    def _check_array(
        self, agent: Any, value: Any, shape: tuple[int, ...], during: str, key: str = ""
    ) -> None:
        """One observation array (``key``: its entry of a ``Dict`` observation) to the
        contract: the space's shape, numbers, finite."""
        name = f"{agent!r}[{key!r}]" if key else repr(agent)
        array = np.asarray(value)
        if array.shape != shape:
            raise self._failed(
                f"the observation of {name} has shape {array.shape}, not the observation "
                f"space's {shape}",
                during,
            )
        if array.dtype.kind not in "biuf":
            raise self._failed(
                f"the observation of {name} holds {array.dtype} values, not numbers", during
            )
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            raise self._failed(f"the observation of {name} holds NaN or inf", during)

    def render(self) -> np.ndarray:  # type: ignore[override]
        """The env's ``rgb_array`` frame as ``uint8`` (:func:`as_frame`)."""
        with users_code(lambda text: self._failed(text, "render")):
            frame = self.env.render()
        try:
            return as_frame(frame)
        except ValueError as exc:
            raise self._failed(str(exc), "render") from None

    def close(self) -> None:
        close_quietly(self.env)


def agent_groups(
    agents: tuple[str, ...], named: Mapping[str, list[str]] | None = None
) -> dict[str, tuple[str, ...]]:
    """The agents' groups, each in the agents' order: those named in the config
    (``env.pettingzoo.groups``), else by name prefix (PettingZoo's convention: ``adversary_0``
    is in ``adversary``, the part before the last ``_``; a name without one is its own group).

    Raises:
        ValueError: one line naming the agent that is not the env's, or in no group, or in two.
    """
    if not named:
        groups: dict[str, list[str]] = {}
        for agent in agents:
            groups.setdefault(agent.rpartition("_")[0] or agent, []).append(agent)
        return {name: tuple(members) for name, members in groups.items()}
    seen: dict[str, str] = {}
    for name, members in named.items():
        for agent in members:
            if agent not in agents:
                raise ValueError(
                    f"env.pettingzoo.groups.{name}: {agent!r} is no agent of the env "
                    f"(its possible_agents: {', '.join(agents)})"
                )
            if agent in seen:
                raise ValueError(
                    f"env.pettingzoo.groups: {agent!r} is in {seen[agent]!r} and {name!r}"
                )
            seen[agent] = name
    missing = [agent for agent in agents if agent not in seen]
    if missing:
        raise ValueError(f"env.pettingzoo.groups: {', '.join(map(repr, missing))} in no group")
    return {name: tuple(a for a in agents if seen[a] == name) for name in named}


def check_select(select: str, groups: Mapping[str, Any]) -> None:
    """Refuse an ``env.pettingzoo.select`` that names none of ``groups`` (the agents' groups), or
    any where the agents form one group (its return is the team's: nothing to select).

    Raises:
        ValueError: one line (without the key: the caller's).
    """
    if len(groups) < 2:
        (name,) = groups
        raise ValueError(
            f"{select!r}: the agents form one group ({name!r}), whose return is the team's: "
            "nothing to select (leave it out, or name two groups or more in "
            "env.pettingzoo.groups)"
        )
    if select not in groups:
        raise ValueError(f"{select!r} is no group of the env (its groups: {', '.join(groups)})")


def indicated_spaces(spaces: EnvSpaces, width: int | None = None) -> EnvSpaces:
    """``spaces`` with each observation followed by the agent's one-hot index (SuperSuit's agent
    indication, :class:`AgentIndicator`): a vector ``(d,)`` becomes ``(d + n,)``, an image
    ``(h, w[, c])`` gains ``n`` channels, ``n`` the index's ``width`` (the agents; the groups
    where the index is the agent's group's).

    Raises:
        ValueError: for an observation space SuperSuit's indication does not take (a ``Box`` of
            more than 3 dimensions), in one line.
    """
    from supersuit.utils.agent_indicator import change_obs_space

    observation = spaces.observation_space
    if masked(spaces):
        raise ValueError(
            "the observations carry an action mask (a Dict): the agent's one-hot index is "
            "appended to a Box only (use algo.sharing: shared)"
        )
    if len(observation.shape) > 3:
        raise ValueError(
            f"observation space {observation} has {len(observation.shape)} dimensions: the "
            "agent's one-hot index (algo.sharing) is appended to a vector or an image of at most "
            "3 (flatten it, e.g. with SuperSuit's flatten_v0)"
        )
    width = spaces.n_agents if width is None else width
    return EnvSpaces(spaces.agents, change_obs_space(observation, width), spaces.action_space)


class AgentIndicator(BaseParallelWrapper):
    """A guarded env (:class:`ContractGuard`) whose observations end in the agent's one-hot
    index, for ``algo.sharing: shared_id`` and ``per_agent`` (:func:`harness.factory.make_env`
    builds every env of such a config in it: training's copies, evaluation's episodes, so both
    see one observation). The index is SuperSuit's (``agent_indicator_v0``'s functions, agent
    ``k`` of ``possible_agents`` at entry ``k``): its value is the observation space's largest
    bound, or 1 where a bound is infinite. (``agent_indicator_v0`` itself converts a parallel env
    to an AEC one and back, which hides the guard's ``live_agents`` and ``spaces``.)

    With ``groups`` (``algo.sharing: per_group``) the index is the agent's group's instead: group
    ``g`` (of ``groups``' order) at entry ``g`` of ``len(groups)``, so that a per-agent policy of
    ``len(groups)`` networks gives each group one network, shared by its agents."""

    def __init__(
        self, env: ContractGuard, groups: Mapping[str, tuple[str, ...]] | None = None
    ) -> None:
        from supersuit.utils.agent_indicator import change_observation

        super().__init__(env)
        self._change = change_observation
        self._base = env.spaces.observation_space
        agents = env.spaces.agents
        if groups is None:
            self._index = {agent: k for k, agent in enumerate(agents)}
        else:
            self._index = {a: g for g, members in enumerate(groups.values()) for a in members}
        self._width = len(agents) if groups is None else len(groups)
        self.spaces = indicated_spaces(env.spaces, self._width)

    def observation_space(self, agent: Any) -> Any:
        return self.spaces.observation_space

    def _indicated(self, observations: dict[Any, Any]) -> dict[Any, Any]:
        n = self._width
        return {
            agent: self._change(np.asarray(value), self._base, (self._index[agent], n))
            for agent, value in observations.items()
        }

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[Any, Any], dict[Any, Any]]:
        observations, infos = self.env.reset(seed=seed, options=options)
        return self._indicated(observations), infos

    def step(self, actions: dict[Any, Any]) -> tuple[dict[Any, Any], ...]:
        observations, *rest = self.env.step(actions)
        return (self._indicated(observations), *rest)


def as_frame(frame: Any) -> np.ndarray:
    """An ``rgb_array`` frame as an ``uint8 (H, W, 3)`` picture: ``uint8`` as it is, floats in
    [0, 1] scaled by 255 (saved as they are, they would be a black picture), other integers in
    [0, 255] converted.

    Raises:
        ValueError: one line naming what ``render()`` returned instead.
    """
    if frame is None:
        raise ValueError(
            "render() returned None, not an rgb_array frame (the harness builds the env with "
            "render_mode='rgb_array': does the constructor pass it on?)"
        )
    array = np.asarray(frame)
    if array.ndim != 3 or array.shape[2] != 3 or 0 in array.shape:
        raise ValueError(
            f"render() returned {_kind(frame)} of shape {array.shape}, not an (H, W, 3) picture"
        )
    if array.dtype == np.uint8:
        return array
    kind = array.dtype.kind
    low, high = (float(array.min()), float(array.max())) if kind in "biuf" else (0.0, -1.0)
    if kind == "f" and low >= 0.0 and high <= 1.0:
        return (array * 255.0).round().astype(np.uint8)
    if kind in "biu" and low >= 0 and high <= 255:
        return array.astype(np.uint8)
    raise ValueError(
        f"render() returned a {array.dtype} frame with values in [{low:g}, {high:g}]: give uint8 "
        "in [0, 255] or floats in [0, 1]"
    )


def _kind(value: Any) -> str:
    """What a value is, for a line that says it is not what was asked: ``a tuple of 4``."""
    if isinstance(value, tuple):
        return f"a tuple of {len(value)}"
    return f"a {type(value).__name__}"


def _finite(value: Any) -> bool:
    """Whether a reward is a finite real number (a 0-d array's too)."""
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value.item()
    return isinstance(value, numbers.Real) and math.isfinite(value)
