"""README's results table quotes the committed reference evaluations, digit for digit."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TABLE_HEADER = "| experiment | thesis | this project | T | walls | greedy |"


def results_rows() -> list[dict[str, str]]:
    """The rows of README's results table as ``{column: cell}``."""
    lines = (ROOT / "README.md").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(TABLE_HEADER))
    header = [c.strip() for c in lines[start].strip("|").split("|")]
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append(dict(zip(header, (c.strip() for c in line.strip("|").split("|")))))
    return rows


def eval_files(row: dict[str, str]) -> tuple[dict, dict]:
    """The tuned (``eval.json``) and greedy evaluations a row quotes."""
    ref = ROOT / "runs" / "reference" / row["config"].strip("`")
    steps = re.search(r"(\d+) steps", row["experiment"]).group(1)
    config_steps = re.search(r"max_steps: (\d+)", (ref / "config.yaml").read_text()).group(1)
    setting = "" if steps == config_steps else f"env.max_steps-{steps}"
    tuned = ref / (f"eval-{setting}.json" if setting else "eval.json")
    greedy = ref / f"eval-{setting + '_' if setting else ''}eval.temperature-0.json"
    return json.loads(tuned.read_text()), json.loads(greedy.read_text())


def cell(d: dict) -> str:
    """How the table writes an evaluation: median (IQR), one decimal."""
    return f"{d['coverage_median']:.1%} ({d['coverage_iqr']:.1%})".replace("%", " %")


ROWS = results_rows()


def test_results_table_has_every_row_of_the_thesis() -> None:
    assert len(ROWS) == 10  # SPEC §6: 2 on 15x15, 4 + 2 on 50x50, 2 on the cave


@pytest.mark.parametrize("row", ROWS, ids=lambda r: r["experiment"])
def test_results_row_quotes_its_reference_evaluation(row: dict[str, str]) -> None:
    tuned, greedy = eval_files(row)
    assert tuned["episodes"] == greedy["episodes"] == 100
    assert row["this project"].replace("**", "") == cell(tuned)
    assert float(row["T"]) == tuned["temperature"]
    assert float(row["walls"]) == round(tuned["wall_hits_mean"], 2)
    assert row["greedy"] == cell(greedy) and greedy["temperature"] == 0.0
