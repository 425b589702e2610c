"""Shared fixtures and helpers: small hand-built grids and envs made for them, and the check of a
one-line error."""

from __future__ import annotations

import numpy as np
import pytest

from envs import coverage_v0


def grid_from(text: str) -> np.ndarray:
    """Grid from the text map format (``#`` wall, ``.`` free), ignoring surrounding whitespace."""
    rows = [line.strip() for line in text.strip().splitlines()]
    return np.array([[ch == "#" for ch in row] for row in rows], dtype=bool)


@pytest.fixture
def make_env():
    """Factory: an env reset on the given text grid with fixed start cells."""

    def _make(text: str, starts: list[tuple[int, int]], **kwargs):
        grid = grid_from(text)
        env = coverage_v0.parallel_env(
            height=grid.shape[0], width=grid.shape[1], n_agents=len(starts), **kwargs
        )
        obs, infos = env.reset(seed=0, options={"grid": grid, "starts": starts})
        return env, obs

    return _make


def one_error_line(err: str) -> str:
    """The only line of ``err``, checked to be a harness error."""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("harness: error: ") and "Traceback" not in err
    return lines[0]
