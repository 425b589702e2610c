"""scripts/baselines.sh: regenerates the stored baseline evaluations README quotes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_baselines(
    tmp_path: Path, *configs: str, **variables: str
) -> subprocess.CompletedProcess[str]:
    # `harness` from this interpreter's environment, whether or not it is activated
    path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
    env = {**os.environ, "PATH": path, "OUT": str(tmp_path), "EPISODES": "2", **variables}
    return subprocess.run(
        ["bash", str(ROOT / "scripts" / "baselines.sh"), *configs],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )


def test_baselines_script_writes_one_file_per_policy_and_setting(tmp_path):
    done = run_baselines(tmp_path, "ddqn_15x15", "ddqn_1agent:500")
    assert done.returncode == 0, done.stderr
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(
        f"{stem}-{policy}.json"
        for stem in ("ddqn_15x15", "ddqn_1agent-env.max_steps-500")
        for policy in ("random", "local", "frontier")
    )
    short = json.loads((tmp_path / "ddqn_1agent-env.max_steps-500-local.json").read_text())
    assert short["policy"] == "local" and short["episodes"] == 2
    assert short["overrides"] == ["env.max_steps=500"] and short["env"]["max_steps"] == 500
    small = json.loads((tmp_path / "ddqn_15x15-frontier.json").read_text())
    assert small["env"]["height"] == 15 and small["overrides"] == []


def test_baselines_script_runs_only_the_policies_asked_for(tmp_path):
    done = run_baselines(tmp_path, "ddqn_15x15", POLICIES="frontier")
    assert done.returncode == 0, done.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["ddqn_15x15-frontier.json"]


def test_baselines_script_stops_on_an_unknown_config_without_leaving_a_file(tmp_path):
    done = run_baselines(tmp_path, "no_such_config")
    assert done.returncode == 2
    assert "no_such_config" in done.stderr
    assert list(tmp_path.iterdir()) == []
