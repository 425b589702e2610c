"""Re-evaluate every committed reference policy on all the episodes of its committed
``eval.json`` and compare, episode by episode (coverage and wall hits), with what was stored;
with ``--baselines``, every stored written-policy evaluation ``docs/baselines/*.json`` (the
planner rows of docs/results.md and README's baseline tables), every number of it.

The guard that a change of the simulation path (the batched core, the compiled searches) left
every published result as it was: episode ``k`` is seeded with ``seed + k`` and its action noise
too, so a policy evaluated again on the same episodes must give the same numbers.

    python scripts/check_references.py [NAME ...]   # default: every runs/reference/*/eval.json
    python scripts/check_references.py --baselines [PATTERN]  # e.g. '*-frontier_hungarian'

Prints one line per evaluation and exits 1 when any differs. Evaluates copies in a temporary
folder: the committed files are not touched.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

from harness.cli import main as harness

ROOT = Path(__file__).resolve().parents[1]


def check(name: str, scratch: Path) -> bool:
    ref = ROOT / "runs" / "reference" / name
    committed = json.loads((ref / "eval.json").read_text())
    copy = scratch / name
    copy.mkdir()
    for f in ("config.yaml", "model.zip"):
        (copy / f).write_bytes((ref / f).read_bytes())
    start = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = harness(["eval", str(copy), "--episodes", str(committed["episodes"]), "--json"])
    (saved_file,) = copy.glob("eval*.json")
    saved = json.loads(saved_file.read_text())
    same = (
        code == 0
        and saved["temperature"] == committed["temperature"]
        and saved["coverage"] == committed["coverage"]
        and saved["wall_hits"] == committed["wall_hits"]
    )
    took = time.perf_counter() - start
    print(
        f"{name:<28} {committed['episodes']:>4} episodes  coverage_mean "
        f"{saved['coverage_mean']:.4f} (stored {committed['coverage_mean']:.4f})  "
        f"{'same' if same else 'DIFFERENT'}  {took:.0f} s",
        flush=True,
    )
    return same


#: The figures every stored evaluation holds (the tables quote them).
_FIGURES = ("episodes", "coverage_mean", "coverage_median", "wall_hits_mean")


def _same_numbers(new: dict, stored: dict) -> bool:
    """Every figure both hold is equal, and the figures the tables quote are there (fields
    added to the output since, such as an interval, or dropped since, such as an old reward
    setting, are not a difference; nor is the env's settings, which older files wrote in an
    older form: the env is the config's)."""
    new.pop("env", None), stored.pop("env", None)
    shared = set(new) & set(stored)
    return all(k in shared for k in _FIGURES) and all(new[k] == stored[k] for k in shared)


def check_baseline(stored: Path) -> bool:
    """Evaluate a stored baseline again (its config, policy, episodes and max_steps override,
    as ``scripts/baselines.sh`` named it) and compare every number."""
    committed = json.loads(stored.read_text())
    policy = committed["policy"]
    stem = stored.name.removesuffix(f"-{policy}.json")
    config, _, max_steps = stem.partition("-env.max_steps-")
    args = ["eval", "--policy", policy, "--config", str(ROOT / "configs" / f"{config}.yaml")]
    args += ["--episodes", str(committed["episodes"]), "--json"]
    if max_steps:
        args += ["--set", f"env.max_steps={max_steps}"]
    start = time.perf_counter()
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = harness(args)
    same = code == 0 and _same_numbers(json.loads(out.getvalue()), committed)
    print(
        f"{stored.stem:<44} {committed['episodes']:>4} episodes  coverage_mean "
        f"{committed['coverage_mean']:.4f}  {'same' if same else 'DIFFERENT'}  "
        f"{time.perf_counter() - start:.0f} s",
        flush=True,
    )
    return same


def main(names: list[str]) -> int:
    if names[:1] == ["--baselines"]:
        patterns = names[1:] or ["*"]
        stored = sorted(
            {p for pat in patterns for p in (ROOT / "docs" / "baselines").glob(f"{pat}.json")}
        )
        return 0 if all([check_baseline(p) for p in stored]) else 1
    if not names:
        names = sorted(p.parent.name for p in (ROOT / "runs" / "reference").glob("*/eval.json"))
    with tempfile.TemporaryDirectory() as tmp:
        results = [check(name, Path(tmp)) for name in names]
    return 0 if all(results) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
