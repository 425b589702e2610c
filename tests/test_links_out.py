"""Nothing is loaded from or written through a link out of a harness folder, and every file is
written whole or not at all.

One rule (``harness.results.rundir.inside``): every file a command reads from or writes into a
run, checkpoint, seed group, sweep or the folder of ``compare --out`` lies inside it, links
resolved; a link whose target is inside is fine, one leading out is refused in one line (exit
code 2) that names the file and where it leads, before anything is loaded or written. Only what
the user names on the command line is taken from elsewhere. YAML aliases are bounded, and
pictures, GIFs and JSON go through a temporary file renamed into place. (Other instances than
the probe's of issue 74: ``best_model.zip``, ``evaluations.csv``, ``tb/progress.csv``,
``.lock``, a derived ``eval-*.json`` and ``-curves-ci.png``, a checkpoint's ``state.json``, a
seed's log, a sweep's ``best.yaml`` or trial folder.)
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import time
from pathlib import Path

import pytest

from harness.cli import main
from harness.results.groups import GROUP_CONFIG, plan_resume
from harness.results.plots import write_gif
from harness.results.rundir import LinkOutError, RunDir, atomic_write, atomic_write_text
from harness.training.checkpoints import complete_checkpoints
from harness.training.state import run_state
from harness.training.sweep import BEST_CONFIG, BEST_RESULT, TRIALS_TABLE, sweep_file
from tests.conftest import one_error_line
from tests.stopping import harness_lines, resume, snapshot
from tests.test_seeds_and_sweeps import TINY, _fake_run

#: What a hostile file would hold: its bytes must never change.
MINE = b"not yours to change\n"


def _bait(folder: Path) -> tuple[Path, Path]:
    """A config whose env constructor is ``os:system``, which would create ``marker``: loading
    the config runs the command (a config that names an import path is code)."""
    folder.mkdir(parents=True, exist_ok=True)
    marker = folder / "ran"
    config = folder / "bait.yaml"
    config.write_text(
        "name: bait\n"
        f'env: {{pettingzoo: {{make: "os:system", kwargs: {{command: "touch {marker}"}}}}}}\n'
    )
    return config, marker


def _link_out(path: Path, outside: Path, content: bytes = MINE) -> Path:
    """Replace ``path`` by a link to ``outside`` (made with ``content``); return ``outside``."""
    outside.parent.mkdir(parents=True, exist_ok=True)
    outside.write_bytes(content)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.symlink_to(outside)
    return outside


def _refusal(capsys, path: Path, outside: Path, what: str = "the run folder") -> str:
    """The one error line, checked to name ``path``, that it leads out and where to."""
    line = one_error_line(capsys.readouterr().err)
    assert f"{path} leads outside {what}" in line, line
    assert f"(to {outside.resolve()})" in line, line
    return line


# ---------------------------------------------------------------------- the rule itself
def test_a_link_inside_the_folder_is_fine_and_one_out_is_refused_also_before_it_exists(tmp_path):
    run = RunDir(tmp_path / "run")
    (run.path / "tb").mkdir(parents=True)
    (run.path / "notes.json").write_text("{}")
    (run.path / "eval-x.json").symlink_to(run.path / "notes.json")  # inside: fine
    assert run.eval_file("eval-x") == run.path / "eval-x.json"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (run.path / "eval-y.json").symlink_to(elsewhere / "y.json")  # dangling: would create it
    with pytest.raises(LinkOutError, match=r"eval-y\.json leads outside the run folder"):
        run.eval_file("eval-y")
    shutil.rmtree(run.path / "tb")
    (run.path / "tb").symlink_to(elsewhere, target_is_directory=True)
    # A file not written yet, in a folder that leads out: where SB3 would write its CSV.
    with pytest.raises(LinkOutError, match=r"progress-resume3\.csv leads outside"):
        run.inside(run.path / "tb" / "progress-resume3.csv")
    with pytest.raises(LinkOutError, match=r"tb leads outside"):
        run.progress_csv(3)
    assert not list(elsewhere.iterdir())


# ---------------------------------------------------------------------- resume
@pytest.mark.parametrize("name", ["best_model.zip", "evaluations.csv", "tb/progress.csv", ".lock"])
def test_a_resume_refuses_a_run_file_linked_out_before_changing_anything(
    run_copy, tmp_path, capsys, name
):
    # Training would write each (the best model, a log row, SB3's CSV, the lock's pid) through
    # the link into the file it names.
    outside = _link_out(run_copy / name, tmp_path / "elsewhere" / Path(name).name)
    before = snapshot(run_copy)
    assert resume(run_copy) == 2
    _refusal(capsys, run_copy / name, outside)
    assert outside.read_bytes() == MINE
    assert snapshot(run_copy) == before


def test_a_resume_passes_over_a_checkpoint_whose_state_json_links_out(run_copy, tmp_path, capsys):
    older, newest = complete_checkpoints(run_copy / "checkpoints")
    bad = newest / "state.json"
    content = bad.read_bytes()
    outside = _link_out(bad, tmp_path / "elsewhere" / "state.json", content)
    assert resume(run_copy) == 0
    (line,) = [x for x in harness_lines(capsys.readouterr().err) if "resuming from the older" in x]
    assert f"{bad} leads outside the run folder" in line and line.endswith(older.name)
    assert outside.read_bytes() == content


# ---------------------------------------------------------------------- eval, tune, render
def test_a_checkpoint_named_on_the_command_line_is_read_only_inside_its_run(
    run_copy, tmp_path, capsys
):
    newest = complete_checkpoints(run_copy / "checkpoints")[-1]
    outside = _link_out(newest / "state.json", tmp_path / "elsewhere" / "state.json")
    assert main(["eval", str(newest), "--episodes", "2"]) == 2
    _refusal(capsys, newest / "state.json", outside)
    assert outside.read_bytes() == MINE


def test_a_derived_result_linked_out_is_refused_before_the_episodes(run_copy, tmp_path, capsys):
    # model.zip a link to a checkpoint's model: inside the run, so it is used.
    newest = complete_checkpoints(run_copy / "checkpoints")[-1]
    (run_copy / "model.zip").symlink_to(newest / "model.zip")
    outside = _link_out(run_copy / "eval-2ep.json", tmp_path / "elsewhere" / "eval.json")
    assert main(["eval", str(run_copy), "--episodes", "2"]) == 2
    _refusal(capsys, run_copy / "eval-2ep.json", outside)
    assert outside.read_bytes() == MINE
    (run_copy / "eval-2ep.json").unlink()
    assert main(["eval", str(run_copy), "--episodes", "2"]) == 0
    assert json.loads((run_copy / "eval-2ep.json").read_text())["episodes"] == 2


@pytest.mark.parametrize("command", ["tune", "render", "compare", "export"])
def test_a_run_config_linked_to_code_elsewhere_never_runs(tmp_path, capsys, command):
    bait, marker = _bait(tmp_path / "elsewhere")
    run = _fake_run(tmp_path / "run", 0.5, {100: 0.5})
    (run / "model.zip").write_bytes(b"PK never loaded")
    (run / "config.yaml").unlink()
    (run / "config.yaml").symlink_to(bait)
    args = {"compare": ["compare", str(run), "--out", str(tmp_path / "cmp.png")],
            "export": ["export", str(run), "--out", str(tmp_path / "ref")]}  # fmt: skip
    assert main(args.get(command, [command, str(run)])) == 2
    _refusal(capsys, run / "config.yaml", bait)
    assert not marker.exists()
    assert not (tmp_path / "ref").exists() and not (tmp_path / "cmp.png").exists()
    # The bait is live: named on the command line (the user's own choice), it runs.
    main(["eval", "--policy", "random", "--config", str(bait)])
    assert marker.exists()


def test_export_copies_no_file_linked_out_of_the_run(tmp_path, capsys):
    run = _fake_run(tmp_path / "run", 0.5, {100: 0.5})
    (run / "model.zip").write_bytes(b"PK never loaded")
    secret = _link_out(run / "evaluations.csv", tmp_path / "home" / "secret.txt")
    assert main(["export", str(run), "--out", str(tmp_path / "ref")]) == 2
    _refusal(capsys, run / "evaluations.csv", secret)
    assert not (tmp_path / "ref").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".ref")] == []


# ---------------------------------------------------------------------- compare's pictures
def test_compare_writes_no_derived_picture_through_a_link(tmp_path, capsys):
    runs = [_fake_run(tmp_path / f"run{k}", 0.4 + k / 10, {100: 0.4, 200: 0.5}) for k in (0, 1)]
    out = tmp_path / "pictures" / "cmp.png"
    out.parent.mkdir()
    outside = _link_out(out.with_name("cmp-curves-ci.png"), tmp_path / "elsewhere" / "keep.png")
    assert main(["compare", *map(str, runs), "--out", str(out)]) == 2
    _refusal(capsys, out.with_name("cmp-curves-ci.png"), outside, "the folder of --out")
    assert outside.read_bytes() == MINE and not out.exists()
    # A link inside the folder is fine: the picture replaces the link, not the file it named.
    out.with_name("cmp-curves-ci.png").unlink()
    inner = out.with_name("old.png")
    inner.write_bytes(MINE)
    out.with_name("cmp-intervals.png").symlink_to(inner)
    assert main(["compare", *map(str, runs), "--out", str(out)]) == 0
    assert inner.read_bytes() == MINE
    intervals = out.with_name("cmp-intervals.png")
    assert not intervals.is_symlink() and intervals.read_bytes().startswith(b"\x89PNG")


# ---------------------------------------------------------------------- seed groups
def _group(folder: Path, bait: Path, marker: Path) -> Path:
    """A group of one seed never started, whose group.json names ``bait`` and an override that
    would run its command again."""
    folder.mkdir(parents=True)
    data = {"name": "tiny", "config": str(bait), "seeds": [0], "jobs": 1,
            "overrides": [f"env.pettingzoo.kwargs.command=touch {marker}"],
            "runs": [{"seed": 0, "run": "tiny-seed0"}]}  # fmt: skip
    (folder / "group.json").write_text(json.dumps(data))
    return folder


def test_a_resumed_group_never_loads_the_config_its_group_json_names(tmp_path, capsys):
    bait, marker = _bait(tmp_path / "elsewhere")
    group = _group(tmp_path / "g", bait, marker)
    assert main(["run", "--resume", str(group), "--no-progress"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "seed 0 was never started and the group holds no config" in line
    assert not marker.exists() and not (group / "tiny-seed0").exists()
    # With its own copy, the seed starts from that, with only its seed and threads set.
    (group / GROUP_CONFIG).write_text(TINY)
    plan, _ = plan_resume(group, 1, run_state)
    (start,) = [job.cmd for job in plan]
    assert start is not None and str(group / GROUP_CONFIG) in start and str(bait) not in start
    assert [start[i + 1].split("=")[0] for i, a in enumerate(start) if a == "--set"] == [
        "seed",
        "algo.threads",
    ]


@pytest.mark.parametrize("linked", [GROUP_CONFIG, "tiny-seed0.log"])
def test_a_group_file_linked_out_stops_its_resume_before_any_seed_starts(tmp_path, capsys, linked):
    bait, marker = _bait(tmp_path / "elsewhere")
    group = _group(tmp_path / "g", bait, marker)
    (group / GROUP_CONFIG).write_text(TINY)
    content = bait.read_bytes() if linked == GROUP_CONFIG else MINE
    outside = _link_out(group / linked, tmp_path / "elsewhere" / "linked", content)
    assert main(["run", "--resume", str(group), "--no-progress"]) == 2
    _refusal(capsys, group / linked, outside, "the group folder")
    assert outside.read_bytes() == content and not marker.exists()
    assert not (group / "tiny-seed0").exists()


# ---------------------------------------------------------------------- sweep folders
@pytest.mark.parametrize(
    "linked",
    [TRIALS_TABLE, BEST_CONFIG, BEST_RESULT, "journal.log", "worker-1.log", ".lock", "trial-0000"],
)
def test_a_sweep_file_linked_out_stops_the_sweep_before_anything_is_written(
    tmp_path, capsys, linked
):
    config = tmp_path / "tiny.yaml"
    config.write_text(TINY)
    space = tmp_path / "space.yaml"
    space.write_text("algo.gamma: {grid: [0.9, 0.95]}\n")
    folder = tmp_path / "sweeps" / "tiny"
    if linked.startswith("trial-"):  # a trial's run folder: an empty folder elsewhere
        outside = tmp_path / "elsewhere" / "trial"
        outside.mkdir(parents=True)
        folder.mkdir(parents=True)
        (folder / linked).symlink_to(outside)
    else:
        outside = _link_out(folder / linked, tmp_path / "elsewhere" / "linked")
    args = ["sweep", str(config), "--space", str(space), "--trials", "2",
            "--sweeps-dir", str(tmp_path / "sweeps"), "--jobs", "2", "--quiet"]  # fmt: skip
    assert main(args) == 2
    _refusal(capsys, folder / linked, outside, "the sweep folder")
    if outside.is_dir():
        assert list(outside.iterdir()) == []
    else:
        assert outside.read_bytes() == MINE
    # Nothing was started or written: the folder holds the link alone.
    assert [p.name for p in folder.iterdir()] == [linked]
    # A link whose target lies inside the sweep folder is fine.
    (folder / linked).unlink()
    (folder / "kept").write_bytes(MINE)
    (folder / linked).symlink_to(folder / "kept")
    assert sweep_file(folder, linked) == folder / linked


# ---------------------------------------------------------------------- YAML aliases
#: Nine levels of nine aliases: 9^9 (387 million) values from 300 bytes.
BOMB = "".join(
    f"  - &l{k} [{', '.join([f'*l{k - 1}'] * 9)}]\n"
    if k
    else "  - &l0 [0, 0, 0, 0, 0, 0, 0, 0, 0]\n"
    for k in range(9)
)


def test_an_alias_bomb_in_a_config_is_one_line_at_once(tmp_path, capsys):
    bait, marker = _bait(tmp_path / "elsewhere")
    config = tmp_path / "bomb.yaml"
    config.write_text(bait.read_text() + "algo:\n  net_arch:\n" + BOMB)
    assert len(config.read_bytes()) < 1000
    runs = tmp_path / "runs"
    start = time.monotonic()
    assert main(["run", str(config), "--runs-dir", str(runs)]) == 2
    assert time.monotonic() - start < 10
    line = one_error_line(capsys.readouterr().err)
    assert f"{config}: YAML aliases expand it to more than 100,000 values" in line
    assert not marker.exists() and not runs.exists()


def test_an_alias_bomb_in_a_run_config_or_an_override_is_refused(tmp_path, capsys):
    run = _fake_run(tmp_path / "run", 0.5, {100: 0.5})
    (run / "model.zip").write_bytes(b"PK never loaded")
    (run / "config.yaml").write_text(TINY + "extra:\n" + BOMB)
    assert main(["eval", str(run)]) == 2
    assert "YAML aliases expand it" in one_error_line(capsys.readouterr().err)
    (tmp_path / "x.yaml").write_text(TINY)
    bomb = "{a: &a [0, 0, 0, 0, 0, 0, 0, 0, 0, 0]" + "".join(
        f", {b}: &{b} [{', '.join([f'*{a}'] * 60)}]" for a, b in ("ab", "bc", "cd")
    )
    assert main(["run", str(tmp_path / "x.yaml"), "--set", f"env.rewards={bomb}}}"]) == 2
    assert "YAML aliases expand it" in one_error_line(capsys.readouterr().err)
    (run / "config.yaml").write_text("name: &n [*n]\n")  # an alias inside itself: no end
    assert main(["eval", str(run)]) == 2
    assert "an alias names a node it lies inside" in one_error_line(capsys.readouterr().err)


def test_a_few_aliases_and_merge_keys_still_load(tmp_path):
    from harness.config.loading import load_config

    phases = (
        "phases:\n"
        "  - &first {name: one, timesteps: 120, exploration: {start: 1.0, end: 0.1, steps: 80}}\n"
        "  - {<<: *first, name: two}\n"
    )
    config = tmp_path / "c.yaml"
    config.write_text(
        "".join(x for x in TINY.splitlines(True) if not x.startswith("phases")) + phases
    )
    loaded = load_config(config)
    assert [(p.name, p.timesteps) for p in loaded.phases] == [("one", 120), ("two", 120)]


# ---------------------------------------------------------------------- whole files
def _no_temporary_files(folder: Path) -> bool:
    return not [p for p in folder.iterdir() if p.name.endswith(".tmp")]


def test_a_full_disk_while_compare_draws_keeps_the_old_picture(tmp_path, capsys, monkeypatch):
    from matplotlib.figure import Figure

    runs = [_fake_run(tmp_path / f"run{k}", 0.4, {100: 0.4}) for k in (0, 1)]
    out = tmp_path / "pictures" / "cmp.png"
    out.parent.mkdir()
    out.write_bytes(b"\x89PNG the picture of yesterday")
    before = out.read_bytes()

    def full_disk(self, fname, *args, **kwargs):  # half a picture, then no room
        Path(fname).write_bytes(b"\x89PNG half")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(fname))

    monkeypatch.setattr(Figure, "savefig", full_disk)
    assert main(["compare", *map(str, runs), "--out", str(out)]) == 2
    assert "No space left on device" in one_error_line(capsys.readouterr().err)
    assert out.read_bytes() == before
    assert _no_temporary_files(out.parent)


def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(tmp_path, monkeypatch):
    import numpy as np
    from PIL import Image

    result = tmp_path / "eval.json"
    atomic_write_text(result, '{"coverage_mean": 0.5}\n')
    before = result.read_bytes()

    def torn(tmp: Path) -> None:
        tmp.write_text('{"coverage_me')
        raise OSError(errno.EDQUOT, os.strerror(errno.EDQUOT))

    with pytest.raises(OSError):
        atomic_write(result, torn)
    assert result.read_bytes() == before and _no_temporary_files(tmp_path)

    gif = tmp_path / "episode.gif"
    frames = [np.zeros((4, 4, 3), dtype=np.uint8), np.full((4, 4, 3), 255, dtype=np.uint8)]
    write_gif(frames, gif)
    before = gif.read_bytes()

    def interrupted(self, fp, *args, **kwargs):
        Path(fp).write_bytes(b"GIF89a")
        raise KeyboardInterrupt

    monkeypatch.setattr(Image.Image, "save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_gif(frames, gif)
    assert gif.read_bytes() == before and _no_temporary_files(tmp_path)
