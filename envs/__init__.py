"""Environments of coverage-harness, PettingZoo style: ``from envs import coverage_v0``."""

from envs import coverage_v0

__all__ = ["coverage_v0"]
