"""DoubleDQN's invalid-action masking from a ``Dict`` observation's ``"action_mask"`` entry
(PettingZoo's convention), on a tiny env defined here: greedy and ε-random actions, the warm-up
actions, the TD targets, a mask that allows nothing, save/load, and no change without a mask."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import set_random_seed
from stable_baselines3.common.vec_env import DummyVecEnv

import harness.sb3.losses
import harness.sb3.targets
from harness.sb3.dqn import ACTION_MASK_KEY, DoubleDQN, allowed_actions
from harness.sb3.policies import PerAgentQNetwork, TeamMapExtractor
from tests.replay_variants import DevicePrioritizedDictReplayBuffer, PrioritizedDictReplayBuffer
from tests.test_double_dqn import with_loss

N_ACTIONS = 4
GAMMA = 0.5
# Biases of linear Q-networks (zero weights): the Q-values of every observation.
# Online Q = [8, 1, 5, 9]: action 3 is the best, then 0, then 2. (Not action 0: an argmax over
# a row of -inf gives 0, so a missing fallback for a mask that allows nothing would pass.)
Q_ONLINE = [8.0, 1.0, 5.0, 9.0]


def mask_space(kind: str) -> spaces.Space:
    if kind == "box":
        return spaces.Box(0.0, 1.0, shape=(N_ACTIONS,), dtype=np.float32)
    return spaces.MultiBinary(N_ACTIONS)


class MaskedEnv(gym.Env):
    """Observations ``{"obs": 2 numbers, "action_mask": which of 4 actions are allowed}``.

    Each action is allowed with probability 1/2 (at least one always is), and taking a
    disallowed one fails the test. The last observation of an episode (a truncation, so SB3
    bootstraps from it) allows nothing, as a PettingZoo env's final observation may.
    """

    def __init__(self, kind: str = "multibinary", with_mask: bool = True) -> None:
        entries: dict[str, spaces.Space] = {"obs": spaces.Box(-1.0, 1.0, (2,), np.float32)}
        if with_mask:
            entries[ACTION_MASK_KEY] = mask_space(kind)
        self.observation_space = spaces.Dict(entries)
        self.action_space = spaces.Discrete(N_ACTIONS)
        self.with_mask = with_mask
        self.dtype = self.observation_space.spaces.get(ACTION_MASK_KEY, spaces.MultiBinary(1)).dtype
        self._t = 0
        self._mask = np.ones(N_ACTIONS, dtype=self.dtype)

    def _obs(self, last: bool = False) -> dict[str, np.ndarray]:
        obs = {"obs": self.np_random.uniform(-1, 1, size=2).astype(np.float32)}
        if not self.with_mask:
            return obs
        mask = self.np_random.random(N_ACTIONS) < 0.5
        mask[self.np_random.integers(N_ACTIONS)] = True
        self._mask = np.zeros(N_ACTIONS) if last else mask
        obs[ACTION_MASK_KEY] = self._mask.astype(self.dtype)
        return obs

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        self._t = 0
        return self._obs(), {}

    def step(self, action: int) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        assert self._mask[action], f"action {action} is not allowed by {self._mask}"
        self._t += 1
        truncated = self._t >= 10
        return self._obs(last=truncated), float(action == 0), False, truncated, {}


def make_model(
    kind: str = "multibinary",
    n_envs: int = 3,
    q: list[float] | None = None,
    target_q: list[float] | None = None,
    with_mask: bool = True,
    **kwargs: Any,
) -> DoubleDQN:
    """A DoubleDQN on ``n_envs`` MaskedEnv slots; with ``q``, its networks are linear with zero
    weights, so that their Q-values are their biases: ``q`` online, ``target_q`` target."""
    env = DummyVecEnv([lambda: MaskedEnv(kind, with_mask)] * n_envs)
    settings: dict[str, Any] = {"device": "cpu", "seed": 0, "buffer_size": 64, **kwargs}
    if q is not None:
        settings = {"policy_kwargs": dict(net_arch=[]), "learning_rate": 0.0, **settings}
    model = DoubleDQN("MultiInputPolicy", env, gamma=GAMMA, **with_loss(settings))
    model.set_logger(configure(folder=None, format_strings=[]))
    if q is not None:
        for net, bias in ((model.q_net, q), (model.q_net_target, target_q or q)):
            layer = net.q_net[0]
            with th.no_grad():
                layer.weight.zero_()
                layer.bias.copy_(th.tensor(bias))
    return model


def observations(masks: list[list[int]], kind: str = "multibinary") -> dict[str, np.ndarray]:
    dtype = mask_space(kind).dtype
    obs = np.random.default_rng(0).uniform(-1, 1, size=(len(masks), 2)).astype(np.float32)
    return {"obs": obs, ACTION_MASK_KEY: np.array(masks, dtype=dtype)}


def logged(model: DoubleDQN, key: str) -> float:
    return model.logger.name_to_value[key]


# ----------------------------------------------------------------------------------- acting


@pytest.mark.parametrize("kind", ["multibinary", "box"])
def test_greedy_action_is_the_best_allowed_one(kind: str) -> None:
    model = make_model(kind, q=Q_ONLINE)
    assert model.masked
    masks = [
        [0, 1, 1, 0],  # 3 and 0 (the best two) not allowed: 2
        [1, 1, 1, 1],  # all allowed: 3
        [0, 1, 0, 0],  # only 1: 1
        [1, 1, 1, 0],  # 0
        [0, 0, 0, 0],  # nothing allowed: falls back to every action, 3
    ]
    obs = observations(masks, kind)
    expected = [2, 3, 1, 0, 3]
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], expected)
    model.exploration_rate = 0.0
    np.testing.assert_array_equal(model.predict(obs)[0], expected)  # the greedy part of ε-greedy
    single = {key: value[0] for key, value in obs.items()}
    action, _ = model.predict(single, deterministic=True)
    assert np.shape(action) == () and int(action) == 2
    # The network alone (SB3's greedy policy) would take action 3 everywhere.
    np.testing.assert_array_equal(model.policy.predict(obs, deterministic=True)[0], [3] * 5)


def test_greedy_evaluation_masks_as_predict_does() -> None:
    # harness eval's greedy policy is the model's own choice, masked (not SB3's policy.predict,
    # which would take action 3 everywhere).
    from harness.evaluation.episodes import model_policy

    model = make_model(q=Q_ONLINE)
    obs = observations([[0, 1, 1, 0], [1, 1, 1, 1], [0, 1, 0, 0], [1, 1, 1, 0], [0, 0, 0, 0]])
    np.testing.assert_array_equal(model_policy(model)(obs, []), [2, 3, 1, 0, 3])


def test_forced_rows_take_their_one_action_without_the_network(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    model = make_model(q=Q_ONLINE)
    seen: list[int] = []
    forward = type(model.q_net).forward

    def counting(net: Any, obs: Any) -> Any:
        seen.append(len(obs["obs"]))
        return forward(net, obs)

    monkeypatch.setattr(type(model.q_net), "forward", counting)
    masks = [[0, 1, 0, 0], [0, 1, 1, 0], [0, 0, 0, 1], [1, 1, 1, 1]]  # rows 0 and 2 are forced
    obs = observations(masks)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], [1, 2, 3, 3])
    assert seen == [2]  # the network saw the two rows with a choice
    seen.clear()
    forced = observations([[0, 1, 0, 0], [0, 0, 1, 0]])
    np.testing.assert_array_equal(model.predict(forced, deterministic=True)[0], [1, 2])
    assert seen == []  # no choice anywhere: no pass of the network


def test_random_actions_are_uniform_over_the_allowed_actions() -> None:
    model = make_model(q=Q_ONLINE)
    model.exploration_rate = 1.0
    n = 6000
    obs = observations([[1, 0, 1, 1]] * n)
    set_random_seed(0)
    actions, _ = model.predict(obs)
    shares = np.bincount(actions, minlength=N_ACTIONS) / n
    assert shares[1] == 0
    # Each allowed action 1/3; std of a share sqrt(1/3 * 2/3 / 6000) ~ 0.006: tolerance 5 std.
    np.testing.assert_allclose(shares[[0, 2, 3]], 1 / 3, atol=0.03)
    set_random_seed(0)
    np.testing.assert_array_equal(model.predict(obs)[0], actions)  # reproducible

    # Per slot: each slot draws among its own allowed actions, and every one of them comes up.
    masks = [[1, 0, 0, 1], [0, 1, 1, 0], [0, 0, 0, 0]] * 2000
    actions, _ = model.predict(observations(masks))
    assert set(actions[0::3]) == {0, 3}
    assert set(actions[1::3]) == {1, 2}
    assert set(actions[2::3]) == {0, 1, 2, 3}  # nothing allowed: uniform over every action


def test_one_exploration_coin_per_slot_with_a_mask() -> None:
    model = make_model(q=Q_ONLINE)
    model.exploration_rate = 0.5
    n = 4000
    obs = observations([[0, 1, 1, 0]] * n)  # greedy: 2; a random action is 1 or 2
    set_random_seed(1)
    actions, _ = model.predict(obs)
    assert set(actions) == {1, 2}
    # Each slot explores with prob 0.5 and then leaves the greedy action with prob 1/2: 0.25
    # (std ~0.007). One coin for the whole batch would give 0 or ~0.5.
    assert np.mean(actions != 2) == pytest.approx(0.25, abs=0.035)


def test_warm_up_actions_respect_the_mask() -> None:
    model = make_model(learning_starts=1_000)
    model._last_obs = observations([[0, 0, 1, 0], [1, 1, 0, 0], [0, 0, 0, 0]])  # type: ignore[assignment]
    drawn = np.array([model._sample_action(1_000, n_envs=3)[0] for _ in range(400)])
    assert set(drawn[:, 0]) == {2}
    assert set(drawn[:, 1]) == {0, 1}
    assert set(drawn[:, 2]) == {0, 1, 2, 3}  # nothing allowed: any action
    # After the warm-up the actions are predict's, masked as well.
    model.num_timesteps = 1_000
    model.exploration_rate = 1.0
    drawn = np.array([model._sample_action(1_000, n_envs=3)[0] for _ in range(400)])
    assert set(drawn[:, 0]) == {2}
    assert set(drawn[:, 1]) == {0, 1}


# ----------------------------------------------------------------------------------- targets


def test_allowed_actions_of_tensors_and_arrays() -> None:
    mask = [[0, 1, 1, 0], [0, 0, 0, 0], [1, 0, 0, 0]]
    expected = [[False, True, True, False], [True] * 4, [True, False, False, False]]
    tensor = allowed_actions({"obs": th.zeros(3, 2), ACTION_MASK_KEY: th.tensor(mask)}, 4)
    assert isinstance(tensor, th.Tensor) and tensor.dtype == th.bool
    assert tensor.tolist() == expected
    array = allowed_actions({ACTION_MASK_KEY: np.array(mask, dtype=np.float32)}, 4)
    assert isinstance(array, np.ndarray) and array.tolist() == expected
    assert allowed_actions({"obs": th.zeros(3, 2)}, 4) is None
    assert allowed_actions(th.zeros(3, 2), 4) is None


# Online Q(s') = [0, 3, 1, 2], target Q(s') = [3, 4, 1, 7]; r = 1, gamma = 0.5, and the
# transition's action 0 has Q(s, 0) = 0, so |TD error| = the target.
#   mask [1, 0, 1, 0]: Double-Q: online argmax over {0, 2} = 2, target value 1 -> 1.5;
#                      plain: max over {0, 2} = 3 -> 2.5.
#   mask [1, 1, 1, 1]: Double-Q: online argmax 1, target value 4 -> 3.0; plain: 7 -> 4.5.
#   mask [0, 0, 0, 0]: every action, as unmasked: 3.0 and 4.5 (an argmax over -inf would take
#                      action 0: 2.5; a max over -inf would be -inf).
#   mask [0, 0, 0, 0], terminal: the reward alone, 1.0 (not 0 * -inf = NaN).
@pytest.mark.parametrize(
    ("mask", "done", "double_q", "target"),
    [
        ([1, 0, 1, 0], False, True, 1.5),
        ([1, 0, 1, 0], False, False, 2.5),
        ([1, 1, 1, 1], False, True, 3.0),
        ([1, 1, 1, 1], False, False, 4.5),
        ([0, 0, 0, 0], False, True, 3.0),
        ([0, 0, 0, 0], False, False, 4.5),
        ([0, 0, 0, 0], True, True, 1.0),
        ([0, 0, 0, 0], True, False, 1.0),
    ],
)
def test_td_target_bootstraps_from_the_next_observations_allowed_actions(
    mask: list[int], done: bool, double_q: bool, target: float
) -> None:
    model = make_model(
        n_envs=1, q=[0.0, 3.0, 1.0, 2.0], target_q=[3.0, 4.0, 1.0, 7.0], double_q=double_q
    )
    assert model.replay_buffer is not None
    obs = observations([[1, 1, 1, 1]])
    next_obs = observations([mask])
    model.replay_buffer.add(
        obs, next_obs, np.array([[0]]), np.array([1.0]), np.array([done]), [{}]
    )  # fmt: skip
    model.train(gradient_steps=1, batch_size=4)
    assert logged(model, "train/mean_td_error") == pytest.approx(target)
    # Huber of |0 - target|: quadratic below 1, linear above
    huber = 0.5 * target**2 if target <= 1 else target - 0.5
    assert logged(model, "train/loss") == pytest.approx(huber)


def test_the_targets_get_the_negated_mask(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[th.Tensor | None] = []

    def spy(*args: Any) -> th.Tensor:
        seen.append(args[5])
        return harness.sb3.targets.double_q_target(*args)

    monkeypatch.setattr(harness.sb3.losses, "double_q_target", spy)
    model = make_model(n_envs=1, q=Q_ONLINE)
    assert model.replay_buffer is not None
    model.replay_buffer.add(
        observations([[1, 1, 1, 1]]), observations([[0, 1, 1, 0]]), np.array([[1]]),
        np.array([1.0]), np.array([False]), [{}],
    )  # fmt: skip
    model.train(gradient_steps=1, batch_size=2)
    (blocked,) = seen
    assert blocked is not None
    assert blocked.tolist() == [[True, False, False, True]] * 2


# ------------------------------------------------------------------------ training, save/load


@pytest.mark.parametrize(
    "buffer_class", [None, PrioritizedDictReplayBuffer, DevicePrioritizedDictReplayBuffer]
)
def test_training_takes_allowed_actions_only_and_the_loaded_model_keeps_masking(
    tmp_path: Path, buffer_class: type | None
) -> None:
    # MaskedEnv fails on any disallowed action: the warm-up actions, the ε-random ones and the
    # greedy ones are all checked, in every slot; each episode ends on an observation that
    # allows nothing, which the targets bootstrap from (a NaN there stops training).
    model = make_model(
        policy_kwargs=dict(net_arch=[16]),
        learning_starts=30,
        batch_size=16,
        train_freq=2,
        target_update_interval=20,
        exploration_fraction=0.5,
        replay_buffer_class=buffer_class,
        learning_rate=1e-3,
    )
    model.learn(240)
    assert model._n_updates > 0
    model.save(tmp_path / "masked.zip")
    loaded = DoubleDQN.load(tmp_path / "masked.zip", device="cpu")
    assert loaded.masked

    rng = np.random.default_rng(0)
    masks = (rng.random((400, N_ACTIONS)) < 0.5).astype(np.int8)
    masks[np.arange(400), rng.integers(N_ACTIONS, size=400)] = 1
    obs = {"obs": rng.uniform(-1, 1, (400, 2)).astype(np.float32), ACTION_MASK_KEY: masks}
    actions, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(actions, model.predict(obs, deterministic=True)[0])
    assert masks[np.arange(400), actions].all()
    # Not vacuous: the unmasked greedy action is disallowed in many of these observations.
    unmasked, _ = loaded.policy.predict(obs, deterministic=True)
    assert (masks[np.arange(400), unmasked] == 0).sum() > 50


def test_a_model_saved_with_the_retired_settings_loads(tmp_path: Path) -> None:
    # Models saved before the mask came from the observation hold `action_mask` (the wall mask's
    # switch) and `same_moves` in their data; SB3's load sets them on the model, unread.
    model = make_model(q=Q_ONLINE)
    model.action_mask = False  # type: ignore[attr-defined]
    model.same_moves = True  # type: ignore[attr-defined]
    model.save(tmp_path / "old.zip")
    loaded = DoubleDQN.load(tmp_path / "old.zip", device="cpu")
    assert loaded.action_mask is False  # type: ignore[attr-defined]
    assert loaded.masked
    obs = observations([[0, 1, 1, 0], [1, 1, 1, 1]])
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], [2, 3])


def test_a_mask_of_the_wrong_size_is_refused() -> None:
    class WrongMask(MaskedEnv):
        def __init__(self) -> None:
            super().__init__()
            self.observation_space = spaces.Dict(
                {"obs": self.observation_space["obs"], ACTION_MASK_KEY: spaces.MultiBinary(3)}
            )

    with pytest.raises(ValueError, match=r"'action_mask' observation must be a MultiBinary\(4\)"):
        DoubleDQN("MultiInputPolicy", DummyVecEnv([WrongMask]), device="cpu")


# ------------------------------------------------------------------------- network input


def test_the_mask_is_not_an_input_of_the_network() -> None:
    model = make_model(policy_kwargs=dict(net_arch=[8]))
    for net in (model.q_net, model.q_net_target):
        assert set(net.features_extractor.extractors) == {"obs"}  # type: ignore[union-attr]
        assert net.features_dim == 2
    obs = observations([[1, 0, 1, 0], [0, 1, 0, 1]])
    tensors, _ = model.policy.obs_to_tensor(obs)
    other, _ = model.policy.obs_to_tensor({**obs, ACTION_MASK_KEY: 1 - obs[ACTION_MASK_KEY]})
    with th.no_grad():
        th.testing.assert_close(model.q_net(tensors), model.q_net(other), rtol=0, atol=0)


def test_per_agent_team_map_policy_routes_and_masks() -> None:
    class AgentMaskedEnv(MaskedEnv):
        def __init__(self) -> None:
            super().__init__()
            self.observation_space = spaces.Dict(
                {**self.observation_space.spaces, "who": spaces.Box(0.0, 1.0, (2,), np.float32)}
            )

        def _obs(self, last: bool = False) -> dict[str, np.ndarray]:
            return {**super()._obs(last), "who": np.array([1.0, 0.0], dtype=np.float32)}

    policy_kwargs = dict(n_agents=2, agent_key="who", features_extractor_kwargs={"features_dim": 8})
    model = DoubleDQN(
        "PerAgentTeamMapPolicy",
        DummyVecEnv([AgentMaskedEnv]),
        policy_kwargs=policy_kwargs,
        device="cpu",
        seed=0,
    )
    q_net = model.q_net
    assert isinstance(q_net, PerAgentQNetwork) and q_net.agent_key == "who"
    extractor = q_net._template[0].features_extractor
    assert isinstance(extractor, TeamMapExtractor)
    assert set(extractor.branches) == {"obs"}  # neither the agent's index nor the mask
    # Agent 1's set answers [0, 0, 0, 9]: masked greedy takes 1 or 2, where allowed.
    with th.no_grad():
        for name, w in q_net.agent_parameters(1).items():
            w.zero_()
            if name.endswith("q_net.0.bias"):
                w.copy_(th.tensor([0.0, 1.0, 2.0, 9.0]))
    obs = observations([[0, 1, 0, 0], [1, 1, 1, 0], [1, 1, 1, 1]])
    obs["who"] = np.array([[0.0, 1.0]] * 3, dtype=np.float32)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], [1, 2, 3])


# --------------------------------------------------------------------------- without a mask


def test_without_a_mask_key_nothing_changes(monkeypatch: pytest.MonkeyPatch) -> None:
    model = make_model(q=Q_ONLINE, with_mask=False)
    assert not model.masked
    n = 500
    obs = {"obs": np.random.default_rng(0).uniform(-1, 1, (n, 2)).astype(np.float32)}
    greedy, _ = model.predict(obs, deterministic=True)
    np.testing.assert_array_equal(greedy, model.policy.predict(obs, deterministic=True)[0])
    assert set(greedy) == {3}
    # The ε-greedy draw is the unmasked one, number for number: one coin per slot, then a
    # uniform action in [0, n) from the global np.random (hence the legacy calls here).
    model.exploration_rate = 0.5
    set_random_seed(0)
    actions, _ = model.predict(obs)
    set_random_seed(0)
    explore = np.random.random_sample(n) < 0.5  # noqa: NPY002
    expected = np.where(explore, np.random.randint(N_ACTIONS, size=n), greedy)  # noqa: NPY002
    np.testing.assert_array_equal(actions, expected)
    assert set(actions) == set(range(N_ACTIONS))

    seen: list[th.Tensor | None] = []

    def spy(*args: Any) -> th.Tensor:
        seen.append(args[5])
        return harness.sb3.targets.double_q_target(*args)

    monkeypatch.setattr(harness.sb3.losses, "double_q_target", spy)
    assert model.replay_buffer is not None
    first = {"obs": obs["obs"][:3]}
    model.replay_buffer.add(
        first, first, np.array([[1], [2], [3]]), np.zeros(3), np.zeros(3, dtype=bool), [{}] * 3
    )
    model.train(gradient_steps=1, batch_size=4)
    assert seen == [None]  # the targets' max runs over every action
