"""The core refuses what it cannot hold in one line, and mends what it can: NaN or infinite
rewards and maps over ``MAX_MAP_CELLS`` refused by the Python API, a random map too small for
its team refused by a config's check, a damaged compiled cache compiled again, and a
``NUMBA_NUM_THREADS`` below 1 refused before numba loads."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from envs import coverage_v0
from envs.coverage.core import MAX_MAP_CELLS
from harness.config import schema
from tests.conftest import refused_run, root_first_env

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"


@pytest.mark.parametrize(
    "rewards",
    [{"wall_hit": float("-inf")}, {"step": float("nan")}, {"new_cell": "2"}, {"team": True}],
    ids=["inf", "nan", "text", "bool"],
)
def test_the_env_refuses_rewards_that_are_not_finite_numbers(rewards):
    (key,) = rewards
    with pytest.raises(ValueError, match=f"rewards.{key} must be a finite number"):
        coverage_v0.parallel_env(height=6, width=6, n_agents=2, rewards=rewards)


def test_the_env_refuses_a_map_over_its_cap_before_allocating_it():
    assert MAX_MAP_CELLS == schema.MAX_MAP_CELLS  # one bound for the env and the configs
    start = time.monotonic()
    with pytest.raises(ValueError, match=r"a 3000x2000 map has 6,000,000 cells, more than"):
        coverage_v0.parallel_env(height=3000, width=2000, n_agents=2)
    assert time.monotonic() - start < 5
    coverage_v0.parallel_env(height=2000, width=2000, n_agents=2)  # at the cap: built


def test_a_random_map_too_small_for_its_team_is_a_config_error(tmp_path, capsys):
    runs = tmp_path / "runs"
    runs.mkdir()
    overrides = ["env.map=random", "env.height=3", "env.width=3", "env.n_agents=9",
                 "env.test_maps=[]"]  # fmt: skip
    line = refused_run(SMOKE, overrides, runs, capsys)
    assert "n_agents=9" in line and "3x3" in line


def _step_once(env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    code = (
        "from envs import coverage_v0\n"
        "e = coverage_v0.parallel_env(height=7, width=9, n_agents=3)\n"
        "e.reset(seed=1)\n"
        "e.step({a: 1 for a in e.agents})\n"
        "print('stepped')\n"
    )
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=300)  # fmt: skip


@pytest.mark.parametrize("damage", ["index", "data"])
def test_a_damaged_compiled_cache_is_compiled_again(tmp_path, damage):
    env = root_first_env(NUMBA_CACHE_DIR=str(tmp_path))
    first = _step_once(env)
    assert first.returncode == 0 and first.stdout == "stepped\n", first.stderr
    suffix = ".nbi" if damage == "index" else ".nbc"
    damaged = sorted(tmp_path.rglob(f"*{suffix}"))
    assert damaged
    for path in damaged:  # cut short, as a killed write or a full disk leaves it
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
    again = _step_once(env)
    assert again.returncode == 0 and again.stdout == "stepped\n", again.stderr
    lines = again.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("numba cache: a damaged entry in "), lines
    assert "removed, compiling again" in lines[0]
    mended = _step_once(env)  # written afresh: nothing to say
    assert mended.returncode == 0 and mended.stderr == ""


def test_numba_threads_below_one_is_one_line_for_the_command_and_the_env():
    env = root_first_env(NUMBA_NUM_THREADS="-3")
    harness = [sys.executable, "-m", "harness.cli", "eval", "--help"]
    proc = subprocess.run(harness, capture_output=True, text=True, env=env, cwd=ROOT)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.splitlines() == [
        "harness: error: NUMBA_NUM_THREADS=-3: numba needs at least 1 thread; unset it or give "
        "a whole number of at least 1"
    ]
    api = [sys.executable, "-c", "from envs import coverage_v0"]
    proc = subprocess.run(api, capture_output=True, text=True, env=env, cwd=ROOT)
    assert proc.returncode == 1
    assert proc.stderr.splitlines()[-1] == (
        "ValueError: NUMBA_NUM_THREADS=-3: numba needs at least 1 thread; unset it or give a "
        "whole number of at least 1"
    )
