"""``harness run`` end to end on the smoke config, and its errors."""

from __future__ import annotations

import csv
import pickle
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from stable_baselines3.common.buffers import NStepReplayBuffer
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from harness import DoubleDQN, DuelingDQNPolicy
from harness.cli import main
from harness.config.loading import load_config
from harness.results.rundir import RunDir
from harness.sb3.replay import PrioritizedReplayBuffer
from harness.training.checkpoints import complete_checkpoints, latest_checkpoint

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"

TB_TAGS = {
    "rollout/coverage",
    "rollout/wall_hits",
    "rollout/ep_rew_mean",
    "rollout/exploration_rate",
    "train/loss",
    "train/beta",
    "train/epochs",
    "train/learning_rate",
    "eval/coverage_median",
    "time/fps",
}


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    runs = tmp_path_factory.mktemp("runs")
    rc = main(["run", str(SMOKE), "--runs-dir", str(runs), "--no-progress", "--set", "seed=3"])
    assert rc == 0
    (path,) = runs.iterdir()
    return RunDir(path)


def run_smoke(runs_dir: Path, *overrides: str) -> Path:
    """Train the smoke config with ``--set`` ``overrides`` into ``runs_dir``; the run folder."""
    args = ["run", str(SMOKE), "--runs-dir", str(runs_dir), "--no-progress"]
    for override in overrides:
        args += ["--set", override]
    assert main(args) == 0
    (path,) = runs_dir.iterdir()
    return path


def test_run_directory_layout(smoke_run):
    assert smoke_run.path.name.startswith("smoke-")
    for f in ("config.yaml", "command.txt", "model.zip", "episodes.csv", "best_model.zip"):
        assert (smoke_run.path / f).is_file(), f
    latest = latest_checkpoint(smoke_run.checkpoints)
    for f in ("model.zip", "replay_buffer.pkl", "rng.pkl", "state.json"):
        assert (latest / f).is_file(), f
    assert len(complete_checkpoints(smoke_run.checkpoints)) == 2  # older ones are pruned
    assert "harness run" in smoke_run.command.read_text()
    resolved = load_config(smoke_run.config)
    assert resolved == load_config(SMOKE, ["seed=3"])


def test_episodes_csv_numbers_every_episode_across_phases(smoke_run):
    cfg = load_config(smoke_run.config)
    with smoke_run.episodes_csv.open() as f:
        rows = list(csv.DictReader(f))
    steps_per_round = cfg.n_slots * cfg.env.max_steps
    rounds = cfg.total_timesteps // steps_per_round
    assert len(rows) >= rounds * cfg.vec.copies
    assert [int(r["episode"]) for r in rows] == list(range(len(rows)))
    assert {r["phase"] for r in rows} == {"initial", "optimizing"}
    assert all(0.0 < float(r["coverage"]) <= 1.0 for r in rows)
    assert all(len(r["new_cells"].split(";")) == cfg.env.n_agents for r in rows)


def test_evaluations_csv_holds_every_tensorboard_evaluation(smoke_run):
    cfg = load_config(smoke_run.config)
    with smoke_run.evaluations_csv.open() as f:
        rows = list(csv.DictReader(f))
    events = EventAccumulator(str(smoke_run.tb))
    events.Reload()
    logged = events.Scalars("eval/coverage_median")
    assert [int(r["timesteps"]) for r in rows] == [e.step for e in logged]
    assert [float(r["coverage_median"]) for r in rows] == pytest.approx([e.value for e in logged])
    assert len(rows) >= cfg.total_timesteps // cfg.eval.every - 1
    assert all(int(r["timesteps"]) % cfg.eval.every < cfg.n_slots for r in rows)
    assert {int(r["episodes"]) for r in rows} == {cfg.eval.episodes}
    for r in rows:
        assert float(r["coverage_q1"]) <= float(r["coverage_median"]) <= float(r["coverage_q3"])


def test_tensorboard_has_the_documented_tags(smoke_run):
    events = EventAccumulator(str(smoke_run.tb))
    events.Reload()
    assert set(events.Tags()["scalars"]) >= TB_TAGS


def test_model_loads_and_acts(smoke_run):
    model = DoubleDQN.load(smoke_run.model)
    assert model.double_q is True
    assert model.num_timesteps >= load_config(smoke_run.config).total_timesteps
    assert model.policy.q_net.q_net is not None


def test_dueling_policy_trains_through_the_harness(tmp_path):
    rc = main(
        [
            "run", str(SMOKE), "--runs-dir", str(tmp_path), "--no-progress", "--name", "duel",
            "--set", "algo.policy=DuelingMlpPolicy", "--set", "algo.dueling_aggregator=max",
            "--set", "phases.initial.timesteps=600", "--set", "phases.optimizing.timesteps=200",
            "--set", "eval.every=0", "--set", "checkpoint.every=0",
        ]
    )  # fmt: skip
    assert rc == 0
    (path,) = tmp_path.iterdir()
    model = DoubleDQN.load(path / "model.zip")
    assert isinstance(model.policy, DuelingDQNPolicy)
    assert path.name.startswith("duel-")


def test_imitation_config_trains_towards_the_frontier_step(tmp_path):
    # algo.imitation reaches the model (expert = the planner-backed action, the frontier step
    # 5), its loss is logged, and a weight that the TD term cannot hold makes the greedy policy
    # the step's.
    path = run_smoke(
        tmp_path,
        "env.observation={teammap: {crop: 7}}", "algo.policy=TeamMapPolicy",
        "env.frontier={action: step}", "algo.learning_starts=100",
        "algo.imitation={margin: 0.5, weight: 2.0}",
        "phases.initial.timesteps=1200", "phases.optimizing.timesteps=200",
        "eval.every=0", "checkpoint.every=0",
    )  # fmt: skip
    model = DoubleDQN.load(path / "model.zip")
    assert (model.expert_action, model.margin, model.margin_weight) == (5, 0.5, 2.0)
    events = EventAccumulator(str(path / "tb"))
    events.Reload()
    agreement = [e.value for e in events.Scalars("train/expert_agreement")]
    assert "train/margin_loss" in events.Tags()["scalars"]
    assert agreement[-1] > 0.9


@pytest.mark.parametrize(
    ("observation", "prioritized", "buffer_class"),
    [
        ("thesis", True, PrioritizedReplayBuffer),
        ("teammap", True, PrioritizedReplayBuffer),  # Dict observations: a storage option
        ("thesis", False, NStepReplayBuffer),
    ],
)
def test_n_step_returns_reach_the_buffer_from_the_config(
    tmp_path, observation, prioritized, buffer_class
):
    teammap = ["env.observation=teammap", "algo.policy=TeamMapPolicy"]
    path = run_smoke(
        tmp_path,
        "algo.n_steps=3", "algo.gamma=0.5", f"algo.prioritized={str(prioritized).lower()}",
        *(teammap if observation == "teammap" else []),
        "phases.initial.timesteps=600", "phases.optimizing.timesteps=200",
        "eval.every=0", "checkpoint.every=400",
        "algo.device=cpu",  # the host buffers (a GPU machine's run keeps its buffer there)
    )  # fmt: skip
    with (latest_checkpoint(path / "checkpoints") / "replay_buffer.pkl").open("rb") as f:
        buffer = pickle.load(f)
    assert type(buffer) is buffer_class
    assert (buffer.n_steps, buffer.gamma) == (3, 0.5)
    discounts = buffer.sample(64).discounts.cpu().numpy()  # .cpu(): on a GPU machine too
    assert set(np.unique(discounts)) <= {0.5, 0.25, 0.125} and 0.125 in discounts


def test_run_folders_are_never_reused():
    now = datetime(2026, 1, 2, 3, 4, 5, tzinfo=timezone.utc)
    root = Path(__import__("tempfile").mkdtemp())
    a = RunDir.create(root, "x", now)
    b = RunDir.create(root, "x", now)
    assert a.path != b.path
    assert a.path.name == "x-20260102T030405Z" and b.path.name == "x-20260102T030405Z-1"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["run", "missing.yaml"], "missing.yaml: config file not found"),
        (["run", str(SMOKE), "--set", "env.n_agents=0"], "env.n_agents: Input should be greater"),
        (["run", str(SMOKE), "--name", "../../etc"], "name: must be 1-64 characters"),
    ],
)
def test_bad_input_is_one_line_and_exit_code_2(args, message, capsys, tmp_path):
    assert main([*args, "--runs-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("harness: error:") and message in err
    assert "\n" not in err
    assert list(tmp_path.iterdir()) == []  # nothing created


def test_unwritable_runs_folder(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["run", str(SMOKE), "--runs-dir", str(blocker / "runs")]) == 2
    assert "cannot create a run folder" in capsys.readouterr().err


def test_console_script_reports_errors_without_traceback(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("env: {n_agents: 2\n")
    proc = subprocess.run(
        [sys.executable, "-m", "harness.cli", "run", str(bad)], capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().startswith("harness: error:")
    assert "invalid YAML" in proc.stderr


@pytest.mark.slow
def test_both_vec_backends_train_the_same_run(tmp_path, smoke_run):
    # The same seed on SuperSuit's VecEnv: the same episodes, the same learning, the same log.
    other = run_smoke(tmp_path, "seed=3", "vec.backend=supersuit")
    assert (other / "episodes.csv").read_text() == smoke_run.episodes_csv.read_text()


def test_env_worker_processes_need_the_supersuit_backend(tmp_path, capsys):
    args = ["run", str(SMOKE), "--runs-dir", str(tmp_path), "--set", "vec.num_cpus=2"]
    assert main(args) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "vec.num_cpus > 1 needs vec.backend: supersuit" in line
    assert not any(tmp_path.iterdir())
