"""Walkers on a line of cells meet: the tests' own PettingZoo env (docs/your-own-env.md)."""

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv


class MeetEnv(ParallelEnv):
    metadata = {"name": "meet_v0", "render_modes": ["rgb_array"]}  # noqa: RUF012

    def __init__(self, n_agents=2, size=5, max_steps=10, render_mode=None):
        self.possible_agents = [f"walker_{i}" for i in range(n_agents)]
        self.size, self.max_steps, self.render_mode = size, max_steps, render_mode
        self.rng = np.random.default_rng()
        self._observation = spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float32)  # own, mean cell
        self._action = spaces.Discrete(3)  # left, stay, right

    def observation_space(self, agent):
        return self._observation  # one space for every agent: they share one network

    def action_space(self, agent):
        return self._action

    def reset(self, seed=None, options=None):
        if seed is not None:  # seeded once; later resets continue the generator
            self.rng = np.random.default_rng(seed)
        self.agents, self.t = list(self.possible_agents), 0
        self.cells = self.rng.integers(0, self.size, len(self.agents))
        return self._observe(), {a: {} for a in self.agents}

    def step(self, actions):
        self.cells = np.clip(self.cells + [actions[a] - 1 for a in self.agents], 0, self.size - 1)
        self.t += 1
        spread = int(self.cells.max() - self.cells.min())
        rewards = {a: -float(spread) for a in self.agents}  # shared: the team's spread
        infos = {a: {"spread": spread, "cell": int(c)} for a, c in zip(self.agents, self.cells)}
        terms = {a: False for a in self.agents}
        truncs = {a: self.t >= self.max_steps for a in self.agents}  # a time limit: truncation
        obs = self._observe()
        if self.t >= self.max_steps:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    def _observe(self):
        mean = self.cells.mean() / (self.size - 1)
        return {
            a: np.array([c / (self.size - 1), mean], np.float32)
            for a, c in zip(self.possible_agents, self.cells)
        }

    def render(self):
        frame = np.zeros((8, 8 * self.size, 3), np.uint8)
        for c in self.cells:
            frame[:, 8 * c : 8 * c + 8] = (255, 160, 0)
        return frame


def parallel_env(**kwargs):
    return MeetEnv(**kwargs)
