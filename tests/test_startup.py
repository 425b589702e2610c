"""The command starts fast: ``harness --help``, ``harness run --help`` and a config error do not
import torch or Stable-Baselines3 (about 1.5 s of the 2 s that ``import harness.cli`` once took;
measure with ``python -X importtime -c "import harness.cli"``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "stable_baselines3", "supersuit", "matplotlib")

PROBE = f"""
import contextlib, io, json, sys
from harness.cli import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    rc = main(sys.argv[1:])
print(json.dumps({{"rc": rc, "loaded": [m for m in {HEAVY!r} if m in sys.modules]}}))
"""


@pytest.mark.parametrize(
    ("args", "rc"),
    [
        (["--help"], 0),
        (["run", "--help"], 0),
        (["eval", "--help"], 0),
        (["run", "configs/smoke.yaml", "--set", "env.n_agentz=2"], 2),
        (["run", "configs/smoke.yaml", "--set", "algo.policy=Nope"], 2),
        (["run", "missing.yaml"], 2),
    ],
    ids=["help", "run-help", "eval-help", "unknown-key", "unknown-policy", "missing-config"],
)
def test_help_and_config_errors_do_not_import_torch(args, rc):
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, *args], capture_output=True, text=True, cwd=ROOT
    )
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["rc"] == rc
    assert result["loaded"] == []
