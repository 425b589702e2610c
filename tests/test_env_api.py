"""The environment against PettingZoo's own conformance and seed tests."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from envs import coverage_v0


@pytest.mark.parametrize(
    "kwargs",
    [
        {"height": 12, "width": 15, "n_agents": 3, "max_steps": 60},
        {"height": 8, "width": 8, "n_agents": 1, "max_steps": 30, "coords": "raw"},
        {"map": "cave_100x50", "n_agents": 2, "max_steps": 40},
    ],
)
def test_parallel_api_conformance(kwargs):
    parallel_api_test(coverage_v0.parallel_env(**kwargs), num_cycles=100)


def test_parallel_seed_test_passes():
    parallel_seed_test(
        lambda: coverage_v0.parallel_env(height=10, width=10, n_agents=2, max_steps=50)
    )


def test_aec_form_runs_an_episode():
    env = coverage_v0.env(height=6, width=6, n_agents=2, max_steps=5)
    env.reset(seed=1)
    for agent in env.agent_iter():
        *_, term, trunc, _ = env.last()
        env.step(None if term or trunc else env.action_space(agent).sample())
    assert env.agents == []


def test_metadata_and_agent_names():
    env = coverage_v0.parallel_env(n_agents=3)
    assert env.metadata["name"] == "coverage_v0"
    assert env.possible_agents == ["agent_0", "agent_1", "agent_2"]


def test_same_seed_same_maps_and_starts_across_resets():
    a = coverage_v0.parallel_env(height=20, width=20, n_agents=2)
    b = coverage_v0.parallel_env(height=20, width=20, n_agents=2)
    a.reset(seed=7)
    b.reset(seed=7)
    for _ in range(3):
        assert np.array_equal(a.walls, b.walls)
        assert np.array_equal(a.positions, b.positions)
        a.reset()
        b.reset()
    c = coverage_v0.parallel_env(height=20, width=20, n_agents=2)
    c.reset(seed=8)
    assert not np.array_equal(a.walls, c.walls)


def test_observations_lie_in_the_observation_space():
    env = coverage_v0.parallel_env(height=15, width=15, n_agents=2, max_steps=100, coords="raw")
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(0)
    while env.agents:
        for agent, o in obs.items():
            assert env.observation_space(agent).contains(o), o
        obs, *_ = env.step({a: int(rng.integers(5)) for a in env.agents})
