"""Both VecEnv backends (the batched core's and SuperSuit's): slots, seeding, truncation as a
time-out, episode info."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from harness.config.schema import EnvConfig
from harness.training.adapters import make_vec_env
from tests.conftest import group_left, spawn

SMALL = EnvConfig(height=8, width=9, n_agents=2, max_steps=6, coords="raw")


@pytest.fixture(params=["core", "supersuit"])
def backend(request) -> str:
    return request.param


def run_until_done(venv, rng):
    venv.reset()
    for _ in range(SMALL.max_steps):
        obs, rewards, dones, infos = venv.step(rng.integers(0, 5, venv.num_envs))
    return obs, rewards, dones, infos


@pytest.mark.parametrize(("copies", "n_agents"), [(1, 1), (3, 2), (2, 4)])
def test_one_slot_per_agent_per_copy(copies, n_agents, backend):
    env = SMALL.model_copy(update={"n_agents": n_agents})
    venv = make_vec_env(env, copies=copies, seed=0, backend=backend)
    assert venv.num_envs == n_agents * copies
    assert venv.reset().shape == (n_agents * copies, 13)
    venv.close()


def test_slots_are_agent_major_within_copies(backend):
    venv = make_vec_env(SMALL, copies=2, seed=3, backend=backend)
    obs = venv.reset()
    # Slot 2k+1's teammate is slot 2k (two agents per copy): positions cross-reference.
    for copy in range(2):
        a, b = obs[2 * copy], obs[2 * copy + 1]
        np.testing.assert_array_equal(a[11:13], b[9:11])
        np.testing.assert_array_equal(b[11:13], a[9:11])
    venv.close()


def test_seeded_copies_differ_from_each_other_and_repeat(backend):
    first = make_vec_env(SMALL, copies=3, seed=11, backend=backend).reset()
    second = make_vec_env(SMALL, copies=3, seed=11, backend=backend).reset()
    np.testing.assert_array_equal(first, second)
    assert not np.array_equal(first[0:2], first[2:4])  # copies get different episodes
    other = make_vec_env(SMALL, copies=3, seed=12, backend=backend).reset()
    assert not np.array_equal(first, other)


def test_seeding_does_not_depend_on_process_count():
    in_process = make_vec_env(SMALL, copies=3, seed=5)  # the core
    two_procs = make_vec_env(SMALL, copies=3, seed=5, num_cpus=2, backend="supersuit")
    try:
        np.testing.assert_array_equal(in_process.reset(), two_procs.reset())
        actions = np.arange(6) % 5
        for _ in range(SMALL.max_steps + 2):  # across an automatic reset too
            a = in_process.step(actions)
            b = two_procs.step(actions)
            np.testing.assert_array_equal(a[0], b[0])
            np.testing.assert_array_equal(a[1], b[1])
    finally:
        in_process.close()
        two_procs.close()


def test_truncation_reaches_sb3_as_a_timeout_with_episode_metrics(backend):
    venv = make_vec_env(SMALL, copies=2, seed=0, backend=backend)
    _, _, dones, infos = run_until_done(venv, np.random.default_rng(0))
    assert dones.all()
    for info in infos:
        assert info["TimeLimit.truncated"] is True
        assert info["terminal_observation"].shape == (13,)
        episode = info["episode"]
        assert episode["l"] == SMALL.max_steps
        assert 0.0 < episode["coverage"] <= 1.0
        assert {"new_cells", "wall_hits"} <= set(episode)
    venv.close()


def test_final_coverage_is_not_hidden_by_the_automatic_reset(backend):
    # SuperSuit merges reset infos over the last step's infos; the env's reset infos are empty
    # so the episode's final coverage survives.
    venv = make_vec_env(SMALL, copies=1, seed=0, backend=backend)
    rng = np.random.default_rng(1)
    venv.reset()
    coverages = []
    for _ in range(SMALL.max_steps):
        _, _, dones, infos = venv.step(rng.integers(0, 5, venv.num_envs))
        coverages.append(infos[0]["coverage"])
    assert dones.all()
    assert infos[0]["episode"]["coverage"] == coverages[-1] == max(coverages)
    venv.close()


def test_the_goal_actions_int8_mask_reaches_sb3_as_the_env_gives_it(backend):
    # The env follows PettingZoo (int8), and the models take the mask as it comes (the goal
    # references, saved with a float32 one, were migrated: research/performance-history.md): the
    # VecEnv, its terminal observations and the model checks all keep the env's form.
    from harness.config.loading import config_from_dict
    from harness.factory import make_env
    from harness.training.checks import _slot_spaces

    goal = {
        "height": 10, "width": 12, "n_agents": 2, "max_steps": 4,
        "observation": {"teammap": {"crop": 7, "global_size": 6}},
        "frontier": {"action": {"goal": {"k": 4}}, "planner": "pocket"},
    }  # fmt: skip
    env_space = make_env(goal).observation_space("agent_0")
    assert env_space["action_mask"].dtype == np.int8
    venv = make_vec_env(goal, copies=2, seed=0, backend=backend)
    assert venv.observation_space == env_space
    obs = venv.reset()
    assert obs["action_mask"].dtype == np.int8 and obs["action_mask"].shape == (4, 4)
    for _ in range(goal["max_steps"]):
        obs, _, dones, infos = venv.step(np.zeros(venv.num_envs, dtype=np.int64))
    assert dones.all() and obs["action_mask"].dtype == np.int8
    assert all(i["terminal_observation"]["action_mask"].dtype == np.int8 for i in infos)
    venv.close()
    # The model's slot spaces the memory checks size (the replay buffer holds int8 masks).
    config = config_from_dict({"env": goal, "algo": {"policy": "SlotTeamMapPolicy"}})
    assert _slot_spaces(config)[0] == venv.observation_space


#: A process that starts SuperSuit env workers and ends without closing them, as a second
#: Ctrl-C that lands in training's cleanup leaves it.
UNCLOSED_WORKERS = (
    "import sys\n"
    "from harness.config.schema import EnvConfig\n"
    "from harness.training.adapters import make_vec_env\n"
    "venv = make_vec_env(EnvConfig(height=8, width=9, n_agents=2, max_steps=6), copies=2,\n"
    "                    num_cpus=2, seed=0, backend='supersuit')\n"
    "venv.reset()\n"
    "print(*(proc.pid for proc in venv.unwrapped.procs), flush=True)\n"
    "sys.exit(130)\n"
)


def test_env_workers_left_unclosed_end_with_their_process():
    # multiprocessing's exit waits for every child that is not a daemon: the workers, waiting
    # for an instruction that never comes, would hold the process there for ever.
    proc = spawn([sys.executable, "-c", UNCLOSED_WORKERS], stdout=subprocess.PIPE, text=True)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130 and len(out.split()) == 2
    assert not group_left(proc)
