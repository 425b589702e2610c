"""A PettingZoo env of one's own (``env: {pettingzoo: {make, kwargs}}``, docs/your-own-env.md):
its config, its refusals (one line, exit 2), its episodes, and every command on the tests' own
env (tests/envs/meet.py) and on mpe2's simple_spread (configs/mpe_spread.yaml), tiny budgets."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from harness.cli import main
from harness.config.loading import config_from_dict, load_config
from harness.config.schema import ConfigError, ExperimentConfig, PettingZooEnvConfig, VecConfig
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import run_episodes, selection_score, summarize
from harness.factory import make_env
from harness.results.rundir import RunDir, rewind_logs
from harness.tasks.pettingzoo import PettingZooTask
from harness.training.checkpoints import read_state
from tests.conftest import one_error_line, root_first_env

ROOT = Path(__file__).resolve().parents[1]
MEET = ROOT / "tests" / "data" / "meet.yaml"
MPE = ROOT / "configs" / "mpe_spread.yaml"
MASKED = ROOT / "tests" / "data" / "meet_masked.yaml"


def meet(make: str = "tests.envs.meet:parallel_env", **extra) -> dict:
    """A config mapping of the meet env (``make`` another constructor of tests.envs)."""
    raw = yaml.safe_load(MEET.read_text())
    raw["env"]["pettingzoo"]["make"] = make
    raw.update(extra)
    return raw


@pytest.fixture(autouse=True)
def _importable(monkeypatch):
    # The seed groups' and sweeps' processes import tests.envs.meet too.
    monkeypatch.setenv("PYTHONPATH", root_first_env()["PYTHONPATH"])


# ---------------------------------------------------------------------- the config
def test_a_pettingzoo_source_reads_its_agents_and_picks_supersuit():
    config = config_from_dict(meet())
    assert isinstance(config.env, PettingZooEnvConfig)
    assert config.env.n_agents == 2 and config.n_slots == 4
    assert config.vec.backend == "supersuit"  # not given: chosen for it
    again = config_from_dict(yaml.safe_load(config.to_yaml()))  # a run's config.yaml reloads
    assert again.env == config.env and again.vec.backend == "supersuit"


def test_the_backend_chosen_for_a_pettingzoo_env_leaves_the_vec_section_given_alone():
    env = config_from_dict(meet()).env
    vec = VecConfig(copies=3)
    config = ExperimentConfig(env=env, vec=vec)
    assert config.vec.backend == "supersuit" and config.vec.copies == 3
    assert vec.backend == "core" and "backend" not in vec.model_fields_set
    # The coverage env keeps the core with the very same section.
    assert ExperimentConfig(vec=vec).vec.backend == "core"


def test_an_env_padded_to_one_action_space_as_the_contract_advises_is_accepted():
    config = config_from_dict(meet("tests.envs.odd:padded"))
    results = run_episodes(make_baseline("random", 0), config.env, 2, 5)
    assert [r.length for r in results] == [10, 10]


def test_an_aec_env_is_converted_to_a_parallel_one():
    config = config_from_dict(meet("tests.envs.odd:aec"))
    assert config.env.n_agents == 2
    (result,) = run_episodes(make_baseline("random", 0), config.env, 1, 5)
    assert result.length == 10


@pytest.mark.parametrize(
    ("make", "extra", "message"),
    [
        ("tests.envs.nowhere:parallel_env", {}, "cannot import module 'tests.envs.nowhere'"),
        ("tests.envs.broken:parallel_env", {}, "ImportError: this module cannot be imported"),
        ("tests.envs.meet", {}, "is not an import path 'package.module:constructor'"),
        ("tests.envs.meet:nothing", {}, "module 'tests.envs.meet' has no 'nothing'"),
        ("tests.envs.odd:not_callable", {}, "is not callable"),
        ("tests.envs.odd:failing", {}, "the constructor failed (RuntimeError: no such world)"),
        ("tests.envs.odd:mixed_actions", {}, "agent 'walker_1': action space Discrete(4)"),
        ("tests.envs.odd:mixed_observations", {}, "agent 'walker_1': observation space Box("),
        ("tests.envs.odd:continuous", {}, "action space Box(-1.0, 1.0, (1,), float32) is not"),
        ("tests.envs.odd:dict_observation", {}, "observation space Dict("),
        ("tests.envs.meet:parallel_env", {"vec": {"backend": "core"}}, "vec.backend: core"),
        ("tests.envs.odd:image", {"algo": {"sharing": "per_agent"}}, "needs vector observations"),
        ("tests.envs.odd:block", {"algo": {"sharing": "shared_id"}}, "has 4 dimensions: the"),
        (
            "tests.envs.meet:parallel_env",
            {"algo": {"policy": "TeamMapPolicy"}},
            "reads the coverage env's team map",
        ),
    ],
)
def test_bad_sources_are_one_line_and_exit_2(tmp_path, capsys, make, extra, message):
    raw = meet(make)
    for section, values in extra.items():
        raw.setdefault(section, {}).update(values)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["run", str(path), "--runs-dir", str(tmp_path / "runs")]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert message in line, line
    assert not (tmp_path / "runs").exists()


def test_a_coverage_baseline_is_refused_for_a_pettingzoo_env(capsys):
    assert main(["eval", "--policy", "frontier", "--config", str(MEET)]) == 2
    assert "a pettingzoo env takes random" in one_error_line(capsys.readouterr().err)


# ---------------------------------------------------------------------- episodes
def test_episodes_are_seeded_whatever_the_copies():
    env = config_from_dict(meet()).env
    one = run_episodes(make_baseline("random", 3), env, 5, 100, copies=1)
    # The random baseline draws for the whole batch: compare the seeded part, the starts.
    done: list[int] = []  # episodes finished, after each batch of copies
    assert [r.infos["cell"] for r in run_episodes(_stay, env, 5, 100, copies=1)] == [
        r.infos["cell"] for r in run_episodes(_stay, env, 5, 100, copies=3, progress=done.append)
    ]
    assert done == [3, 5]
    assert all(r.length == 10 and len(r.returns) == 2 for r in one)
    summary = summarize(one)
    assert summary["source"] == "pettingzoo" and "coverage_mean" not in summary
    assert summary["return_mean"] == pytest.approx(np.mean([r.team_return for r in one]))
    assert set(summary["infos"]) == {"cell", "spread"}
    assert [a["agent"] for a in summary["per_agent"]] == ["walker_0", "walker_1"]
    assert selection_score(summary) == summary["return_mean"]


def test_a_coverage_the_env_reports_is_summarised_and_nothing_else_of_the_coverage_env():
    env = config_from_dict(meet("tests.envs.odd:reports_coverage")).env
    results = run_episodes(_stay, env, 4, 100, copies=2)
    summary = summarize(results)
    # Each episode's coverage: its last step's, the mean over the agents (all report the same).
    last = [float(np.mean(r.infos["coverage"])) for r in results]
    assert summary["coverage_mean"] == pytest.approx(np.mean(last))
    assert summary["coverage_median"] == pytest.approx(np.median(last))
    assert set(summary["infos"]) == {"cell", "spread", "coverage"}
    # The coverage env's own figures (wall hits, steps to a coverage, the bound) are not made up.
    assert not {k for k in summary if k.startswith(("wall_hits", "steps_to", "efficiency"))}


def _stay(obs, envs):
    return np.ones(len(obs), dtype=np.int64)  # action 1: stay where the seed put them


# ---------------------------------------------------------------------- every command
@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A meet run, trained once for the module's commands."""
    root = tmp_path_factory.mktemp("meet")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("PYTHONPATH", root_first_env()["PYTHONPATH"])
        assert main(["run", str(MEET), "--no-progress", "--into", str(root / "run")]) == 0
    return root / "run"


def test_run_logs_team_and_agent_returns_and_the_env_infos(trained):
    with (trained / "episodes.csv").open() as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == PettingZooTask.episode_columns
    first = dict(zip(rows[0], rows[1], strict=True))
    returns = [float(r) for r in first["returns"].split(";")]
    assert float(first["team_return"]) == pytest.approx(sum(returns)) and first["length"] == "10"
    infos = json.loads(first["infos"])
    assert set(infos) == {"cell", "spread"} and len(infos["spread"]) == 2
    with (trained / "evaluations.csv").open() as f:
        assert next(csv.reader(f))[3] == "return_median"
    tags = (trained / "tb" / "progress.csv").read_text().splitlines()[0].split(",")
    assert {"rollout/team_return", "rollout/walker_1/return", "rollout/info/spread"} <= set(tags)
    assert {"rollout/walker_0/cell", "eval/return_median", "eval/info/spread"} <= set(tags)
    # A resume reads these logs back (rewound to its checkpoint: nothing after it to drop).
    state = read_state(sorted((trained / "checkpoints").iterdir())[-1])
    assert rewind_logs(RunDir(trained), state.next_episode, state.num_timesteps) == (0, 0)


def test_eval_tune_and_render(trained, tmp_path, capsys):
    assert main(["eval", str(trained), "--episodes", "4"]) == 0
    out = capsys.readouterr().out
    assert "team return  median" in out and "spread_mean" in out
    saved = json.loads((trained / "eval-4ep.json").read_text())
    assert saved["source"] == "pettingzoo" and len(saved["team_return"]) == 4
    assert main(["eval", "--policy", "random", "--config", str(MEET), "--episodes", "4"]) == 0
    out = capsys.readouterr().out
    assert "policy    random" in out
    random_mean = float(out.split("mean", 1)[1].split()[0])  # the team return's mean
    # --against compares the team return episode by episode, on the same episodes.
    assert main(["eval", str(trained), "--episodes", "4", "--against", "random"]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.startswith("against   random on the same 4 episodes: mean team return ")
    against = json.loads((trained / "against-random-4ep.json").read_text())
    assert against["metric"] == "team_return" and against["team_return"] == saved["team_return"]
    assert against["against_mean"] == pytest.approx(random_mean, rel=1e-3)
    # --plot draws the team return of each episode (no coverage or wall hits to draw).
    plot = tmp_path / "returns.png"
    assert main(["eval", str(trained), "--episodes", "4", "--plot", str(plot)]) == 0
    assert f"saved {plot}" in capsys.readouterr().err
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["tune", str(trained), "--episodes", "2", "--temperatures", "0.5", "1"]) == 0
    assert "(team return)" in capsys.readouterr().out
    gif = tmp_path / "meet.gif"
    assert main(["render", str(trained), "--gif", str(gif), "--out", str(tmp_path / "m.png")]) == 0
    assert gif.stat().st_size > 0 and (tmp_path / "m.png").is_file()


def test_the_return_plot_draws_the_team_and_each_group(tmp_path):
    from harness.results.plots import plot_eval_returns

    out = plot_eval_returns(
        [3.0, -1.0, 2.5], tmp_path / "r.png", groups={"good": [2, 0, 1], "adversary": [1, -1, 1.5]}
    )
    assert out.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="at least one episode"):
        plot_eval_returns([], tmp_path / "none.png")


@pytest.mark.parametrize("sharing", ["shared_id", "per_agent"])
def test_agent_indication_trains_and_evaluates(tmp_path, capsys, sharing):
    from harness.commands import load_model_target
    from harness.sb3.policies import PerAgentQNetwork

    run = tmp_path / "run"
    overrides = ["--set", f"algo.sharing={sharing}"]
    assert main(["run", str(MEET), "--no-progress", "--into", str(run), *overrides]) == 0
    target = load_model_target(run, [], None)
    # The observation: the env's 2 numbers, then the agent's one-hot index (SuperSuit's).
    assert target.model.observation_space.shape == (2 + 2,)
    assert isinstance(target.model.q_net, PerAgentQNetwork) == (sharing == "per_agent")
    env = make_env(target.config.env)
    obs, _ = env.reset(seed=3)
    assert [o[2:].tolist() for o in obs.values()] == [[1.0, 0.0], [0.0, 1.0]]
    assert main(["eval", str(run), "--episodes", "3", "--against", "random"]) == 0
    assert "against   random on the same 3 episodes" in capsys.readouterr().out
    assert len(json.loads((run / "eval-3ep.json").read_text())["team_return"]) == 3


def test_an_image_observation_gains_the_index_as_channels():
    raw = meet("tests.envs.odd:image")
    raw["algo"]["sharing"] = "shared_id"
    config = config_from_dict(raw)
    assert config.env.spaces.observation_space.shape == (1, 2, 1 + 2)
    (result,) = run_episodes(make_baseline("random", 0), config.env, 1, 5)
    assert result.length == 10


def test_render_refuses_an_env_without_frames(tmp_path, capsys):
    path = tmp_path / "no_frames.yaml"
    path.write_text(yaml.safe_dump(meet("tests.envs.odd:no_frames")))
    args = ["render", "--policy", "random", "--config", str(path), "--out", str(tmp_path / "r.png")]
    assert main(args) == 2
    assert "does not render rgb_array frames" in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "r.png").exists()


def test_seeds_eval_group_and_compare(trained, tmp_path, capsys):
    runs = tmp_path / "runs"
    args = ["run", str(MEET), "--seeds", "2", "--no-progress", "--runs-dir", str(runs)]
    args += ["--set", "phases.initial.timesteps=300", "--set", "eval.every=200"]
    assert main(args) == 0
    (group,) = runs.iterdir()
    assert "median team return" in capsys.readouterr().err
    assert main(["eval", str(group), "--episodes", "100"]) == 0
    assert "mean team return" in capsys.readouterr().out
    over = json.loads((group / "group-eval.json").read_text())["return_mean_over_seeds"]
    assert over["seeds"] == 2
    png = tmp_path / "cmp.png"
    assert main(["compare", str(group), "--out", str(png), "--reps", "100"]) == 0
    out = capsys.readouterr().out
    assert "| group | seeds | mean test team return [95 % CI] | IQM [95 % CI] |" in out
    # Each seed's row: the team return's median and IQR, no coverage env's wall hits.
    header = next(line for line in out.splitlines() if line.startswith("experiment"))
    assert header.split() == ["experiment", "run", "median", "return", "return", "IQR"]
    assert png.is_file() and png.with_name("cmp-curves-ci.png").is_file()


def test_compare_refuses_to_mix_the_coverage_env_and_a_pettingzoo_env(trained, tmp_path, capsys):
    coverage = tmp_path / "coverage"
    coverage.mkdir()
    (coverage / "config.yaml").write_text("name: c\n")
    (coverage / "episodes.csv").write_text(
        "episode,phase,timesteps,copy,coverage,reward_mean,wall_hits,new_cells,length\n"
        "0,only,20,0,0.5,1.0,0,3;4,20\n"
    )
    args = ["compare", str(trained), str(coverage), "--out", str(tmp_path / "c.png")]
    assert main(args) == 2
    assert "mix tasks: coverage (coverage) and pettingzoo (team return)" in one_error_line(
        capsys.readouterr().err
    )


def test_sweep(tmp_path, capsys):
    space = tmp_path / "space.yaml"
    space.write_text("algo.gamma: {float: [0.8, 0.99]}\n")
    sweeps = tmp_path / "sweeps"
    args = ["sweep", str(MEET), "--space", str(space), "--trials", "1", "--sweeps-dir"]
    assert main([*args, str(sweeps), "--set", "phases.initial.timesteps=300"]) == 0
    best = json.loads((sweeps / "meet" / "best.json").read_text())
    assert best["objective"].startswith("median team return")
    assert "validation team return" in capsys.readouterr().out


# ---------------------------------------------------------------------- mpe2's simple_spread
def test_the_mpe_example_through_every_command(tmp_path, capsys):
    # mpe2 comes with the dev extra (pyproject.toml), so CI runs this; tiny budgets.
    pytest.importorskip("mpe2")
    config = load_config(MPE)
    assert config.env.n_agents == 3 and config.vec.backend == "supersuit"
    tiny = ["--set", "phases.initial.timesteps=300", "--set", "algo.learning_starts=120"]
    tiny += ["--set", "eval.every=300", "--set", "eval.episodes=2", "--set", "vec.copies=2"]
    runs = tmp_path / "runs"
    args = ["run", str(MPE), "--seeds", "2", "--no-progress", "--runs-dir", str(runs), *tiny]
    assert main(args) == 0
    (group,) = runs.iterdir()
    assert main(["eval", str(group), "--episodes", "100"]) == 0
    assert "mean team return" in capsys.readouterr().out
    over = json.loads((group / "group-eval.json").read_text())["return_mean_over_seeds"]
    assert over["seeds"] == 2
    assert main(["eval", "--policy", "random", "--config", str(MPE), "--episodes", "3"]) == 0
    png = tmp_path / "mpe.png"
    assert main(["compare", str(group), "--out", str(png), "--reps", "100"]) == 0
    assert "mean test team return" in capsys.readouterr().out and png.is_file()
    space = tmp_path / "space.yaml"
    space.write_text("algo.gamma: {float: [0.8, 0.99]}\n")
    sweep = ["sweep", str(MPE), "--space", str(space), "--trials", "1"]
    assert main([*sweep, "--sweeps-dir", str(tmp_path / "sweeps"), *tiny]) == 0
    best = json.loads((tmp_path / "sweeps" / "mpe_spread" / "best.json").read_text())
    assert best["objective"].startswith("median team return")


def test_the_mpe_example_with_shared_id(tmp_path, capsys):
    # One network that reads each agent's one-hot index (SuperSuit's agent indication).
    pytest.importorskip("mpe2")
    from harness.commands import load_model_target

    base = load_config(MPE).env.spaces.observation_space.shape[0]
    tiny = ["--set", "phases.initial.timesteps=300", "--set", "algo.learning_starts=120"]
    tiny += ["--set", "eval.every=300", "--set", "eval.episodes=2", "--set", "vec.copies=2"]
    run = tmp_path / "run"
    args = ["run", str(MPE), "--no-progress", "--into", str(run), *tiny]
    assert main([*args, "--set", "algo.sharing=shared_id"]) == 0
    target = load_model_target(run, [], None)
    assert target.model.observation_space.shape == (base + 3,)
    assert main(["eval", str(run), "--episodes", "3", "--against", "random"]) == 0
    assert "against   random on the same 3 episodes" in capsys.readouterr().out


def _figure(value: float) -> str:
    """A return as the results page writes it: one decimal, a true minus sign."""
    return f"{value:.1f}".replace("-", "\u2212")


def test_the_results_page_gives_the_stored_mpe_evaluations():
    # docs/results.md's simple_spread table is made of docs/seeds/mpe_spread's stored files.
    page = (ROOT / "docs" / "results.md").read_text()
    rows = page.split("## Your own env: mpe2's simple_spread", 1)[1].split("\n## ", 1)[0]
    seeds = ROOT / "docs" / "seeds" / "mpe_spread"
    over = json.loads((seeds / "group-eval.json").read_text())["return_mean_over_seeds"]
    low, high = over["mean_ci95"]
    assert over["seeds"] == 3
    assert f"| {_figure(over['mean'])} [{_figure(low)}, {_figure(high)}] |" in rows
    for seed in range(3):
        ev = json.loads((seeds / f"mpe_spread-seed{seed}" / "eval.json").read_text())
        low, high = ev["return_mean_ci"]
        assert f"{_figure(ev['return_mean'])} [{_figure(low)}, {_figure(high)}]" in rows
        assert _figure(ev["return_median"]) in rows
    rand = json.loads((seeds / "random.json").read_text())
    low, high = rand["return_mean_ci"]
    assert f"| random | {_figure(rand['return_mean'])} [{_figure(low)}, {_figure(high)}] |" in rows


def test_a_config_error_names_the_pettingzoo_key():
    raw = meet()
    raw["env"]["pettingzoo"]["kwargs"]["render_mode"] = "human"
    with pytest.raises(ConfigError, match=r"env\.pettingzoo\.kwargs: .*render_mode"):
        config_from_dict(raw, "x.yaml")


def test_a_time_limit_reaches_the_replay_buffer_as_a_time_out():
    from harness.training.adapters import make_vec_env

    config = config_from_dict(meet())
    venv = make_vec_env(config.env, copies=2, seed=0, backend="supersuit")
    venv.reset()
    for step in range(1, 11):
        _, _, dones, infos = venv.step(np.ones(venv.num_envs, dtype=np.int64))
        assert dones.all() == (step == 10)
    assert all(info["TimeLimit.truncated"] is True for info in infos)
    assert all("terminal_observation" in info and "episode" in info for info in infos)
    venv.close()


def test_the_docs_show_the_tested_env_and_config():
    page = (ROOT / "docs" / "your-own-env.md").read_text()
    assert (ROOT / "tests" / "envs" / "meet_masked.py").read_text() in page
    assert MASKED.read_text() in page


def test_the_docs_masked_example_trains_and_beats_nothing_masked(tmp_path, capsys):
    # The env raises on a masked action: training, evaluation and the random baseline play none.
    run = tmp_path / "run"
    assert main(["run", str(MASKED), "--into", str(run)]) == 0
    assert main(["eval", str(run), "--episodes", "4", "--against", "random"]) == 0
    assert "team return" in capsys.readouterr().out


def test_a_run_repeats_from_its_seed(tmp_path):
    for name in ("a", "b"):
        args = ["run", str(MEET), "--no-progress", "--into", str(tmp_path / name)]
        assert main([*args, "--set", "phases.initial.timesteps=300", "--set", "eval.every=0"]) == 0

    def returns(name: str) -> list[str]:
        with (tmp_path / name / "episodes.csv").open() as f:
            return [row["returns"] for row in csv.DictReader(f)]

    assert returns("a") == returns("b") and len(set(returns("a"))) > 1


def test_a_stopped_run_resumes_with_consecutive_episodes(tmp_path):
    import signal

    from tests.conftest import interrupted_past

    run = tmp_path / "run"
    args = ["run", str(MEET), "--no-progress", "--into", str(run), "--set", "checkpoint.every=200"]
    with interrupted_past(400):
        assert main(args) == 128 + signal.SIGINT
    assert main(["run", "--resume", str(run), "--no-progress"]) == 0
    with (run / "episodes.csv").open() as f:
        numbers = [int(row["episode"]) for row in csv.DictReader(f)]
    # 600 transitions are 30 episodes of 10 steps of 2 agents; those the stop cut are not resumed
    assert numbers == list(range(len(numbers))) and 26 <= len(numbers) <= 30
    with (run / "evaluations.csv").open() as f:
        assert [row["timesteps"] for row in csv.DictReader(f)] == ["400"]
