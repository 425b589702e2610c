"""Re-evaluate every committed reference policy on all the episodes of its committed
``eval.json`` and compare, episode by episode (coverage and wall hits), with what was stored.

The guard that a change of the simulation path (the batched core) left every reference's
results as they were: episode ``k`` is seeded with ``seed + k`` and its action noise too, so a
reference evaluated again on the same episodes must give the same numbers.

    python scripts/check_references.py [NAME ...]   # default: every runs/reference/*/eval.json

Prints one line per reference and exits 1 when any differs. Evaluates copies in a temporary
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


def main(names: list[str]) -> int:
    if not names:
        names = sorted(p.parent.name for p in (ROOT / "runs" / "reference").glob("*/eval.json"))
    with tempfile.TemporaryDirectory() as tmp:
        results = [check(name, Path(tmp)) for name in names]
    return 0 if all(results) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
