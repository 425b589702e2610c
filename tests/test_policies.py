"""DuelingDQNPolicy: shapes, aggregation identities, net_arch forms, save/load; the per-agent
policies' agent key and the features extractors' indifference to the action mask."""

from __future__ import annotations

import inspect
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import CombinedExtractor
from stable_baselines3.common.utils import ConstantSchedule
from torch import nn

from harness import DoubleDQN, DuelingDQNPolicy
from harness.sb3.policies import (
    ACTION_MASK_KEY,
    AGENT_KEY,
    DuelingHead,
    DuelingQNetwork,
    DuelingTeamMapPolicy,
    PerAgentDuelingMlpPolicy,
    PerAgentQNetwork,
    TeamMapExtractor,
    TeamMapPolicy,
    split_agent_id,
    without_action_mask,
    without_agent_id,
)

OBS_SPACE = spaces.Box(-1.0, 1.0, shape=(3, 2), dtype=np.float32)  # flattened to 6 features
N_ACTIONS = 5
ACTION_SPACE = spaces.Discrete(N_ACTIONS)


def make_policy(**kwargs: object) -> DuelingDQNPolicy:
    return DuelingDQNPolicy(OBS_SPACE, ACTION_SPACE, ConstantSchedule(1e-3), **kwargs)  # type: ignore[arg-type]


def streams(q_net: DuelingQNetwork, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """(V, A) computed from the network's own streams."""
    features = q_net.extract_features(obs, q_net.features_extractor)
    head = q_net.q_net
    assert isinstance(head, DuelingHead)
    return head.value_net(features), head.advantage_net(features)


def linear_sizes(module: nn.Module) -> list[tuple[int, int]]:
    return [(m.in_features, m.out_features) for m in module.modules() if isinstance(m, nn.Linear)]


@pytest.fixture
def obs() -> th.Tensor:
    return th.rand(7, *OBS_SPACE.shape, generator=th.Generator().manual_seed(0)) * 2 - 1


def test_output_shape_and_default_arch(obs: th.Tensor) -> None:
    policy = make_policy()
    assert isinstance(policy.q_net, DuelingQNetwork)
    assert isinstance(policy.q_net_target, DuelingQNetwork)
    assert policy.q_net_target is not policy.q_net
    assert policy.q_net(obs).shape == (7, N_ACTIONS)
    assert policy(obs).shape == (7,)  # greedy actions
    head = policy.q_net.q_net
    assert linear_sizes(head.value_net) == [(6, 64), (64, 64), (64, 1)]
    assert linear_sizes(head.advantage_net) == [(6, 64), (64, 64), (64, N_ACTIONS)]


def test_mean_aggregation_identity(obs: th.Tensor) -> None:
    q_net = make_policy(aggregator="mean").q_net
    q = q_net(obs)
    value, advantage = streams(q_net, obs)
    # Q = V + A - mean(A)  =>  mean_a Q = V
    assert th.allclose(q.mean(dim=1, keepdim=True), value, atol=1e-6)
    assert th.allclose(q, value + advantage - advantage.mean(dim=1, keepdim=True), atol=1e-6)


def test_max_aggregation_identity(obs: th.Tensor) -> None:
    q_net = make_policy(aggregator="max").q_net
    q = q_net(obs)
    value, advantage = streams(q_net, obs)
    # Q = V + A - max(A)  =>  max_a Q = V, reached at the greedy action
    assert th.allclose(q.max(dim=1, keepdim=True).values, value, atol=1e-6)
    assert th.equal(q.argmax(dim=1), advantage.argmax(dim=1))


def test_net_arch_list_and_dict() -> None:
    head = make_policy(net_arch=[16, 16, 16]).q_net.q_net
    assert linear_sizes(head.value_net) == [(6, 16), (16, 16), (16, 16), (16, 1)]
    assert linear_sizes(head.advantage_net) == [(6, 16), (16, 16), (16, 16), (16, N_ACTIONS)]

    head = make_policy(net_arch={"value": [8], "advantage": [12, 4]}).q_net.q_net
    assert linear_sizes(head.value_net) == [(6, 8), (8, 1)]
    assert linear_sizes(head.advantage_net) == [(6, 12), (12, 4), (4, N_ACTIONS)]


def test_invalid_arguments() -> None:
    with pytest.raises(ValueError, match="aggregator"):
        make_policy(aggregator="sum")
    with pytest.raises(ValueError, match="aggregator"):
        DuelingHead(4, 2, [8], aggregator="median")
    with pytest.raises(ValueError, match="value"):
        make_policy(net_arch={"value": [8], "adv": [8]})


def test_policy_save_load_keeps_aggregator(tmp_path: Path, obs: th.Tensor) -> None:
    policy = make_policy(aggregator="max", net_arch={"value": [8], "advantage": [12]})
    path = tmp_path / "policy.pt"
    policy.save(path)
    loaded = DuelingDQNPolicy.load(path, device="cpu")
    assert type(loaded) is DuelingDQNPolicy
    assert loaded.aggregator == "max"
    assert loaded.q_net.aggregator == "max"
    assert loaded.q_net.q_net.aggregator == "max"
    assert loaded.net_arch == {"value": [8], "advantage": [12]}
    with th.no_grad():
        assert th.allclose(loaded.q_net(obs), policy.q_net(obs))


def test_model_save_load_keeps_dueling_policy(tmp_path: Path) -> None:
    env = gym.make("CartPole-v1")
    model = DoubleDQN(
        "DuelingMlpPolicy",
        env,
        policy_kwargs=dict(net_arch=[16], aggregator="max"),
        learning_starts=0,
        device="cpu",
        seed=0,
    )
    model.save(tmp_path / "model.zip")
    loaded = DoubleDQN.load(tmp_path / "model.zip", device="cpu")
    assert type(loaded.policy) is DuelingDQNPolicy
    assert loaded.policy.aggregator == "max"
    assert isinstance(loaded.q_net, DuelingQNetwork)
    assert isinstance(loaded.q_net_target, DuelingQNetwork)
    observations = np.stack([env.observation_space.sample() for _ in range(16)])
    np.testing.assert_array_equal(
        loaded.predict(observations, deterministic=True)[0],
        model.predict(observations, deterministic=True)[0],
    )


# ------------------------------------------------------------ agent key and the action mask


def test_the_default_agent_key_is_the_envs_agent_indication() -> None:
    # The SB3 layer names the key itself (it imports nothing from envs); it must stay the key
    # under which the coverage env adds the agent's one-hot index.
    from envs.coverage.observations import AGENT_ID_KEY

    assert AGENT_KEY == AGENT_ID_KEY
    assert inspect.signature(PerAgentQNetwork).parameters["agent_key"].default == AGENT_KEY


def _agent_space(key: str) -> spaces.Dict:
    return spaces.Dict(
        {
            "vector": spaces.Box(-1.0, 1.0, (3,), np.float32),
            key: spaces.Box(0.0, 1.0, (2,), np.float32),
            ACTION_MASK_KEY: spaces.MultiBinary(N_ACTIONS),
        }
    )


def test_agent_key_selects_the_one_hot_entry() -> None:
    space = _agent_space("who")
    assert set(without_agent_id(space, 2, "who").spaces) == {"vector", ACTION_MASK_KEY}
    with pytest.raises(ValueError, match="'agent_id'"):
        without_agent_id(space, 2)  # the default key is not in this space
    obs = {"vector": th.zeros(3, 3), "who": th.eye(2)[[1, 0, 1]]}
    inner, agent = split_agent_id(obs, 2, "who")
    assert set(inner) == {"vector"}
    assert agent.tolist() == [1, 0, 1]
    # The vector form (the one-hot at the end) has no key: unchanged.
    inner, agent = split_agent_id(th.cat([th.ones(2, 3), th.eye(2)], dim=1), 2, "who")
    assert inner.shape == (2, 3) and agent.tolist() == [0, 1]  # type: ignore[union-attr]


def test_per_agent_policy_saves_its_agent_key(tmp_path: Path) -> None:
    policy = PerAgentDuelingMlpPolicy(
        _agent_space("who"), ACTION_SPACE, ConstantSchedule(1e-3),
        n_agents=2, agent_key="who", features_extractor_class=CombinedExtractor,
    )  # fmt: skip
    assert policy.q_net.agent_key == policy.q_net_target.agent_key == "who"
    policy.save(tmp_path / "policy.pt")
    loaded = PerAgentDuelingMlpPolicy.load(tmp_path / "policy.pt", device="cpu")
    assert loaded.agent_key == loaded.q_net.agent_key == "who"
    obs = {
        "vector": th.rand(4, 3),
        "who": th.eye(2)[[0, 1, 1, 0]],
        ACTION_MASK_KEY: th.ones(4, N_ACTIONS, dtype=th.int8),
    }
    with th.no_grad():
        th.testing.assert_close(loaded.q_net(obs), policy.q_net(obs))


def test_a_model_saved_without_an_agent_key_loads_with_the_default(tmp_path: Path) -> None:
    # Models saved before agent_key existed have policy_kwargs without it.
    class AgentEnv(gym.Env):
        observation_space = spaces.Dict(
            {"vector": spaces.Box(-1.0, 1.0, (3,), np.float32), AGENT_KEY: spaces.Box(0, 1, (2,))}
        )
        action_space = ACTION_SPACE

    model = DoubleDQN(
        "PerAgentTeamMapPolicy", AgentEnv(), policy_kwargs=dict(n_agents=2), device="cpu"
    )
    assert "agent_key" not in model.policy_kwargs
    model.save(tmp_path / "model.zip")
    loaded = DoubleDQN.load(tmp_path / "model.zip", device="cpu")
    assert isinstance(loaded.q_net, PerAgentQNetwork) and loaded.q_net.agent_key == AGENT_KEY


def test_team_map_extractor_is_built_without_the_action_mask() -> None:
    space = spaces.Dict(
        {
            "local": spaces.Box(0, 255, (2, 5, 5), np.uint8),
            "vector": spaces.Box(-1.0, 1.0, (3,), np.float32),
            ACTION_MASK_KEY: spaces.MultiBinary(N_ACTIONS),
        }
    )
    for policy_class in (TeamMapPolicy, DuelingTeamMapPolicy):
        policy = policy_class(space, ACTION_SPACE, ConstantSchedule(1e-3))
        for net in (policy.q_net, policy.q_net_target):
            assert isinstance(net.features_extractor, TeamMapExtractor)
            assert set(net.features_extractor.branches) == {"local", "vector"}
        obs = {
            "local": th.randint(0, 255, (2, 2, 5, 5), dtype=th.uint8),
            "vector": th.rand(2, 3),
            ACTION_MASK_KEY: th.tensor([[1, 0, 1, 0, 1], [0, 1, 0, 1, 0]], dtype=th.int8),
        }
        flipped = {**obs, ACTION_MASK_KEY: 1 - obs[ACTION_MASK_KEY]}
        with th.no_grad():
            th.testing.assert_close(policy.q_net(obs), policy.q_net(flipped), rtol=0, atol=0)
    # A space without a mask builds the same extractor as before.
    plain = spaces.Dict({k: v for k, v in space.spaces.items() if k != ACTION_MASK_KEY})
    assert without_action_mask(space) == plain
    assert without_action_mask(plain) is plain
    assert without_action_mask(OBS_SPACE) is OBS_SPACE
