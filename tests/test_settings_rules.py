"""A setting is what it says: a device this machine lacks is refused in one line wherever the
config comes from (``--set``, a sweep's space, a run's ``config.yaml`` edited before
``--resume``), not trained on the CPU without a word; counts are whole numbers, capped."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from harness.cli import main
from tests.conftest import one_error_line
from tests.stopping import snapshot
from tests.test_seeds_and_sweeps import TINY

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"

#: A CUDA device this machine does not have.
MISSING = f"cuda:{torch.cuda.device_count()}" if torch.cuda.is_available() else "cuda"


def test_a_resume_of_a_config_edited_to_a_missing_device_is_refused(run_copy, capsys):
    config = run_copy / "config.yaml"
    config.write_text(config.read_text().replace("device: auto", f"device: {MISSING}"))
    assert f"device: {MISSING}" in config.read_text()
    before = snapshot(run_copy)
    assert main(["run", "--resume", str(run_copy), "--no-progress"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith(f"harness: error: {config}: algo.device: '{MISSING}' asked for")
    assert snapshot(run_copy) == before  # nothing changed


def test_a_sweep_space_naming_a_missing_device_is_refused_before_any_trial(tmp_path, capsys):
    config = tmp_path / "tiny.yaml"
    config.write_text(TINY)
    space = tmp_path / "space.yaml"
    space.write_text(f"algo.device: {{choice: [cpu, '{MISSING}']}}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(config), "--space", str(space), "--trials", "2", "--sweeps-dir",
            str(sweeps)]  # fmt: skip
    assert main(args) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith(f"harness: error: space key algo.device='{MISSING}': algo.device: ")
    assert not list(sweeps.glob("*/trial-*"))


@pytest.mark.parametrize(
    ("override", "words"),
    [
        ("vec.copies=true", "vec.copies: Input should be a valid integer"),
        ("vec.copies=2.0", "vec.copies: Input should be a valid integer"),
        ("vec.copies=5000", "vec.copies: Input should be less than or equal to 4096"),
        ("eval.rollout.samples=2e3", "eval.rollout.samples: Input should be a valid integer"),
        ("eval.rollout.samples=8.0", "eval.rollout.samples: Input should be a valid integer"),
        ("eval.rollout.samples=1000", "eval.rollout.samples: Input should be less than or equal"),
    ],
)
def test_counts_are_whole_numbers_within_their_caps(tmp_path, capsys, override, words):
    runs = tmp_path / "runs"
    assert main(["run", str(SMOKE), "--runs-dir", str(runs), "--set", override]) == 2
    assert words in one_error_line(capsys.readouterr().err)
    assert not runs.exists() or not list(runs.iterdir())


def test_copies_times_agents_is_capped_at_the_documented_slots(tmp_path, capsys):
    from harness.config.schema import MAX_SLOTS

    runs = tmp_path / "runs"
    sets = ["--set", "env.n_agents=3", "--set", f"vec.copies={MAX_SLOTS // 3 + 1}"]
    assert main(["run", str(SMOKE), "--runs-dir", str(runs), *sets]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"vec.copies: {MAX_SLOTS // 3 + 1:,} copies of 3 agents make" in line
    assert f"more than the {MAX_SLOTS:,} a run can step" in line
