"""The team-map side of the learner: the CNN features extractor, the TeamMap policies (save and
load), Double-DQN steps on Dict batches with prioritized replay, the replay memory estimate, and a
tiny end-to-end run through the command. The Dict buffer's sampling law, IS weights and flat
indices are checked with the array buffer's tests (``tests/test_buffers.py``, both classes)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from harness.buffers import PrioritizedDictReplayBuffer, replay_memory_bytes
from harness.cli import main
from harness.dqn import DoubleDQN
from harness.policies import DuelingTeamMapPolicy, TeamMapExtractor, TeamMapPolicy

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


@pytest.mark.parametrize("policy", ["TeamMapPolicy", "DuelingTeamMapPolicy"])
def test_policy_save_and_load_give_the_same_q_values(tmp_path, policy):
    from harness.adapters import make_vec_env

    venv = make_vec_env(
        {"height": 9, "width": 9, "n_agents": 2, "max_steps": 10, "observation": "teammap",
         "crop": 5, "global_size": 7},
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


def test_double_dqn_gradient_step_on_dict_batches_updates_priorities():
    from harness.adapters import make_vec_env

    venv = make_vec_env(
        {"height": 9, "width": 9, "n_agents": 2, "max_steps": 20, "observation": "teammap",
         "crop": 5, "global_size": 7},
        copies=2,
        seed=0,
    )  # fmt: skip
    model = DoubleDQN(
        "DuelingTeamMapPolicy",
        venv,
        buffer_size=400,
        learning_starts=40,
        batch_size=16,
        train_freq=1,
        replay_buffer_class=PrioritizedDictReplayBuffer,
        replay_buffer_kwargs={"alpha": 0.6, "beta": 0.4},
        policy_kwargs={"features_extractor_kwargs": {"features_dim": 16, "channels": [4, 8]}},
    )
    model.learn(120)
    assert model._n_updates > 0
    raw = model.replay_buffer.raw_priorities
    stored = raw[: model.replay_buffer.n_transitions]
    assert len(set(np.round(stored, 9))) > 2  # TD errors replaced the initial max priority
    assert np.isfinite(model.logger.name_to_value["train/loss"])
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


def test_policy_and_observation_must_fit(tmp_path, capsys):
    path = tmp_path / "c.yaml"
    path.write_text("env: {observation: teammap}\nalgo: {policy: MlpPolicy}\n")
    assert main(["run", str(path)]) == 2
    assert "is for observation 'thesis'" in capsys.readouterr().err


@pytest.mark.slow
def test_tiny_teammap_run_trains_evaluates_and_resumes(tmp_path, capsys):
    config = tmp_path / "tm.yaml"
    config.write_text(
        "name: tm\n"
        "env: {height: 12, width: 12, n_agents: 2, max_steps: 40, observation: teammap,"
        " crop: 7, global_size: 7}\n"
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
    capsys.readouterr()
    assert main(["eval", str(run), "--episodes", "3", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert 0 < summary["coverage_mean"] <= 1
    assert main(["tune", str(run), "--episodes", "2", "--temperatures", "0.5", "1"]) == 0
    assert main(["render", str(run), "--out", str(tmp_path / "p.png")]) == 0
    # Resume from the older checkpoint: the run finishes again from there.
    state = json.loads(
        sorted((run / "checkpoints").iterdir())[-1].joinpath("state.json").read_text()
    )
    assert state["finished"] is True
