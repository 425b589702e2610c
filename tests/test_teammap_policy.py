"""The team-map side of the learner: the CNN features extractor, the TeamMap policies (save and
load), Double-DQN steps on Dict batches with prioritized replay, the replay memory estimate, and a
tiny end-to-end run through the command. The Dict buffer's sampling law, IS weights and flat
indices are checked with the array buffer's tests (``tests/test_buffers.py``, both classes)."""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.utils import set_random_seed

from harness.cli import main
from harness.sb3.buffers import replay_memory_bytes
from harness.sb3.dqn import DoubleDQN
from harness.sb3.policies import DuelingTeamMapPolicy, TeamMapExtractor, TeamMapPolicy
from harness.training.checks import format_bytes
from tests.replay_variants import PrioritizedDictReplayBuffer

ROOT = Path(__file__).resolve().parents[1]


def teammap_space(crop: int = 7, g: int = 7) -> spaces.Dict:
    return spaces.Dict(
        {
            "local": spaces.Box(0, 255, (5, crop, crop), np.uint8),
            "global": spaces.Box(0, 255, (6, g, g), np.uint8),
            "vector": spaces.Box(0.0, 1.0, (3,), np.float32),
        }
    )


def sample_batch(space: spaces.Dict, n: int, seed: int = 0) -> dict[str, th.Tensor]:
    space.seed(seed)
    batch = [space.sample() for _ in range(n)]
    return {k: th.as_tensor(np.stack([b[k] for b in batch])).float() for k in space.spaces}


@pytest.mark.parametrize(("crop", "g"), [(5, 7), (15, 13), (21, 16)])
def test_extractor_output_shape_for_any_sizes(crop, g):
    space = teammap_space(crop, g)
    extractor = TeamMapExtractor(space, features_dim=32, channels=(4, 8))
    out = extractor(sample_batch(space, 3))
    assert out.shape == (3, 32)
    # Flat size: 8 filters x ceil(side / 2)^2 per image (stride 2, padding 1), plus the vector.
    expected = 8 * ((crop + 1) // 2) ** 2 + 8 * ((g + 1) // 2) ** 2 + 3
    assert extractor.linear[0].in_features == expected


def test_extractor_gives_the_ego_view_its_own_branch():
    space = spaces.Dict(
        {**teammap_space(5, 7).spaces, "ego": spaces.Box(0, 255, (5, 9, 9), np.uint8)}
    )
    extractor = TeamMapExtractor(space, features_dim=16, channels=(4, 8))
    assert set(extractor.branches) == {"local", "global", "ego", "vector"}
    assert extractor.linear[0].in_features == 8 * 3**2 + 8 * 4**2 + 8 * 5**2 + 3
    batch = sample_batch(space, 2)
    out = extractor(batch)
    batch["ego"] = batch["ego"].flip(-1)  # the ego view changes the features
    assert not th.equal(out, extractor(batch))


@pytest.mark.parametrize(
    ("policy", "ego_size", "frontier"),
    [
        ("TeamMapPolicy", 0, None),
        ("DuelingTeamMapPolicy", 0, None),
        ("TeamMapPolicy", 5, None),
        ("DuelingTeamMapPolicy", 0, {}),
    ],
)
def test_policy_save_and_load_give_the_same_q_values(tmp_path, policy, ego_size, frontier):
    from harness.config.schema import EnvConfig
    from harness.training.adapters import make_vec_env

    teammap = {"crop": 7, "global_size": 7, "ego_size": ego_size, "ego_block": 3}
    venv = make_vec_env(
        EnvConfig(
            height=9, width=9, n_agents=2, max_steps=10, observation={"teammap": teammap},
            frontier=frontier,
        ),
    )  # fmt: skip
    model = DoubleDQN(
        policy,
        venv,
        buffer_size=100,
        policy_kwargs={"features_extractor_kwargs": {"features_dim": 16, "channels": [4, 8]}},
    )
    expected_class = TeamMapPolicy if policy == "TeamMapPolicy" else DuelingTeamMapPolicy
    assert type(model.policy) is expected_class
    obs = venv.reset()
    model.save(tmp_path / "m.zip")
    loaded = DoubleDQN.load(tmp_path / "m.zip")
    assert type(loaded.policy) is expected_class
    with th.no_grad():
        a = model.q_net(model.policy.obs_to_tensor(obs)[0])
        b = loaded.q_net(loaded.policy.obs_to_tensor(obs)[0])
    th.testing.assert_close(a, b)
    venv.close()


def test_double_dqn_on_dict_batches_learns_and_sets_priorities_to_double_q_td_errors(monkeypatch):
    from harness.config.schema import EnvConfig
    from harness.training.adapters import make_vec_env

    set_random_seed(0)
    venv = make_vec_env(
        EnvConfig(
            height=9, width=9, n_agents=2, max_steps=20,
            observation={"teammap": {"crop": 5, "global_size": 7}},
        ),
        copies=2,
        seed=0,
    )  # fmt: skip
    model = DoubleDQN(
        "DuelingTeamMapPolicy",
        venv,
        buffer_size=400,
        learning_starts=40,
        batch_size=16,
        gamma=0.9,
        train_freq=1,
        replay_buffer_class=PrioritizedDictReplayBuffer,
        replay_buffer_kwargs={"alpha": 0.6, "beta": 0.4, "eps": 1e-3},
        policy_kwargs={"features_extractor_kwargs": {"features_dim": 16, "channels": [4, 8]}},
    )
    model.learn(240)  # a tiny run through SuperSuit's VecEnv of Dict observations
    buffer = model.replay_buffer
    assert isinstance(buffer, PrioritizedDictReplayBuffer)
    assert model._n_updates > 0
    assert len(set(np.round(buffer.raw_priorities[: buffer.n_transitions], 9))) > 2

    # One more step, checked by hand: the target network differs from the online one, so the
    # Double-Q target (online argmax, target value) differs from the max-Q target.
    with th.no_grad():
        for p in model.q_net_target.parameters():
            p.add_(0.3 * th.randn_like(p))
    online, target = copy.deepcopy(model.q_net), model.q_net_target
    drawn = []
    sample = buffer.sample

    def spy(*args, **kwargs):
        drawn.append(sample(*args, **kwargs))
        return drawn[-1]

    monkeypatch.setattr(buffer, "sample", spy)
    model.train(gradient_steps=1, batch_size=16)
    (batch,) = drawn
    with th.no_grad():
        next_online, next_target = online(batch.next_observations), target(batch.next_observations)
        best = next_online.argmax(dim=1, keepdim=True)
        y = batch.rewards + 0.9 * (1 - batch.dones) * next_target.gather(1, best)
        y_max_q = batch.rewards + 0.9 * (1 - batch.dones) * next_target.max(dim=1, keepdim=True)[0]
        q = online(batch.observations).gather(1, batch.actions.long())
    assert not th.allclose(y, y_max_q)
    td = (q - y).abs().ravel().cpu().numpy()  # .cpu(): the batch is on the GPU where there is one
    np.testing.assert_allclose(buffer.raw_priorities[batch.indices], td + 1e-3, rtol=1e-5)
    loss = (batch.weights * th.nn.functional.smooth_l1_loss(q, y, reduction="none")).mean()
    assert model.logger.name_to_value["train/loss"] == pytest.approx(loss.item(), rel=1e-5)
    # The step moved the online network.
    assert not th.allclose(model.q_net(batch.observations), online(batch.observations))
    venv.close()


def test_replay_memory_estimate_hand_computed():
    space = teammap_space(15, 13)
    # obs bytes: 5*15*15 + 6*13*13 + 3*4 = 1125 + 1014 + 12 = 2151; x2 with next_obs = 4302,
    # action int64 8, reward/done/timeout 3 x 4 = 12 -> 4322 bytes per transition.
    assert replay_memory_bytes(space, spaces.Discrete(5), 1000, 4, prioritized=False) == 4322000
    # PER: + 8 (raw priority) per transition + 2 * 1024 tree nodes x 8 bytes.
    with_per = replay_memory_bytes(space, spaces.Discrete(5), 1000, 4, prioritized=True)
    assert with_per == 4322000 + 8 * 1000 + 16 * 1024
    # buffer_size is split into whole rows of n_envs: 1001 // 4 = 250 rows.
    assert replay_memory_bytes(space, spaces.Discrete(5), 1001, 4, prioritized=False) == 4322000


def test_replay_memory_estimate_is_what_the_buffer_allocates():
    space, actions = teammap_space(7, 9), spaces.Discrete(5)
    buffer = PrioritizedDictReplayBuffer(30, space, actions, device="cpu", n_envs=4)
    arrays = [
        *buffer.observations.values(),
        *buffer.next_observations.values(),
        buffer.actions,
        buffer.rewards,
        buffer.dones,
        buffer.timeouts,
        buffer._raw_priorities,
        buffer._tree.nodes,
    ]
    assert sum(a.nbytes for a in arrays) == replay_memory_bytes(space, actions, 30, 4)


def test_a_buffer_larger_than_the_available_memory_is_refused():
    from harness.config.schema import ExperimentConfig
    from harness.training.checks import check_replay_memory

    def config(observation: str, policy: str) -> ExperimentConfig:
        return ExperimentConfig.model_validate(
            {"env": {"observation": observation}, "vec": {"copies": 2},
             "algo": {"policy": policy, "buffer_size": 1_000_000}}
        )  # fmt: skip

    # A million team-map transitions (15x15 crop, 13x13 map) need ~4.3 GB; thesis ones ~0.1 GB.
    thesis = check_replay_memory(config("thesis", "MlpPolicy"), available=2**31)
    assert thesis < 2**28
    with pytest.raises(ValueError, match=r"^algo\.buffer_size: a replay buffer of 1,000,000 "):
        check_replay_memory(config("teammap", "TeamMapPolicy"), available=2**31)


@pytest.mark.parametrize(
    ("observation", "policy", "message"),
    [
        ("teammap", "MlpPolicy", "algo.policy MlpPolicy is for observation 'thesis'"),
        ("teammap", "DuelingMlpPolicy", "is for observation 'thesis'"),
        ("thesis", "TeamMapPolicy", "algo.policy TeamMapPolicy is for observation 'teammap'"),
        ("thesis", "DuelingTeamMapPolicy", "is for observation 'teammap'"),
    ],
)
def test_policy_and_observation_must_fit(tmp_path, capsys, observation, policy, message):
    path = tmp_path / "c.yaml"
    path.write_text(f"env: {{observation: {observation}}}\nalgo: {{policy: {policy}}}\n")
    assert main(["run", str(path), "--runs-dir", str(tmp_path / "runs")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("harness: error:"), lines
    assert message in lines[0]
    assert not (tmp_path / "runs").exists()


def test_teammap_policy_defaults_from_a_config():
    from harness.config.schema import ExperimentConfig
    from harness.training.adapters import make_vec_env
    from harness.training.train import build_model

    config = ExperimentConfig.model_validate(
        {"env": {"height": 9, "width": 9, "n_agents": 2, "observation": "teammap"},
         "vec": {"copies": 1}, "algo": {"policy": "TeamMapPolicy", "buffer_size": 100}}
    )  # fmt: skip
    # The thesis's 3x512 head is the MLP policies' default; a TeamMap policy has none.
    assert config.algo.net_arch == []
    venv = make_vec_env(config.env, config.vec.copies, seed=0)
    model = build_model(config, venv)
    extractor = model.q_net.features_extractor
    assert isinstance(extractor, TeamMapExtractor)
    assert extractor.features_dim == 256
    convs = [m for m in extractor.branches["local"] if isinstance(m, th.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [8, 16]
    (head,) = model.q_net.q_net  # one linear layer: features -> 5 Q-values
    assert (head.in_features, head.out_features) == (256, 5)
    venv.close()


@pytest.mark.slow
def test_tiny_teammap_run_trains_evaluates_and_resumes(tmp_path, capsys):
    config = tmp_path / "tm.yaml"
    config.write_text(
        "name: tm\n"
        "env: {height: 12, width: 12, n_agents: 2, max_steps: 40,"
        " observation: {teammap: {crop: 7, global_size: 7}}}\n"
        "vec: {copies: 2}\n"
        "algo: {policy: DuelingTeamMapPolicy, net_arch: [], buffer_size: 2000,"
        " learning_starts: 100, target_update_interval: 200, optimizer: Adam,"
        " features_dim: 32, cnn_channels: [4, 8]}\n"
        "phases:\n"
        "  - {name: initial, timesteps: 600, learning_rate: 2.5e-4, batch_size: 16,"
        " train_freq: 2, exploration: {start: 1.0, end: 0.1, steps: 400},"
        " beta: {start: 0.4, end: 1.0, steps: 600}}\n"
        "  - {name: optimizing, timesteps: 200, learning_rate: [1.0e-4, 1.0e-5], batch_size: 16,"
        " train_freq: 2}\n"
        "eval: {every: 300, episodes: 2}\n"
        "checkpoint: {every: 300}\n"
    )
    runs = tmp_path / "runs"
    assert main(["run", str(config), "--runs-dir", str(runs), "--no-progress"]) == 0
    (run,) = runs.iterdir()
    assert (run / "best_model.zip").is_file()
    # The estimate printed at start: 2,000 transitions over 4 slots, 7x7 crop, 7x7 map, PER.
    space = teammap_space(7, 7)
    estimate = format_bytes(replay_memory_bytes(space, spaces.Discrete(5), 2000, 4))
    assert f"replay buffer: 2,000 transitions, about {estimate} when full" in (
        capsys.readouterr().err
    )
    assert main(["eval", str(run), "--episodes", "3", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert 0 < summary["coverage_mean"] <= 1
    assert main(["tune", str(run), "--episodes", "2", "--temperatures", "0.5", "1"]) == 0
    assert main(["render", str(run), "--out", str(tmp_path / "p.png")]) == 0
    # Resume from the older checkpoint (the newest one gone, as after a kill while it was
    # written): its Dict replay buffer with priorities loads and the run finishes again.
    older, newest = sorted((run / "checkpoints").iterdir(), key=lambda p: int(p.name[5:]))
    shutil.rmtree(newest)
    assert main(["run", "--resume", str(run), "--no-progress"]) == 0
    (last,) = [p for p in (run / "checkpoints").iterdir() if p != older]
    assert json.loads((last / "state.json").read_text())["finished"] is True
