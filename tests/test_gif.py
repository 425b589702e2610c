"""``harness render --gif``: the header band, the frame spacing rule, the title and the refusal of
a GIF too large for memory."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from envs.coverage import render
from harness.cli import main
from harness.config.loading import load_config
from harness.config.schema import EnvConfig
from harness.evaluation.baselines import make_baseline
from harness.evaluation.episodes import CHECKPOINT_FRACTIONS
from harness.results import plots

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"


def tiny_env(n_agents: int = 2, max_steps: int = 30, size: int = 8) -> EnvConfig:
    return EnvConfig(height=size, width=size, n_agents=n_agents, max_steps=max_steps)


# ---------------------------------------------------------------------- the rules
@pytest.mark.parametrize(
    ("steps", "every"), [(1, 1), (50, 1), (200, 1), (201, 2), (1000, 5), (20_000, 100)]
)
def test_gif_every_keeps_at_most_twenty_seconds(steps: int, every: int) -> None:
    assert plots.gif_every(steps) == every


def test_gif_every_lasts_ten_to_twenty_seconds_from_100_steps() -> None:
    for steps in [*range(100, 2001), 5_000, 20_000, 123_457]:
        frames = len(plots.frame_steps(steps, plots.gif_every(steps)))
        assert 10 <= frames / plots.GIF_FPS <= 20.1, steps


@pytest.mark.parametrize(("steps", "every"), [(10, 3), (12, 3), (7, 1), (7, 10)])
def test_frame_steps_are_the_frames_play_episode_keeps(steps: int, every: int) -> None:
    rec = plots.play_episode(tiny_env(2, steps, 6), make_baseline("random", 0), 1, every)
    kept = plots.frame_steps(steps, every)
    assert len(rec.frames) == len(kept) == 1 + math.ceil(steps / every)
    assert kept[0] == 0 and kept[-1] == steps


def test_gif_title_names_policy_seed_and_final_coverage() -> None:
    assert plots.gif_title("frontier", 3, 0.87654) == "frontier, seed 3: final coverage 87.7%"
    title = plots.gif_title("runs/a/model.zip", 1000003, 1.0, "Boltzmann, temperature 0.5")
    assert title == (
        "runs/a/model.zip, seed 1000003: final coverage 100.0% (Boltzmann, temperature 0.5)"
    )
    assert plots.gif_status(40, 1000, 0.25) == "step 40 / 1000    coverage 25.0%"


def test_coverage_by_step_follows_the_episode() -> None:
    env = tiny_env(3, 40, size=9)
    rec = plots.play_episode(env, make_baseline("frontier", 0), seed=4, frames=False)
    coverage = plots.coverage_by_step(rec)
    assert coverage.shape == (41,)
    assert np.all(np.diff(coverage) >= 0)
    assert coverage[-1] == pytest.approx(rec.coverage)
    marks = [max(1, round(f * env.max_steps)) for f in CHECKPOINT_FRACTIONS]
    np.testing.assert_allclose(coverage[marks], rec.coverage_at)


# ---------------------------------------------------------------------- the frames
@pytest.mark.parametrize(("size", "n_agents"), [(6, 2), (60, 4)])
def test_gif_frames_add_a_header_band_and_leave_the_map_to_the_markers(
    size: int, n_agents: int
) -> None:
    rec = plots.play_episode(tiny_env(n_agents, 12, size), make_baseline("random", 0), 2, 4)
    title = plots.gif_title("random", 2, rec.coverage)
    frames = plots.gif_frames(rec, 4, title)
    assert len(frames) == len(rec.frames) == 4
    raw = rec.frames[0].shape[:2]
    layout = plots.gif_layout(raw, n_agents, 12, title)
    k = layout.scale
    assert k == max(1, plots.GIF_MIN_MAP_PIXELS // max(raw))
    assert layout.band > 40 and layout.height == layout.band + raw[0] * k
    cell = render.CELL_PIXELS * k
    for step, frame, env_frame in zip(plots.frame_steps(12, 4), frames, rec.frames, strict=True):
        assert frame.shape == (layout.height, layout.width, 3) and frame.dtype == np.uint8
        header = frame[: layout.band]
        assert np.array_equal(header[: layout.status_y], frames[0][: layout.status_y])  # title
        assert step == 0 or not np.array_equal(header, frames[0][: layout.band])  # the status
        map_area = frame[layout.band :, layout.map_x : layout.map_x + raw[1] * k]
        enlarged = np.repeat(np.repeat(env_frame, k, axis=0), k, axis=1)
        changed = np.argwhere(np.any(map_area != enlarged, axis=2))
        centres = np.array([(p[step] + 0.5) * cell for p in rec.paths])
        distance = np.linalg.norm(changed[:, None, :] - centres[None], axis=2).min(axis=1)
        radius = max(0.75 * cell, 10.0)
        assert len(changed) > 0 and distance.max() <= radius + 2  # only the agents' discs
        # A disc spans more than one cell: big enough to see on a large map.
        r, c = rec.paths[0][step]
        row = map_area[int((r + 0.5) * cell)]
        colour = render.agent_colour(0)
        assert np.all(row == colour, axis=1).sum() > cell  # agent 0 is drawn on top


def test_gif_palette_holds_every_colour_of_the_map() -> None:
    palette = {tuple(c) for c in plots.gif_palette().tolist()}
    assert len(palette) <= 256
    for colour in (render.WALL_COLOUR, render.FREE_COLOUR, *render.VISITED_COLOURS):
        assert tuple(int(v) for v in colour) in palette
    for colour in render.AGENT_COLOURS:
        assert tuple(int(v) for v in colour) in palette


# ---------------------------------------------------------------------- end to end
def render_args(tmp_path: Path, *more: str) -> list[str]:
    return [
        "render",
        "--policy",
        "random",
        "--config",
        str(SMOKE),
        "--out",
        str(tmp_path / "paths.png"),
        "--gif",
        str(tmp_path / "episode.gif"),
        *more,
    ]


@pytest.mark.parametrize(
    ("more", "frames"),
    [
        (["--set", "env.max_steps=450"], 1 + math.ceil(450 / 3)),  # gif_every(450) == 3
        ([], 51),  # 50 steps: every step
        (["--set", "env.max_steps=450", "--every", "7"], 1 + math.ceil(450 / 7)),
    ],
)
def test_render_gif_frames_follow_the_rule(tmp_path: Path, more: list[str], frames: int) -> None:
    assert main(render_args(tmp_path, *more)) == 0
    config = load_config(SMOKE, [])
    title = plots.gif_title("random", config.eval.seed, 1.0)
    pixels = (10 * render.CELL_PIXELS, 10 * render.CELL_PIXELS)
    steps = 450 if more else 50
    layout = plots.gif_layout(pixels, 2, steps, title)
    with Image.open(tmp_path / "episode.gif") as im:
        assert im.n_frames == frames  # a new step counter on each: none merged
        assert im.size == (layout.width, layout.height)
        assert im.size[1] > pixels[0] * layout.scale  # the header band above the map
        assert im.info["duration"] == 1000 // plots.GIF_FPS and im.info["loop"] == 0
        im.seek(im.n_frames - 1)
        assert im.info["duration"] == 1000 // plots.GIF_FPS + 1000 * plots.GIF_HOLD


@pytest.mark.parametrize(
    ("frames_fitting", "advice"), [(20, "use --every 3 or more"), (0, "a smaller map or no --gif")]
)
def test_render_refuses_a_gif_too_large_for_memory_in_one_line(
    tmp_path: Path, monkeypatch, capsys, frames_fitting: int, advice: str
) -> None:
    config = load_config(SMOKE, [])
    title = plots.gif_title("random", config.eval.seed, 1.0)
    _, per_frame = plots.gif_bytes((10, 10), 2, 50, 1, title)
    monkeypatch.setattr(plots, "MAX_GIF_BYTES", per_frame * frames_fitting)

    def no_episode(*args, **kwargs):
        raise AssertionError("the episode was played")

    monkeypatch.setattr(plots, "play_episode", no_episode)
    capsys.readouterr()
    assert main(render_args(tmp_path, "--every", "1")) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("harness: error: --gif ")
    assert "51 frames of a 10-row, 10-column map (one every 1 of 50 steps)" in err
    assert err.rstrip().endswith(advice)
    assert not (tmp_path / "episode.gif").exists() and not (tmp_path / "paths.png").exists()


def test_render_fits_the_advised_every(tmp_path: Path, monkeypatch) -> None:
    config = load_config(SMOKE, [])
    title = plots.gif_title("random", config.eval.seed, 1.0)
    _, per_frame = plots.gif_bytes((10, 10), 2, 50, 1, title)
    monkeypatch.setattr(plots, "MAX_GIF_BYTES", per_frame * 20)
    assert main(render_args(tmp_path, "--every", "3")) == 0
    with Image.open(tmp_path / "episode.gif") as im:
        assert im.n_frames == 18 <= 20
