"""README's results table quotes the committed reference evaluations, digit for digit."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TABLE_HEADER = "| experiment | thesis | this project | T | walls | greedy |"


def table_rows(header_start: str) -> list[dict[str, str]]:
    """The rows of the README table whose header line starts with ``header_start``, as
    ``{column: cell}``."""
    lines = (ROOT / "README.md").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    header = [c.strip() for c in lines[start].strip("|").split("|")]
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append(dict(zip(header, (c.strip() for c in line.strip("|").split("|")))))
    return rows


def row_max_steps(row: dict[str, str]) -> str | None:
    """The ``--set env.max_steps`` a results row is evaluated at, ``None`` for its config's own."""
    ref = ROOT / "runs" / "reference" / row["config"].strip("`")
    steps = re.search(r"(\d+) steps", row["experiment"]).group(1)
    config_steps = re.search(r"max_steps: (\d+)", (ref / "config.yaml").read_text()).group(1)
    return None if steps == config_steps else steps


def eval_files(row: dict[str, str]) -> tuple[dict, dict]:
    """The tuned (``eval.json``) and greedy evaluations a row quotes."""
    ref = ROOT / "runs" / "reference" / row["config"].strip("`")
    max_steps = row_max_steps(row)
    setting = f"env.max_steps-{max_steps}" if max_steps else ""
    tuned = ref / (f"eval-{setting}.json" if setting else "eval.json")
    greedy = ref / f"eval-{setting + '_' if setting else ''}eval.temperature-0.json"
    return json.loads(tuned.read_text()), json.loads(greedy.read_text())


def percent(x: float, sep: str = " ") -> str:
    """One decimal, as the tables write it (``sep`` between number and ``%``)."""
    return f"{x:.1%}".replace("%", f"{sep}%")


def cell(d: dict, sep: str = " ") -> str:
    """How the tables write an evaluation: median (IQR), one decimal."""
    return f"{percent(d['coverage_median'], sep)} ({percent(d['coverage_iqr'], sep)})"


ROWS = table_rows(TABLE_HEADER)


def test_results_table_has_every_row_of_the_thesis() -> None:
    assert len(ROWS) == 10  # the thesis's rows: 2 on 15x15, 4 + 2 on 50x50, 2 on the cave


@pytest.mark.parametrize("row", ROWS, ids=lambda r: r["experiment"])
def test_results_row_quotes_its_reference_evaluation(row: dict[str, str]) -> None:
    tuned, greedy = eval_files(row)
    assert tuned["episodes"] == greedy["episodes"] == 100
    assert row["this project"].replace("**", "") == cell(tuned)
    assert float(row["T"]) == tuned["temperature"]
    assert float(row["walls"]) == round(tuned["wall_hits_mean"], 2)
    assert row["greedy"] == cell(greedy) and greedy["temperature"] == 0.0


# The baseline columns quote `harness eval --policy P --config configs/C.yaml [--set ...] --json`,
# stored as docs/baselines/C[-KEY-VALUE]-P.json (see README "Evaluation, baselines, ...").
BASELINES = ROOT / "docs" / "baselines"
POLICIES = ("random", "local", "frontier")


def baseline_file(config: str, policy: str, max_steps: str | None) -> dict:
    """A stored baseline evaluation of ``configs/<config>.yaml`` (at ``max_steps`` if not None)."""
    setting = f"-env.max_steps-{max_steps}" if max_steps else ""
    return json.loads((BASELINES / f"{config}{setting}-{policy}.json").read_text())


@pytest.mark.parametrize("row", ROWS, ids=lambda r: r["experiment"])
def test_results_row_quotes_the_stored_baselines(row: dict[str, str]) -> None:
    config = row["config"].strip("`")
    for policy in POLICIES:
        stored = baseline_file(config, policy, row_max_steps(row))
        assert stored["episodes"] == 100 and stored["policy"] == policy
        # a median of exactly 1 is written "100 %"
        quoted = row[policy].replace("100 %", "100.0 %")
        assert quoted == percent(stored["coverage_median"]), (policy, quoted)


BASELINE_ROWS = table_rows("| map | agents | random | local | frontier | command |")


@pytest.mark.parametrize("row", BASELINE_ROWS, ids=lambda r: r["command"])
def test_baseline_table_quotes_the_stored_baselines(row: dict[str, str]) -> None:
    command = re.fullmatch(
        r"`--config configs/(\w+)\.yaml(?: --set env\.max_steps=(\d+))?`", row["command"]
    )
    assert command, row["command"]
    config, max_steps = command.groups()
    for policy in POLICIES:
        stored = baseline_file(config, policy, max_steps)
        assert stored["env"]["n_agents"] == int(row["agents"])
        if max_steps:
            assert stored["overrides"] == [f"env.max_steps={max_steps}"]
        assert row[policy] == cell(stored, sep=""), policy
        if policy != "random":
            assert stored["wall_hits_mean"] == 0  # "local and frontier never hit a wall"
