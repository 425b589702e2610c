"""``algo.sharing``: one shared network, one with the agent's index (agent indication), or one
parameter set per agent routed inside one model. Config, observations, routing, the isolation of
the per-agent sets, the double-Q target, and the three modes end to end (train, stop, resume,
evaluate, render, compare), with the team-size rule."""

from __future__ import annotations

import json
import signal
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBufferSamples
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import DummyVecEnv

from envs import coverage_v0
from harness import DoubleDQN, PrioritizedReplayBuffer
from harness.cli import main
from harness.config.loading import load_config
from harness.config.schema import ConfigError, EnvConfig
from harness.factory import env_kwargs
from harness.sb3.dqn import per_agent_loss
from harness.sb3.policies import PerAgentQNetwork, without_agent_id
from harness.sb3.registry import POLICIES
from harness.training.adapters import make_vec_env
from harness.training.checkpoints import complete_checkpoints
from harness.training.checks import network_parameters
from tests.conftest import interrupted_past
from tests.test_resume import TINY as RESUME_TINY

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
MODES = ("shared", "shared_id", "per_agent")
SMALL = {"height": 8, "width": 8, "n_agents": 2, "max_steps": 12}
TEAMMAP = {**SMALL, "observation": {"teammap": {"crop": 5, "global_size": 6}}}


# ----------------------------------------------------------------------------------- config
def test_sharing_defaults_to_shared_and_only_the_other_modes_add_the_agent_id():
    assert load_config(SMOKE).algo.sharing == "shared"
    assert "agent_id" not in env_kwargs(load_config(SMOKE).env)
    for mode in ("shared_id", "per_agent"):
        config = load_config(SMOKE, [f"algo.sharing={mode}"])
        assert env_kwargs(config.env)["agent_id"] is True
        assert f"sharing: {mode}" in config.to_yaml()
        assert "agent_id" not in config.to_yaml()  # algo.sharing is its one key


def test_an_unknown_sharing_mode_is_a_one_line_config_error(capsys):
    with pytest.raises(ConfigError, match=r"algo\.sharing: Input should be 'shared', 'shared_id'"):
        load_config(SMOKE, ["algo.sharing=independent"])
    assert main(["run", str(SMOKE), "--set", "algo.sharing=independent"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "algo.sharing" in err[0]


def test_per_agent_memory_check_counts_one_network_per_agent():
    shared = network_parameters(load_config(SMOKE))
    per_agent = network_parameters(load_config(SMOKE, ["algo.sharing=per_agent"]))
    # Two agents: two networks of the shared one's size (each without the one-hot input).
    assert per_agent == 2 * shared


# ----------------------------------------------------------------------------- observations
@pytest.mark.parametrize("n_agents", [1, 3])
def test_thesis_observation_ends_in_the_agents_one_hot_index(n_agents):
    plain = coverage_v0.parallel_env(**{**SMALL, "n_agents": n_agents})
    env = coverage_v0.parallel_env(**{**SMALL, "n_agents": n_agents}, agent_id=True)
    space = env.observation_space("agent_0")
    assert space.shape == (13 + n_agents,)
    obs, _ = env.reset(seed=4)
    base, _ = plain.reset(seed=4)
    for i, agent in enumerate(env.agents):
        assert space.contains(obs[agent])
        np.testing.assert_array_equal(obs[agent][:13], base[agent])
        np.testing.assert_array_equal(obs[agent][13:], np.eye(n_agents)[i])
    obs, *_ = env.step(dict.fromkeys(env.agents, 4))
    np.testing.assert_array_equal(obs[env.agents[-1]][13:], np.eye(n_agents)[-1])


def test_teammap_observation_gets_an_agent_id_key():
    env = coverage_v0.parallel_env(**TEAMMAP, agent_id=True)
    space = env.observation_space("agent_0")
    assert set(space.spaces) == {"local", "global", "vector", "agent_id"}
    assert space["agent_id"].shape == (2,) and space["agent_id"].dtype == np.float32
    obs, _ = env.reset(seed=0)
    assert space.contains(obs["agent_1"])
    np.testing.assert_array_equal(obs["agent_1"]["agent_id"], [0.0, 1.0])


def test_agent_id_must_be_a_bool():
    with pytest.raises(ValueError, match="agent_id must be True or False"):
        coverage_v0.parallel_env(**SMALL, agent_id=1)


def test_vecenv_slot_k_is_agent_k_mod_n():
    venv = make_vec_env({**SMALL, "n_agents": 3, "agent_id": True}, copies=2, seed=0)
    try:
        obs = venv.reset()
        np.testing.assert_array_equal(obs[:, 13:].argmax(axis=1), [0, 1, 2, 0, 1, 2])
    finally:
        venv.close()


# ------------------------------------------------------------------- every policy, each mode
def _model(env: dict[str, Any], policy: str, sharing: str, **kwargs: Any) -> DoubleDQN:
    th.manual_seed(0)
    venv = make_vec_env({**env, "agent_id": sharing != "shared"}, copies=2, seed=0)
    entry = POLICIES[policy]
    policy_kwargs: dict[str, Any] = {"net_arch": [16]}
    if entry.team_map:
        policy_kwargs["features_extractor_kwargs"] = {"features_dim": 16, "channels": [4, 4]}
    if sharing == "per_agent":
        policy_kwargs["n_agents"] = env["n_agents"]
        policy = entry.per_agent_name
    model = DoubleDQN(
        policy,
        venv,
        buffer_size=400,
        learning_starts=0,
        batch_size=8,
        train_freq=4,
        policy_kwargs=policy_kwargs,
        device="cpu",
        seed=None,  # SuperSuit's VecEnv has no seed(): torch is seeded here instead
        **kwargs,
    )
    model.set_logger(configure(None, []))
    return model


@pytest.mark.parametrize("sharing", ["shared_id", "per_agent"])
# The slot policy needs the goal action's env and has no per-agent version (tests/test_goals.py);
# a masked env's policy takes no agent indication (tests/test_action_masks_pettingzoo.py).
@pytest.mark.parametrize(
    "policy", [name for name, p in POLICIES.items() if not p.slots and not p.masked]
)
def test_every_policy_trains_predicts_and_reloads_with_agent_indication(policy, sharing, tmp_path):
    env = TEAMMAP if POLICIES[policy].observation == "teammap" else SMALL
    dict_obs = POLICIES[policy].observation == "teammap"
    buffer = None if dict_obs else PrioritizedReplayBuffer
    model = _model(env, policy, sharing, replay_buffer_class=buffer)
    model.learn(48)  # collects and trains a few gradient steps
    assert model._n_updates > 0
    obs = model.env.reset()
    actions, _ = model.predict(obs, deterministic=True)
    assert actions.shape == (4,)
    model.save(tmp_path / "m.zip")
    loaded = DoubleDQN.load(tmp_path / "m.zip", device="cpu")
    assert type(loaded.policy) is type(model.policy)
    with th.no_grad():
        q = model.q_net(model.policy.obs_to_tensor(obs)[0])
        q_loaded = loaded.q_net(loaded.policy.obs_to_tensor(obs)[0])
    th.testing.assert_close(q, q_loaded, rtol=0, atol=0)
    model.env.close()


def test_per_agent_linear_weights_are_input_major_and_stay_so_through_training_and_loading(
    tmp_path,
):
    # Stored (N, out, in) with the (N, in, out) layout, their vmap gradients need no transposed
    # copy (PerAgentQNetwork's _input_major); saving, loading and the target sync must keep that.
    model = _model(SMALL, "MlpPolicy", "per_agent", target_update_interval=4)
    model.learn(48)
    model.save(tmp_path / "m.zip")
    loaded = DoubleDQN.load(tmp_path / "m.zip", device="cpu")
    for net in (model.q_net, model.q_net_target, loaded.q_net, loaded.q_net_target):
        weights = [p for k, p in net.params.items() if k.endswith("weight")]
        assert len(weights) == 2  # the hidden layer and the output layer
        for w in weights:
            assert w.transpose(-1, -2).is_contiguous() and not w.is_contiguous()
    for w in model.q_net.params.values():  # the optimizer's running averages: same layout
        assert model.policy.optimizer.state[w]["square_avg"].stride() == w.stride()
    for name, w in model.q_net.params.items():
        th.testing.assert_close(w, loaded.q_net.params[name], rtol=0, atol=0)
    model.env.close()


# ---------------------------------------------------------------------------------- routing
def test_each_sample_uses_its_own_agents_network_in_any_order():
    th.manual_seed(0)
    env = coverage_v0.parallel_env(**{**SMALL, "n_agents": 3}, agent_id=True)
    space = env.observation_space("agent_0")
    policy_class = POLICIES["DuelingMlpPolicy"].load(per_agent=True)
    policy = policy_class(space, env.action_space("agent_0"), lambda _: 1e-3, n_agents=3)
    q_net = policy.q_net
    assert isinstance(q_net, PerAgentQNetwork)
    # Three networks of the base kind, built separately: their weights differ.
    base = POLICIES["DuelingMlpPolicy"].load()(
        without_agent_id(space, 3), env.action_space("agent_0"), lambda _: 1e-3
    )
    nets = [base.make_q_net() for _ in range(3)]
    routed = PerAgentQNetwork(space, env.action_space("agent_0"), nets)
    rng = np.random.default_rng(0)
    agents = np.array([2, 0, 0, 1, 2, 2, 1])  # any order, unequal counts
    obs = np.concatenate([rng.uniform(-1, 1, (7, 13)), np.eye(3)[agents]], axis=1)
    obs_t = th.as_tensor(obs, dtype=th.float32)
    with th.no_grad():
        q = routed(obs_t)
        for j, a in enumerate(agents):
            expected = nets[a](obs_t[j : j + 1, :13])
            th.testing.assert_close(q[j : j + 1], expected)
        assert not th.allclose(nets[0](obs_t[:, :13]), nets[1](obs_t[:, :13]))
    np.testing.assert_array_equal(routed.agents_of(obs_t).numpy(), agents)


def test_any_block_width_of_the_largest_group_or_more_gives_the_same_values_and_gradients(
    monkeypatch,
):
    # On an accelerator the routing block is as wide as the batch (no read of the group sizes);
    # on the CPU as the largest group. Both give the same Q-values and the same gradients.
    th.manual_seed(0)
    env = coverage_v0.parallel_env(**{**SMALL, "n_agents": 3}, agent_id=True)
    policy_class = POLICIES["MlpPolicy"].load(per_agent=True)
    space = env.observation_space("agent_0")
    q_net = policy_class(space, env.action_space("agent_0"), lambda _: 1e-3, n_agents=3).q_net
    agents = np.array([2, 0, 0, 1, 2, 2, 1])
    rng = np.random.default_rng(0)
    obs = np.concatenate([rng.uniform(-1, 1, (7, 13)), np.eye(3)[agents]], axis=1)
    obs_t = th.as_tensor(obs, dtype=th.float32)

    def values_and_grads() -> tuple[th.Tensor, list[th.Tensor]]:
        q_net.zero_grad()
        q = q_net(obs_t)
        (q * th.arange(q.numel()).reshape(q.shape)).sum().backward()
        return q.detach(), [p.grad.clone() for p in q_net.parameters()]

    onehot = th.nn.functional.one_hot(th.as_tensor(agents), 3)
    assert PerAgentQNetwork._block_width(onehot) == 3  # agent 2's three samples
    assert PerAgentQNetwork._block_width(onehot.to("meta")) == 7  # the batch, nothing read
    narrow = values_and_grads()
    monkeypatch.setattr(PerAgentQNetwork, "_block_width", staticmethod(lambda o: o.shape[0]))
    wide = values_and_grads()
    th.testing.assert_close(wide[0], narrow[0])
    for a, b in zip(wide[1], narrow[1], strict=True):
        th.testing.assert_close(a, b)


def test_vecenv_slots_are_routed_to_agent_slot_mod_n():
    model = _model(SMALL, "MlpPolicy", "per_agent")
    with th.no_grad():  # agent 1's set answers zero everywhere, agent 0's does not
        for w in model.q_net.agent_parameters(1).values():
            w.zero_()
        q = model.q_net(model.policy.obs_to_tensor(model.env.reset())[0])
    assert (q[[1, 3]] == 0).all()  # slots 1 and 3: copies 0 and 1, agent 1
    assert (q[[0, 2]] != 0).any(dim=1).all()
    model.env.close()


# ------------------------------------------------------------------- isolation of agent sets
def _filled_per_agent_model(**kwargs: Any) -> DoubleDQN:
    model = _model(
        SMALL,
        "MlpPolicy",
        "per_agent",
        replay_buffer_class=PrioritizedReplayBuffer,
        learning_rate=1e-2,
        **kwargs,
    )
    model.learning_starts = 10**9  # fill the buffer without training
    model.learn(200)
    return model


def _rows(samples: Any, keep: th.Tensor) -> Any:
    return type(samples)(*(x[keep] if isinstance(x, th.Tensor) else x for x in samples))


def _agent_weights(model: DoubleDQN, agent: int) -> dict[str, th.Tensor]:
    return {k: v.detach().clone() for k, v in model.q_net.agent_parameters(agent).items()}


@pytest.mark.parametrize("optimizer", ["RMSprop", "Adam"])
def test_a_step_on_agent_0s_transitions_leaves_agent_1s_weights_bit_identical(optimizer):
    model = _filled_per_agent_model()
    if optimizer == "Adam":
        model.policy.optimizer = th.optim.Adam(model.policy.parameters(), lr=1e-2)
    samples = model.replay_buffer.sample(64)
    agent = model.q_net.agents_of(samples.observations)
    only_0 = _rows(samples, agent == 0)
    assert 0 < len(only_0.rewards) < 64
    before_0, before_1 = _agent_weights(model, 0), _agent_weights(model, 1)
    target_before_1 = {k: v.clone() for k, v in model.q_net_target.agent_parameters(1).items()}
    model._gradient_step(only_0)
    after_0, after_1 = _agent_weights(model, 0), _agent_weights(model, 1)
    for name in before_1:
        assert th.equal(before_1[name], after_1[name]), name
        assert th.equal(target_before_1[name], model.q_net_target.agent_parameters(1)[name])
    assert any(not th.equal(before_0[k], after_0[k]) for k in before_0)
    model.env.close()


def test_each_agents_gradient_comes_from_its_own_samples_as_a_separate_learner():
    model = _filled_per_agent_model()
    samples = model.replay_buffer.sample(64)
    agent = model.q_net.agents_of(samples.observations)

    def gradients(batch: Any) -> list[th.Tensor]:
        model.policy.optimizer.zero_grad()
        with th.no_grad():
            weights = batch.weights
        loss = _loss(model, batch, weights)
        loss.backward()
        return [p.grad[1].clone() for p in model.q_net.params.values()]

    mixed = gradients(samples)
    alone = gradients(_rows(samples, agent == 1))
    for g_mixed, g_alone in zip(mixed, alone):
        th.testing.assert_close(g_mixed, g_alone)
    model.env.close()


def _loss(model: DoubleDQN, batch: Any, weights: th.Tensor) -> th.Tensor:
    """The training loss of ``batch`` as ``DoubleDQN._gradient_step`` builds it."""
    from harness.sb3.targets import double_q_target

    with th.no_grad():
        target = double_q_target(
            batch.rewards,
            batch.dones,
            model.gamma,
            model.q_net(batch.next_observations),
            model.q_net_target(batch.next_observations),
        )
    current = th.gather(model.q_net(batch.observations), 1, batch.actions.long())
    per_sample = th.nn.functional.smooth_l1_loss(current, target, reduction="none")
    return per_agent_loss(per_sample, model.q_net.agents_of(batch.observations), 2, weights)


def test_per_agent_loss_is_the_sum_of_each_agents_weighted_mean():
    losses = th.tensor([1.0, 2.0, 3.0, 4.0, 5.0])
    agent = th.tensor([0, 1, 0, 0, 1])
    weights = th.tensor([0.5, 1.0, 0.25, 1.0, 0.5])  # agent 1's largest is 1.0, agent 0's 1.0
    expected = (0.5 * 1 + 0.25 * 3 + 1.0 * 4) / 3 + (1.0 * 2 + 0.5 * 5) / 2
    assert per_agent_loss(losses, agent, 2, weights).item() == pytest.approx(expected)
    # IS weights normalised per agent: halving one agent's weights changes nothing.
    halved = th.where(agent == 1, weights / 2, weights)
    assert per_agent_loss(losses, agent, 2, halved).item() == pytest.approx(expected)
    assert per_agent_loss(losses, agent, 3).item() == pytest.approx(8 / 3 + 7 / 2)


def test_per_agent_training_samples_batch_size_per_agent(monkeypatch):
    model = _filled_per_agent_model()
    sizes = []
    sample = model.replay_buffer.sample

    def spy(batch_size: int, env: Any = None) -> Any:
        sizes.append(batch_size)
        return sample(batch_size, env)

    monkeypatch.setattr(model.replay_buffer, "sample", spy)
    model.train(gradient_steps=2, batch_size=16)
    assert sizes == [32, 32]  # 2 agents x 16
    model.env.close()


def test_gradient_clipping_is_per_agent():
    model = _filled_per_agent_model()
    for p in model.q_net.params.values():
        p.grad = th.zeros_like(p)
        p.grad[0] = 100.0  # agent 0: a huge gradient; agent 1: a small one
        p.grad[1] = 1e-4
    small = [p.grad[1].clone() for p in model.q_net.params.values()]
    model.q_net.clip_grad_norm_(1.0)
    norm_0 = th.sqrt(sum(p.grad[0].pow(2).sum() for p in model.q_net.params.values()))
    assert norm_0.item() == pytest.approx(1.0, rel=1e-4)
    for p, g in zip(model.q_net.params.values(), small):
        assert th.equal(p.grad[1], g)  # under the norm: untouched by agent 0's clipping
    model.env.close()


# ------------------------------------------------------------------------- double-Q target
class TwoAgentTinyEnv(gym.Env):
    """2-d observations plus a 2-agent one-hot index (the per-agent policy's input)."""

    observation_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
    action_space = spaces.Discrete(2)

    def reset(self, *, seed: int | None = None, options: Any = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return np.zeros(4, dtype=np.float32), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict]:
        return np.zeros(4, dtype=np.float32), 0.0, False, True, {}


def test_double_q_target_per_agent_matches_hand_computation():
    # Linear Q(x) = W x per agent; column 0 acts on s, column 1 on s' (Q(s, a) = 0).
    # Agent 0: online Q(s') = [2, 1] -> a* = 0; target Q(s') = [0, 3] -> bootstrap 0.
    # Agent 1: online Q(s') = [1, 2] -> a* = 1; target Q(s') = [5, 3] -> bootstrap 3 (max: 5).
    weights = {
        0: ([[0.0, 2.0], [0.0, 1.0]], [[0.0, 0.0], [0.0, 3.0]]),
        1: ([[0.0, 1.0], [0.0, 2.0]], [[0.0, 5.0], [0.0, 3.0]]),
    }
    model = DoubleDQN(
        "PerAgentMlpPolicy",
        DummyVecEnv([TwoAgentTinyEnv]),
        learning_rate=0.0,
        gamma=0.5,
        buffer_size=4,
        policy_kwargs={"net_arch": [], "n_agents": 2},
        device="cpu",
        seed=0,
    )
    model.set_logger(configure(None, []))
    with th.no_grad():
        for agent, (online, target) in weights.items():
            for net, w in ((model.q_net, online), (model.q_net_target, target)):
                params = net.agent_parameters(agent)
                params["q_net.0.weight"].copy_(th.tensor(w))
                params["q_net.0.bias"].zero_()

    def obs(x: list[float], agent: int) -> list[float]:
        return [*x, 1.0 - agent, float(agent)]

    agents = [0, 1, 1]
    batch = ReplayBufferSamples(
        observations=th.tensor([obs([1.0, 0.0], a) for a in agents]),
        actions=th.tensor([[1], [1], [0]]),
        next_observations=th.tensor([obs([0.0, 1.0], a) for a in agents]),
        dones=th.zeros(3, 1),
        rewards=th.tensor([[1.0], [1.0], [-1.0]]),
    )
    loss, abs_td = model._gradient_step(batch)
    # targets: 1 + 0.5 * 0 = 1; 1 + 0.5 * 3 = 2.5; -1 + 0.5 * 3 = 0.5
    th.testing.assert_close(abs_td, th.tensor([1.0, 2.5, 0.5]))
    # Huber: 0.5; 2.0 and 0.125 (mean 1.0625 for agent 1); the mean over the two sets (the
    # step minimises their sum)
    assert float(loss) / 2 == pytest.approx((0.5 + (2.0 + 0.125) / 2) / 2)
    model.double_q = False
    _, abs_td = model._gradient_step(batch)
    th.testing.assert_close(abs_td, th.tensor([2.5, 3.5, 1.5]))  # max: 3 and 5


# ------------------------------------------------------------------------------ end to end
# The resume tests' tiny run, on one thread: a tiny net's second thread only waits (and slows
# a busy machine).
TINY = [*RESUME_TINY, "algo.threads=1"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One tiny run per mode, stopped by Ctrl-C at about step 1000, then resumed to the end."""
    out = {}
    for mode in MODES:
        folder = tmp_path_factory.mktemp(mode)
        args = ["run", str(SMOKE), "--runs-dir", str(folder), "--no-progress"]
        args += [a for o in [*TINY, f"algo.sharing={mode}"] for a in ("--set", o)]
        with interrupted_past(1000):
            assert main(args) == 128 + signal.SIGINT
        (run,) = folder.iterdir()
        assert complete_checkpoints(run / "checkpoints")
        assert not (run / "model.zip").exists()
        assert main(["run", "--resume", str(run), "--no-progress"]) == 0
        out[mode] = run
    return out


@pytest.mark.parametrize("mode", MODES)
def test_each_mode_trains_resumes_and_evaluates(runs, mode, capsys):
    run = runs[mode]
    assert load_config(run / "config.yaml").algo.sharing == mode
    model = DoubleDQN.load(run / "model.zip", device="cpu")
    assert model.num_timesteps >= 1600
    assert isinstance(model.q_net, PerAgentQNetwork) == (mode == "per_agent")
    expected = 13 if mode == "shared" else 15
    assert model.observation_space.shape == (expected,)
    assert main(["eval", str(run), "--episodes", "2", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["episodes"] == 2 and len(result["per_agent"]) == 2
    assert (run / "eval-2ep.json").is_file()
    assert main(["render", str(run), "--out", str(run / "paths.png")]) == 0
    assert (run / "paths.png").stat().st_size > 0


def test_the_three_modes_compare(runs, tmp_path, capsys):
    out = tmp_path / "compare.png"
    args = ["compare", *(str(runs[m]) for m in MODES), "--labels", *MODES, "--out", str(out)]
    assert main(args) == 0
    assert out.stat().st_size > 0


@pytest.mark.parametrize("mode", ["shared_id", "per_agent"])
def test_another_team_size_is_refused_in_one_line(runs, mode, capsys):
    capsys.readouterr()
    assert main(["eval", str(runs[mode]), "--episodes", "1", "--set", "env.n_agents=3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0]
    assert f"algo.sharing={mode} model" in err[0] and "for 2 agents" in err[0]
    assert "env.n_agents=3" in err[0]


def test_a_shared_model_plays_another_team_size(runs, capsys):
    assert main(["eval", str(runs["shared"]), "--episodes", "1", "--set", "env.n_agents=3"]) == 0
    assert "3 agent(s)" in capsys.readouterr().out


def test_env_config_alone_has_no_agent_id():
    # Baselines and benchmarks build EnvConfig directly: plain observations.
    assert "agent_id" not in env_kwargs(EnvConfig(**SMALL))
