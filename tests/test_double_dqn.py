"""DoubleDQN: hand-computed updates, prioritized training, per-slot exploration, save/load, and
the SB3 layer's independence of the env."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import ConstantSchedule, LinearSchedule, set_random_seed
from stable_baselines3.common.vec_env import DummyVecEnv

import harness.sb3.dqn
import harness.sb3.losses
import harness.sb3.targets
from harness import DoubleDQN, DuelingDQNPolicy, PrioritizedReplayBuffer
from harness.sb3.losses import LossOptions
from tests.replay_variants import DevicePrioritizedReplayBuffer

S = np.array([[1.0, 0.0]], dtype=np.float32)  # state s
S_NEXT = np.array([[0.0, 1.0]], dtype=np.float32)  # next state s'
# Linear Q-networks Q(x) = W x (net_arch=[], zero bias); column 0 acts on s, column 1 on s'.
# Online: Q(s) = [0, 0], Q(s') = [2, 1] -> argmax_a Q_online(s', a) = 0.
# Target: Q(s') = [0, 3] -> Double-Q bootstraps with Q_target(s', 0) = 0, plain DQN with 3.
W_ONLINE = [[0.0, 2.0], [0.0, 1.0]]
W_TARGET = [[0.0, 0.0], [0.0, 3.0]]
GAMMA = 0.5


class TinyEnv(gym.Env):
    """Random 2-d observations, ``n_actions`` actions, reward for action 0, 10-step episodes."""

    def __init__(self, n_actions: int = 2) -> None:
        self.observation_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.action_space = spaces.Discrete(n_actions)
        self._t = 0

    def _obs(self) -> np.ndarray:
        return self.np_random.uniform(-1, 1, size=2).astype(np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._t = 0
        return self._obs(), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self._t += 1
        return self._obs(), float(action == 0), False, self._t >= 10, {}


def set_linear_weights(model: DQN, online: list[list[float]], target: list[list[float]]) -> None:
    for net, weights in ((model.q_net, online), (model.q_net_target, target)):
        layer = net.q_net[0]
        assert isinstance(layer, th.nn.Linear)
        with th.no_grad():
            layer.weight.copy_(th.tensor(weights))
            layer.bias.zero_()


LOSS_KEYS = ("double_q", "expert_action", "margin", "margin_weight")


def with_loss(kwargs: dict[str, Any]) -> dict[str, Any]:
    """``kwargs`` with DoubleDQN's loss options (``double_q=``, ``margin=``, ...) grouped into
    its ``loss`` argument, a :class:`LossOptions`."""
    options = {key: kwargs.pop(key) for key in LOSS_KEYS if key in kwargs}
    return {**kwargs, "loss": LossOptions(**options)} if options else kwargs


def make_linear_model(cls: type[DQN] = DoubleDQN, **kwargs: Any) -> DQN:
    """A model whose Q-networks are single Linear layers and whose updates change nothing."""
    kwargs = {
        "policy_kwargs": dict(net_arch=[]),
        "learning_rate": 0.0,  # the loss is computed but the weights stay as set
        "gamma": GAMMA,
        "buffer_size": 2,
        "device": "cpu",
        "seed": 0,
        **kwargs,
    }
    model = cls("MlpPolicy", DummyVecEnv([TinyEnv]), **with_loss(kwargs))
    model.set_logger(configure(folder=None, format_strings=[]))
    set_linear_weights(model, W_ONLINE, W_TARGET)
    return model


def add_transition(model: DQN, reward: float, action: int = 1) -> None:
    assert model.replay_buffer is not None
    model.replay_buffer.add(
        S, S_NEXT, np.array([[action]]), np.array([reward]), np.array([False]), [{}]
    )


def logged(model: DQN, key: str) -> float:
    return model.logger.name_to_value[key]


# ------------------------------------------------------------------------- training targets


def test_double_q_update_hand_computed() -> None:
    model = make_linear_model(double_q=True)
    add_transition(model, reward=1.0)
    model.train(gradient_steps=1, batch_size=4)
    # target = 1 + 0.5 * Q_target(s', argmax Q_online(s')) = 1 + 0.5 * 0 = 1; Q(s, 1) = 0
    # Huber(0 - 1) = 0.5 * 1**2 = 0.5
    assert logged(model, "train/loss") == pytest.approx(0.5)
    assert logged(model, "train/mean_td_error") == pytest.approx(1.0)
    assert logged(model, "train/n_updates") == 1


def test_plain_target_reproduces_sb3() -> None:
    ours = make_linear_model(double_q=False)
    sb3 = make_linear_model(cls=DQN)
    for model in (ours, sb3):
        add_transition(model, reward=1.0)
        model.train(gradient_steps=1, batch_size=4)
    # target = 1 + 0.5 * max(0, 3) = 2.5; Huber(0 - 2.5) = 2.5 - 0.5 = 2.0
    assert logged(ours, "train/loss") == pytest.approx(2.0)
    assert logged(sb3, "train/loss") == pytest.approx(logged(ours, "train/loss"))


def test_default_optimizer_is_rmsprop_and_sb3_training_otherwise() -> None:
    model = make_linear_model(learning_rate=1e-3)
    assert isinstance(model.policy.optimizer, th.optim.RMSprop)
    assert type(model.replay_buffer) is ReplayBuffer
    add_transition(model, reward=1.0)
    before = model.q_net.q_net[0].weight.detach().clone()
    model.train(gradient_steps=2, batch_size=4)
    assert not th.equal(before, model.q_net.q_net[0].weight)
    assert model._n_updates == 2


def test_n_step_discounts_are_passed_through(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[Any] = []

    def spy(*args: Any) -> th.Tensor:
        seen.append(args[2])
        return harness.sb3.targets.double_q_target(*args)

    monkeypatch.setattr(harness.sb3.losses, "double_q_target", spy)
    model = make_linear_model(n_steps=2, buffer_size=8)
    assert type(model.replay_buffer).__name__ == "NStepReplayBuffer"
    for _ in range(3):
        add_transition(model, reward=1.0)
    model.train(gradient_steps=1, batch_size=16)
    (discounts,) = seen
    assert isinstance(discounts, th.Tensor)
    # gamma ** k with k = 2 steps, or 1 for the newest transition (cut at the buffer end)
    assert set(discounts.ravel().tolist()) <= {GAMMA, GAMMA**2}


# --------------------------------------------------------------------- prioritized training


def make_prioritized_model(
    buffer_class: type[PrioritizedReplayBuffer] = PrioritizedReplayBuffer, **kwargs: Any
) -> DQN:
    """The linear model with a prioritized buffer (the host's, or ``buffer_class``) holding two
    transitions of raw priorities 1 and 3."""
    model = make_linear_model(
        replay_buffer_class=buffer_class,
        replay_buffer_kwargs=dict(alpha=1.0, beta=1.0, eps=1.0),
        **kwargs,
    )
    add_transition(model, reward=1.0)  # flat index 0, TD error -1 (target = r, Q(s, 1) = 0)
    add_transition(model, reward=3.0)  # flat index 1, TD error -3
    buffer = model.replay_buffer
    assert isinstance(buffer, PrioritizedReplayBuffer)
    buffer.update_priorities(np.array([0, 1]), np.array([0.0, 2.0]))  # raw priorities 1 and 3
    return model


# The host path, and the device path on CPU tensors: the same update.
BUFFERS = pytest.mark.parametrize(
    "buffer_class", [PrioritizedReplayBuffer, DevicePrioritizedReplayBuffer], ids=["host", "device"]
)


@BUFFERS
def test_importance_weighted_loss_and_priority_update(
    buffer_class: type[PrioritizedReplayBuffer],
) -> None:
    model = make_prioritized_model(buffer_class)
    model.train(gradient_steps=1, batch_size=4)
    # Strata of width 1 over total 4: indices [0, 1, 1, 1]. P = [1/4, 3/4], N = 2, beta = 1:
    # w ∝ 1 / (N P) = [2, 2/3] -> normalised [1, 1/3]. Huber: 0.5 (TD 1) and 2.5 (TD 3).
    # loss = (1 * 0.5 + 3 * (1/3) * 2.5) / 4 = 0.75 (unweighted it would be 2.0)
    assert logged(model, "train/loss") == pytest.approx(0.75)
    assert logged(model, "train/beta") == 1.0
    # New raw priorities |TD| + eps
    np.testing.assert_allclose(model.replay_buffer.raw_priorities, [2.0, 4.0])  # type: ignore[union-attr]


@BUFFERS
def test_priorities_updated_after_every_gradient_step(
    monkeypatch: pytest.MonkeyPatch, buffer_class: type[PrioritizedReplayBuffer]
) -> None:
    model = make_prioritized_model(buffer_class)
    buffer = model.replay_buffer
    calls: list[str] = []
    sample, update = buffer.sample, buffer.update_priorities  # type: ignore[union-attr]

    def spy_sample(*args: Any, **kwargs: Any) -> Any:
        calls.append("sample")
        return sample(*args, **kwargs)

    def spy_update(indices: np.ndarray, td_errors: np.ndarray) -> None:
        calls.append("update")
        assert indices.shape == td_errors.shape == (4,)
        update(indices, td_errors)

    monkeypatch.setattr(buffer, "sample", spy_sample)
    monkeypatch.setattr(buffer, "update_priorities", spy_update)
    model.train(gradient_steps=3, batch_size=4)
    assert calls == ["sample", "update"] * 3
    assert model._n_updates == 3
    assert logged(model, "train/n_updates") == 3


# ----------------------------------------------------------------- per-slot epsilon-greedy


@pytest.fixture(scope="module")
def five_action_model() -> DoubleDQN:
    return DoubleDQN("MlpPolicy", DummyVecEnv([lambda: TinyEnv(5)]), device="cpu", seed=0)


def test_per_slot_exploration_fraction(five_action_model: DoubleDQN) -> None:
    model = five_action_model
    n_slots = 4000
    obs = np.random.default_rng(0).uniform(-1, 1, size=(n_slots, 2)).astype(np.float32)
    greedy, _ = model.predict(obs, deterministic=True)

    model.exploration_rate = 0.5
    set_random_seed(0)
    actions, _ = model.predict(obs)
    assert actions.shape == greedy.shape == (n_slots,)
    assert np.all((actions >= 0) & (actions < 5))
    deviating = np.mean(actions != greedy)
    # Each slot explores with prob 0.5 and a random action differs from the greedy one with
    # prob 4/5: expect 0.4. Std is sqrt(0.4 * 0.6 / 4000) ~ 0.0077, tolerance 5 std. SB3's
    # DQN.predict would give 0 or ~0.8 (one coin for the whole batch).
    assert deviating == pytest.approx(0.4, abs=0.04)

    # Reproducible from np.random's seed, which SB3 sets in set_random_seed.
    set_random_seed(0)
    np.testing.assert_array_equal(model.predict(obs)[0], actions)


def test_greedy_when_no_exploration(five_action_model: DoubleDQN) -> None:
    model = five_action_model
    obs = np.random.default_rng(1).uniform(-1, 1, size=(64, 2)).astype(np.float32)
    greedy, _ = model.predict(obs, deterministic=True)
    model.exploration_rate = 0.0
    np.testing.assert_array_equal(model.predict(obs)[0], greedy)
    model.exploration_rate = 1.0
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], greedy)


def test_single_observation_like_sb3(five_action_model: DoubleDQN) -> None:
    model = five_action_model
    single = np.zeros(2, dtype=np.float32)
    model.exploration_rate = 0.0
    action, _ = model.predict(single)
    assert np.shape(action) == ()
    model.exploration_rate = 1.0
    set_random_seed(3)
    actions = {int(model.predict(single)[0]) for _ in range(100)}
    assert actions == set(range(5))


class SpaceEnv(gym.Env):
    """Samples of any observation space, 2 actions (``predict``'s input only)."""

    def __init__(self, space: spaces.Space) -> None:
        self.observation_space = space
        self.action_space = spaces.Discrete(2)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        super().reset(seed=seed)
        self.observation_space.seed(seed)
        return self.observation_space.sample(), {}

    def step(self, action: int) -> Any:
        return self.observation_space.sample(), 0.0, False, False, {}


#: Observation spaces and the policy that reads them: a vector; a dict of a vector, a
#: channel-first uint8 image and a MultiBinary entry; a dict with a channel-last image (the
#: policy's space is SB3's transposed one, channel-first: SB3 transposes the observations).
PREDICT_SPACES = {
    "box": ("MlpPolicy", spaces.Box(-1.0, 1.0, (3,), np.float32)),
    "dict": (
        "MultiInputPolicy",
        spaces.Dict(
            {
                "vec": spaces.Box(-1.0, 1.0, (3,), np.float32),
                "img": spaces.Box(0, 255, (2, 36, 36), np.uint8),
                "bits": spaces.MultiBinary(4),
            }
        ),
    ),
    "channel_last": (
        "MultiInputPolicy",
        spaces.Dict(
            {
                "vec": spaces.Box(-1.0, 1.0, (3,), np.float32),
                "img": spaces.Box(0, 255, (36, 36, 3), np.uint8),
            }
        ),
    ),
}


def predict_model(name: str) -> tuple[DoubleDQN, Any]:
    policy, space = PREDICT_SPACES[name]
    env = DummyVecEnv([lambda: SpaceEnv(space)] * 3)
    model = DoubleDQN(policy, env, buffer_size=8, device="cpu", seed=0)
    env.seed(0)
    return model, env.reset()


@pytest.mark.parametrize("name", list(PREDICT_SPACES))
def test_greedy_actions_are_sb3s(name: str) -> None:
    # Without an action mask the greedy action is SB3's policy.predict's, for a batch and for
    # one observation, whatever the observation space.
    model, batch = predict_model(name)
    one = {k: v[0] for k, v in batch.items()} if isinstance(batch, dict) else batch[0]
    for obs in (batch, one):
        action, _ = model.predict(obs, deterministic=True)
        expected, _ = model.policy.predict(obs, deterministic=True)
        assert np.shape(action) == np.shape(expected) == ((3,) if obs is batch else ())
        np.testing.assert_array_equal(action, expected)


def test_an_observation_of_the_wrong_shape_gets_sb3s_error() -> None:
    model, obs = predict_model("dict")
    obs["bits"] = np.zeros((3, 5), dtype=np.int8)  # the first key: SB3 checks it
    with pytest.raises(ValueError, match="Unexpected observation shape"):
        model.predict(obs, deterministic=True)


# ---------------------------------------------------------------------- imitation loss
# (Invalid-action masking: tests/test_action_mask.py.)


def test_margin_loss_is_added_to_the_td_loss_hand_computed() -> None:
    model = make_linear_model(expert_action=1, margin=0.8, margin_weight=0.5)
    add_transition(model, reward=1.0)
    model.train(gradient_steps=1, batch_size=4)
    # TD: Huber(0 - 1) = 0.5 (as in test_double_q_update_hand_computed).
    # Margin: Q(s) = [0, 0], expert 1: max(0 + 0.8, 0) - 0 = 0.8, weighted 0.5 -> 0.4.
    assert logged(model, "train/loss") == pytest.approx(0.5 + 0.4)
    assert logged(model, "train/margin_loss") == pytest.approx(0.8)
    # argmax of the tie [0, 0] is action 0, not the expert's
    assert logged(model, "train/expert_agreement") == 0.0
    assert logged(model, "train/mean_td_error") == pytest.approx(1.0)  # the priorities' error


def _trained_greedy_actions(**kwargs: Any) -> np.ndarray:
    """Greedy actions on fresh observations after training on uniformly random actions in a
    3-action TinyEnv (reward 1 for action 0)."""
    set_random_seed(0)
    env = DummyVecEnv([lambda: TinyEnv(n_actions=3)])
    model = DoubleDQN(
        "MlpPolicy",
        env,
        policy_kwargs=dict(net_arch=[16]),
        learning_rate=1e-2,
        gamma=0.5,
        buffer_size=500,
        batch_size=32,
        device="cpu",
        seed=0,
        **with_loss(kwargs),
    )
    model.set_logger(configure(folder=None, format_strings=[]))
    assert model.replay_buffer is not None
    rng = np.random.default_rng(0)
    for _ in range(300):
        obs = rng.uniform(-1, 1, size=(1, 2)).astype(np.float32)
        action = int(rng.integers(3))
        model.replay_buffer.add(
            obs, obs, np.array([[action]]), np.array([float(action == 0)]), np.array([False]), [{}]
        )
    model.train(gradient_steps=300, batch_size=32)
    test_obs = rng.uniform(-1, 1, size=(50, 2)).astype(np.float32)
    actions, _ = model.predict(test_obs, deterministic=True)
    return actions


def test_margin_loss_makes_the_greedy_policy_follow_the_expert() -> None:
    # Without the loss the greedy policy takes the rewarded action 0; with a margin larger than
    # the TD evidence for action 0 (worth 1 more) it takes the expert's action 2.
    assert (_trained_greedy_actions() == 0).mean() > 0.9
    assert (_trained_greedy_actions(expert_action=2, margin=3.0) == 2).mean() > 0.9


def test_full_weight_margin_outweighs_any_evidence() -> None:
    # Action 0 is worth 1 more than the others, more than the margin of 0.2, yet at weight 1 the
    # margin term (gradient 1 on every sample) beats the Huber TD term (gradient <= 1 on the
    # third of the samples that took action 0): the expert's action stays greedy.
    assert (_trained_greedy_actions(expert_action=2, margin=0.2) == 2).mean() > 0.9


def test_small_weight_margin_gives_way_to_evidence() -> None:
    # The margin term pulls with a constant force (its weight) on every sample; the TD term
    # holds each action's value with at most (share of samples that took it) x (Huber slope).
    # Weight 0.05 against a third of the samples: the values move by about 0.15, less than the
    # evidence (1), so the rewarded action stays greedy.
    actions = _trained_greedy_actions(expert_action=2, margin=0.2, margin_weight=0.05)
    assert (actions == 0).mean() > 0.9
    # Weight 0.5 is above what the TD term can hold (1/3): the expert's action wins.
    actions = _trained_greedy_actions(expert_action=2, margin=0.2, margin_weight=0.5)
    assert (actions == 2).mean() > 0.9


def test_imitation_settings_are_saved_with_the_model(tmp_path: Path) -> None:
    make_linear_model(expert_action=1, margin=0.3, margin_weight=2.0).save(tmp_path / "m.zip")
    loaded = DoubleDQN.load(tmp_path / "m.zip", device="cpu")
    assert (loaded.expert_action, loaded.margin, loaded.margin_weight) == (1, 0.3, 2.0)
    assert make_linear_model().expert_action is None


def test_expert_action_must_be_an_action() -> None:
    with pytest.raises(ValueError, match="expert_action 2 is not an action of Discrete"):
        make_linear_model(expert_action=2)


# ------------------------------------------------------------------- schedules and options


def test_schedules_replaced_by_callback() -> None:
    class ReplaceSchedules(BaseCallback):
        def _on_training_start(self) -> None:
            self.model.exploration_schedule = ConstantSchedule(0.123)
            self.model.beta_schedule = LinearSchedule(0.5, 1.0, 1.0)  # type: ignore[attr-defined]

        def _on_step(self) -> bool:
            return True

    model = DoubleDQN(
        "MlpPolicy",
        make_vec_env(TinyEnv, n_envs=2, seed=0),
        replay_buffer_class=PrioritizedReplayBuffer,
        replay_buffer_kwargs=dict(alpha=0.6, beta=0.4),
        learning_starts=16,
        batch_size=8,
        device="cpu",
        seed=0,
    )
    assert model.beta_schedule(1.0) == 0.4  # default: constant initial beta
    model.learn(64, callback=ReplaceSchedules())
    assert model.exploration_rate == 0.123
    progress_remaining = model._current_progress_remaining
    assert model.replay_buffer.beta == pytest.approx(1.0 - 0.5 * progress_remaining)  # type: ignore[union-attr]
    assert model.replay_buffer.beta > 0.9  # type: ignore[union-attr]


def test_optimizer_resolution() -> None:
    env = DummyVecEnv([TinyEnv])
    kwargs = dict(optimizer_class="Adam", optimizer_kwargs=dict(eps=1e-5))
    model = DoubleDQN("MlpPolicy", env, policy_kwargs=kwargs, device="cpu")
    assert isinstance(model.policy.optimizer, th.optim.Adam)
    assert model.policy.optimizer.defaults["eps"] == 1e-5
    assert kwargs["optimizer_class"] == "Adam"  # the caller's dict is left alone

    model = DoubleDQN("MlpPolicy", env, policy_kwargs=dict(optimizer_class=th.optim.SGD))
    assert type(model.policy.optimizer) is th.optim.SGD
    with pytest.raises(ValueError, match="Adamm"):
        DoubleDQN("MlpPolicy", env, policy_kwargs=dict(optimizer_class="Adamm"))
    with pytest.raises(ValueError, match="Optimizer"):
        DoubleDQN("MlpPolicy", env, policy_kwargs=dict(optimizer_class=th.nn.Linear))


def test_save_load_round_trip(tmp_path: Path) -> None:
    env = DummyVecEnv([TinyEnv])
    model = DoubleDQN(
        "DuelingMlpPolicy",
        env,
        loss=LossOptions(double_q=False),
        replay_buffer_class=PrioritizedReplayBuffer,
        replay_buffer_kwargs=dict(alpha=0.7, beta=0.3),
        policy_kwargs=dict(
            net_arch={"value": [8], "advantage": [16]},
            aggregator="max",
            optimizer_class="Adam",
            optimizer_kwargs=dict(eps=1e-5),
        ),
        exploration_final_eps=0.02,
        device="cpu",
        seed=0,
    )
    # A closure installed by a callback must not break saving; it is not restored either.
    model.exploration_schedule = lambda _progress: 0.5
    model.save(tmp_path / "model")
    loaded = DoubleDQN.load(tmp_path / "model.zip", env=env, device="cpu")

    assert loaded.double_q is False
    assert type(loaded.policy) is DuelingDQNPolicy
    assert loaded.policy.aggregator == "max"
    assert loaded.policy.net_arch == {"value": [8], "advantage": [16]}
    assert type(loaded.policy.optimizer) is th.optim.Adam
    assert loaded.policy.optimizer.defaults["eps"] == 1e-5
    assert isinstance(loaded.replay_buffer, PrioritizedReplayBuffer)
    assert (loaded.replay_buffer.alpha, loaded.replay_buffer.beta) == (0.7, 0.3)
    assert loaded.beta_schedule(0.0) == 0.3
    assert isinstance(loaded.exploration_schedule, LinearSchedule)
    assert loaded.exploration_schedule(0.0) == 0.02
    obs = np.random.default_rng(0).uniform(-1, 1, size=(32, 2)).astype(np.float32)
    np.testing.assert_array_equal(
        loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0]
    )


def test_two_slot_smoke_training(tmp_path: Path) -> None:
    env = make_vec_env("CartPole-v1", n_envs=2, seed=0)
    model = DoubleDQN(
        "DuelingMlpPolicy",
        env,
        replay_buffer_class=PrioritizedReplayBuffer,
        replay_buffer_kwargs=dict(alpha=0.6, beta=0.4),
        policy_kwargs=dict(net_arch=[32, 32], aggregator="mean"),
        learning_rate=1e-3,
        buffer_size=1_000,
        learning_starts=100,
        batch_size=32,
        train_freq=4,
        gradient_steps=2,
        target_update_interval=100,
        device="cpu",
        seed=0,
    )
    model.learn(400)
    buffer = model.replay_buffer
    assert isinstance(buffer, PrioritizedReplayBuffer)
    assert buffer.n_transitions == 400
    # (400 - 100) / (4 steps * 2 envs) rollouts with 2 gradient steps each
    assert model._n_updates > 50
    assert np.unique(buffer.raw_priorities[:400]).size > 10  # TD errors were written back

    model.save(tmp_path / "smoke.zip")
    loaded = DoubleDQN.load(tmp_path / "smoke.zip", device="cpu")
    obs = env.reset()
    np.testing.assert_array_equal(
        loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0]
    )
    with th.no_grad():
        observations = th.as_tensor(np.stack([env.observation_space.sample() for _ in range(8)]))
        assert th.allclose(loaded.q_net(observations), model.q_net(observations))


# ---------------------------------------------------------------------------------- layering


def test_the_sb3_layer_imports_no_env_module() -> None:
    # A fresh interpreter: this test process has imported envs through other tests already.
    code = (
        "import harness.sb3.dqn, harness.sb3.policies, harness.sb3.buffers, harness.sb3.targets, "
        "harness.sb3.schedules, sys; "
        "print([m for m in sys.modules if m == 'envs' or m.startswith('envs.')])"
    )
    root = Path(__file__).resolve().parents[1]
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=True
    )
    assert result.stdout.strip() == "[]"
