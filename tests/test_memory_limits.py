"""Short of memory, one line that says so: a replay buffer that fits the free memory but not the
process's address-space limit (``ulimit -v``) is refused up front naming both; a MemoryError
where the optimizer or the model is built is "out of memory", not a bad setting."""

from __future__ import annotations

import resource
from pathlib import Path

import pytest

import harness.training.train as train_module
from harness.cli import main
from harness.config.loading import load_config
from harness.training import checks
from tests.stopping import harness_lines

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"


def _limit_at(mp: pytest.MonkeyPatch, spare: int) -> int:
    """An address-space limit ``spare`` bytes above what this process maps now."""
    with open("/proc/self/status", encoding="ascii") as f:
        used = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
    limit = used + spare
    mp.setattr(resource, "getrlimit", lambda which: (limit, resource.RLIM_INFINITY))
    return limit


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="reads /proc")
def test_a_buffer_over_the_address_space_limit_is_refused_naming_both(monkeypatch):
    config = load_config(SMOKE, ["algo.buffer_size=3000000"])
    need = checks.check_replay_memory(config)  # no limit: fits the free memory
    _limit_at(monkeypatch, need // 2)
    with pytest.raises(ValueError) as refused:
        checks.check_replay_memory(config)
    words = str(refused.value)
    assert words.startswith(
        f"algo.buffer_size: a replay buffer of 3,000,000 transitions needs about "
        f"{checks.format_bytes(need)} (and training about 128.0 MiB more), more than the "
    )
    assert "this process may still map under its address-space limit of " in words
    assert words.endswith("(ulimit -v)")
    _limit_at(monkeypatch, need + checks.ADDRESS_SPACE_MARGIN // 2)  # the buffer fits, no more
    with pytest.raises(ValueError, match=r"^the address-space limit of .* \(ulimit -v\) leaves"):
        checks.check_replay_memory(config)
    _limit_at(monkeypatch, need + checks.ADDRESS_SPACE_MARGIN + (64 << 20))
    assert checks.check_replay_memory(config) == need  # room enough: passes


def test_out_of_memory_building_the_optimizer_is_said_so(monkeypatch):
    def throwaway(*args: object) -> None:
        raise MemoryError

    monkeypatch.setattr(checks, "_throwaway", throwaway)
    with pytest.raises(ValueError, match=r"^out of memory building the optimizer Adam \("):
        checks.check_optimizer("Adam", {})


def test_out_of_memory_building_the_model_is_one_line(tmp_path, monkeypatch, capsys):
    def build_model(*args: object) -> None:
        raise MemoryError  # as numpy raises it for a buffer a memory limit refuses

    monkeypatch.setattr(train_module, "build_model", build_model)
    runs = tmp_path / "runs"
    args = ["run", str(SMOKE), "--runs-dir", str(runs), "--no-progress",
            "--set", "algo.buffer_size=4000"]  # fmt: skip
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert harness_lines(err) == [
        "harness: error: out of memory building the model and its replay buffer of 4,000 "
        "transitions: lower algo.buffer_size, or raise the memory limit"
    ]
