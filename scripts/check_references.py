"""Re-evaluate every committed reference policy on all the episodes of its committed
``eval.json`` and compare, episode by episode (coverage and wall hits), with what was stored (a
map prior's reference: its log-loss scores);
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
from harness.results.rundir import RunDir

ROOT = Path(__file__).resolve().parents[1]


def check(name: str, scratch: Path) -> bool:
    ref = RunDir(ROOT / "runs" / "reference" / name)
    committed = json.loads(ref.eval_json.read_text())
    copy = RunDir(scratch / name)
    copy.path.mkdir()
    for file in ("config", "model"):
        getattr(copy, file).write_bytes(getattr(ref, file).read_bytes())
    copy = copy.path
    start = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = harness(["eval", str(copy), "--episodes", str(committed["episodes"]), "--json"])
    (saved_file,) = copy.glob("eval*.json")
    saved = json.loads(saved_file.read_text())
    took = time.perf_counter() - start
    if "unseen_logloss" in committed:  # a map prior's reference (docs/prior.md): its score
        keys = ("unseen_logloss", "density_logloss", "cells", "maps")
        same = code == 0 and all(saved[k] == committed[k] for k in keys)
        print(
            f"{name:<28} {committed['episodes']:>4} episodes  unseen_logloss "
            f"{saved['unseen_logloss']:.4f} (stored {committed['unseen_logloss']:.4f})  "
            f"{'same' if same else 'DIFFERENT'}  {took:.0f} s",
            flush=True,
        )
        return same
    same = (
        code == 0
        and saved["temperature"] == committed["temperature"]
        and saved["coverage"] == committed["coverage"]
        and saved["wall_hits"] == committed["wall_hits"]
    )
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
    for drop in ("env", "overrides"):  # how the run was named, not what it measured
        new.pop(drop, None), stored.pop(drop, None)
    shared = set(new) & set(stored)
    return all(k in shared for k in _FIGURES) and all(new[k] == stored[k] for k in shared)


def _config_of(stored: Path, committed: dict, scratch: Path) -> tuple[Path, list[str]]:
    """The config file and overrides that evaluate ``stored`` again: the config named by the
    file (``<config>[-env.max_steps-N]-<policy>.json``, as ``scripts/baselines.sh`` names
    them), or, for a file named by its setting (the team-map rows), a config made from the env
    the file stored, its older flat form (``crop``, ``frontier_action``, ...) translated."""
    stem = stored.name.removesuffix(f"-{committed['policy']}.json")
    config, _, max_steps = stem.partition("-env.max_steps-")
    path = ROOT / "configs" / f"{config}.yaml"
    if path.is_file():
        return path, ["--set", f"env.max_steps={max_steps}"] if max_steps else []
    env = dict(committed["env"])
    view = {k: env.pop(k) for k in ("crop", "global_size", "ego_size", "ego_block") if k in env}
    if env.pop("trail", 0):
        raise ValueError(f"{stored.name}: a trail is not an option any more")
    if env.get("observation") == "teammap" and view:
        env["observation"] = {"teammap": view}
    step, claims = env.pop("frontier_action", False), env.pop("frontier_claims", False)
    if isinstance(env.get("frontier"), bool):
        on = env["frontier"] or step or claims
        env["frontier"] = ({"action": "step"} if step else {}) if on else None
    team_map = isinstance(env.get("observation"), dict) or env.get("observation") == "teammap"
    doc = {"name": stem, "env": env, "eval": {"seed": committed["seed"]}}
    if team_map:
        doc["algo"] = {"policy": "TeamMapPolicy"}
    path = scratch / f"{stem}.yaml"
    path.write_text(json.dumps(doc))  # JSON is YAML
    return path, []


def check_baseline(stored: Path, scratch: Path) -> bool:
    """Evaluate a stored baseline again (:func:`_config_of`) and compare every figure."""
    committed = json.loads(stored.read_text())
    config, overrides = _config_of(stored, committed, scratch)
    args = ["eval", "--policy", committed["policy"], "--config", str(config), *overrides]
    args += ["--episodes", str(committed["episodes"]), "--json"]
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
    if names[:1] in (["-h"], ["--help"]):
        print(__doc__)
        return 0
    if names[:1] == ["--baselines"]:
        patterns = names[1:] or ["*"]
        stored = sorted(
            {p for pat in patterns for p in (ROOT / "docs" / "baselines").glob(f"{pat}.json")}
        )
        if not stored:
            print(f"error: no docs/baselines/PATTERN.json matches {patterns}", file=sys.stderr)
            return 2
        with tempfile.TemporaryDirectory() as tmp:
            return 0 if all([check_baseline(p, Path(tmp)) for p in stored]) else 1
    references = (ROOT / "runs" / "reference").iterdir()
    known = sorted(p.name for p in references if RunDir(p).eval_json.is_file())
    unknown = [name for name in names if name not in known]
    if unknown:
        print(f"error: no reference {unknown[0]!r}; known: {', '.join(known)}", file=sys.stderr)
        return 2
    names = names or known
    with tempfile.TemporaryDirectory() as tmp:
        results = [check(name, Path(tmp)) for name in names]
    return 0 if all(results) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
