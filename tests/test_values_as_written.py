"""A value is read as it is written: a number with a leading zero is refused (YAML 1.1 reads
``010`` as octal 8), a key twice inside one ``--set`` value is refused as in a file, a name YAML
reads as a number is its text and one it reads as a bool is refused, and a ``compare`` label
is one line of printable text."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from harness.cli import main
from harness.config.loading import load_config
from harness.config.schema import ConfigError
from tests.conftest import one_error_line
from tests.test_seeds_and_sweeps import TINY

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"


@pytest.mark.parametrize("value", ["07", "0012", "+017", "-05", "0_10"])
def test_a_set_number_with_a_leading_zero_is_refused(value):
    with pytest.raises(ConfigError, match=f"{re.escape(value)}: a number with a leading zero"):
        load_config(SMOKE, [f"eval.episodes={value}"])


def test_a_file_number_with_a_leading_zero_is_refused_where_it_is(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("name: lead\nenv: {height: 8, width: 8}\neval: {episodes: 005}\n")
    with pytest.raises(ConfigError, match=r"line 3, column 18: invalid YAML \(005: a number"):
        load_config(path)


@pytest.mark.parametrize("value", ["0", "10", "0.5", "0x10", "1_000"])
def test_numbers_without_a_leading_zero_read_as_before(value):
    assert load_config(SMOKE, [f"env.rewards.team={value}"] if "." in value else []) is not None


def test_a_key_twice_inside_one_set_value_is_refused():
    with pytest.raises(ConfigError, match=r"^--set 'eval=\{episodes: 3, every: 0, episodes: 5': "
                       "duplicate key 'episodes'$"):  # fmt: skip
        load_config(SMOKE, ["eval={episodes: 3, every: 0, episodes: 5}"])


@pytest.mark.parametrize(("written", "name"), [("2031", "2031"), ("'0042'", "0042")])
def test_a_name_yaml_reads_as_a_number_is_its_text(tmp_path, written, name):
    path = tmp_path / "c.yaml"
    path.write_text(f"name: {written}\n")
    config = load_config(path)
    assert config.name == name
    assert load_config(_written(tmp_path, config.to_yaml())).name == name  # and stays text


def _written(folder: Path, text: str) -> Path:
    path = folder / "again.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("written", ["false", "on", "No"])
def test_a_name_yaml_reads_as_a_bool_is_refused(tmp_path, written):
    path = tmp_path / "c.yaml"
    path.write_text(f"name: {written}\n")
    with pytest.raises(ConfigError, match="name: a name is text; YAML read this one as"):
        load_config(path)


@pytest.mark.parametrize("label", ["two\nlines", "tab\there", "bell\x07", "  "])
def test_a_compare_label_that_is_not_one_printable_line_is_refused(tmp_path, capsys, label):
    runs = []
    for k in range(2):
        run = tmp_path / f"r{k}"
        run.mkdir()
        (run / "config.yaml").write_text(TINY)
        runs.append(str(run))
    out = tmp_path / "cmp.png"
    assert main(["compare", *runs, "--labels", "fine", label, "--out", str(out)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.endswith("a label is one line of printable text")
    assert not out.exists()
