"""The coverage environment, split Jumanji-style into types, maps, observations, step helpers,
the env and rendering."""

# First, before any kernel is compiled or loaded: a damaged compiled cache is compiled again.
from envs.coverage import numba_cache  # noqa: F401
from envs.coverage.env import CoverageEnv

__all__ = ["CoverageEnv"]
