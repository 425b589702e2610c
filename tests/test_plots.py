"""Figures and GIFs: each writer produces a readable file, and the data helpers are right."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from envs import coverage_v0
from harness.config.schema import EnvConfig
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import EpisodeResult, run_episodes
from harness.results import plots, rundir
from harness.tasks.coverage import CoverageTask

EPISODE_COLUMNS = CoverageTask.episode_columns

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_png(path: Path, min_size: tuple[int, int] = (300, 200)) -> tuple[int, int]:
    """Assert ``path`` is a PNG that Pillow decodes; return its (width, height)."""
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    with Image.open(path) as im:
        im.load()  # decodes every byte, so a truncated file fails here
        assert im.format == "PNG"
        assert im.size[0] >= min_size[0] and im.size[1] >= min_size[1]
        return im.size


def tiny_env(n_agents: int = 2, max_steps: int = 30, size: int = 8) -> EnvConfig:
    return EnvConfig(height=size, width=size, n_agents=n_agents, max_steps=max_steps)


@pytest.fixture(scope="module")
def episodes() -> dict[int, EpisodeResult]:
    """A short frontier episode with 1 and with 4 agents (paths only)."""
    policy = make_baseline("frontier", 0)
    return {
        n: plots.play_episode(tiny_env(n, 40, size=10), policy, seed=3, frames=False)
        for n in (1, 4)
    }


# ---------------------------------------------------------------------- paths
@pytest.mark.parametrize("n_agents", [1, 4])
def test_plot_paths_writes_png(tmp_path: Path, episodes, n_agents: int) -> None:
    rec = episodes[n_agents]
    assert len(rec.paths) == n_agents and rec.paths[0].shape == (41, 2)
    out = plots.plot_paths(rec.walls, rec.paths, tmp_path / "sub" / "paths.png", title="t")
    assert out == tmp_path / "sub" / "paths.png"
    width, height = check_png(out)
    # Team panel plus one per agent, side by side: wider with more agents.
    assert width > (n_agents + 1) * 250


def test_plot_paths_without_snapshots_is_one_row(tmp_path: Path, episodes) -> None:
    rec = episodes[4]
    _, with_rows = check_png(plots.plot_paths(rec.walls, rec.paths, tmp_path / "a.png"))
    _, one_row = check_png(
        plots.plot_paths(rec.walls, rec.paths, tmp_path / "b.png", snapshots=False)
    )
    assert one_row < 0.7 * with_rows


def test_plot_paths_rejects_bad_paths(tmp_path: Path) -> None:
    walls = np.zeros((4, 4), dtype=bool)
    with pytest.raises(ValueError, match="at least one"):
        plots.plot_paths(walls, [], tmp_path / "x.png")
    with pytest.raises(ValueError, match="same length"):
        plots.plot_paths(walls, [np.zeros((3, 2)), np.zeros((4, 2))], tmp_path / "x.png")


def test_first_visits_follow_the_crediting_rule() -> None:
    # Both agents enter (0, 1) at step 1: the lower index is credited, as in the env.
    paths = [np.array([[0, 0], [0, 1], [0, 2]]), np.array([[1, 1], [0, 1], [1, 1]])]
    first_step, credited = plots.first_visits((2, 3), paths)
    np.testing.assert_array_equal(first_step, [[0, 1, 2], [-1, 0, -1]])
    np.testing.assert_array_equal(credited, [[0, 0, 0], [-1, 1, -1]])


def test_first_visits_match_the_env() -> None:
    env = coverage_v0.parallel_env(height=9, width=9, n_agents=3, max_steps=60)
    env.reset(seed=4)
    policy = make_baseline("random", 1)
    path = [env.positions]
    while env.agents:
        actions = policy(np.zeros((3, 13)), [env]).tolist()
        env.step(dict(zip(env.possible_agents, actions)))
        path.append(env.positions)
    _, credited = plots.first_visits(env.walls.shape, list(np.stack(path, axis=1)))
    np.testing.assert_array_equal(credited, env.credited_by)


# ---------------------------------------------------------------------- test episodes
def test_plot_eval_episodes_from_results_and_from_numbers(tmp_path: Path) -> None:
    results = run_episodes(make_baseline("random", 0), tiny_env(2, 20), episodes=6, seed=0)
    check_png(plots.plot_eval_episodes(results, None, tmp_path / "r.png", "Random"))
    coverages = [0.41, 0.62, 0.58, 0.7]
    check_png(plots.plot_eval_episodes(coverages, [0, 0, 3, 0], tmp_path / "n.png", "Numbers"))
    check_png(plots.plot_eval_episodes(np.array(coverages), None, tmp_path / "c.png", ""))
    with pytest.raises(ValueError, match="3 wall-hit counts for 4 episodes"):
        plots.plot_eval_episodes(coverages, [0, 0, 0], tmp_path / "bad.png", "")


# ---------------------------------------------------------------------- learning curves
def write_episodes_csv(path: Path, timesteps: np.ndarray, coverage: np.ndarray) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(EPISODE_COLUMNS)
        for k, (t, c) in enumerate(zip(timesteps, coverage)):
            writer.writerow([k, "initial", int(t), k % 4, f"{c:.6f}", -0.5, 0, 12, 150])


def test_read_episodes_csv_round_trip(tmp_path: Path) -> None:
    ts = np.array([600, 600, 1200, 1800, 2400])
    cov = np.array([0.1, 0.25, 0.3, 0.5, 0.45])
    path = tmp_path / "episodes.csv"
    write_episodes_csv(path, ts, cov)
    got_ts, got_cov = rundir.read_episodes_csv(path)
    assert got_ts.dtype == np.int64 and got_cov.dtype == np.float64
    np.testing.assert_array_equal(got_ts, ts)
    np.testing.assert_allclose(got_cov, cov)
    # Rows out of order (copies finishing in one step) come back sorted by timesteps.
    write_episodes_csv(path, ts[::-1], cov[::-1])
    np.testing.assert_array_equal(rundir.read_episodes_csv(path)[0], ts)
    # A header-only file is an empty run.
    write_episodes_csv(path, np.array([]), np.array([]))
    assert all(len(a) == 0 for a in rundir.read_episodes_csv(path))


def test_read_episodes_csv_errors_name_the_problem(tmp_path: Path) -> None:
    path = tmp_path / "episodes.csv"
    path.write_text("episode,timesteps\n0,10\n")
    with pytest.raises(ValueError, match="missing column"):
        rundir.read_episodes_csv(path)
    path.write_text("episode,timesteps,coverage\n0,10,0.5\n1,20,oops\n")
    with pytest.raises(ValueError, match="line 3"):
        rundir.read_episodes_csv(path)


def test_smooth_is_a_trailing_median() -> None:
    x = [1.0, 5.0, 2.0, 8.0, 3.0]
    np.testing.assert_allclose(plots.smooth(x, 1), x)
    np.testing.assert_allclose(plots.smooth(x, 3), [1.0, 3.0, 2.0, 5.0, 3.0])
    np.testing.assert_allclose(plots.smooth(x, 50), [1.0, 3.0, 2.0, 3.5, 3.0])
    assert plots.smooth([], 5).shape == (0,)
    with pytest.raises(ValueError):
        plots.smooth(x, 0)


def fake_run(rng: np.random.Generator, n: int, end: int) -> tuple[np.ndarray, np.ndarray]:
    ts = np.sort(rng.integers(0, end, n))
    return ts, np.clip(0.7 * ts / end + rng.normal(0, 0.05, n), 0, 1)


@pytest.mark.parametrize("band", ["minmax", "iqr"])
def test_plot_learning_curves_one_and_several_runs(tmp_path: Path, band: str) -> None:
    rng = np.random.default_rng(0)
    seeds = [fake_run(rng, 200, 100_000), fake_run(rng, 150, 80_000), fake_run(rng, 120, 100_000)]
    curves = {
        "ddqn (3 seeds)": seeds,
        "dueling": [fake_run(rng, 90, 100_000)],
    }
    out = plots.plot_learning_curves(
        curves, tmp_path / "curves.png", "Compare", band=band, references={"frontier": 0.95}
    )
    check_png(out)


def test_plot_learning_curves_from_csv_files(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    for k in range(3):
        write_episodes_csv(tmp_path / f"run{k}.csv", *fake_run(rng, 40, 10_000))
    curves = {"exp": [rundir.read_episodes_csv(tmp_path / f"run{k}.csv") for k in range(3)]}
    check_png(plots.plot_learning_curves(curves, tmp_path / "c.png", window=5))
    with pytest.raises(ValueError, match="no run"):
        plots.plot_learning_curves({"empty": [(np.array([]), np.array([]))]}, tmp_path / "e.png")


def test_read_evaluations_csv_and_draw_the_evaluations_panel(tmp_path: Path) -> None:
    path = tmp_path / "evaluations.csv"
    path.write_text(
        "timesteps,episodes,temperature,coverage_median,coverage_q1,coverage_q3,"
        "coverage_mean,wall_hits_mean\n"
        "2000,4,1.0,0.5,0.4,0.6,0.5,0.0\n1000,4,1.0,0.25,0.2,0.3,0.25,0.5\n",
        encoding="utf-8",
    )
    ts, median = rundir.read_evaluations_csv(path)
    np.testing.assert_array_equal(ts, [1000, 2000])
    np.testing.assert_array_equal(median, [0.25, 0.5])
    rng = np.random.default_rng(2)
    curves = {"a": [fake_run(rng, 50, 2000)], "b": [fake_run(rng, 50, 2000)]}
    single = check_png(plots.plot_learning_curves(curves, tmp_path / "one.png", window=5))
    evals = {"a": [(ts, median), (ts[:1], median[:1])]}
    both = check_png(
        plots.plot_learning_curves(curves, tmp_path / "two.png", window=5, evaluations=evals)
    )
    assert both[0] > 1.5 * single[0]  # a second panel beside the first
    path.write_text("timesteps,coverage_median\n10,high\n", encoding="utf-8")
    with pytest.raises(ValueError, match="line 2"):
        rundir.read_evaluations_csv(path)


# ---------------------------------------------------------------------- episodes and GIFs
def test_episode_frames_and_gif(tmp_path: Path) -> None:
    env = tiny_env(2, 10, size=6)
    frames = plots.episode_frames(env, make_baseline("random", 0), seed=2, every=3)
    assert len(frames) == 5  # steps 0, 3, 6, 9 and the last (10)
    assert all(f.shape == (48, 48, 3) and f.dtype == np.uint8 for f in frames)
    out = plots.write_gif(frames, tmp_path / "gif" / "episode.gif", fps=5)
    assert out.read_bytes()[:6] == b"GIF89a"
    with Image.open(out) as im:
        assert im.n_frames > 1
        assert im.size == (48, 48)
        assert im.info["loop"] == 0 and im.info["duration"] == 200
    with pytest.raises(ValueError):
        plots.write_gif([], tmp_path / "empty.gif")


def test_play_episode_is_episode_zero_of_run_episodes() -> None:
    env = tiny_env(3, 25, size=9)
    policy = make_baseline("frontier", 0)
    rec = plots.play_episode(env, policy, seed=7, every=5)
    (result,) = run_episodes(policy, env, episodes=1, seed=7, record_paths=True)
    assert rec.coverage == result.coverage
    assert rec.wall_hits == result.wall_hits
    for a, b in zip(rec.paths, result.paths):
        np.testing.assert_array_equal(a, b)
    assert len(rec.frames) == 6


def test_a_group_has_one_colour_in_every_figure_of_a_comparison(
    tmp_path: Path, monkeypatch
) -> None:
    from rliable import plot_utils

    from harness.results import stats

    seen: dict[str, dict] = {}
    real_intervals = plot_utils.plot_interval_estimates
    real_curve = plot_utils.plot_sample_efficiency_curve

    def intervals(*args, **kwargs):
        seen["intervals"] = dict(kwargs["colors"])
        return real_intervals(*args, **kwargs)

    def curve(*args, **kwargs):
        seen.setdefault("curves", {}).update(kwargs["colors"])
        return real_curve(*args, **kwargs)

    monkeypatch.setattr(plot_utils, "plot_interval_estimates", intervals)
    monkeypatch.setattr(plot_utils, "plot_sample_efficiency_curve", curve)
    scores = {"b": [0.5, 0.6, 0.7], "a": [0.4, 0.5, 0.6]}
    steps = np.array([100, 200])
    curves = {name: [(steps, np.array(v[:2])) for _ in v] for name, v in scores.items()}
    colours = stats.group_colours(["b", "a"])
    stats.plot_intervals(stats.seed_statistics(scores, reps=200), tmp_path / "i.png", colours)
    stats.plot_curves_with_ci(curves, tmp_path / "c.png", reps=200, colours=colours)
    # Labels carry the seed count ("b (3 seeds)"); each group's colour is the same in both.
    for name in scores:
        (i_colour,) = [c for label, c in seen["intervals"].items() if label.startswith(name)]
        (c_colour,) = [c for label, c in seen["curves"].items() if label.startswith(name)]
        assert i_colour == c_colour == colours[name]
    assert colours["a"] != colours["b"]
