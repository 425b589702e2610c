"""The environment against PettingZoo's own conformance and seed tests, and its refusal of
actions and reset options that are not what the API takes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test

from envs import coverage_v0


def _half(seen: np.ndarray, free: np.ndarray) -> np.ndarray:
    """A map prior: every unseen cell a wall with probability 1/2."""
    return np.where(seen, ~free, 0.5).astype(float)


#: The team map as the goal configs have it (small crop: the tests' maps are small).
TEAMMAP = {"teammap": {"crop": 7, "global_size": 6, "ego_size": 5, "ego_block": 3}}
#: Every observation and action kind: the thesis vector (normalised and raw coordinates, agent
#: indication), the team map with options, its frontier field and compass, a planner's claims,
#: the frontier step and the goal action (whose observation holds an ``action_mask``), with a map
#: prior's predicted views.
KINDS = {
    "thesis": {"height": 12, "width": 15, "n_agents": 3, "max_steps": 60},
    "thesis-raw": {"height": 8, "width": 8, "n_agents": 1, "max_steps": 30, "coords": "raw"},
    "thesis-cave": {"map": "cave_100x50", "n_agents": 2, "max_steps": 40},
    "thesis-agent-id": {"height": 9, "width": 9, "n_agents": 2, "max_steps": 30, "agent_id": True},
    "teammap": {"height": 10, "width": 12, "n_agents": 2, "max_steps": 40, "observation": TEAMMAP},
    "teammap-frontier-field": {
        "height": 10, "width": 12, "n_agents": 2, "max_steps": 40, "observation": TEAMMAP,
        "frontier": {},
    },
    "teammap-planner-claims": {
        "height": 10, "width": 12, "n_agents": 3, "max_steps": 40, "observation": TEAMMAP,
        "frontier": {"planner": "hungarian"},
    },
    "frontier-step": {
        "height": 10, "width": 12, "n_agents": 2, "max_steps": 40, "observation": TEAMMAP,
        "frontier": {"action": "step", "planner": "pocket"}, "agent_id": True,
    },
    "goal-action": {
        "height": 12, "width": 14, "n_agents": 2, "max_steps": 60, "observation": TEAMMAP,
        "frontier": {"action": {"goal": {"k": 8}}, "planner": "pocket"},
    },
    "goal-action-predicted": {
        "height": 12, "width": 14, "n_agents": 2, "max_steps": 60,
        "observation": {"teammap": {**TEAMMAP["teammap"], "predicted": True}},
        "frontier": {"action": {"goal": {"k": 8}}, "planner": "pocket", "prior": _half},
    },
}  # fmt: skip


@pytest.mark.parametrize("kwargs", list(KINDS.values()), ids=list(KINDS))
def test_parallel_api_conformance(kwargs):
    parallel_api_test(coverage_v0.parallel_env(**kwargs), num_cycles=100)


@pytest.mark.parametrize("kwargs", list(KINDS.values()), ids=list(KINDS))
def test_aec_api_conformance(kwargs):
    api_test(coverage_v0.env(**kwargs), num_cycles=20)


def test_the_goal_actions_mask_is_pettingzoos_int8_and_samples_only_candidates():
    env = coverage_v0.parallel_env(**KINDS["goal-action"])
    obs, _ = env.reset(seed=2)
    space = env.observation_space("agent_0")["action_mask"]
    assert space.dtype == np.int8 and space.shape == (8,)
    for agent, o in obs.items():
        mask = o["action_mask"]
        assert mask.dtype == np.int8 and space.contains(mask)
        for _ in range(20):  # Gymnasium's masked sample refuses any dtype but int8
            assert mask[env.action_space(agent).sample(mask)] == 1


@pytest.mark.parametrize(
    "action",
    [1.5, 2.0, "up", None, math.nan, np.float32(1.0), True, np.array([1, 2]), 5, -1],
    ids=["float", "integral-float", "str", "none", "nan", "np-float", "bool", "array", "5", "-1"],
)
def test_an_action_that_is_not_an_integer_of_the_space_names_the_agent_and_what_is_allowed(
    action,
):
    env = coverage_v0.parallel_env(height=8, width=8, n_agents=2, max_steps=10)
    env.reset(seed=0)
    before = env.positions
    shown = "an array of shape (2,)" if isinstance(action, np.ndarray) else repr(action)
    if isinstance(action, np.generic):
        shown = repr(action.item())
    with pytest.raises(ValueError, match=r"actions must be in 0\.\.4 \(integers\)") as err:
        env.step({"agent_0": 1, "agent_1": action})
    assert str(err.value).endswith("for agent_1") and shown in str(err.value)
    assert env.steps == 0 and np.array_equal(env.positions, before)  # nothing was stepped


def test_python_and_numpy_integers_stay_actions():
    env = coverage_v0.parallel_env(height=8, width=8, n_agents=2, max_steps=10)
    env.reset(seed=0)
    for a, b in [(4, np.int64(3)), (np.uint8(2), np.int32(1)), (np.array(0), 4)]:
        env.step({"agent_0": a, "agent_1": b})
    assert env.steps == 3


def test_the_core_refuses_a_float_batch_by_its_dtype_naming_the_copy():
    from envs.coverage.core import CoreSpec, CoverageCore

    core = CoverageCore(CoreSpec.parse(height=6, width=6, n_agents=2, max_steps=5), copies=3)
    for copy in range(3):
        core.reset(copy, seed=copy)
    # A float batch is refused by its dtype (even its integral values), an integer one by range.
    with pytest.raises(ValueError, match=r"got 0\.0 for agent_0 of copy 0"):
        core.step(np.array([0, 1, 2, 0.5, 4, 0]))
    with pytest.raises(ValueError, match=r"in 0\.\.4 \(integers\), got 7 for agent_1 of copy 1"):
        core.step(np.array([0, 1, 2, 7, 4, 0]))
    with pytest.raises(ValueError, match=r"expected 6 actions \(3 copies x 2 agents\)"):
        core.step(np.zeros(5, dtype=np.int64))
    core.step(np.zeros((3, 2), dtype=np.int32))  # any integer dtype
    assert core.steps.tolist() == [1, 1, 1]


@pytest.mark.parametrize("options", ["abc", [("grid", None)], 3])
def test_reset_options_that_are_not_a_dict_are_refused_by_name(options):
    env = coverage_v0.parallel_env(height=8, width=8, n_agents=2, max_steps=10)
    with pytest.raises(ValueError, match=r"options must be a dict .* or None, got "):
        env.reset(options=options)


def test_actions_that_are_not_a_dict_are_refused():
    env = coverage_v0.parallel_env(height=8, width=8, n_agents=2, max_steps=10)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="actions must be a dict of agent name to action"):
        env.step([0, 1])


def test_an_action_for_a_misspelt_agent_is_refused_by_name():
    env = coverage_v0.parallel_env(height=8, width=8, n_agents=2, max_steps=10)
    env.reset(seed=0, options={"starts": [(1, 1), (2, 2)]})
    with pytest.raises(ValueError, match=r"an action for 'agent_O', which is no agent"):
        env.step({"agent_0": 4, "agent_1": 4, "agent_O": 0})
    env.step({"agent_0": 4, "agent_1": 4})
    assert env.unwrapped._core.steps.tolist() == [1]  # the refused call stepped nothing


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
