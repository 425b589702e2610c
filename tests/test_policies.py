"""DuelingDQNPolicy: shapes, aggregation identities, net_arch forms, save/load."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.utils import ConstantSchedule
from torch import nn

from harness import DoubleDQN, DuelingDQNPolicy
from harness.sb3.policies import DuelingHead, DuelingQNetwork

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
