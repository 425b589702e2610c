"""Resuming survives damage: a kill before the first checkpoint, a second process on the same
run, an unreadable newest checkpoint, tampered or torn files, an edited config.yaml, a finished
run without its checkpoints. Each case either resumes correctly or stops with one line and exit
code 2, changing nothing."""

from __future__ import annotations

import csv
import errno
import hashlib
import json
import os
import pickle
import shutil
import signal
from pathlib import Path
from typing import Any

import pytest
import yaml

from harness.cli import main
from harness.config.loading import load_config
from harness.results.rundir import RunDir, RunDirError
from harness.training.checkpoints import TrainingState, complete_checkpoints, save_checkpoint
from harness.training.start import StartMode, check_resumable, resume_start, train_run
from harness.training.train import StopOnSignal, stop_on_signals
from tests.conftest import interrupted_past

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
TINY = [
    "phases.initial.timesteps=1200",
    "phases.optimizing.timesteps=400",
    "checkpoint.every=400",
    "eval.every=600",
    "eval.episodes=2",
]


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny run stopped by Ctrl-C at about step 1000 (checkpoints kept: 800 and ~1000)."""
    runs = tmp_path_factory.mktemp("runs")
    args = ["run", str(SMOKE), "--runs-dir", str(runs), "--no-progress"]
    args += [a for o in TINY for a in ("--set", o)]
    with interrupted_past(1000):
        assert main(args) == 128 + signal.SIGINT
    (run,) = runs.iterdir()
    assert len(complete_checkpoints(run / "checkpoints")) == 2
    return run


@pytest.fixture
def run_copy(stopped_run: Path, tmp_path: Path) -> Path:
    copy = tmp_path / stopped_run.name
    shutil.copytree(stopped_run, copy)
    return copy


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (but the lock file) with a hash of its content."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


def episode_numbers(run: Path) -> list[int]:
    with (run / "episodes.csv").open(newline="") as f:
        return [int(row["episode"]) for row in csv.DictReader(f)]


def resume(run: Path) -> int:
    return main(["run", "--resume", str(run), "--no-progress"])


def one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith("harness: error:"), err
    assert "Traceback" not in "\n".join(err)
    return err[-1]


def newest(run: Path) -> Path:
    return complete_checkpoints(run / "checkpoints")[-1]


def test_resume_finishes_with_consecutive_episodes(run_copy, capsys):
    assert resume(run_copy) == 0
    numbers = episode_numbers(run_copy)
    assert numbers == list(range(len(numbers)))
    assert (run_copy / "model.zip").is_file()


def test_resume_before_the_first_checkpoint_starts_again_in_the_same_folder(tmp_path, capsys):
    run = RunDir(tmp_path / "killed-early")
    run.tb.mkdir(parents=True)
    run.checkpoints.mkdir()
    run.config.write_text(load_config(SMOKE, TINY).to_yaml())
    # What a first attempt killed at step ~300 left behind (0.123456: a marker).
    run.episodes_csv.write_text(
        "episode,phase,timesteps,copy,coverage,reward_mean,wall_hits,new_cells,length\n"
        "0,initial,200,0,0.123456,1.0,0,1;2,50\n"
    )
    assert resume(run.path) == 0
    assert "starting the run again from step 0" in capsys.readouterr().err
    text = run.episodes_csv.read_text()
    assert "0.123456" not in text
    assert episode_numbers(run.path) == list(range(len(episode_numbers(run.path))))
    assert run.model.is_file()


def test_the_training_layer_says_what_a_resume_does_and_changes_nothing(run_copy, tmp_path):
    # The decision (and its line) is harness.training.start's; the CLI prints it and trains.
    run = RunDir(run_copy)
    before = snapshot(run_copy)
    start = resume_start(run, load_config(run.config))
    assert (start.mode, start.message, start.trains) == (
        StartMode.RESUME,
        f"resuming {run.path}",
        True,
    )
    early = RunDir(tmp_path / "killed-early")
    early.checkpoints.mkdir(parents=True)
    early.config.write_text(run.config.read_text())
    start = resume_start(early, load_config(early.config))
    assert start.mode is StartMode.RESTART and "from step 0 in the same folder" in start.message
    with pytest.raises(RunDirError, match="not a run folder"):
        check_resumable(RunDir(tmp_path / "empty"))
    with pytest.raises(RunDirError, match="is a checkpoint of"):
        check_resumable(RunDir(newest(run_copy)))
    with pytest.raises(ValueError, match="not trained"):
        train_run(load_config(run.config), run, StartMode.FINISHED)
    assert snapshot(run_copy) == before


def test_a_second_process_on_a_live_run_is_refused(run_copy, capsys):
    before = snapshot(run_copy)
    with RunDir(run_copy).lock():  # this process plays the live run
        assert resume(run_copy) == 2
    err = one_line_error(capsys)
    assert f"in use by process {os.getpid()}" in err
    assert snapshot(run_copy) == before


def test_a_lock_left_by_a_dead_process_is_taken_over(run_copy):
    (run_copy / ".lock").write_text("999999999\n")  # no process holds it any more
    assert resume(run_copy) == 0


def test_unreadable_newest_checkpoint_falls_back_to_the_older_one(run_copy, capsys):
    older, latest = complete_checkpoints(run_copy / "checkpoints")
    (latest / "model.zip").write_bytes(b"not a zip")
    assert resume(run_copy) == 0
    err = capsys.readouterr().err
    assert f"resuming from the older {older.name}" in err and "model.zip: unreadable" in err
    # The unreadable one is kept to look at, but no longer counts among the two kept.
    assert (latest.parent / f"unusable-{latest.name}" / "model.zip").read_bytes() == b"not a zip"
    assert len(complete_checkpoints(run_copy / "checkpoints")) == 2
    assert latest not in complete_checkpoints(run_copy / "checkpoints")
    assert episode_numbers(run_copy) == list(range(len(episode_numbers(run_copy))))


@pytest.mark.parametrize("damaged", ["model.zip", "rng.pkl", "state.json", "replay_buffer.pkl"])
def test_no_readable_checkpoint_is_one_line_and_changes_nothing(run_copy, capsys, damaged):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        (checkpoint / damaged).write_bytes(b"\x80garbage")
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    assert f"{damaged}: unreadable" in one_line_error(capsys)
    assert snapshot(run_copy) == before


def test_a_checkpoint_of_an_older_model_format_is_refused_in_one_line(run_copy, capsys):
    import zipfile

    from harness.sb3.dqn import FORMAT_KEY

    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        model = checkpoint / "model.zip"
        with zipfile.ZipFile(model) as zin:
            items = [(item, zin.read(item.filename)) for item in zin.infolist()]
        with zipfile.ZipFile(model, "w") as zout:  # the zip as a version before formats wrote it
            for item, content in items:
                if item.filename == "data":
                    data = json.loads(content)
                    del data[FORMAT_KEY]
                    content = json.dumps(data).encode()
                zout.writestr(item, content)
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = one_line_error(capsys)
    assert "older version of the harness (model format 1" in err
    assert err.endswith("retrain it with this version")
    assert snapshot(run_copy) == before


def test_every_shipped_model_is_in_todays_format():
    from harness.prior.evaluate import is_prior_run
    from harness.sb3.dqn import MODEL_FORMAT, saved_model_format

    folders = (ROOT / "runs" / "reference").iterdir()
    models = [RunDir(p).model for p in folders if not is_prior_run(p)]
    models = [m for m in models if m.is_file()] + sorted((ROOT / "docs").rglob("*.zip"))
    assert len(models) == 22
    assert {saved_model_format(m) for m in models} == {MODEL_FORMAT}


def test_tampered_state_never_deletes_episode_rows(run_copy, capsys):
    latest = newest(run_copy)
    state = json.loads((latest / "state.json").read_text())
    assert state["next_episode"] > 0
    state["next_episode"] = 0  # would drop every row if it were believed
    (latest / "state.json").write_text(json.dumps(state))
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = one_line_error(capsys)
    assert "episodes.csv" in err and "nothing was changed" in err
    assert snapshot(run_copy) == before


def test_state_that_contradicts_its_model_is_not_used(run_copy, capsys):
    latest = newest(run_copy)
    state = json.loads((latest / "state.json").read_text())
    state["num_timesteps"] += 4000
    (latest / "state.json").write_text(json.dumps(state))
    assert resume(run_copy) == 0  # the older checkpoint is consistent
    assert "but the model is at step" in capsys.readouterr().err


def test_torn_last_line_is_dropped_and_numbering_continues(run_copy):
    with (run_copy / "episodes.csv").open("a") as f:
        f.write("57,initial,99999,1,0.5")  # a kill in the middle of an append
    assert resume(run_copy) == 0
    numbers = episode_numbers(run_copy)
    assert numbers == list(range(len(numbers)))


def test_damaged_episode_log_is_one_line_and_changes_nothing(run_copy, capsys):
    lines = (run_copy / "episodes.csv").read_text().splitlines(keepends=True)
    lines.insert(2, "this,is,not,an,episode\n")
    (run_copy / "episodes.csv").write_text("".join(lines))
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    assert "episodes.csv: line 3" in one_line_error(capsys)
    assert snapshot(run_copy) == before


def test_an_interrupted_checkpoint_write_leaves_no_temporary_folder(tmp_path):
    class FailingModel:
        num_timesteps = 40

        def save(self, f):
            f.write(b"half")
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(FailingModel(), tmp_path / "checkpoints", TrainingState())
    assert list((tmp_path / "checkpoints").iterdir()) == []


def test_second_ctrl_c_while_saving_waits_for_the_save(capsys):
    stopper = StopOnSignal()
    with stop_on_signals(stopper):
        os.kill(os.getpid(), signal.SIGINT)  # first: a clean stop is asked for
        assert stopper.signum == signal.SIGINT
        with stopper.saving():
            os.kill(os.getpid(), signal.SIGINT)  # second, during the save: ignored
        assert "still writing the checkpoint" in capsys.readouterr().err
        with pytest.raises(KeyboardInterrupt):  # outside a save it interrupts at once
            os.kill(os.getpid(), signal.SIGINT)


def test_rng_file_round_trip_checks_its_content(run_copy):
    from harness.training.checkpoints import CheckpointError, read_rng

    latest = newest(run_copy)
    read_rng(latest)  # intact: fine
    with (latest / "rng.pkl").open("wb") as f:
        pickle.dump({"numpy": "nonsense"}, f)
    with pytest.raises(CheckpointError, match=r"rng\.pkl: unreadable"):
        read_rng(latest)


# ---------------------------------------------------------------------- what is in the folder
def edit_config(run: Path, key: str, value: object) -> None:
    """Set ``key`` (dotted, phases by name) in the run's config.yaml, as a person would."""
    path = run / "config.yaml"
    data = yaml.safe_load(path.read_text())
    *parents, last = key.split(".")
    node = data
    for part in parents:
        node = next(p for p in node if p["name"] == part) if isinstance(node, list) else node[part]
    node[last] = value
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def only_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("harness: error:"), err
    return err[0]


@pytest.mark.parametrize(
    ("key", "value", "shown"),
    [
        ("env.n_agents", 3, "env.n_agents: 2 -> 3"),
        ("algo.net_arch", [32], "algo.net_arch: [64, 64] -> [32]"),
        ("vec.copies", 3, "vec.copies: 2 -> 3"),
        ("algo.buffer_size", 4000, "algo.buffer_size: 5000 -> 4000"),
        ("phases.initial.timesteps", 600, "phases.initial.timesteps: 1200 -> 600"),
    ],
)
def test_an_edited_config_is_refused_naming_the_keys(run_copy, capsys, key, value, shown):
    edit_config(run_copy, key, value)
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = only_line(capsys)
    assert f"{run_copy / 'config.yaml'}: changed since {newest(run_copy).name}" in err
    assert shown in err, err
    assert snapshot(run_copy) == before


def test_settings_of_the_machine_may_change(run_copy):
    edit_config(run_copy, "algo.threads", 1)
    edit_config(run_copy, "checkpoint.every", 300)
    assert resume(run_copy) == 0


def written_before_config_copies(checkpoint: Path) -> None:
    """Make ``checkpoint`` as written before checkpoints kept their config: no ``config.yaml``,
    and a ``state.json`` that lists no guard files."""
    (checkpoint / "config.yaml").unlink()
    state = json.loads((checkpoint / "state.json").read_text())
    del state["guards"]
    (checkpoint / "state.json").write_text(json.dumps(state))


def test_checkpoints_without_their_config_still_resume(run_copy):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        written_before_config_copies(checkpoint)
    assert resume(run_copy) == 0
    stored = yaml.safe_load((newest(run_copy) / "config.yaml").read_text())
    assert stored == yaml.safe_load((run_copy / "config.yaml").read_text())


def test_checkpoints_without_their_config_still_refuse_another_team_size(run_copy, capsys):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        written_before_config_copies(checkpoint)
    edit_config(run_copy, "env.n_agents", 3)
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    assert "env.n_agents x vec.copies is 6" in one_line_error(capsys)
    assert snapshot(run_copy) == before


def test_a_deleted_config_copy_does_not_let_an_edited_config_through(run_copy, capsys):
    older = complete_checkpoints(run_copy / "checkpoints")[0]
    (newest(run_copy) / "config.yaml").unlink()  # its state.json says it was written
    edit_config(run_copy, "algo.net_arch", [32])
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = one_line_error(capsys)
    # The newest checkpoint is damaged; the older one's copy still sees the edit.
    assert f"changed since {older.name} was written (algo.net_arch: [64, 64] -> [32])" in err
    assert snapshot(run_copy) == before


def test_checkpoints_that_all_lost_their_config_copy_are_refused(run_copy, capsys):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        (checkpoint / "config.yaml").unlink()
    edit_config(run_copy, "algo.buffer_size", 4000)
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = one_line_error(capsys)
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        assert f"{checkpoint / 'config.yaml'}: missing (written with the checkpoint" in err
    assert snapshot(run_copy) == before


def test_tune_write_of_an_unfinished_run_is_refused_and_keeps_its_resume(run_copy, capsys):
    model = newest(run_copy) / "model.zip"
    before = snapshot(run_copy)
    args = ["tune", str(model), "--temperatures", "2.5", "--episodes", "1", "--write"]
    assert main(args) == 2
    err = only_line(capsys)
    assert f"--write: {run_copy} has not finished training" in err
    assert "nothing was written" in err
    assert snapshot(run_copy) == before
    assert resume(run_copy) == 0


def test_a_finished_run_without_checkpoints_is_refused_and_keeps_its_model(run_copy, capsys):
    assert resume(run_copy) == 0
    capsys.readouterr()
    shutil.rmtree(run_copy / "checkpoints")
    model = (run_copy / "model.zip").read_bytes()
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = only_line(capsys)
    assert "this run is finished" in err and "no checkpoint to resume from" in err
    assert "model.zip is kept" in err
    assert (run_copy / "model.zip").read_bytes() == model
    assert snapshot(run_copy) == before


@pytest.mark.parametrize(
    "fails", ["harness.cli.atomic_write_text", "harness.training.train.make_vec_env"]
)
def test_a_full_disk_at_start_removes_the_new_run_folder(tmp_path, capsys, monkeypatch, fails):
    def full_disk(path, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(fails, full_disk)
    runs = tmp_path / "runs"
    assert main(["run", str(SMOKE), "--runs-dir", str(runs), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("harness: error: No space left on device"), err
    assert "; removed the run folder " in err[-1] and "(nothing was trained)" in err[-1]
    assert list(runs.iterdir()) == []


# ------------------------------------------------------------------ the buffer's file


class _BufferHolder:
    """What SB3's save_replay_buffer / load_replay_buffer use of a model."""

    import torch

    verbose = 0
    device = torch.device("cpu")

    def __init__(self, buffer: Any) -> None:
        self.replay_buffer = buffer

    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    save_replay_buffer = OffPolicyAlgorithm.save_replay_buffer
    load_replay_buffer = OffPolicyAlgorithm.load_replay_buffer


def _same(a: Any, b: Any) -> bool:
    """Deep equality of a buffer's state: arrays and tensors by value, dtype and shape."""
    import numpy as np
    import torch as th

    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b)
    if isinstance(a, th.Tensor):
        return isinstance(b, th.Tensor) and a.dtype == b.dtype and th.equal(a, b)
    if hasattr(a, "__dict__") and type(a).__module__.startswith("harness"):
        return _same(vars(a), vars(b))
    if isinstance(a, th.Generator):
        return th.equal(a.get_state(), b.get_state())
    return type(a) is type(b)


OBS = 64


def _buffers() -> dict[str, Any]:
    import numpy as np
    from gymnasium import spaces
    from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer

    from harness.sb3.policies import ACTION_MASK_KEY
    from harness.sb3.replay import PrioritizedReplayBuffer
    from tests.replay_variants import (
        DevicePrioritizedReplayBuffer,
        DeviceReplayBuffer,
        PerDecisionPrioritizedDictReplayBuffer,
    )

    # Observations large beside the sum tree and the scratch, as a real buffer's are.
    box = spaces.Box(-1, 1, shape=(OBS,), dtype=np.float32)
    act = spaces.Discrete(3)
    masked = spaces.Dict({"x": box, ACTION_MASK_KEY: spaces.Box(0, 1, shape=(3,), dtype=np.int8)})
    return {
        "sb3": ReplayBuffer(400, box, act, n_envs=2),
        "sb3_dict": DictReplayBuffer(400, spaces.Dict({"x": box}), act, n_envs=2),
        "prioritized": PrioritizedReplayBuffer(400, box, act, n_envs=2, n_steps=3),
        "device": DevicePrioritizedReplayBuffer(400, box, act, device="cpu", n_envs=2),
        "device_uniform": DeviceReplayBuffer(400, box, act, device="cpu", n_envs=2, n_steps=2),
        "per_decision": PerDecisionPrioritizedDictReplayBuffer(
            400, masked, act, n_envs=2, labels=True
        ),
    }


@pytest.mark.parametrize(
    "kind", ["sb3", "sb3_dict", "prioritized", "device", "device_uniform", "per_decision"]
)
@pytest.mark.parametrize("steps", [0, 7, 200, 230])  # empty, part-filled, full, wrapped round
def test_a_saved_buffer_leaves_out_its_unfilled_rows_and_loads_equal(
    tmp_path: Path, kind: str, steps: int
) -> None:
    import numpy as np

    from harness.training.checkpoints import save_replay_buffer

    buffer = _buffers()[kind]
    rng = np.random.default_rng(0)
    for _ in range(steps):
        x, x2 = rng.uniform(-1, 1, (2, OBS)).astype(np.float32), rng.uniform(-1, 1, (2, OBS))
        if kind.startswith("sb3_dict"):
            x, x2 = {"x": x}, {"x": x2.astype(np.float32)}
        elif kind == "per_decision":
            mask = np.ones((2, 3), dtype=np.int8)
            x, x2 = {"x": x, "action_mask": mask}, {"x": x2.astype(np.float32), "action_mask": mask}
        infos = [{"expert_action": 1}, {}] if kind == "per_decision" else [{}, {}]
        buffer.add(
            x, x2, rng.integers(0, 3, (2, 1)), rng.normal(size=2), rng.random(2) < 0.1, infos
        )
    if kind in ("prioritized", "device") and steps:
        buffer.update_priorities(np.arange(4), np.array([0.5, 2.0, 1.0, 3.0]))
    before = dict(vars(buffer))
    path = tmp_path / "buffer.pkl"
    with path.open("wb") as f:
        save_replay_buffer(_BufferHolder(buffer), f)
    assert all(vars(buffer)[name] is value for name, value in before.items())  # untouched
    whole = len(pickle.dumps(buffer, protocol=pickle.HIGHEST_PROTOCOL))
    if 0 < steps < 200:  # a part-filled buffer's file holds about its stored share
        assert path.stat().st_size < whole * 0.2
    elif steps >= 200:  # full: nothing to leave out
        assert path.stat().st_size >= whole * 0.95
    # SB3's loader and a plain unpickling both give the whole buffer back.
    loaded = _BufferHolder(None)
    with path.open("rb") as f:
        loaded.load_replay_buffer(f)
    with path.open("rb") as f:
        unpickled = pickle.load(f)
    for other in (loaded.replay_buffer, unpickled):
        assert type(other) is type(buffer)
        assert vars(other).keys() == vars(buffer).keys()
        for name, value in vars(buffer).items():
            assert _same(value, getattr(other, name)), name


def test_a_device_buffers_state_keeps_its_tensors_until_the_checkpoint_has_cut_them() -> None:
    # A checkpoint cuts the unfilled rows where the tensors are (on a GPU), then copies only
    # the kept rows to the host: stored_state hands over the buffer's own tensors, not copies.
    import torch

    buffer = _buffers()["device"]
    state = buffer.stored_state()  # flat: each part's fields under its name
    assert state["storage.observations"] is buffer.observations
    assert state["sampler._raw_priorities"] is buffer._raw_priorities
    assert "sampler._cursor" not in state  # made again on loading
    host = buffer.host_state(state)
    tensors = [value for value in host.values() if isinstance(value, torch.Tensor)]
    assert tensors and all(tensor.device.type == "cpu" for tensor in tensors)
    assert host["pos"] == buffer.pos and host["sampler._generator"] == state["sampler._generator"]
