"""Envs as the community writes them (issue 72): ParallelEnvs that pass PettingZoo's own
``parallel_api_test`` yet define no ``render_mode`` or ``metadata``, and envs whose agents leave
mid-episode (knights_archers_zombies' style), trained and evaluated through the commands
(docs/your-own-env.md). The envs are this file's own: configs name them by import path."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.test import parallel_api_test

from harness.cli import main
from tests.conftest import root_first_env

ROOT = Path(__file__).resolve().parents[1]


class BareEnv(ParallelEnv):
    """Two agents count to ``max_steps``: no ``render_mode`` and no ``metadata`` of its own
    (the class attributes PettingZoo's base class declares are removed below)."""

    def __init__(self, max_steps: int = 10) -> None:
        self.possible_agents = ["agent_0", "agent_1"]
        self.max_steps = max_steps
        self._observation = spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float32)
        self._action = spaces.Discrete(2)

    def observation_space(self, agent: str) -> spaces.Space:
        return self._observation

    def action_space(self, agent: str) -> spaces.Space:
        return self._action

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        self.agents, self.t = list(self.possible_agents), 0
        return self._observe(), {a: {} for a in self.agents}

    def _ends(self, agent: str) -> tuple[bool, bool]:
        """(terminated, truncated) of ``agent`` after step ``t``."""
        return False, self.t >= self.max_steps

    def step(self, actions: dict[str, Any]) -> tuple[dict[str, Any], ...]:
        self.t += 1
        agents = list(self.agents)
        obs = self._observe(agents)
        rewards = {a: float(actions[a]) for a in agents}  # action 1 earns 1
        ends = {a: self._ends(a) for a in agents}
        terms = {a: ends[a][0] for a in agents}
        truncs = {a: ends[a][1] for a in agents}
        self.agents = [a for a in agents if not any(ends[a])]
        return obs, rewards, terms, truncs, {a: {"t": self.t} for a in agents}

    def _observe(self, agents: list[str] | None = None) -> dict[str, np.ndarray]:
        phase = min(self.t / self.max_steps, 1.0)
        return {
            a: np.array([phase, i], np.float32)
            for i, a in enumerate(self.possible_agents)
            if agents is None or a in agents
        }


class LeavingEnv(BareEnv):
    """:class:`BareEnv` whose ``agent_1`` terminates at step ``leaves`` and leaves ``agents``,
    while ``agent_0`` goes on until the time limit; with a ``metadata`` and ``render_mode``."""

    metadata = {"name": "leaving_v0", "render_modes": []}  # noqa: RUF012

    def __init__(self, max_steps: int = 10, leaves: int = 3) -> None:
        super().__init__(max_steps)
        self.leaves, self.render_mode = leaves, None

    def _ends(self, agent: str) -> tuple[bool, bool]:
        if agent == "agent_1":
            return self.t >= self.leaves, False
        return False, self.t >= self.max_steps


def bare(**kwargs: Any) -> BareEnv:
    """A :class:`BareEnv` without ``render_mode`` or ``metadata`` anywhere."""
    env = BareEnv(**kwargs)
    assert not hasattr(env, "render_mode") and not hasattr(env, "metadata")
    return env


def leaving(**kwargs: Any) -> LeavingEnv:
    return LeavingEnv(**kwargs)


def config(tmp_path: Path, make: str) -> Path:
    """A tiny config of one of this file's envs."""
    raw = {
        "name": make,
        "seed": 0,
        "env": {"pettingzoo": {"make": f"tests.test_community_envs:{make}", "kwargs": {}}},
        "vec": {"copies": 2},
        "algo": {
            "net_arch": [16],
            "buffer_size": 2000,
            "learning_starts": 100,
            "target_update_interval": 200,
        },
        "phases": [
            {
                "name": "initial",
                "timesteps": 400,
                "learning_rate": 1.0e-3,
                "exploration": {"start": 1.0, "end": 0.1, "steps": 200},
                "epochs": [[0.0, 1]],
            }
        ],
        "eval": {"every": 400, "episodes": 2},
        "checkpoint": {"every": 400},
    }
    path = tmp_path / f"{make}.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.fixture(autouse=True)
def _importable(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", root_first_env()["PYTHONPATH"])


@pytest.mark.parametrize("make", [bare, leaving])
def test_the_envs_pass_pettingzoos_own_api_test(make):
    parallel_api_test(make(), num_cycles=20)


def test_an_env_without_render_mode_or_metadata_trains_and_evaluates(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["run", str(config(tmp_path, "bare")), "--no-progress", "--into", str(run)]) == 0
    assert main(["eval", str(run), "--episodes", "2"]) == 0
    saved = json.loads((run / "eval-2ep.json").read_text())
    assert saved["length_mean"] == 10


def test_an_agent_that_left_keeps_its_slot_with_zeros_until_the_episode_ends(tmp_path):
    from harness.config.loading import load_config
    from harness.training.adapters import make_vec_env

    env = load_config(config(tmp_path, "leaving")).env
    venv = make_vec_env(env, copies=1, seed=0, backend="supersuit")
    venv.reset()
    for step in range(1, 11):
        obs, rewards, dones, infos = venv.step(np.array([1, 1]))
        gone = step > 3 and step < 10  # agent_1 left at step 3 (step 10: the next episode's)
        assert (obs[1] == 0).all() == gone and rewards.tolist() == [1.0, float(step <= 3)]
        assert dones.tolist() == [step == 10] * 2  # one end for both slots: the episode's
    assert [info["episode"]["r"] for info in infos] == [10.0, 3.0]
    assert "TimeLimit.truncated" not in infos[1]  # it terminated: no time-out to bootstrap
    venv.close()


def test_agents_that_leave_train_and_count_only_their_own_steps(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["run", str(config(tmp_path, "leaving")), "--no-progress", "--into", str(run)]) == 0
    with (run / "episodes.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert rows and all(row["length"] == "10" for row in rows)  # one row per episode
    for row in rows:  # agent_1 earns only in its 3 steps
        first, second = (float(r) for r in row["returns"].split(";"))
        assert 0 <= first <= 10 and 0 <= second <= 3
    # The random baseline takes action 1 (1 point) half the time: agent_1 earns at most 3.
    assert main(["eval", str(run), "--episodes", "4"]) == 0
    saved = json.loads((run / "eval-4ep.json").read_text())
    returns = {row["agent"]: row["return_mean"] for row in saved["per_agent"]}
    assert 0 <= returns["agent_1"] <= 3 and 0 <= returns["agent_0"] <= 10
    assert saved["length_mean"] == 10
    # Each agent's infos are those of its own last step: agent_1's of step 3.
    assert {row["agent"]: row["t_mean"] for row in saved["per_agent"]} == {
        "agent_0": 10,
        "agent_1": 3,
    }
