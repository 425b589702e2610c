"""The written planners on every test setting: the table of docs/results.md ("The strongest
written planners"), made from the stored evaluations docs/baselines/<config>-<policy>.json
(``scripts/baselines.sh`` with ``POLICIES="frontier frontier_pocket frontier_utility
frontier_minpos frontier_hungarian"`` writes them: 100 test episodes each, the configs'
``eval.seed``). ``tests/test_readme_results.py`` checks that the page holds exactly this table.

    python scripts/planner_table.py       # prints the markdown table
"""

from __future__ import annotations

import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: (config, the setting in words) of every test setting.
SETTINGS = (
    ("ddqn_1agent", "50x50 random, 1 agent"),
    ("ddqn_2agents", "50x50 random, 2 agents"),
    ("ddqn_3agents", "50x50 random, 3 agents"),
    ("ddqn_4agents", "50x50 random, 4 agents"),
    ("ddqn_15x15", "15x15 random, 2 agents"),
    ("cave_2agents", "cave_100x50, 2 agents"),
    ("cave_4agents", "cave_100x50, 4 agents"),
    ("maze_2agents", "maze_100x50, 2 agents"),
    ("maze_4agents", "maze_100x50, 4 agents"),
)
PLANNERS = (
    "frontier",
    "frontier_pocket",
    "frontier_utility",
    "frontier_minpos",
    "frontier_hungarian",
)


def load(config: str, policy: str) -> dict:
    return json.loads((ROOT / "docs" / "baselines" / f"{config}-{policy}.json").read_text())


def rank_key(d: dict) -> tuple[float, float, float]:
    """Best first: the higher mean coverage (to 0.1 point), then the fewer steps to 99 %, then
    to 90 % (an episode set that never got there: last)."""

    def steps(key: str) -> float:
        return float("inf") if d[key] is None else d[key]

    return (-round(d["coverage_mean"], 3), steps("steps_to_99"), steps("steps_to_90"))


def strongest(config: str) -> str:
    return min(PLANNERS, key=lambda p: rank_key(load(config, p)))


def cell(d: dict) -> str:
    low, high = d["coverage_mean_ci"]
    steps = " / ".join("–" if d[k] is None else f"{d[k]:g}" for k in ("steps_to_90", "steps_to_99"))
    return (
        f"{d['coverage_mean']:.1%} [{low:.1%}, {high:.1%}]; {d['efficiency']:.3f}; {steps}"
    ).replace("%", " %")


def table() -> str:
    header = "| setting | bound | " + " | ".join(f"`{p}`" for p in PLANNERS) + " | strongest |"
    lines = [header, "|" + "---|" * (len(PLANNERS) + 3)]
    for config, words in SETTINGS:
        runs = {p: load(config, p) for p in PLANNERS}
        bound = runs["frontier"]["bound"]
        best = strongest(config)
        cells = [cell(runs[p]) for p in PLANNERS]
        bound_text = f"{bound:.1%}".replace("%", " %")
        lines.append(f"| {words} | {bound_text} | " + " | ".join(cells) + f" | `{best}` |")
    return "\n".join(lines)


def summary() -> str:
    """README's lines: per setting, the strongest planner and its margin over ``frontier``."""
    lines = [
        "| setting | strongest written planner | mean coverage | over `frontier` |",
        "|---|---|---|---|",
    ]
    for config, words in SETTINGS:
        best = strongest(config)
        mine, base = load(config, best), load(config, "frontier")
        margin = 100 * (mine["coverage_mean"] - base["coverage_mean"])
        if round(margin, 1) == 0 and mine["steps_to_99"] and base["steps_to_99"]:
            versus = f"{mine['steps_to_99']:g} vs {base['steps_to_99']:g} steps to 99 %"
        else:
            versus = f"{margin:+.1f} points"
        covered = f"{mine['coverage_mean']:.1%}".replace("%", " %")
        lines.append(f"| {words} | `{best}` | {covered} | {versus} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(table())
    print()
    print(summary())
