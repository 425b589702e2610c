"""A tiny PettingZoo env of one's own, for the tests and docs/your-own-env.md: agents on a line
of ``size`` cells walk (left, stay, right) towards each other; each step every agent is
rewarded ``-spread`` (the team's spread, shared), and the episode ends after ``max_steps``."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv


class MeetEnv(ParallelEnv):
    metadata: ClassVar[dict] = {"name": "meet_v0", "render_modes": ["rgb_array"]}

    def __init__(self, n_agents=2, size=5, max_steps=10, render_mode=None):
        self.possible_agents = [f"walker_{i}" for i in range(n_agents)]
        self.size, self.max_steps, self.render_mode = size, max_steps, render_mode
        self._observation = spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float32)  # own, mean cell
        self._action = spaces.Discrete(3)  # left, stay, right

    def observation_space(self, agent):
        return self._observation  # one object for all agents: they share one network

    def action_space(self, agent):
        return self._action

    def _obs(self):
        mean = self.cells.mean() / (self.size - 1)
        return {
            a: np.array([c / (self.size - 1), mean], np.float32)
            for a, c in zip(self.agents, self.cells)
        }

    def reset(self, seed=None, options=None):
        self.rng = np.random.default_rng(seed)  # every draw of an episode comes from its seed
        self.agents, self.t = list(self.possible_agents), 0
        self.cells = self.rng.integers(0, self.size, len(self.agents))
        return self._obs(), {a: {} for a in self.agents}

    def step(self, actions):
        moves = np.array([actions[a] - 1 for a in self.agents])
        self.cells = np.clip(self.cells + moves, 0, self.size - 1)
        self.t += 1
        spread = int(self.cells.max() - self.cells.min())
        rewards = {a: -float(spread) for a in self.agents}
        done = self.t >= self.max_steps  # a time limit: truncation, not termination
        obs = self._obs()
        infos = {a: {"spread": spread, "cell": int(c)} for a, c in zip(self.agents, self.cells)}
        terms = {a: False for a in self.agents}
        truncs = {a: done for a in self.agents}
        if done:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    def render(self):
        frame = np.zeros((8, 8 * self.size, 3), np.uint8)
        for c in self.cells:
            frame[:, 8 * c : 8 * c + 8] = (255, 160, 0)
        return frame


def parallel_env(**kwargs):
    """The constructor a config names: ``tests.envs.meet:parallel_env``."""
    return MeetEnv(**kwargs)
