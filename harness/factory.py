"""The one env factory: every environment of the harness (training copies, evaluation episodes,
pictures, benchmarks, the checks of a config) is built here from the ``env`` section of a config.

It is also where a config meets the env's own checks: the config's schema validates each key
without building anything, and :func:`check_env` builds one env and draws a few maps, once,
before training or evaluation starts, so that a map too small or too walled for the team is a
one-line config error rather than a failure part-way through.

A PettingZoo env of one's own (``env: {pettingzoo: ...}``, :class:`PettingZooEnvConfig`) is
built here too, by its constructor (:func:`harness.config.pettingzoo.build`, which owns the
contract); it has no batched core.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from envs import coverage_v0
from envs.coverage import generators
from envs.coverage.core import CoreSpec
from harness.config.maps import build_source
from harness.config.pettingzoo import AgentIndicator, build, resolve_constructor
from harness.config.schema import ConfigError, EnvConfig, PettingZooEnvConfig

#: Maps drawn by :func:`check_env` (random and generated sources).
CHECK_DRAWS = 3


def env_kwargs(env: EnvConfig) -> dict[str, Any]:
    """Keyword arguments of ``coverage_v0.parallel_env`` for the ``env`` section of a config:
    map sources built, test maps left out of generated ones, options as the env's objects."""
    out = env.model_dump(exclude={"map_sha256", "test_maps", "frontier", "prior"})
    out["wall_fraction"] = tuple(out["wall_fraction"])
    out["frontier"] = env.frontier_options
    if env.prior is not None:  # the loaded prior, an object of the env's frontier options
        out["frontier"] = dataclasses.replace(out["frontier"], prior=map_prior(env.prior))
    if env.agent_id:
        out["agent_id"] = True
    if isinstance(env.map, dict):
        out["map"] = build_source(env.map, env.height, env.width)
    if env.test_maps and (isinstance(env.map, dict) or env.map == "random"):
        # Generated maps only: a fixed map named in env.map is used as given (evaluation on a
        # test map); `harness run` refuses to train on one.
        source = (
            out["map"]
            if isinstance(env.map, dict)
            else generators.from_name("random", env.height, env.width, env.wall_fraction)
        )
        try:
            out["map"] = generators.WithoutMaps(source, env.test_grids())
        except ValueError as exc:
            raise ConfigError(f"env.map: {exc} (it is in env.test_maps)") from None
    return out


@functools.lru_cache(maxsize=4)
def _load_prior(path: str, stamp: float) -> Any:
    from harness.prior.model import load_prior  # torch: only for a prior

    return load_prior(path)


def map_prior(path: str) -> Any:
    """The map prior of ``env.prior`` (:class:`harness.prior.model.MapPrior`), loaded once per
    process and file version: every env copy of a process shares it.

    Raises:
        ConfigError: one line naming ``env.prior``.
    """
    try:
        return _load_prior(str(Path(path).resolve()), Path(path).stat().st_mtime)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"env.prior: {exc}") from None


def make_env(
    env: EnvConfig | PettingZooEnvConfig | Mapping[str, Any], render_mode: str | None = None
) -> Any:
    """The PettingZoo env of a config's ``env`` section (or of ``parallel_env``'s keyword
    arguments, for code that builds envs without a config: benchmarks, tests): a
    :class:`CoverageEnv`, or the ``ParallelEnv`` of a ``pettingzoo`` source.

    Raises:
        ConfigError: the env's own ``ValueError`` (a map file's content, start cells on a wall,
            ...), as one line naming ``env``.
    """
    if isinstance(env, PettingZooEnvConfig):
        return make_pettingzoo_env(env, render_mode)
    kwargs = env_kwargs(env) if isinstance(env, EnvConfig) else dict(env)
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    try:
        return coverage_v0.parallel_env(**kwargs)
    except ValueError as exc:
        raise ConfigError(f"env: {exc}") from None


def make_pettingzoo_env(env: PettingZooEnvConfig, render_mode: str | None = None) -> Any:
    """The ``ParallelEnv`` of a ``pettingzoo`` source (``render_mode`` given when not ``None``),
    its observations ending in the agent's one-hot index where ``env.agent_id`` is on
    (``algo.sharing``: :class:`~harness.config.pettingzoo.AgentIndicator`; its group's index for
    ``per_group``).

    Raises:
        ConfigError: the import's or the constructor's error, as one line naming ``env``.
    """
    source = env.pettingzoo
    extra = {} if render_mode is None else {"render_mode": render_mode}
    try:
        built = build(resolve_constructor(source.make), source.kwargs, source.step_limit, **extra)
    except ValueError as exc:
        raise ConfigError(f"env.pettingzoo: {exc}") from None
    if not env.agent_id:
        return built
    return AgentIndicator(built, env.groups if env.by_group else None)


def make_core_spec(env: EnvConfig | Mapping[str, Any]) -> CoreSpec:
    """The batched core's objects (:class:`envs.coverage.core.CoreSpec`) of a config's ``env``
    section (or of ``parallel_env``'s keyword arguments), parsed as :func:`make_env` parses them
    (it is that env's spec).

    Raises:
        ConfigError: the env's own ``ValueError``, as one line naming ``env``.
    """
    return make_env(env).core.spec


def check_env(env: EnvConfig) -> Any:
    """Build the coverage env once and draw :data:`CHECK_DRAWS` maps of a generated source, so
    that a map too small or too walled to place the team is a config error; returns the env
    (the coverage task's start, :meth:`harness.tasks.coverage.CoverageTask.start`; a
    ``pettingzoo`` env is probed by its own, :meth:`harness.config.schema.PettingZooSource.probe`).

    Raises:
        ConfigError: naming ``env`` and the problem.
    """
    built = make_env(env)
    if env.map == "random" or isinstance(env.map, dict):
        for seed in range(CHECK_DRAWS):
            try:
                built.reset(seed=seed)
            except ValueError as exc:
                raise ConfigError(f"env: {exc}") from None
            except Exception as exc:  # a generator that cannot draw this size at all
                raise ConfigError(
                    f"env.map: cannot draw a {env.height}x{env.width} map from {env.map!r} "
                    f"({type(exc).__name__}: {exc})"
                ) from None
    return built
