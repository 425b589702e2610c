"""The coverage environment, split Jumanji-style into types, maps, observations, step helpers,
the env and rendering."""

from envs.coverage.env import CoverageEnv

__all__ = ["CoverageEnv"]
