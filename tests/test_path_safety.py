"""Files nobody named are never loaded: a group's runs live inside its folder, and a model zip
that would unpack to more than a model may take is refused before anything is unpacked."""

from __future__ import annotations

import json
import struct
import zipfile
from pathlib import Path

import pytest

import harness.commands
from harness.cli import main
from harness.commands import MAX_MODEL_UNPACKED
from harness.results.groups import GroupError, group_members
from tests.test_seeds_and_sweeps import TINY, _fake_group, _fake_run


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("harness: error:") and "\n" not in err, err
    return err


# ---------------------------------------------------------------------- group members
@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """A run folder beside the group, not in it: what a hostile group.json would point at."""
    return _fake_run(tmp_path / "elsewhere", 0.5, {100: 0.5})


def _point_group_at(group: Path, run: str) -> None:
    (group / "group.json").write_text(json.dumps({"runs": [{"seed": 0, "run": run}]}))


@pytest.mark.parametrize("command", ["eval", "tune"])
@pytest.mark.parametrize("how", ["absolute", "dotdot", "link"])
def test_a_group_naming_a_run_outside_its_folder_is_refused(
    tmp_path, outside, capsys, command, how
):
    group = _fake_group(tmp_path / "group", [0.4], [{100: 0.4}])
    if how == "absolute":
        _point_group_at(group, str(outside))
    elif how == "dotdot":
        _point_group_at(group, "../elsewhere")
    else:  # a link inside the group that leads out of it
        (group / "sneaky").symlink_to(outside, target_is_directory=True)
        _point_group_at(group, "sneaky")
    before = sorted(p.name for p in outside.iterdir())
    assert main([command, str(group)]) == 2
    err = one_line_error(capsys)
    assert str(group / "group.json") in err and "outside the group folder" in err
    assert sorted(p.name for p in outside.iterdir()) == before  # nothing written there


@pytest.mark.parametrize("command", ["eval", "tune"])
@pytest.mark.parametrize("file", ["model.zip", "best_model.zip", "config.yaml"])
def test_a_member_file_linked_out_of_the_group_is_refused(tmp_path, outside, capsys, command, file):
    group = _fake_group(tmp_path / "group", [0.4], [{100: 0.4}])
    (member,) = group_members(group)
    target = outside / file  # what a hostile group would have unpickled
    if file == "config.yaml":
        target.write_text((member / file).read_text())
    else:
        target.write_bytes(b"PK not a model")
    (member / file).unlink(missing_ok=True)
    (member / file).symlink_to(target)
    assert main([command, str(group)]) == 2
    err = one_line_error(capsys)
    assert str(member / file) in err and "leads outside the group folder" in err


@pytest.mark.parametrize("name", ["", ".", 3, None, "a/../../b"])
def test_group_entries_that_are_not_run_folders_inside_it_are_one_line_errors(tmp_path, name):
    group = _fake_group(tmp_path / "group", [0.4], [{100: 0.4}])
    _point_group_at(group, name)
    with pytest.raises(GroupError, match=r"group\.json: run ") as raised:
        group_members(group)
    assert "\n" not in str(raised.value)


def test_runs_in_subfolders_of_the_group_are_members(tmp_path):
    group = _fake_group(tmp_path / "group", [0.4], [{100: 0.4}])
    _point_group_at(group, "./sub/run-seed0")
    assert group_members(group) == [group / "sub" / "run-seed0"]


# ---------------------------------------------------------------------- model zip sizes
@pytest.fixture
def unpacked(monkeypatch) -> list[str]:
    """The zip members anything opens (to be read or unpacked) during the test."""
    opened: list[str] = []
    real_open = zipfile.ZipFile.open

    def spy(self, name, mode="r", *args, **kwargs):
        if mode == "r":  # not the writes that make the test's zips
            opened.append(getattr(name, "filename", name))
        return real_open(self, name, mode, *args, **kwargs)

    monkeypatch.setattr(zipfile.ZipFile, "open", spy)
    return opened


def _run_with_model(folder: Path, write_zip) -> Path:
    folder.mkdir()
    (folder / "config.yaml").write_text(TINY)
    with zipfile.ZipFile(folder / "model.zip", "w", zipfile.ZIP_DEFLATED) as archive:
        write_zip(archive)
    return folder


@pytest.mark.parametrize("command", ["eval", "tune", "export"])
def test_a_model_zip_that_unpacks_too_large_is_refused_unread(
    tmp_path, capsys, monkeypatch, unpacked, command
):
    # 4 MB of zeros deflate to a few KB; the limit is lowered to 1 MB instead of writing GBs.
    run = _run_with_model(tmp_path / "run", lambda z: z.writestr("policy.pth", bytes(4 << 20)))
    assert (run / "model.zip").stat().st_size < 64 << 10
    monkeypatch.setattr(harness.commands, "MAX_MODEL_UNPACKED", 1 << 20)
    extra = ["--out", str(tmp_path / "ref")] if command == "export" else []
    assert main([command, str(run), *extra]) == 2
    err = one_line_error(capsys)
    assert str(run / "model.zip") in err and "4,194,304 bytes" in err and "1,048,576" in err
    assert unpacked == [] and not (tmp_path / "ref").exists()


def test_a_zip_declaring_gigabytes_is_refused_at_the_real_limit(tmp_path, capsys, unpacked):
    def lying(archive: zipfile.ZipFile) -> None:
        archive.writestr("data", "{}")
        archive.writestr("policy.pth", bytes(16))

    run = _run_with_model(tmp_path / "run", lying)
    # The central directory's entry of policy.pth now declares 3.75 GiB (offset 24: its size).
    raw = bytearray((run / "model.zip").read_bytes())
    entry = raw.rindex(b"PK\x01\x02")
    declared = 0xF000_0000
    raw[entry + 24 : entry + 28] = struct.pack("<I", declared)
    (run / "model.zip").write_bytes(bytes(raw))
    assert declared > MAX_MODEL_UNPACKED
    assert main(["eval", str(run)]) == 2
    err = one_line_error(capsys)
    assert f"{declared + 2:,} bytes" in err and "'policy.pth'" in err and unpacked == []


def test_a_damaged_zip_is_still_one_line(tmp_path, capsys):
    run = _run_with_model(tmp_path / "run", lambda z: z.writestr("data", "{}"))
    (run / "model.zip").write_bytes(b"not a zip")
    assert main(["eval", str(run)]) == 2
    assert "cannot load model (BadZipFile" in one_line_error(capsys)


# ---------------------------------------------------------------------- export --model
@pytest.mark.parametrize("how", ["dotdot", "absolute", "link"])
def test_export_loads_only_a_model_of_the_run(tmp_path, outside, capsys, how):
    run = _fake_run(tmp_path / "run", 0.4, {100: 0.4})
    elsewhere = outside / "model.zip"
    elsewhere.write_bytes(b"PK not a model")  # what a hostile name would have unpickled
    if how == "dotdot":  # from run/ up to tmp_path, then down to the other model
        name = str(Path("..") / elsewhere.relative_to(tmp_path).with_suffix(""))
    elif how == "absolute":
        name = str(elsewhere.with_suffix(""))
    else:
        (run / "sneaky.zip").symlink_to(elsewhere)
        name = "sneaky"
    out = tmp_path / "ref"
    assert main(["export", str(run), "--out", str(out), "--model", name]) == 2
    err = one_line_error(capsys)
    assert ("not a model of" in err) if how != "link" else ("leads outside the run folder" in err)
    assert not out.exists()
