"""The meet env with PettingZoo's action masks: a walker at an end of the line may not step off
it (docs/your-own-env.md's worked example)."""

import numpy as np
from gymnasium import spaces

from tests.envs.meet import MeetEnv


class MaskedMeetEnv(MeetEnv):
    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._observation = spaces.Dict(
            {"observation": self._observation, "action_mask": spaces.MultiBinary(3)}
        )

    def _mask(self, agent):
        cell = self.cells[self.possible_agents.index(agent)]
        return np.array([cell > 0, 1, cell < self.size - 1], np.int8)  # left, stay, right

    def _observe(self):
        plain = super()._observe()
        return {a: {"observation": o, "action_mask": self._mask(a)} for a, o in plain.items()}

    def step(self, actions):
        for agent, action in actions.items():
            if not self._mask(agent)[action]:  # the harness never plays a masked action
                raise ValueError(f"{agent}: action {action} is masked")
        return super().step(actions)


def parallel_env(**kwargs):
    return MaskedMeetEnv(**kwargs)
