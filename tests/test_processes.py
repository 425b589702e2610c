"""The processes the harness starts (seed groups, sweep workers, the memory benchmark) import
only the installed packages and this harness, never a module planted in the folder they are
started from (``harness.processes``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from harness.processes import harness_command, python_command
from harness.training import sweep
from tests.test_seeds_and_sweeps import TINY

PLANTED = ("yaml", "json", "numpy", "resource")


@pytest.fixture
def planted(tmp_path: Path) -> Path:
    """A folder whose yaml.py, json.py, numpy.py and resource.py each leave a mark when run."""
    for name in PLANTED:
        mark = tmp_path / f"ran-{name}"
        (tmp_path / f"{name}.py").write_text(f"open({str(mark)!r}, 'w').close()\n")
    return tmp_path


def marks(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.glob("ran-*"))


def test_the_planted_modules_would_run_in_a_plain_python_m_child(planted):
    # The hole the helpers close: `python -m` from that folder imports the planted yaml.py.
    subprocess.run([sys.executable, "-m", "harness.cli", "--help"], cwd=planted, check=False)
    assert marks(planted)


def test_a_harness_child_runs_nothing_from_its_start_folder(planted):
    proc = subprocess.run(harness_command("--help"), cwd=planted, capture_output=True, text=True)
    assert proc.returncode == 0 and "usage: harness" in proc.stdout
    assert marks(planted) == []


def test_a_python_child_runs_nothing_from_its_start_folder(planted):
    code = "import json, yaml, numpy, resource\nprint(numpy.__file__)"
    proc = subprocess.run(python_command(code), cwd=planted, capture_output=True, text=True)
    assert proc.returncode == 0 and "site-packages" in proc.stdout
    assert marks(planted) == []


def test_a_seed_group_started_from_a_planted_folder_runs_none_of_it(planted):
    # `harness run --seeds` starts one child per seed (harness.results.groups): end to end.
    (planted / "tiny.yaml").write_text(TINY)
    harness = Path(sys.executable).parent / "harness"  # the installed entry point
    cmd = [str(harness), "run", "tiny.yaml", "--seeds", "0,1", "--jobs", "2", "--no-progress"]
    proc = subprocess.run(cmd, cwd=planted, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert len(list(planted.glob("runs/tiny-*/tiny-seed*/model.zip"))) == 2
    assert marks(planted) == []


def test_sweep_workers_are_started_through_the_helper():
    study = sweep._Study(
        config_path=Path("c.yaml"),
        overrides=(),
        space_path=Path("s.yaml"),
        trials=2,
        study_name="s",
        sweeps_dir=Path("sweeps"),
        storage_url=None,
        pruner="none",
    )
    cmd = study.worker_command(1)
    assert cmd[:3] == harness_command()[:3] and cmd[3:5] == ["sweep", "c.yaml"]


def test_a_child_started_in_a_deleted_folder_says_so_in_one_line(tmp_path):
    # The bootstrap itself asks for the current folder (to drop it from sys.path).
    gone = tmp_path / "gone"
    gone.mkdir()
    cmd = ["sh", "-c", 'cd "$0" && rmdir "$0" && exec "$@"', str(gone)]
    proc = subprocess.run([*cmd, *python_command("print('ran')")], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.splitlines() == [
        "harness: error: the current folder was deleted: cd to an existing folder and run the "
        "command again"
    ]
