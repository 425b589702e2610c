"""``harness eval``, ``compare`` and ``render`` end to end on a smoke run and on baselines;
``compare`` refuses numbers too large for it in one line."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from PIL import Image

from harness.cli import main
from harness.commands import (
    choose_temperature,
    format_against,
    format_group_against,
    paired_steps_to_99,
)
from harness.config.loading import load_config
from harness.results.rundir import against_filename, result_filename
from tests.conftest import one_error_line, root_first_env
from tests.test_seeds_and_sweeps import TINY

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
#: The coverage env's shipped configs (configs/mpe_spread.yaml, a PettingZoo env of one's own,
#: is tests/test_your_own_env.py's: the coverage baselines and keys do not apply to it).
CONFIGS = [
    p for p in sorted((ROOT / "configs").glob("*.yaml")) if "pettingzoo:" not in p.read_text()
]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory) -> Path:
    runs = tmp_path_factory.mktemp("runs")
    short = ["--set", "phases.initial.timesteps=1500", "--set", "phases.optimizing.timesteps=500"]
    assert main(["run", str(SMOKE), "--runs-dir", str(runs), "--no-progress", *short]) == 0
    (run,) = runs.iterdir()
    return run


def eval_json(capsys, *args: str) -> dict:
    capsys.readouterr()
    assert main(["eval", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_eval_json_keys_ranges_and_saved_file(smoke_run, capsys):
    out = eval_json(capsys, str(smoke_run), "--episodes", "6")
    assert out["episodes"] == 6
    for key in ("coverage_median", "coverage_mean", "coverage_iqr"):
        assert 0.0 <= out[key] <= 1.0
    assert out["wall_hits_mean"] >= 0.0
    assert [a["agent"] for a in out["per_agent"]] == ["agent_0", "agent_1"]
    for a in out["per_agent"]:
        assert 0.0 <= a["useful_coverage"] <= 1.0 and 0.0 <= a["total_coverage"] <= 1.0
    saved = json.loads((smoke_run / "eval-6ep.json").read_text())
    assert saved["coverage_median"] == out["coverage_median"]
    assert len(saved["coverage"]) == 6


def test_eval_is_repeatable_with_a_seed(smoke_run, capsys):
    a = eval_json(capsys, str(smoke_run), "--episodes", "4", "--seed", "5")
    b = eval_json(capsys, str(smoke_run), "--episodes", "4", "--seed", "5")
    c = eval_json(capsys, str(smoke_run), "--episodes", "4", "--seed", "6")
    assert a == b
    assert a["coverage_mean"] != c["coverage_mean"] or a["per_agent"] != c["per_agent"]


def test_eval_of_a_model_zip_with_overrides_and_plot(smoke_run, capsys, tmp_path):
    plot = tmp_path / "episodes.png"
    out = eval_json(
        capsys, str(smoke_run / "model.zip"), "--episodes", "3",
        "--set", "env.max_steps=20", "--plot", str(plot),
    )  # fmt: skip
    assert out["env"]["max_steps"] == 20
    assert (smoke_run / "eval-3ep_env.max_steps-20.json").is_file()
    assert plot.read_bytes()[:8] == PNG_SIGNATURE


def test_each_model_and_setting_gets_its_own_eval_file(smoke_run, capsys):
    standard = eval_json(capsys, str(smoke_run))  # model.zip, 100 episodes, config eval.seed
    eval_json(capsys, str(smoke_run / "best_model.zip"), "--episodes", "3")
    eval_json(capsys, str(smoke_run), "--episodes", "2", "--seed", "4")
    assert (smoke_run / "eval-best_model_3ep.json").is_file()
    assert (smoke_run / "eval-2ep_seed4.json").is_file()
    saved = json.loads((smoke_run / "eval.json").read_text())
    assert saved["episodes"] == 100 and saved["coverage_median"] == standard["coverage_median"]


def test_overrides_that_read_alike_get_files_of_their_own(smoke_run, tmp_path, capsys):
    # "/" and "-" both read as "-", and long names are cut: each setting still gets its own file
    # (the readable name, then a short hash of the exact overrides).
    free, walled = "#" + "." * 8 + "#", "#..##....#"
    maps = {"a-b.txt": [walled] + [free] * 7, "a/b.txt": [free] * 8}
    sets = []
    for name, rows in maps.items():
        path = tmp_path / "maps" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(["#" * 10, *rows, "#" * 10]) + "\n")
        sets.append([f"env.map={path}"])
    start = [f"name={'x' * 64}", "env.max_steps=50"]  # over 100 characters with the last one
    sets += [[*start, "eval.temperature=0.25"], [*start, "eval.temperature=0.5"]]
    before = {p.name for p in smoke_run.glob("eval*.json")}
    for overrides in sets:
        eval_json(
            capsys, str(smoke_run), "--episodes", "1", *[a for o in overrides for a in ("--set", o)]
        )
    made = {p.name: p for p in smoke_run.glob("eval*.json") if p.name not in before}
    assert len(made) == len(sets), sorted(made)
    assert sorted(json.loads(p.read_text())["overrides"] for p in made.values()) == sorted(sets)
    assert all("~" in name for name in made)  # each has its hash


@pytest.mark.parametrize(
    "path", sorted(ROOT.glob("runs/reference/*/eval-*.json")), ids=lambda p: p.parent.name
)
def test_shipped_evaluations_keep_the_names_harness_eval_gives_them(path):
    # Docs and tests name these files, and a new evaluation of the same setting must land on
    # the same name: a readable name that says its setting exactly gets no hash.
    saved = json.loads(path.read_text())
    model = "final_model" if path.name.startswith("eval-final_model_") else "model"
    name = result_filename("eval", saved["overrides"], model, saved["episodes"])
    assert name == path.name


@pytest.mark.parametrize("named", ["model zip", "folder"])
def test_eval_of_a_checkpoint_goes_to_its_run_not_into_the_checkpoint(named, smoke_run, capsys):
    checkpoint = sorted((smoke_run / "checkpoints").glob("step-*"))[-1]
    before = sorted(p.name for p in checkpoint.iterdir())
    capsys.readouterr()
    target = checkpoint / "model.zip" if named == "model zip" else checkpoint
    assert main(["eval", str(target), "--episodes", "2"]) == 0
    saved = smoke_run / f"eval-{checkpoint.name}_2ep.json"
    assert f"saved {saved}" in capsys.readouterr().err
    assert json.loads(saved.read_text())["policy"] == str(checkpoint / "model.zip")
    assert sorted(p.name for p in checkpoint.iterdir()) == before  # nothing written into it


@pytest.mark.parametrize("named", ["model zip", "folder"])
def test_tune_write_of_a_checkpoint_writes_the_runs_config(named, smoke_run, tmp_path, capsys):
    run = tmp_path / smoke_run.name
    shutil.copytree(smoke_run, run)
    checkpoint = sorted((run / "checkpoints").glob("step-*"))[-1]
    copy = (checkpoint / "config.yaml").read_bytes()
    capsys.readouterr()
    target = checkpoint / "model.zip" if named == "model zip" else checkpoint
    args = ["tune", str(target), "--temperatures", "2.5", "--episodes", "1"]
    assert main([*args, "--write"]) == 0
    err = capsys.readouterr().err
    assert f"saved eval.temperature=2.5 in {run / 'config.yaml'} (was 0)" in err
    assert load_config(run / "config.yaml").eval.temperature == 2.5
    assert (checkpoint / "config.yaml").read_bytes() == copy  # the resume's copy: untouched
    assert (run / f"tune-{checkpoint.name}.json").is_file()
    assert sorted(p.name for p in checkpoint.glob("*.json")) == ["state.json"]


def test_a_resume_of_a_checkpoint_names_its_run(smoke_run, capsys):
    checkpoint = sorted((smoke_run / "checkpoints").glob("step-*"))[-1]
    before = sorted(p.name for p in checkpoint.iterdir())
    capsys.readouterr()
    assert main(["run", "--resume", str(checkpoint)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"is a checkpoint of {smoke_run}: resume the run" in line
    assert sorted(p.name for p in checkpoint.iterdir()) == before


def test_eval_table_is_readable(smoke_run, capsys):
    capsys.readouterr()
    assert main(["eval", str(smoke_run), "--episodes", "2"]) == 0
    table = capsys.readouterr().out
    assert "coverage  median" in table and "useful coverage" in table and "agent_1" in table


@pytest.mark.parametrize("config", CONFIGS, ids=lambda p: p.stem)
@pytest.mark.parametrize("policy", ["random", "frontier"])
def test_baselines_work_on_every_shipped_config(config, policy, capsys):
    out = eval_json(
        capsys, "--policy", policy, "--config", str(config), "--episodes", "1",
        "--set", "env.max_steps=30",
    )  # fmt: skip
    assert out["policy"] == policy and 0.0 < out["coverage_median"] <= 1.0
    if policy == "frontier":
        # Its early moves nearly all enter new cells, also where the config's actions are the
        # goal action's slots (it plays the moves there: the goal action off).
        assert out["wall_hits_mean"] == 0.0 and out["efficiency"] > 0.5


def test_a_planner_on_a_goal_config_plays_its_moves_on_the_same_episodes(capsys):
    # The goal action's slot 0 is the pocket planner's own target, so frontier_step there walks
    # what frontier_pocket walks: the same coverage, episode by episode (min, median, max of 3).
    args = ["--config", str(ROOT / "configs" / "goals_2agents.yaml"), "--episodes", "3"]
    args += ["--set", "env.max_steps=80"]
    planner = eval_json(capsys, "--policy", "frontier_pocket", *args)
    slot_0 = eval_json(capsys, "--policy", "frontier_step", *args)
    keys = ("coverage_min", "coverage_median", "coverage_max")
    assert [planner[k] for k in keys] == [slot_0[k] for k in keys]
    assert planner["env"]["frontier"] is None and slot_0["env"]["frontier"] is not None


def test_a_long_evaluation_says_where_it_is_on_stderr(capsys, monkeypatch):
    args = ["--config", str(SMOKE), "--episodes", "20", "--set", "env.max_steps=20"]
    # A short evaluation prints no progress: the summary is all.
    capsys.readouterr()
    assert main(["eval", "--policy", "frontier", *args, "--against", "random"]) == 0
    assert "episodes," not in capsys.readouterr().err
    # Every batch of copies side by side (8) once it has taken long enough, never the last.
    monkeypatch.setattr("harness.cli.EVAL_PROGRESS_EVERY_S", 0.0)
    assert main(["eval", "--policy", "frontier", *args, "--against", "random"]) == 0
    lines = [line.split(", ")[0].strip() for line in capsys.readouterr().err.splitlines()]
    assert lines == [
        "frontier: 8/20 episodes",
        "frontier: 16/20 episodes",
        "random: 8/20 episodes",
        "random: 16/20 episodes",
    ]


def test_frontier_beats_random_on_the_same_episodes(capsys):
    args = ["--config", str(SMOKE), "--episodes", "5"]
    frontier = eval_json(capsys, "--policy", "frontier", *args)
    random = eval_json(capsys, "--policy", "random", *args)
    assert frontier["coverage_median"] > random["coverage_median"]


def test_against_plays_the_baselines_on_the_models_episodes_and_pairs_them(smoke_run, capsys):
    args = ["--episodes", "4", "--against", "frontier", "random", "frontier"]  # each played once
    out = eval_json(capsys, str(smoke_run), *args)
    assert [c["against"] for c in out["against"]] == ["frontier", "random"]
    own = json.loads((smoke_run / "eval-4ep.json").read_text())["coverage"]
    for c in out["against"]:
        # The baseline's episodes are the ones `harness eval --policy` plays on the run's config.
        alone = eval_json(
            capsys, "--policy", c["against"], "--config", str(smoke_run / "config.yaml"),
            "--episodes", "4",
        )  # fmt: skip
        assert c["against_mean"] == pytest.approx(alone["coverage_mean"])
        saved = json.loads((smoke_run / f"against-{c['against']}-4ep.json").read_text())
        assert saved["coverage"] == own and len(saved["against_coverage"]) == 4
        pairs = list(zip(own, saved["against_coverage"], strict=True))
        assert c["ahead"] == sum(a > b for a, b in pairs)
        assert c["behind"] == sum(a < b for a, b in pairs)
        assert c["ahead"] + c["behind"] + c["equal"] == 4
        assert c["difference"] == pytest.approx(c["mean"] - c["against_mean"])
        low, high = c["difference_ci95"]
        assert low <= c["difference"] <= high
        assert "coverage" not in c and "against_coverage" not in c  # the file keeps the lists
        both = [
            (x, y)
            for x, y in zip(
                saved["steps_to_99_each"], saved["against_steps_to_99_each"], strict=True
            )
            if x is not None and y is not None
        ]
        steps = c["steps_to_99"]
        assert (steps is None) == (not both)
        if both:
            assert steps["episodes"] == len(both)
            assert steps["mean"] == pytest.approx(sum(x for x, _ in both) / len(both))


def test_a_baseline_against_itself_is_equal_in_every_episode(capsys):
    args = ["eval", "--policy", "frontier", "--config", str(SMOKE), "--episodes", "3"]
    assert main([*args, "--against", "frontier"]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.startswith("against   frontier on the same 3 episodes: mean coverage ")
    assert line.endswith(
        "difference +0.00 points [+0.00, +0.00] (95 % bootstrap over the episodes); this policy "
        "ahead in 0, behind in 0, equal in 3"
    )


def test_against_set_to_the_targets_own_value_changes_nothing_but_the_file_name(smoke_run, capsys):
    # eval.rollout.after=0.8 is the default (and frontier_pocket reads no eval.rollout): the
    # baseline plays as plain --against does, in a file of its own beside the plain one.
    alike = ["--against", "frontier_pocket", "--against-set", "eval.rollout.after=0.8"]
    args = ["--policy", "frontier_pocket", "--config", str(SMOKE), "--episodes", "2"]
    (itself,) = eval_json(capsys, *args, *alike)["against"]
    assert itself["difference"] == 0.0 and itself["difference_ci95"] == [0.0, 0.0]
    assert itself["against_set"] == ["eval.rollout.after=0.8"]
    (plain,) = eval_json(capsys, str(smoke_run), "--episodes", "2", *alike[:2])["against"]
    (with_set,) = eval_json(capsys, str(smoke_run), "--episodes", "2", *alike)["against"]
    assert "against_set" not in plain
    assert {**plain, "against_set": ["eval.rollout.after=0.8"]} == with_set
    saved = json.loads((smoke_run / "against-frontier_pocket-2ep.json").read_text())
    named = smoke_run / "against-frontier_pocket-2ep+eval.rollout.after-0.8.json"
    assert {**saved, "against_set": ["eval.rollout.after=0.8"]} == json.loads(named.read_text())


def test_against_set_plays_the_baseline_under_its_settings_on_the_same_episodes(capsys):
    # frontier_step follows env.frontier.planner: under hungarian it walks otherwise than under
    # the config's pocket, as `--policy frontier_step --set env.frontier.planner=hungarian` does.
    args = ["--config", str(ROOT / "configs" / "goals_2agents.yaml"), "--episodes", "2"]
    args += ["--set", "env.map=random", "--set", "env.height=12", "--set", "env.width=12"]
    args += ["--set", "env.max_steps=60", "--policy", "frontier_step"]
    other = "env.frontier.planner=hungarian"
    out = eval_json(capsys, *args, "--against", "frontier_step", "--against-set", other)
    (comparison,) = out["against"]
    alone = eval_json(capsys, *args, "--set", other)
    assert comparison["against_mean"] == alone["coverage_mean"] != out["coverage_mean"]
    assert comparison["difference"] != 0.0 and comparison["against_set"] == [other]
    capsys.readouterr()
    assert main(["eval", *args, "--against", "frontier_step", "--against-set", other]) == 0
    assert f"against   frontier_step --against-set {other} on the same 2 episodes" in (
        capsys.readouterr().out
    )


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--against-set", "eval.rollout.after=0.5"], "--against-set sets the config of the"),
        (["--against-set", "env.max_steps=20"], "env.max_steps makes the episodes"),
        (["--against-set", "seed=3"], "seed makes the episodes"),
        (["--against-set", "env={n_agents: 3}"], "env.n_agents makes the episodes"),
        (["--against-set", "env.map.cave.height=20"], "env.map makes the episodes"),
        (["--against-set", "env.starts=[[1, 1]]"], "env.starts makes the episodes"),
        (["--against-set", "eval.rollout.nope=1"], "eval.rollout.nope: Extra inputs"),
        (["--against-set", "eval.rollout.after=7"], "less than or equal to 1"),
        (["--against-set", "nothing"], "--against-set: --set 'nothing': expected key.path=value"),
    ],
)
def test_against_set_is_refused_in_one_line_writing_nothing(smoke_run, extra, message, capsys):
    against = [] if "sets the config" in message else ["--against", "frontier"]
    before = sorted(p.name for p in smoke_run.iterdir())
    capsys.readouterr()
    assert main(["eval", str(smoke_run), "--episodes", "2", *against, *extra]) == 2
    captured = capsys.readouterr()
    assert message in one_error_line(captured.err) and captured.out == ""
    assert sorted(p.name for p in smoke_run.iterdir()) == before


def test_against_set_files_are_named_apart_from_the_evaluations_own_sets():
    # --set X --against P is the evaluation's setting (both play it); --against-set X is the
    # baseline's alone: two files. A value that reads back ambiguously gets its hash.
    assert against_filename("rollout", ["eval.rollout.after=0.6"]) == (
        "against-rollout-eval.rollout.after-0.6.json"
    )
    assert against_filename("rollout", [], against_set=["eval.rollout.after=0.6"]) == (
        "against-rollout+eval.rollout.after-0.6.json"
    )
    hashed = against_filename("rollout", [], episodes=10, against_set=["eval.x=1", "c=x-y"])
    assert re.fullmatch(r"against-rollout-10ep\+eval\.x-1_c-x-y~[0-9a-f]{8}\.json", hashed)
    assert hashed != against_filename("rollout", [], episodes=10, against_set=["eval.x=1", "c=x/y"])


def test_steps_to_99_are_paired_on_the_episodes_both_reach_it_in():
    steps = paired_steps_to_99([10, None, 30, 40], [12, 20, None, 40])
    assert steps is not None
    assert (steps["episodes"], steps["mean"], steps["against_mean"]) == (2, 25.0, 26.0)
    assert steps["difference"] == -1.0  # (10 - 12 + 40 - 40) / 2
    low, high = steps["difference_ci95"]
    assert -2.0 <= low <= -1.0 <= high <= 0.0  # resampled means of the differences -2 and 0
    assert paired_steps_to_99([None, 5], [7, None]) is None


def test_the_against_line_reads_its_numbers():
    comparison = {
        "against": "frontier_pocket",
        "episodes": 4,
        "metric": "coverage",
        "mean": 0.5,
        "against_mean": 0.6,
        "difference": -0.1,
        "difference_ci95": [-0.125, -0.0625],
        "ahead": 1,
        "behind": 3,
        "equal": 0,
    }
    line = (
        "against   frontier_pocket on the same 4 episodes: mean coverage 60.0% (this policy "
        "50.0%), difference -10.00 points [-12.50, -6.25] (95 % bootstrap over the episodes); "
        "this policy ahead in 1, behind in 3, equal in 0"
    )
    assert format_against(comparison) == line
    comparison["steps_to_99"] = {
        "episodes": 2,
        "mean": 25.0,
        "against_mean": 26.0,
        "difference": -1.0,
        "difference_ci95": [-2.0, 0.0],
    }
    assert format_against(comparison) == line + (
        "\n          steps to 99 %, on the 2 episodes both reach it in: mean 26.0 (this policy "
        "25.0), difference -1.0 [-2.0, +0.0]"
    )


def test_the_group_against_lines_read_their_numbers():
    comparison = {
        "against": "frontier_hungarian",
        "metric": "coverage",
        "difference_over_seeds": {
            "seeds": 3, "mean": -0.002, "mean_ci95": [-0.005, 0.001],
            "iqm": -0.002, "iqm_ci95": [-0.005, 0.001],
        },
        "steps_to_99_difference_over_seeds": {
            "seeds": 3, "mean": 12.5, "mean_ci95": [-3.0, 30.25],
            "iqm": 12.5, "iqm_ci95": [-3.0, 30.25],
        },
    }  # fmt: skip
    assert format_group_against(comparison).splitlines() == [
        "== over 3 seeds against frontier_hungarian (paired on each run's episodes), mean "
        "difference (points of coverage) -0.20 [-0.50, +0.10], IQM -0.20 [-0.50, +0.10]",
        "   steps to 99 % (each run's on the episodes both reach it in), mean difference +12.5 "
        "[-3.0, +30.2], IQM +12.5 [-3.0, +30.2]",
    ]


def test_render_writes_png_and_gif(smoke_run, tmp_path, capsys):
    png, gif = tmp_path / "paths.png", tmp_path / "episode.gif"
    assert main(["render", str(smoke_run), "--out", str(png), "--gif", str(gif)]) == 0
    with Image.open(png) as img:
        assert img.format == "PNG" and img.size[0] > 400
    with Image.open(gif) as img:
        assert img.format == "GIF" and img.n_frames > 1
    assert main(["render", str(smoke_run)]) == 0
    assert (smoke_run / "paths.png").read_bytes()[:8] == PNG_SIGNATURE


def test_render_a_baseline(tmp_path):
    png = tmp_path / "frontier.png"
    args = ["render", "--policy", "frontier", "--config", str(SMOKE), "--out", str(png)]
    assert main(args) == 0
    assert png.read_bytes()[:8] == PNG_SIGNATURE


def test_compare_writes_a_plot_and_a_table(smoke_run, tmp_path, capsys):
    assert main(["eval", str(smoke_run)]) == 0
    out = tmp_path / "cmp.png"
    capsys.readouterr()
    copy = tmp_path / "copy"  # the same run named twice would count twice: a copy is another
    shutil.copytree(smoke_run, copy)
    assert main(["compare", str(smoke_run), str(copy), "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert "smoke" in table and "%" in table
    assert out.read_bytes()[:8] == PNG_SIGNATURE
    labelled = ["compare", str(smoke_run), str(copy), "--out", str(out), "--labels", "a", "b"]
    assert main(labelled) == 0
    out_lines = capsys.readouterr().out.splitlines()
    table = out_lines[: out_lines.index("")]  # the per-run table, before the over-seeds part
    assert [line.split()[0] for line in table[1:]] == ["a", "b"]
    assert "| a | 1 |" in "\n".join(out_lines)


# ---------------------------------------------------------------------- compare's numbers
EPISODES = "episode,phase,timesteps,copy,coverage,reward_mean,wall_hits,new_cells,length\n"


def fake_run(folder: Path, episodes: str, ev: str | None = None) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(TINY)
    (folder / "episodes.csv").write_text(EPISODES + episodes)
    if ev is not None:
        (folder / "eval.json").write_text(ev)
    return folder


HUGE = "1" + "0" * 400
HUGE_EVAL = f'{{"coverage_median": 0.5, "coverage_mean": {HUGE}, "wall_hits_mean": 1}}'
TOO_LARGE = [
    ({"eval.json": HUGE_EVAL}, "eval.json: the number 100000000000... (401 digits) is too large"),
    ({"episodes.csv": EPISODES + "1,0,1e300,0,0.5,0.1,0,10,20\n"},
     "episodes.csv, line 2: timesteps 1e300 is out of range"),
    ({"evaluations.csv": "timesteps,coverage_median\n1e300,0.5\n"},
     "evaluations.csv, line 2: timesteps 1e300 is out of range"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("files", "message"),
    TOO_LARGE,
    ids=["eval-json-400-digits", "episodes-1e300", "evaluations-1e300"],
)
def test_compare_refuses_numbers_too_large_in_one_line(tmp_path, capsys, files, message):
    run = fake_run(tmp_path / "run", "0,0,20,0,0.5,0.1,0,10,20\n")
    for name, text in files.items():
        (run / name).write_text(text)
    capsys.readouterr()
    assert main(["compare", str(run), "--out", str(tmp_path / "c.png"), "--reps", "10"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"{run}/{message}" in line


def test_the_console_script_refuses_a_huge_eval_json_without_traceback(tmp_path):
    ev = f'{{"coverage_median": {HUGE}, "coverage_iqr": 0, "coverage_mean": 0.5}}'
    run = fake_run(tmp_path / "run", "0,0,20,0,0.5,0.1,0,10,20\n", ev)
    proc = subprocess.run(
        [sys.executable, "-m", "harness.cli", "compare", str(run), "--out",
         str(tmp_path / "c.png")],
        capture_output=True, text=True, cwd=tmp_path, env=root_first_env(),
    )  # fmt: skip
    assert proc.returncode == 2
    assert "is too large for an evaluation" in one_error_line(proc.stderr)


def test_large_but_finite_numbers_still_compare(tmp_path, capsys):
    ev = '{"coverage_median": 0.5, "coverage_iqr": 0, "coverage_mean": 0.5, "wall_hits_mean": 1}'
    run = fake_run(tmp_path / "run", "0,0,9000000000000000000,0,0.5,0.1,0,10,20\n", ev)
    assert main(["compare", str(run), "--out", str(tmp_path / "c.png"), "--reps", "10"]) == 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["eval", "no/such/run"], "no such run folder or model file"),
        (
            ["eval", str(SMOKE)],
            "is a config, not a run or a model: evaluate a baseline on it with --policy NAME",
        ),
        (["eval", "--policy", "greedy", "--config", str(SMOKE)], "unknown policy 'greedy'"),
        (["eval", "--policy", "random"], "needs --config"),
        (
            ["eval", "--policy", "random", "--config", str(SMOKE), "--against", "greedy"],
            "--against: unknown policy 'greedy'",
        ),
        (
            ["eval", "--policy", "random", "--config", str(SMOKE), "--against", "frontier_step"],
            "--against frontier_step: the frontier_step baseline needs env.frontier.action",
        ),
        (
            ["eval", "--policy", "frontier_step", "--config", str(SMOKE)],
            "--policy frontier_step: the frontier_step baseline needs env.frontier.action",
        ),
        (["eval"], "give a run folder or model zip"),
        (["eval", "--policy", "random", "--config", str(SMOKE), "--episodes", "0"], "--episodes"),
        (["compare", "no/such/run"], "not a run folder with episodes.csv"),
        (["compare", "a", "b", "--labels", "x"], "--labels needs one label per run (2)"),
        (["render", "--policy", "random", "--config", "nope.yaml"], "config file not found"),
    ],
)
def test_bad_input_is_one_line_and_exit_code_2(args, message, capsys):
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("harness: error:") and message in err and "\n" not in err


def test_missing_and_corrupt_models(smoke_run, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text((smoke_run / "config.yaml").read_text())
    assert main(["eval", str(run)]) == 2
    assert "no model.zip yet" in capsys.readouterr().err
    (run / "model.zip").write_bytes(b"garbage")
    assert main(["eval", str(run)]) == 2
    assert "cannot load model" in capsys.readouterr().err
    with zipfile.ZipFile(run / "model.zip", "w") as z:
        z.writestr("data", "{}")
    assert main(["eval", str(run)]) == 2
    assert "cannot load model" in capsys.readouterr().err


def test_export_makes_a_compact_reference_that_evaluates_the_same(
    smoke_run, tmp_path, capsys, monkeypatch
):
    monkeypatch.chdir(tmp_path)  # a reference's results go to runs/evals/ under the cwd
    ref = tmp_path / "reference" / "smoke"
    assert main(["export", str(smoke_run), "--out", str(ref)]) == 0
    for f in ("config.yaml", "command.txt", "episodes.csv", "evaluations.csv"):
        assert (ref / f).read_bytes() == (smoke_run / f).read_bytes(), f
    assert (ref / "model.zip").stat().st_size < 0.5 * (smoke_run / "model.zip").stat().st_size
    # In today's format: no migration, and no loading shim, reads it.
    from harness.sb3.dqn import MODEL_FORMAT, saved_model_format

    assert saved_model_format(ref / "model.zip") == MODEL_FORMAT
    original = eval_json(capsys, str(smoke_run), "--episodes", "3", "--seed", "9")
    exported = eval_json(capsys, str(ref), "--episodes", "3", "--seed", "9")
    assert {k: v for k, v in exported.items() if k != "policy"} == {
        k: v for k, v in original.items() if k != "policy"
    }
    assert main(["render", str(ref), "--out", str(tmp_path / "p.png")]) == 0
    assert main(["export", str(smoke_run), "--out", str(ref)]) == 2  # never overwritten
    assert "already exists" in capsys.readouterr().err


def test_export_refuses_a_tune_file_that_is_not_json(smoke_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(smoke_run, run)
    (run / "tune.json").write_text("{not json")
    out = tmp_path / "reference" / "smoke"
    assert main(["export", str(run), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("harness: error:") and "tune.json: not JSON" in err and "\n" not in err
    assert not out.exists() and not list(out.parent.glob(".smoke.*"))  # nothing half-made


def test_export_of_best_model_keeps_its_own_tune_sweep(smoke_run, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a reference's results go to runs/evals/ under the cwd
    (smoke_run / "tune.json").write_text('{"policy": "model.zip"}')
    (smoke_run / "tune-best_model.json").write_text('{"policy": "best_model.zip"}')
    ref = tmp_path / "best"
    try:
        assert main(["export", str(smoke_run), "--model", "best_model", "--out", str(ref)]) == 0
    finally:
        (smoke_run / "tune.json").unlink()
        (smoke_run / "tune-best_model.json").unlink()
    assert json.loads((ref / "tune.json").read_text()) == {"policy": "best_model.zip"}
    lines = (ref / "command.txt").read_text().splitlines()
    assert lines[:-1] == (smoke_run / "command.txt").read_text().splitlines()
    assert lines[-1] == "# exported: best_model.zip (harness export --model best_model)"
    best = eval_json(capsys, str(smoke_run / "best_model.zip"), "--episodes", "2", "--seed", "9")
    exported = eval_json(capsys, str(ref), "--episodes", "2", "--seed", "9")
    assert exported["coverage_median"] == best["coverage_median"]


@pytest.mark.parametrize(
    ("name", "eval_file", "overrides", "episodes"),
    [
        ("ddqn_15x15", "eval.json", [], 8),
        ("ddqn_15x15", "eval-eval.temperature-1.json", ["eval.temperature=1"], 8),
        ("ddqn_4agents", "eval.json", [], 3),
        ("ddqn_2agents", "eval-eval.temperature-0.json", ["eval.temperature=0"], 3),
        ("ddqn_1agent", "eval-env.max_steps-500.json", ["env.max_steps=500"], 3),
        ("ddqn_3agents", "eval.json", [], 2),
        ("maze_4agents", "eval-eval.temperature-0.json", ["eval.temperature=0"], 2),
        ("cave_4agents", "eval.json", [], 2),
    ],
)
def test_reference_policy_repeats_its_committed_numbers(
    name, eval_file, overrides, episodes, tmp_path, capsys
):
    ref = ROOT / "runs" / "reference" / name
    committed = json.loads((ref / eval_file).read_text())
    copy = tmp_path / name  # evaluate a copy: the committed files stay as they are
    copy.mkdir()
    for f in ("config.yaml", "model.zip"):
        (copy / f).write_bytes((ref / f).read_bytes())
    sets = [arg for o in overrides for arg in ("--set", o)]
    eval_json(capsys, str(copy), "--episodes", str(episodes), *sets)
    (saved_file,) = copy.glob("eval*.json")
    saved = json.loads(saved_file.read_text())
    # Episode k is seeded with seed + k whatever the count (its action noise too): the first
    # episodes of the committed 100.
    assert saved["coverage"] == committed["coverage"][:episodes]
    assert saved["wall_hits"] == committed["wall_hits"][:episodes]


def test_evaluation_runs_torch_single_threaded_whatever_algo_threads(smoke_run, capsys):
    import torch

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        eval_json(capsys, str(smoke_run), "--episodes", "1", "--set", "algo.threads=2")
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_eval_with_a_temperature_samples_and_names_its_file(smoke_run, capsys):
    greedy = eval_json(capsys, str(smoke_run), "--episodes", "3")
    soft = eval_json(capsys, str(smoke_run), "--episodes", "3", "--set", "eval.temperature=1.5")
    again = eval_json(capsys, str(smoke_run), "--episodes", "3", "--set", "eval.temperature=1.5")
    assert soft == again  # seeded: the same episodes draw the same actions
    assert soft["temperature"] == 1.5 and greedy["temperature"] == 0.0
    saved = json.loads((smoke_run / "eval-3ep_eval.temperature-1.5.json").read_text())
    assert saved["coverage_median"] == soft["coverage_median"]
    assert saved["coverage"] != json.loads((smoke_run / "eval-3ep.json").read_text())["coverage"]


def test_best_model_is_chosen_on_validation_episodes(smoke_run, capsys):
    cfg = load_config(smoke_run / "config.yaml")
    rows = (smoke_run / "evaluations.csv").read_text().splitlines()[1:]
    header = (smoke_run / "evaluations.csv").read_text().splitlines()[0].split(",")
    # Fewest wall hits first, then the highest median (first such row on ties).
    best = min(
        (dict(zip(header, r.split(","), strict=True)) for r in rows),
        key=lambda r: (float(r["wall_hits_mean"]), -float(r["coverage_median"])),
    )
    validation = eval_json(
        capsys, str(smoke_run / "best_model.zip"), "--episodes", str(cfg.eval.episodes),
        "--seed", str(cfg.eval.validation_seed),
    )  # fmt: skip
    assert validation["coverage_median"] == pytest.approx(float(best["coverage_median"]))
    assert validation["wall_hits_mean"] == pytest.approx(float(best["wall_hits_mean"]))


def test_selection_score_puts_zero_wall_hits_before_coverage():
    from harness.evaluation.episodes import selection_score

    clean = selection_score({"coverage_median": 0.30, "wall_hits_mean": 0.0})
    one_hit = selection_score({"coverage_median": 0.95, "wall_hits_mean": 1 / 999})
    wider = selection_score({"coverage_median": 0.31, "wall_hits_mean": 0.0})
    assert wider > clean > one_hit
    assert selection_score({"coverage_median": 0.9, "wall_hits_mean": 0.05}) > selection_score(
        {"coverage_median": 0.2, "wall_hits_mean": 0.10}
    )


def test_selection_score_breaks_coverage_ties_by_speed_and_only_ties():
    from harness.evaluation.episodes import selection_score

    def score(median: float, steps: float | None, walls: float = 0.0) -> float:
        return selection_score(
            {"coverage_median": median, "wall_hits_mean": walls, "steps_to_99": steps}
        )

    # A whole-map team: the same median, the faster one first; never reaching 99 % is last.
    assert score(1.0, 540) > score(1.0, 648) > score(1.0, None)
    assert score(1.0, 648) - score(1.0, 649) == pytest.approx(1e-12, rel=1e-3)
    # Speed never outweighs the smallest coverage difference (half a cell of 500,000) ...
    assert score(0.99 + 1 / 1_000_000, None) > score(0.99, 1)
    # ... nor a wall hit.
    assert score(0.5, None) > score(1.0, 1, walls=1 / 999)
    # A summary without the key (older rows) counts as never reaching 99 %.
    assert selection_score({"coverage_median": 1.0, "wall_hits_mean": 0.0}) == score(1.0, None)


def _row(t: float, median: float, walls: float) -> dict:
    return {"temperature": t, "coverage_median": median, "wall_hits_mean": walls}


def test_choose_temperature_puts_zero_wall_hits_before_coverage():
    rows = [_row(0.5, 0.60, 0.0), _row(1.0, 0.70, 0.02), _row(1.5, 0.75, 0.5)]
    assert choose_temperature(rows)["temperature"] == 0.5
    rows = [_row(0.5, 0.60, 0.0), _row(0.75, 0.66, 0.0), _row(1.0, 0.70, 0.02)]
    assert choose_temperature(rows)["temperature"] == 0.75
    rows = [_row(1.0, 0.66, 0.0), _row(0.75, 0.66, 0.0)]  # a tie goes to the lower temperature
    assert choose_temperature(rows)["temperature"] == 0.75
    rows = [_row(0.5, 0.50, 0.3), _row(1.0, 0.70, 0.1)]  # none without: the fewest wall hits
    assert choose_temperature(rows)["temperature"] == 1.0


def test_tune_sweeps_temperatures_on_validation_episodes(smoke_run, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    for f in ("config.yaml", "model.zip"):
        (run / f).write_bytes((smoke_run / f).read_bytes())
    cfg = load_config(run / "config.yaml")
    capsys.readouterr()
    args = ["tune", str(run), "--temperatures", "0", "0.5", "3", "--episodes", "3", "--json"]
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["seed"] == cfg.eval.validation_seed != cfg.eval.seed
    assert [r["temperature"] for r in result["rows"]] == [0.0, 0.5, 3.0]
    assert result["chosen"] == choose_temperature(result["rows"])["temperature"]
    assert json.loads((run / "tune.json").read_text())["rows"] == result["rows"]
    # Each row is harness eval at that temperature on the same validation episodes (T = 0: the
    # greedy policy, eval's default).
    for row in result["rows"]:
        ev = eval_json(
            capsys, str(run), "--episodes", "3", "--seed", str(cfg.eval.validation_seed),
            "--set", f"eval.temperature={row['temperature']}",
        )  # fmt: skip
        assert ev["coverage_median"] == row["coverage_median"]
        assert ev["wall_hits_mean"] == row["wall_hits_mean"]
    # --write stores the choice as the run's test temperature, which harness eval then uses.
    assert main([*args, "--temperatures", "2.5", "--write"]) == 0
    assert load_config(run / "config.yaml").eval.temperature == 2.5
    assert json.loads((run / "tune.json").read_text())["previous_temperature"] == 0.0
    assert eval_json(capsys, str(run), "--episodes", "2")["temperature"] == 2.5


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--temperatures", "-0.5"], "--temperatures: temperatures must be finite and >= 0"),
        (["--temperatures", "nan"], "--temperatures: temperatures must be finite and >= 0"),
        (["--temperatures", "inf"], "--temperatures: temperatures must be finite and >= 0"),
        (["--episodes", "0"], "--episodes: the value must be >= 1"),
        (["--seed", "-1"], "--seed: seed must be in [0, 2147483647]"),
        (["--write", "--set", "env.max_steps=20"], "--write stores a choice"),
    ],
)
def test_tune_bad_input_is_one_line_and_exit_code_2(smoke_run, extra, message, capsys):
    assert main(["tune", str(smoke_run), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("harness: error:") and message in err and "\n" not in err


#: The references of trained policies (a map prior's reference is tests/test_prior.py's).
REFERENCES = sorted(
    p
    for p in (ROOT / "runs" / "reference").iterdir()
    if p.is_dir() and "\nprior:" not in (p / "config.yaml").read_text()
)


@pytest.mark.parametrize("ref", REFERENCES, ids=lambda p: p.name)
def test_reference_numbers_are_made_with_its_tuned_test_policy(ref: Path) -> None:
    cfg = load_config(ref / "config.yaml")
    if (ref / "tune.json").exists():
        tune = json.loads((ref / "tune.json").read_text())
        assert tune["chosen"] == cfg.eval.temperature
        assert tune["seed"] == cfg.eval.validation_seed != cfg.eval.seed  # off the test maps
        assert tune["chosen"] == choose_temperature(tune["rows"])["temperature"]
    else:
        # Greedy by its config (harness tune chooses among Boltzmann temperatures only): the
        # goal action walks a planner's paths, so there are no loops for noise to break.
        assert cfg.eval.temperature == 0 and cfg.env.frontier["action"].keys() == {"goal"}
    standard = json.loads((ref / "eval.json").read_text())
    assert standard["temperature"] == cfg.eval.temperature
    assert standard["seed"] == cfg.eval.seed and standard["episodes"] == 100


@pytest.mark.parametrize("ref", REFERENCES, ids=lambda p: p.name)
def test_config_tests_with_its_references_tuned_temperature(ref: Path) -> None:
    # `harness eval --config configs/<experiment>.yaml` and a fresh run's in-training evaluations
    # use the config's temperature: it must be the one its reference was tuned to.
    config = ROOT / "configs" / f"{ref.name}.yaml"
    assert config.is_file(), f"no config for reference {ref.name}"
    tune = ref / "tune.json"
    tuned = json.loads(tune.read_text())["chosen"] if tune.exists() else 0.0  # greedy (above)
    assert load_config(config).eval.temperature == tuned


def test_evaluating_a_shipped_reference_changes_none_of_its_files(tmp_path, monkeypatch, capsys):
    reference = ROOT / "runs" / "reference" / "ddqn_15x15"
    before = {p.name: p.read_bytes() for p in reference.iterdir()}
    monkeypatch.chdir(tmp_path)  # results of a reference go to runs/evals/ under the cwd
    assert main(["eval", str(reference), "--episodes", "2"]) == 0
    assert {p.name: p.read_bytes() for p in reference.iterdir()} == before
    saved = Path("runs") / "evals" / "ddqn_15x15" / "eval-2ep.json"
    assert f"saved {saved}" in capsys.readouterr().err
    assert json.loads((tmp_path / saved).read_text())["episodes"] == 2
