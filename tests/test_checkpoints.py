"""Checkpoints (``harness.training.checkpoints``): only complete ones count; each keeps the
SHA-256 of its replay buffer, and a damaged or unguarded buffer falls back to the older
checkpoint or is a one-line refusal; ``state.json`` reads back what was written, and older
forms of it still read."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from harness.training.checkpoints import (
    CheckpointError,
    TrainingState,
    complete_checkpoints,
    latest_checkpoint,
)
from tests.stopping import contiguous, evaluation_steps, harness_lines, resume, snapshot, state_of


def test_half_written_checkpoints_are_ignored(tmp_path):
    folder = tmp_path / "checkpoints"
    (folder / ".step-000000000300.tmp").mkdir(parents=True)  # crash while writing
    (folder / "step-000000000200").mkdir()
    (folder / "step-000000000200" / "state.json").write_text(TrainingState().to_json())
    (folder / "step-000000000400").mkdir()  # no state.json: incomplete
    assert latest_checkpoint(folder).name == "step-000000000200"
    with pytest.raises(CheckpointError, match="no complete checkpoint"):
        latest_checkpoint(tmp_path / "nothing")


def test_training_state_json_round_trip():
    state = TrainingState(phase=1, phase_start=40, next_episode=7, best_eval=0.5, resumes=2)
    assert TrainingState.from_json(state.to_json()) == state
    fresh = TrainingState()
    assert TrainingState.from_json(fresh.to_json()).best_eval == float("-inf")


# ------------------------------------------------------------------ 3. a damaged replay buffer
def flip_a_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # in the middle: the arrays' bytes, which unpickle regardless
    path.write_bytes(bytes(data))


def test_checkpoints_keep_the_sha256_of_their_replay_buffer(run_copy):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        stored = (checkpoint / "replay_buffer.pkl.sha256").read_text().split()
        digest = hashlib.sha256((checkpoint / "replay_buffer.pkl").read_bytes()).hexdigest()
        assert stored == [digest, "replay_buffer.pkl"]  # as sha256sum writes it


def test_a_flipped_byte_in_the_replay_buffer_falls_back_to_the_older_checkpoint(run_copy, capsys):
    older, newest = complete_checkpoints(run_copy / "checkpoints")
    flip_a_byte(newest / "replay_buffer.pkl")
    assert resume(run_copy) == 0
    err = capsys.readouterr().err
    (line,) = [line for line in harness_lines(err) if "resuming from the older" in line]
    assert f"{newest / 'replay_buffer.pkl'}: unreadable (damaged: its SHA-256" in line
    assert line.endswith(f"resuming from the older {older.name}")
    assert (newest.parent / f"unusable-{newest.name}").is_dir()  # set aside, as a bad model is
    assert contiguous(run_copy) and evaluation_steps(run_copy) == [600, 1200]


def test_a_flipped_byte_in_the_only_checkpoint_is_a_one_line_refusal(run_copy, capsys):
    older, newest = complete_checkpoints(run_copy / "checkpoints")
    shutil.rmtree(older)
    flip_a_byte(newest / "replay_buffer.pkl")
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("harness: error: ") and "Traceback" not in "\n".join(err)
    assert f"{newest / 'replay_buffer.pkl'}: unreadable (damaged: its SHA-256" in err[-1]
    assert snapshot(run_copy) == before


def written_before_guards(checkpoint: Path, *files: str) -> None:
    """Make ``checkpoint`` as written before it kept ``files``: without them, and with a
    ``state.json`` that does not list its guard files."""
    for name in files:
        (checkpoint / name).unlink()
    state = json.loads((checkpoint / "state.json").read_text())
    del state["guards"]
    (checkpoint / "state.json").write_text(json.dumps(state))


def test_checkpoints_without_a_stored_sha256_still_resume(run_copy):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        written_before_guards(checkpoint, "replay_buffer.pkl.sha256")
    assert resume(run_copy) == 0
    assert contiguous(run_copy)


def test_a_deleted_sha256_falls_back_to_the_older_checkpoint(run_copy, capsys):
    older, newest = complete_checkpoints(run_copy / "checkpoints")
    assert state_of(newest).guards == ["replay_buffer.pkl.sha256", "config.yaml"]
    (newest / "replay_buffer.pkl.sha256").unlink()  # its buffer must not load unchecked
    assert resume(run_copy) == 0
    err = capsys.readouterr().err
    (line,) = [line for line in harness_lines(err) if "resuming from the older" in line]
    assert f"{newest / 'replay_buffer.pkl.sha256'}: missing (written with the checkpoint" in line
    assert line.endswith(f"resuming from the older {older.name}")
    assert (newest.parent / f"unusable-{newest.name}").is_dir()
    assert contiguous(run_copy)


def test_checkpoints_that_all_lost_their_sha256_are_a_one_line_refusal(run_copy, capsys):
    for checkpoint in complete_checkpoints(run_copy / "checkpoints"):
        (checkpoint / "replay_buffer.pkl.sha256").unlink()
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("harness: error: ") and "Traceback" not in "\n".join(err)
    assert "replay_buffer.pkl.sha256: missing" in err[-1]
    assert snapshot(run_copy) == before


def test_a_state_listing_unknown_guards_is_unreadable():
    data = json.loads(TrainingState().to_json())
    for bad in ("config.yaml", ["model.zip"], [1]):
        with pytest.raises(ValueError, match="guards"):
            TrainingState.from_json(json.dumps({**data, "guards": bad}))


def test_a_state_without_pending_eval_still_reads():
    state = TrainingState(next_episode=3, num_timesteps=40)
    data = json.loads(state.to_json())
    del data["pending_eval"]  # as written before checkpoints kept it
    assert TrainingState.from_json(json.dumps(data)) == state
    for bad in (-1, True, 1.5):
        with pytest.raises(ValueError, match="pending_eval"):
            TrainingState.from_json(json.dumps({**data, "pending_eval": bad}))


@pytest.mark.parametrize("linked", ["replay_buffer.pkl", "checkpoint"])
def test_a_checkpoint_that_links_out_of_its_run_is_not_loaded(linked, run_copy, tmp_path, capsys):
    # A downloaded run whose newest checkpoint (or its buffer) is a link to a file elsewhere:
    # that pickle is never loaded; the resume goes on from the older checkpoint.
    older, newest = complete_checkpoints(run_copy / "checkpoints")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    if linked == "checkpoint":
        moved = elsewhere / newest.name
        shutil.move(newest, moved)
        newest.symlink_to(moved, target_is_directory=True)
        bad = newest
    else:
        outside = elsewhere / "replay_buffer.pkl"
        shutil.move(newest / "replay_buffer.pkl", outside)
        (newest / "replay_buffer.pkl").symlink_to(outside)
        bad = newest / "replay_buffer.pkl"
    assert resume(run_copy) == 0
    err = capsys.readouterr().err
    (line,) = [line for line in harness_lines(err) if "resuming from the older" in line]
    assert f"{bad} leads outside the run folder" in line
    assert line.endswith(f"resuming from the older {older.name}")
    assert contiguous(run_copy)
