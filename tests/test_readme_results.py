"""The results tables (docs/results.md, and the finished research lines' tables in
research/results-notes.md) quote the committed reference evaluations and stored baselines, digit
for digit."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from harness.config.loading import load_config

ROOT = Path(__file__).resolve().parents[1]
#: The page that holds the current results tables (README links to it).
RESULTS = ROOT / "docs" / "results.md"
#: The lab record's page beside it, which holds the tables of finished research lines (the
#: team-map references), checked as those of docs/results.md are.
RESULTS_NOTES = ROOT / "research" / "results-notes.md"
#: The page that describes the sweep on a real question (the lab record, research/).
SWEEPS = ROOT / "research" / "guide-measurements.md"
TABLE_HEADER = "| experiment | thesis | this project | T | walls | greedy |"


def table_rows(header_start: str, page: Path = RESULTS) -> list[dict[str, str]]:
    """The rows of the results table of ``page`` (docs/results.md unless given) whose header
    line starts with ``header_start``, as ``{column: cell}``."""
    lines = page.read_text().splitlines()
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
# stored as docs/baselines/C[-KEY-VALUE]-P.json (see docs/evaluation.md, "Baselines").
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


TIE_BREAK_HEADER = "| map | agents | frontier | frontier_pocket | frontier_random |"


@pytest.mark.parametrize("row", table_rows(TIE_BREAK_HEADER), ids=lambda r: r["config"])
def test_tie_break_table_quotes_the_stored_baselines(row: dict[str, str]) -> None:
    config = row["config"].strip("`")
    steps = []
    for policy in ("frontier", "frontier_pocket", "frontier_random"):
        stored = baseline_file(config, policy, None)
        assert stored["env"]["n_agents"] == int(row["agents"]) and stored["episodes"] == 100
        assert stored["wall_hits_mean"] == 0 and stored["policy"] == policy
        assert row[policy] == percent(stored["coverage_mean"])
        reached = [stored[k] for k in ("steps_to_90", "steps_to_99")]
        steps.append(" / ".join("–" if s is None else f"{s:g}" for s in reached))
    assert row["steps to 90 % / 99 %: frontier, pocket, random"] == ", ".join(steps)


# ---------------------------------------------------------------------- the team-map table
TEAMMAP_HEADER = "| test setting | agents | policy | coverage | greedy | unshielded |"
#: Each test setting and team size: the evaluation a reference has of it (file stem in the
#: reference folder) and the config whose stored baselines ran the same episodes.
TEAMMAP_SETTINGS: dict[tuple[str, str], tuple[str, str]] = {
    ("50x50 random, 1000 steps", "1"): ("eval-env.map-random", "ddqn_1agent"),
    ("50x50 random, 1000 steps", "2"): ("eval-env.map-random", "ddqn_2agents"),
    ("50x50 random, 1000 steps", "4"): ("eval-env.map-random", "ddqn_4agents"),
    ("cave_100x50, 1000 steps", "2"): ("eval-env.map-cave_100x50", "cave_2agents"),
    ("cave_100x50, 1000 steps", "4"): ("eval-env.map-cave_100x50", "cave_4agents"),
    ("maze_100x50, 1000 steps", "2"): ("eval-env.map-maze_100x50", "maze_2agents"),
    ("maze_100x50, 1000 steps", "4"): ("eval-env.map-maze_100x50", "maze_4agents"),
    ("15x15 random, 150 steps", "2"): (
        "eval-env.map-random_env.height-15_env.width-15_env.max_steps-150",
        "ddqn_15x15",
    ),
}
#: The frontier_step baseline of each setting (every agent always takes the env's frontier step),
#: run on `configs/teammap_2agents.yaml --set env.frontier=true --set env.frontier_action=true`
#: (today `--set 'env.frontier={action: step}'`) with the setting's overrides:
#: docs/baselines/teammap-<stem>-frontier_step.json (their stored `env` has the old keys).
TEAMMAP_STEP_BASELINES: dict[tuple[str, str], str] = {
    ("50x50 random, 1000 steps", "1"): "random-1agent",
    ("50x50 random, 1000 steps", "2"): "random-2agents",
    ("50x50 random, 1000 steps", "4"): "random-4agents",
    ("cave_100x50, 1000 steps", "2"): "cave-2agents",
    ("cave_100x50, 1000 steps", "4"): "cave-4agents",
    ("maze_100x50, 1000 steps", "2"): "maze-2agents",
    ("maze_100x50, 1000 steps", "4"): "maze-4agents",
    ("15x15 random, 150 steps", "2"): "15x15-2agents",
}
TEAMMAP_ROWS = [r for r in table_rows(TEAMMAP_HEADER, RESULTS_NOTES) if r["policy"].startswith("`")]


def teammap_eval(reference: str, stem: str, agents: str, variant: str = "") -> dict:
    """An evaluation of a team-map reference: ``stem`` (see :data:`TEAMMAP_SETTINGS`), played by
    ``agents`` agents (a team size other than the reference's own adds ``_env.n_agents-K``, as
    ``harness eval --set env.n_agents=K`` names it), with an optional ``variant``
    (``eval.temperature-0``, ``eval.shield-false``). A reference trained on random 50x50 maps
    evaluates them as its own test, in ``eval.json``/``eval-<variant>.json``."""
    folder = ROOT / "runs" / "reference" / reference
    own = load_config(folder / "config.yaml").env.n_agents
    if int(agents) != own:
        stem += f"_env.n_agents-{agents}"
    path = folder / (f"{stem}_{variant}.json" if variant else f"{stem}.json")
    if not path.is_file() and stem == "eval-env.map-random":
        path = folder / (f"eval-{variant}.json" if variant else "eval.json")
    return json.loads(path.read_text())


@pytest.mark.parametrize("row", TEAMMAP_ROWS, ids=lambda r: f"{r['test setting']}-{r['agents']}")
def test_teammap_row_quotes_its_reference_evaluations(row: dict[str, str]) -> None:
    reference = row["policy"].split("`")[1]
    stem = TEAMMAP_SETTINGS[(row["test setting"], row["agents"])][0]
    agents = row["agents"]
    tuned = teammap_eval(reference, stem, agents)
    assert tuned["shield"] is True and tuned["wall_hits_mean"] == 0
    mean, median = percent(tuned["coverage_mean"]), percent(tuned["coverage_median"])
    assert row["coverage"] == f"{mean} ({median})"
    if row["greedy"] != "–":
        greedy = teammap_eval(reference, stem, agents, "eval.temperature-0")
        assert greedy["temperature"] == 0 and row["greedy"] == percent(greedy["coverage_mean"])
    if row["unshielded"] != "–":
        plain = teammap_eval(reference, stem, agents, "eval.shield-false")
        assert plain["shield"] is False
        expected = f"{percent(plain['coverage_mean'])}, {plain['wall_hits_mean']:.1f}"
        assert row["unshielded"] == expected


def test_teammap_table_has_every_setting_of_the_goals() -> None:
    assert {(r["test setting"], r["agents"]) for r in TEAMMAP_ROWS} == set(TEAMMAP_SETTINGS)


@pytest.mark.parametrize(
    "row",
    table_rows(TEAMMAP_HEADER, RESULTS_NOTES),
    ids=lambda r: f"{r['test setting']}-{r['agents']}",
)
def test_teammap_row_quotes_the_stored_baselines_on_the_same_episodes(row: dict[str, str]) -> None:
    config = TEAMMAP_SETTINGS[(row["test setting"], row["agents"])][1]
    for policy, column in (
        ("local", "local"),
        ("frontier", "frontier"),
        ("frontier_pocket", "frontier pocket"),
    ):
        stored = json.loads((ROOT / "docs" / "baselines" / f"{config}-{policy}.json").read_text())
        assert stored["seed"] == 1_000_003 and stored["episodes"] == 100
        assert row[column] == percent(stored["coverage_mean"]), policy
    step_file = f"teammap-{TEAMMAP_STEP_BASELINES[(row['test setting'], row['agents'])]}"
    step = json.loads((ROOT / "docs" / "baselines" / f"{step_file}-frontier_step.json").read_text())
    local = json.loads((ROOT / "docs" / "baselines" / f"{config}-local.json").read_text())
    # The same episodes as the config's stored baselines: same seed, team and map size.
    assert step["seed"] == local["seed"] and step["episodes"] == local["episodes"]
    assert step["env"]["n_agents"] == local["env"]["n_agents"]
    assert step["env"]["max_steps"] == local["env"]["max_steps"]
    assert step["env"]["frontier_action"] is True and step["wall_hits_mean"] == 0
    assert row["frontier step"] == percent(step["coverage_mean"])


SEEDS_HEADER = "| comparison | seeds | test coverage: mean [95 % CI] |"


def interval_cell(stats) -> str:
    """How the seeds table writes a statistic: ``mean [low, high]``, one decimal."""
    return f"{percent(stats[0])} [{percent(stats[1][0])}, {percent(stats[1][1])}]"


@pytest.mark.parametrize(
    ("row_start", "name", "agents"),
    [
        ("the step config", "teammap_2agents_step", 2),
        ("the imitation config", "teammap_2agents_imitation", 2),
        ("the pocket config", "teammap_2agents_pocket", 2),
        ("the pocket config", "teammap_2agents_pocket", 1),
        ("the pocket config", "teammap_2agents_pocket", 4),
    ],
)
def test_teammap_seeds_row_quotes_the_three_seeds(row_start: str, name: str, agents: int) -> None:
    # Seed 0 is the reference; seeds 1 and 2 are in docs/seeds/<name>/<name>-seed<k>. The
    # 2-agent networks played by another team size have `_env.n_agents-K` in their file names.
    from harness.results.stats import seed_statistics

    (row,) = [
        r
        for r in table_rows(TEAMMAP_HEADER, RESULTS_NOTES)
        if r["policy"].startswith(row_start) and r["agents"] == str(agents)
    ]
    folders = [ROOT / "runs" / "reference" / name] + [
        ROOT / "docs" / "seeds" / name / f"{name}-seed{k}" for k in (1, 2)
    ]
    stem = "eval-env.map-random" + ("" if agents == 2 else f"_env.n_agents-{agents}")
    variants = ["", "_eval.temperature-0"] if row["greedy"] != "–" else [""]
    evals = {
        variant: [json.loads((f / f"{stem}{variant}.json").read_text()) for f in folders]
        for variant in variants
    }
    for e in (e for v in evals.values() for e in v):  # the standard random test episodes
        assert e["seed"] == 1_000_003 and e["episodes"] == 100 and e["shield"] is True
        assert e["wall_hits_mean"] == 0 and e["env"]["n_agents"] == agents
    stats = seed_statistics({k: [e["coverage_mean"] for e in v] for k, v in evals.items()})
    tuned = stats[""]
    assert row["coverage"] == interval_cell((tuned.mean, tuned.mean_ci))
    if "_eval.temperature-0" in stats:
        greedy = stats["_eval.temperature-0"]
        assert row["greedy"] == interval_cell((greedy.mean, greedy.mean_ci))


@pytest.mark.parametrize("row", table_rows(SEEDS_HEADER), ids=lambda r: r["comparison"])
def test_seeds_row_quotes_its_groups_evaluations(row: dict[str, str]) -> None:
    from harness.results.groups import group_runs
    from harness.results.stats import seed_statistics

    group = ROOT / row["files"].strip("`")
    runs = group_runs(group)
    assert row["seeds"] == str(len(runs)) and len(runs) >= 3
    tuned = [json.loads((run / "eval.json").read_text()) for run in runs]
    greedy = [json.loads((run / "eval-eval.temperature-0.json").read_text()) for run in runs]
    for run, ev in zip(runs, tuned, strict=True):  # at the temperature its own tune chose
        assert ev["episodes"] == 100 and ev["seed"] == 1_000_003 and not ev["overrides"]
        assert ev["temperature"] == json.loads((run / "tune.json").read_text())["chosen"]
    assert all(g["temperature"] == 0 and g["seed"] == 1_000_003 for g in greedy)
    means = {"tuned": tuned, "greedy": greedy}
    stats = seed_statistics({k: [e["coverage_mean"] for e in v] for k, v in means.items()})
    t, g = stats["tuned"], stats["greedy"]
    assert row["test coverage: mean [95 % CI]"] == interval_cell((t.mean, t.mean_ci))
    assert row["IQM [95 % CI]"] == interval_cell((t.iqm, t.iqm_ci))
    assert row["greedy: mean [95 % CI]"] == interval_cell((g.mean, g.mean_ci))
    walls = sum(e["wall_hits_mean"] for e in tuned) / len(tuned)
    assert row["walls"] == f"{walls:.2f}"
    # The local rule ran on the group's config (a `--set algo.sharing=...` group shares its
    # config's baseline: the rule reads no network).
    config = Path(json.loads((group / "group.json").read_text())["config"]).stem
    local = json.loads((ROOT / "docs" / "baselines" / f"{config}-local.json").read_text())
    assert local["seed"] == 1_000_003 and local["episodes"] == 100
    assert row["local rule"] == percent(local["coverage_mean"])


def test_sweep_paragraph_quotes_the_saved_study() -> None:
    import csv

    folder = ROOT / "docs" / "sweeps" / "ddqn_15x15"
    with (folder / "trials.csv").open() as f:
        rows = list(csv.DictReader(f))
    best = json.loads((folder / "best.json").read_text())
    complete = [float(r["value"]) for r in rows if r["state"] == "COMPLETE"]
    pruned = [r for r in rows if r["state"] == "PRUNED"]
    text = SWEEPS.read_text()
    assert f"{len(rows)} trials (TPE" in text
    assert f"{len(complete)} complete, {len(pruned)} stopped by" in text
    assert f"span {percent(min(complete), '')[:-1]}–{percent(max(complete))}" in text
    assert f"the best, trial {best['trial']} " in text and max(complete) == best["value"]
    assert best["trials"]["complete"] == len(complete)


def _planner_table():
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "planner_table", ROOT / "scripts" / "planner_table.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_planner_table_is_made_from_the_stored_evaluations() -> None:
    # docs/results.md holds exactly the table scripts/planner_table.py makes from the stored
    # 100-episode evaluations, and README exactly its summary (strongest planner per setting).
    module = _planner_table()
    assert module.table() in (ROOT / "docs" / "results.md").read_text()
    assert module.summary() in (ROOT / "README.md").read_text()


def test_planner_evaluations_report_the_physical_bound() -> None:
    module = _planner_table()
    for config, _ in module.SETTINGS:
        for policy in module.PLANNERS:
            d = module.load(config, policy)
            assert d["episodes"] == 100 and d["wall_hits_mean"] == 0
            assert 0 < d["bound"] <= 1 and d["efficiency"] == d["coverage_mean"] / d["bound"]
            low, high = d["coverage_mean_ci"]
            assert low <= d["coverage_mean"] <= high


def test_goal_table_is_made_from_the_stored_evaluations() -> None:
    # docs/results.md holds exactly the learned goal selection's table, made from the three
    # seeds' 100-episode evaluations on the same test episodes as the planners'.
    import importlib.util

    spec = importlib.util.spec_from_file_location("goal_table", ROOT / "scripts" / "goal_table.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.table() in (ROOT / "docs" / "results.md").read_text()
    for _, planner_config, config, suffix, _ in module.SETTINGS:
        planner = module.planners.load(planner_config, "frontier")
        for d in module.learned(config, suffix):
            assert d["episodes"] == 100 and d["seed"] == planner["seed"]
            for key in ("map", "n_agents", "max_steps", "height", "width", "wall_fraction"):
                assert d["env"][key] == planner["env"][key], key
            assert d["bound"] == pytest.approx(planner["bound"])


# ---------------------------------------------------------------------- the rollout chooser
#: The rollout table's settings: its stored evaluation (docs/baselines/rollout/NAME.json) and the
#: config whose stored planner evaluations are on the same episodes.
ROLLOUT = {
    "50x50 random, 4 agents": ("goals_4agents-random", "ddqn_4agents"),
    "50x50 random, 4 agents, 8 maps from 60 %": ("goals_4agents-random-8maps-60", "ddqn_4agents"),
    "50x50 random, 3 agents": ("goals_2agents-random-3agents", "ddqn_3agents"),
    "50x50 random, 2 agents": ("goals_2agents-random", "ddqn_2agents"),
    "50x50 random, 2 agents, 16 maps from 60 %": ("goals_2agents-random-16maps-60", "ddqn_2agents"),
    "cave_100x50, 2 agents": ("goals_2agents-cave_100x50", "cave_2agents"),
    "maze_100x50, 2 agents": ("goals_2agents-maze_100x50", "maze_2agents"),
    "50x50 random, 1 agent": ("goals_2agents-random-1agent", "ddqn_1agent"),
}
ROLLOUT_ROWS = table_rows("| setting | `rollout` |")


def signed(x: float, digits: int) -> str:
    """A difference as the table writes it: a sign (a typographic minus), ``0.00`` for none."""
    text = f"{x:+.{digits}f}"
    return f"{0:.{digits}f}" if float(text) == 0 else text.replace("-", "−")


def test_rollout_table_has_its_settings() -> None:
    assert [row["setting"] for row in ROLLOUT_ROWS] == list(ROLLOUT)


@pytest.mark.parametrize("row", ROLLOUT_ROWS, ids=lambda r: r["setting"])
def test_rollout_row_quotes_its_stored_evaluation_on_the_planners_episodes(row) -> None:
    name, planners = ROLLOUT[row["setting"]]
    d = json.loads((ROOT / "docs" / "baselines" / "rollout" / f"{name}.json").read_text())
    assert d["policy"] == "rollout" and d["episodes"] == 100 and d["wall_hits_mean"] == 0
    # A row that names other parameters than the default played them (eval.rollout).
    chosen = re.search(r"(\d+) maps from (\d+) %", row["setting"])
    rollout = [o for o in d["overrides"] if o.startswith("eval.rollout.")]
    if chosen:
        maps, after = chosen.groups()
        assert sorted(rollout) == [f"eval.rollout.after={int(after) / 100}",
                                   f"eval.rollout.samples={maps}"]  # fmt: skip
    else:
        assert not rollout
    low, high = d["coverage_mean_ci"]
    assert row["`rollout`"].startswith(
        f"{percent(d['coverage_mean'])} [{percent(low)}, {percent(high)}]"
    )
    quoted = row["against the strongest written planner"] + " " + row["against the other"]
    for against in d["against"]:
        policy = against["against"]
        # Its baseline played the episodes of the planners' table: the same mean as stored there.
        stored = json.loads((ROOT / "docs" / "baselines" / f"{planners}-{policy}.json").read_text())
        assert against["against_mean"] == pytest.approx(stored["coverage_mean"])
        assert against["seed"] == stored["seed"]
        steps = against["steps_to_99"]
        if steps is not None and steps["episodes"] == 100:  # compared by speed
            figure = f"`{policy}` {steps['against_mean']:.1f}"
            difference, (lo, hi) = steps["difference"], steps["difference_ci95"]
            digits = 1
        else:  # by coverage, in points
            figure = f"`{policy}` {percent(against['against_mean'])}"
            difference, (lo, hi) = (
                100 * against["difference"],
                (100 * x for x in against["difference_ci95"]),
            )
            digits = 2
        assert figure in quoted, figure
        if difference:
            interval = f"{signed(difference, digits)} [{signed(lo, digits)}, {signed(hi, digits)}]"
            assert interval in quoted, interval


#: The rows of docs/results.md's table of the rollout chooser with a prior: the stored file each
#: quotes (docs/baselines/rollout_prior/, ``harness eval --json``), and the baseline it is paired
#: with there (``rollout``: the same chooser without the prior, ``--against-set``).
PRIOR_CHOOSER = {
    "floor plans 50x100, 4": ("test30_rooms_prior_after075.json", "frontier_pocket"),
    "office floors 50x100, 4 (another generator)": (
        "test30_office_prior_after075.json",
        "frontier_pocket",
    ),
    "random 50x50, 2": ("random_2agents_prior_vs_uniform.json", "rollout"),
}
PRIOR_CHOOSER_ROWS = table_rows("| setting | chooser | coverage | paired with |")


def test_prior_chooser_table_has_its_settings() -> None:
    assert [row["setting"] for row in PRIOR_CHOOSER_ROWS] == list(PRIOR_CHOOSER)


@pytest.mark.parametrize("row", PRIOR_CHOOSER_ROWS, ids=lambda r: r["setting"])
def test_prior_chooser_row_quotes_its_stored_comparison(row) -> None:
    name, paired = PRIOR_CHOOSER[row["setting"]]
    d = json.loads((ROOT / "docs" / "baselines" / "rollout_prior" / name).read_text())
    assert d["policy"] == "rollout" and d["episodes"] == 30 and d["wall_hits_mean"] == 0
    comparison = next(a for a in d["against"] if a["against"] == paired)
    if paired == "rollout":  # the chooser with the prior against itself without one
        assert "eval.rollout.prior=runs/reference/prior_random" in d["overrides"]
        assert comparison["against_set"] == ["eval.rollout.prior=null"]
    mean, theirs = d["coverage_mean"], comparison["against_mean"]
    assert row["coverage"] == f"{100 * mean:.2f} %"
    lo, hi = (100 * x for x in comparison["difference_ci95"])
    quoted = (
        f"{100 * theirs:.2f} %: {signed(100 * comparison['difference'], 2)} "
        f"[{signed(lo, 2)}, {signed(hi, 2)}]"
    )
    assert quoted in row["paired with"], quoted


PRIOR_POLICY_ROWS = table_rows(
    "| policy | maps, agents | seeds | coverage | vs `frontier_pocket` |"
)


@pytest.mark.parametrize("row", PRIOR_POLICY_ROWS, ids=lambda r: r["policy"])
def test_prior_policy_row_quotes_its_reference_comparisons(row) -> None:
    # Seed 0's 30-episode comparisons, kept with its reference (the three seeds gave the same).
    ref = ROOT / "runs" / "reference" / row["policy"].strip("`")
    evaluation = json.loads((ref / "eval-30ep.json").read_text())
    assert row["coverage"] == percent(evaluation["coverage_mean"])
    for policy in ("frontier_pocket", "frontier_minpos"):
        d = json.loads((ref / f"against-{policy}-30ep.json").read_text())
        assert d["episodes"] == 30 and d["coverage"] == evaluation["coverage"]
        figures = (100 * x for x in (d["difference"], *d["difference_ci95"]))
        # This table writes no difference as +0.00.
        diff, lo, hi = (signed(x, 2) if round(x, 2) else "+0.00" for x in figures)
        quoted = f"{diff} [{lo}, {hi}]"
        assert row[f"vs `{policy}`"].startswith(quoted), quoted


def test_maze_prior_policy_group_is_stored_with_its_numbers_over_seeds() -> None:
    group = ROOT / "docs" / "seeds" / "goals_prior_maze_2agents"
    over = json.loads((group / "group-against-frontier_pocket-30ep.json").read_text())
    assert len(over["differences"]) == 3 and set(over["differences"].values()) == {0.0}
    per_seed = [
        json.loads((group / f"goals_prior_maze_2agents-seed{k}" / "eval-30ep.json").read_text())
        for k in range(3)
    ]
    means = [e["coverage_mean"] for e in per_seed]
    over_eval = json.loads((group / "group-eval-30ep.json").read_text())
    assert over_eval["coverage_mean_over_seeds"]["mean"] == pytest.approx(sum(means) / 3)
