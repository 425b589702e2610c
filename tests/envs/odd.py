"""PettingZoo envs that break (or bend) the contract of docs/your-own-env.md, for the tests:
spaces that differ between agents, continuous actions, a Dict observation, an AEC env, a
constructor that fails, a module that fails to import (``tests.envs.broken``); one that
reports a ``coverage`` in its infos, and ones observed as an image or a 4-dimensional block."""

from __future__ import annotations

from gymnasium import spaces
from pettingzoo.utils.conversions import parallel_to_aec

from tests.envs.meet import MeetEnv


class _Spaces(MeetEnv):
    """:class:`MeetEnv` with the spaces given per agent."""

    def __init__(self, observation=None, action=None, **kwargs):
        super().__init__(**kwargs)
        self._per_agent_observation = observation or {}
        self._per_agent_action = action or {}

    def observation_space(self, agent):
        return self._per_agent_observation.get(agent, self._observation)

    def action_space(self, agent):
        return self._per_agent_action.get(agent, self._action)


def mixed_actions(**kwargs):
    """walker_1 has 4 actions where walker_0 has 3."""
    return _Spaces(action={"walker_1": spaces.Discrete(4)}, **kwargs)


def mixed_observations(**kwargs):
    """walker_1 observes 3 numbers where walker_0 observes 2."""
    return _Spaces(observation={"walker_1": spaces.Box(0.0, 1.0, (3,))}, **kwargs)


def padded(**kwargs):
    """:func:`mixed_actions` padded to one action space by SuperSuit, as the contract advises
    (walker_0's extra action acts as its last one)."""
    import supersuit

    return supersuit.pad_action_space_v0(mixed_actions(**kwargs))


def continuous(**kwargs):
    """Every agent's action is a Box (continuous)."""
    box = spaces.Box(-1.0, 1.0, (1,))
    return _Spaces(action={"walker_0": box, "walker_1": box}, **kwargs)


def dict_observation(**kwargs):
    """Every agent observes a Dict."""
    space = spaces.Dict({"cell": spaces.Discrete(5)})
    return _Spaces(observation={"walker_0": space, "walker_1": space}, **kwargs)


def aec(**kwargs):
    """The meet env as an AEC env (the harness converts it back with aec_to_parallel)."""
    return parallel_to_aec(MeetEnv(**kwargs))


def no_frames(**kwargs):
    """The meet env without rgb_array frames."""
    env = MeetEnv(**kwargs)
    env.metadata = {"name": "meet_v0", "render_modes": []}
    return env


def failing(**kwargs):
    """A constructor that raises."""
    raise RuntimeError("no such world")


not_callable = 42


class _Coverage(MeetEnv):
    """:class:`MeetEnv` whose infos also report ``coverage``: the share of cells a walker is on."""

    def step(self, actions):
        obs, rewards, terms, truncs, infos = super().step(actions)
        coverage = len(set(self.cells.tolist())) / self.size
        return (
            obs,
            rewards,
            terms,
            truncs,
            {a: {**i, "coverage": coverage} for a, i in infos.items()},
        )


def reports_coverage(**kwargs):
    """The meet env with a ``coverage`` in every agent's infos."""
    return _Coverage(**kwargs)


class _Shaped(MeetEnv):
    """:class:`MeetEnv` whose two numbers are observed as an array of ``shape``."""

    def __init__(self, shape, **kwargs):
        super().__init__(**kwargs)
        self.shape = shape
        self._observation = spaces.Box(0.0, 1.0, shape=shape, dtype=self._observation.dtype)

    def _observe(self):
        return {a: o.reshape(self.shape) for a, o in super()._observe().items()}


def image(**kwargs):
    """The meet env observed as a 1 x 2 image (one channel)."""
    return _Shaped((1, 2), **kwargs)


def block(**kwargs):
    """The meet env observed as a 1 x 1 x 1 x 2 block (4 dimensions)."""
    return _Shaped((1, 1, 1, 2), **kwargs)
