"""The batched core gives the episodes of the env it replaced, and its two views agree.

* The PettingZoo env (the core's batch of one) reproduces, byte for byte, the seeded episodes
  recorded from the env before the core (``tests/trajectories.py``): every observation kind,
  planner and action kind, map mixes, fixed starts, team rewards, agent indication.
* The core's VecEnv and SuperSuit over the PettingZoo env give the same observations, rewards,
  dones and infos (``terminal_observation`` and ``TimeLimit.truncated`` included) for the same
  seeds and actions, across episode ends and automatic resets (hypothesis).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from envs.coverage import generators
from harness.training.adapters import CoreVecEnv, make_vec_env
from tests import trajectories


@pytest.mark.parametrize("name", sorted(trajectories.CASES))
def test_the_env_replays_the_recorded_episodes(name):
    recorded = json.loads(trajectories.PATH.read_text())
    assert trajectories.digest(*trajectories.CASES[name]) == recorded[name]


def _assert_same(a: Any, b: Any, where: str) -> None:
    if isinstance(a, dict):
        assert isinstance(b, dict) and sorted(a) == sorted(b), where
        for key in a:
            _assert_same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    else:
        assert a == b and type(a) is type(b), f"{where}: {a!r} != {b!r}"


_OBSERVATIONS: list[tuple[Any, Any]] = [
    ("thesis", None),
    ({"teammap": {"crop": 7, "global_size": 6}}, None),
    ({"teammap": {"crop": 7, "global_size": 6, "ego_size": 5}}, {}),
    ({"teammap": {"crop": 7, "global_size": 6}}, {"action": "step"}),
    ({"teammap": {"crop": 7, "global_size": 6}}, {"action": "step", "planner": "pocket"}),
    ({"teammap": {"crop": 7, "global_size": 6}}, {"action": "step", "planner": "minpos"}),
    ({"teammap": {"crop": 7, "global_size": 6}}, {"action": "step", "planner": "order"}),
    ({"teammap": {"crop": 7, "global_size": 6}}, {"action": "step", "planner": "hungarian"}),
    ({"teammap": {"crop": 7, "global_size": 6}}, {"action": "step", "planner": "utility"}),
    ({"teammap": {"crop": 7, "global_size": 6}}, {"action": "goal", "planner": "pocket"}),
    (
        {"teammap": {"crop": 7, "global_size": 6}},
        {"action": {"goal": {"k": 3, "hold": True}}, "planner": "order"},
    ),
]


@st.composite
def settings_(draw: st.DrawFn) -> dict[str, Any]:
    observation, frontier = draw(st.sampled_from(_OBSERVATIONS))
    n_agents = draw(st.integers(1, 4))
    if draw(st.booleans()):
        source: Any = generators.MixGenerator(
            [
                (2.0, generators.RandomMaps(draw(st.integers(6, 12)), draw(st.integers(6, 12)))),
                (1.0, generators.RandomMaps(draw(st.integers(6, 12)), draw(st.integers(6, 12)))),
            ]
        )
        kwargs: dict[str, Any] = {"map": source}
    else:
        kwargs = {"height": draw(st.integers(5, 12)), "width": draw(st.integers(5, 12))}
    kwargs.update(
        n_agents=n_agents,
        max_steps=draw(st.integers(3, 12)),
        observation=observation,
        frontier=frontier,
        coords=draw(st.sampled_from(["normalized", "raw"])),
        agent_id=draw(st.booleans()),
        rewards={"team": draw(st.sampled_from([0.0, 0.5]))},
    )
    return kwargs


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kwargs=settings_(), copies=st.integers(1, 3), seed=st.integers(0, 10_000))
def test_the_core_vecenv_equals_supersuit_over_the_pettingzoo_env(kwargs, copies, seed):
    core = make_vec_env(kwargs, copies, seed=seed, monitor=False, backend="core")
    ref = make_vec_env(kwargs, copies, seed=seed, monitor=False, backend="supersuit")
    assert isinstance(core.unwrapped, CoreVecEnv)
    assert core.observation_space == ref.observation_space
    assert core.action_space == ref.action_space and core.num_envs == ref.num_envs
    _assert_same(core.reset(), ref.reset(), "reset")
    rng = np.random.default_rng(seed)
    n_actions = int(core.action_space.n)
    for step in range(2 * kwargs["max_steps"] + 3):  # two episode ends and auto-resets
        actions = rng.integers(0, n_actions, core.num_envs)
        got, want = core.step(actions), ref.step(actions)
        for part, a, b in zip(("obs", "rewards", "dones", "infos"), got, want):
            if part == "dones":  # SuperSuit's are uint8, SB3's own VecEnvs' (and the core's) bool
                assert a.dtype == bool
                b = b.astype(bool)
            if part == "infos":
                for slot, (ia, ib) in enumerate(zip(a, b)):
                    _assert_same(ia, ib, f"step {step} slot {slot} info")
            else:
                _assert_same(a, b, f"step {step} {part}")
    core.close()
    ref.close()


def test_the_core_vecenv_seeds_per_copy_and_rejects_actions_out_of_range():
    kwargs = {"n_agents": 2, "height": 8, "width": 8, "max_steps": 5}
    venv = make_vec_env(kwargs, 3, monitor=False)
    venv.seed(7)
    first = venv.reset()
    again = make_vec_env(kwargs, 3, monitor=False)
    again.seed(7)
    np.testing.assert_array_equal(first, again.reset())
    # copy i is seeded with 7 + i: copy 1 of this batch is copy 0 of a batch seeded with 8
    other = make_vec_env(kwargs, 1, monitor=False)
    other.seed(8)
    np.testing.assert_array_equal(first[2:4], other.reset())
    with pytest.raises(ValueError, match=r"actions must be in 0\.\.4"):
        venv.step(np.array([0, 1, 2, 3, 4, 5]))
