"""The meet env as a community env may be written, all at once (issue 72): PettingZoo's action
masks (a walker at an end of the line may not step off it), a walker that leaves mid-episode
(the last one terminates at step ``leaves`` and is removed from ``agents``), and no
``render_mode``, ``metadata`` or ``render()`` of its own. It passes PettingZoo's
``parallel_api_test``; the harness trains it, and ``harness render`` refuses it in one line."""

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv


class MeetAllEnv(ParallelEnv):
    def __init__(self, n_agents=3, size=5, max_steps=10, leaves=4):
        self.possible_agents = [f"walker_{i}" for i in range(n_agents)]
        self.size, self.max_steps, self.leaves = size, max_steps, leaves
        self.rng = np.random.default_rng()
        self._observation = spaces.Dict(
            {
                "observation": spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float32),  # own, mean
                "action_mask": spaces.MultiBinary(3),
            }
        )
        self._action = spaces.Discrete(3)  # left, stay, right

    def observation_space(self, agent):
        return self._observation

    def action_space(self, agent):
        return self._action

    def reset(self, seed=None, options=None):
        if seed is not None:  # seeded once; later resets continue the generator
            self.rng = np.random.default_rng(seed)
        self.agents, self.t = list(self.possible_agents), 0
        cells = self.rng.integers(0, self.size, len(self.agents))
        self.cells = dict(zip(self.agents, cells.tolist()))
        return self._observe(self.agents), {a: {} for a in self.agents}

    def step(self, actions):
        agents = list(self.agents)
        for agent in agents:
            if not self._mask(agent)[actions[agent]]:  # the harness never plays a masked action
                raise ValueError(f"{agent}: action {actions[agent]} is masked")
            self.cells[agent] = self.cells[agent] + int(actions[agent]) - 1
        self.t += 1
        live = [self.cells[a] for a in agents]
        spread = max(live) - min(live)
        rewards = {a: -float(spread) for a in agents}  # shared: the spread of those still here
        infos = {a: {"spread": spread} for a in agents}
        leaving = self.possible_agents[-1]
        terms = {a: a == leaving and self.t >= self.leaves for a in agents}
        truncs = {a: self.t >= self.max_steps and not terms[a] for a in agents}
        obs = self._observe(agents)
        self.agents = [a for a in agents if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos

    def _mask(self, agent):
        cell = self.cells[agent]
        return np.array([cell > 0, 1, cell < self.size - 1], np.int8)  # left, stay, right

    def _observe(self, agents):
        mean = np.mean([self.cells[a] for a in agents]) / (self.size - 1)
        return {
            a: {
                "observation": np.array([self.cells[a] / (self.size - 1), mean], np.float32),
                "action_mask": self._mask(a),
            }
            for a in agents
        }


def parallel_env(**kwargs):
    return MeetAllEnv(**kwargs)
