"""Config loading: defaults, YAML errors, unknown keys, overrides, the shipped configs; map files
keep their hash (alone or in a mix), and an override of ``env.map`` is applied before the map it
replaces is checked."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from harness.cli import main
from harness.config.loading import config_from_dict, load_config, parse_override
from harness.config.schema import AlgoConfig, ConfigError, EnvConfig, ExperimentConfig, VecConfig
from harness.factory import check_env, env_kwargs
from harness.training.checks import checked_config
from tests.conftest import one_error_line
from tests.test_seeds_and_sweeps import TINY

CONFIGS = sorted(Path(__file__).resolve().parents[1].joinpath("configs").glob("*.yaml"))


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "exp.yaml"
    path.write_text(text)
    return path


def test_minimal_file_gives_thesis_defaults(tmp_path):
    cfg = load_config(write(tmp_path, "name: defaults\n"))
    assert cfg.env.n_agents == 4 and cfg.env.max_steps == 1000
    assert cfg.algo.optimizer == "RMSprop" and cfg.algo.buffer_size == 100_000
    assert cfg.algo.target_update_interval == 10_000
    initial, optimizing = cfg.phases
    assert (initial.learning_rate, initial.batch_size, initial.train_freq) == (5e-5, 32, 2)
    assert initial.alpha == 0.55 and initial.epochs == [(0.0, 1), (0.4, 5), (0.6, 7)]
    assert optimizing.learning_rate == (5e-6, 1e-6)
    assert (optimizing.batch_size, optimizing.train_freq) == (64, 4)
    assert optimizing.exploration.end == 0.0 and optimizing.beta.start == 1.0
    assert optimizing.epochs == [(0.0, 1), (0.4, 3), (0.6, 5)]


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_shipped_configs_load(path):
    if "mpe2." in path.read_text():  # configs/mpe_spread.yaml: the optional .[mpe] extra
        pytest.importorskip("mpe2")
    cfg = load_config(path)
    assert cfg.name == path.stem or path.stem == "smoke"
    assert cfg.total_timesteps > 0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("env: {n_agentz: 2}", r"exp.yaml: env.n_agentz: Extra inputs are not permitted"),
        ("env: {max_steps: -1}", r"env.max_steps: Input should be greater than 0"),
        (
            "env: {wall_fraction: [0.2, 1.0]}",
            r"env.wall_fraction: wall_fraction must satisfy 0 <= low <= high < 1",
        ),
        ("env: {n_agents: many}", r"env.n_agents: Input should be a valid integer"),
        ("env: {map: nowhere.txt}", r"env.map: 'nowhere.txt' is not 'random'"),
        ("env: {height: 2, width: 2, n_agents: 5}", r"env: n_agents=5 is more than the 2x2 map"),
        ("algo: {policy: CnnPolicy}", r"algo.policy: unknown policy .CnnPolicy.; known: MlpPolicy"),
        ("phases: []", r"phases: needs at least one phase"),
        ("phases: [{name: a}]", r"phases.0.timesteps: Field required"),
        ("phases: [{name: a, timesteps: 5, epochs: [[0.5, 1], [0.1, 2]]}]", r"increasing"),
        ("name: ../escape", r"name: must be 1-64 characters"),
        ("eval: {seed: 5, validation_seed: 50}", r"eval: .*validation_seed must be at least"),
        ("- a\n- b\n", r"exp.yaml: the top level must be a mapping"),
        ("env: {n_agents: 2\n", r"exp.yaml: line \d+, column \d+: invalid YAML"),
    ],
)
def test_config_errors_are_one_line_and_name_file_and_key(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message) as info:
        load_config(write(tmp_path, text))
    assert "\n" not in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.yaml")


def test_env_problems_found_by_the_env_are_config_errors(tmp_path):
    bad_map = tmp_path / "m.txt"
    bad_map.write_text("..\n.x\n")
    # The schema checks keys without building an env; the factory builds it once and turns the
    # env's own complaint into a one-line config error.
    config = load_config(write(tmp_path, f"env: {{map: {bad_map}, n_agents: 1}}"))
    with pytest.raises(ConfigError, match=r"env: .*m.txt: line 2, column 2"):
        check_env(config.env)


def test_runtime_problems_are_config_errors_before_training(tmp_path):
    path = write(tmp_path, "algo: {optimizer: Adamm}")
    config = load_config(path)  # torch is not asked by the schema
    with pytest.raises(
        ConfigError, match=r"exp\.yaml: algo.optimizer: unknown torch optimizer 'Adamm'"
    ):
        checked_config(config, str(path))


def test_overrides_are_typed_and_reach_nested_keys(tmp_path):
    cfg = load_config(
        write(tmp_path, "env: {n_agents: 2}"),
        [
            "env.max_steps=500",
            "env.wall_fraction=[0.1, 0.2]",
            "phases.optimizing.timesteps=123",
            "phases.0.alpha=0.6",
            "algo.net_arch=[32, 32]",
            "name=renamed",
        ],
    )
    assert cfg.env.max_steps == 500 and cfg.env.n_agents == 2
    assert cfg.env.wall_fraction == (0.1, 0.2)
    assert cfg.phases[1].timesteps == 123 and cfg.phases[0].alpha == 0.6
    assert cfg.algo.net_arch == [32, 32] and cfg.name == "renamed"


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("env.max_steps=abc", r"--set env.max_steps=abc: env.max_steps: Input should be"),
        ("env.nope=1", r"env.nope: Extra inputs are not permitted"),
        ("phases.nophase.timesteps=3", r"no item 'nophase' at phases.nophase"),
        ("env.max_steps.x=3", r"env.max_steps is not a section"),
        ("novalue", r"expected key.path=value"),
        ("eval.rollout.samples=0", r"eval.rollout.samples: Input should be greater than 0"),
        ("eval.rollout.after=1.5", r"eval.rollout.after: Input should be less than or equal"),
    ],
)
def test_bad_overrides(tmp_path, override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, "name: x\n"), [override])


def test_parse_override_uses_yaml_types():
    assert parse_override("a.b=3") == (["a", "b"], 3)
    assert parse_override("a=1e-4") == (["a"], 1e-4)
    assert parse_override("a=true") == (["a"], True)
    assert parse_override("a=[1, 2]") == (["a"], [1, 2])
    assert parse_override("a=text") == (["a"], "text")


def test_resolved_yaml_round_trips():
    cfg = ExperimentConfig()
    again = ExperimentConfig.model_validate(yaml.safe_load(cfg.to_yaml()))
    assert again == cfg


def test_validating_a_config_changes_none_of_the_sections_given_to_it():
    # Validators only check; what one section derives from another (the coverage env's agent
    # indication from algo.sharing) is filled in once, into the config's own copy.
    env = EnvConfig(height=8, width=8, n_agents=2)
    vec, algo = VecConfig(copies=2), AlgoConfig(sharing="shared_id")
    before = [(s.model_dump(), dict(s.__pydantic_private__ or {})) for s in (env, vec, algo)]
    indexed = ExperimentConfig(env=env, vec=vec, algo=algo)
    assert indexed.env.agent_id and not env.agent_id
    assert [(s.model_dump(), dict(s.__pydantic_private__ or {})) for s in (env, vec, algo)] == (
        before
    )
    # Another config of the same env section says its own, and leaves the first one's alone.
    shared = ExperimentConfig(env=indexed.env, vec=vec)
    assert not shared.env.agent_id and indexed.env.agent_id
    assert ExperimentConfig(env=env, algo={"sharing": "per_agent"}).env.agent_id


def test_a_map_source_is_built_for_the_check_and_reused_by_the_factory(monkeypatch):
    from harness.config import maps as config_maps

    config_maps._built.cache_clear()
    built: list[tuple[int, int]] = []
    build = config_maps.MapSource.build

    def counted(self, height: int, width: int):
        built.append((height, width))
        return build(self, height, width)

    monkeypatch.setattr(config_maps.MapSource, "build", counted)
    config = config_from_dict(
        {"env": {"height": 24, "width": 30, "n_agents": 2, "map": {"cave": {"iterations": 3}}}}
    )
    assert built.count((24, 30)) == 1  # the check at the env's size (and one at the check size)
    checked = len(built)
    first, second = env_kwargs(config.env)["map"], env_kwargs(config.env)["map"]
    assert len(built) == checked and first is second  # the factory builds none of its own


def test_relative_map_path_is_stored_absolute_with_its_hash(tmp_path, monkeypatch):
    maps = tmp_path / "maps"
    maps.mkdir()
    (maps / "room.txt").write_text("....\n.##.\n....\n")
    monkeypatch.chdir(tmp_path)
    cfg = load_config(write(tmp_path, "env: {map: maps/room.txt, n_agents: 2}\n"))
    assert cfg.env.map == str((maps / "room.txt").resolve())
    assert cfg.env.map_sha256 is not None and len(cfg.env.map_sha256) == 64
    # The run's config.yaml reproduces the run from any directory...
    saved = tmp_path / "run.yaml"
    saved.write_text(cfg.to_yaml())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "maps").mkdir()
    (elsewhere / "maps" / "room.txt").write_text("....\n....\n....\n")  # a different map there
    monkeypatch.chdir(elsewhere)
    again = load_config(saved)
    assert again.env.map == cfg.env.map and again.env.map_sha256 == cfg.env.map_sha256
    # ...and refuses a map file that changed since.
    (maps / "room.txt").write_text("....\n....\n....\n")
    with pytest.raises(ConfigError, match=r"env: .*has changed since this config was written"):
        load_config(saved)


@pytest.mark.parametrize(
    ("raw", "guess"),
    [
        ({"env": {"max_step": 5}}, "env.max_steps"),
        ({"algo": {"polcy": "MlpPolicy"}}, "algo.policy"),
        (
            {"phases": [{"name": "a", "timesteps": 5, "learning_rat": 1e-4}]},
            "phases.0.learning_rate",
        ),
        ({"evall": {}}, "eval"),
    ],
)
def test_an_unknown_key_names_the_nearest_known_one(raw, guess):
    with pytest.raises(
        ConfigError, match=rf"Extra inputs are not permitted \(did you mean `{guess}`\?\)"
    ):
        config_from_dict(raw)


def test_an_unknown_key_far_from_every_known_one_gets_no_guess():
    with pytest.raises(ConfigError) as err:
        config_from_dict({"env": {"zzzzzz": 1}})
    assert "did you mean" not in str(err.value)


MERGED = """\
name: merged
algo: {learning_starts: 50}
phases:
  - &explore {name: explore, timesteps: 300, batch_size: 16, train_freq: 2}
  - &small {name: small, timesteps: 100, batch_size: 8, alpha: 0.25}
  - <<: *explore
    name: exploit
    batch_size: 32
  - <<: [*explore, *small]
    name: both
"""


def test_yaml_merge_keys_merge_and_the_keys_written_beside_them_win(tmp_path):
    explore, _, exploit, both = load_config(write(tmp_path, MERGED)).phases
    assert (exploit.name, exploit.timesteps, exploit.batch_size) == ("exploit", 300, 32)
    assert exploit.train_freq == explore.train_freq == 2
    # Of a list of merged mappings the earlier one wins (YAML's rule), the later one fills in.
    assert (both.name, both.timesteps, both.batch_size) == ("both", 300, 16)
    assert both.alpha == 0.25


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("    name: again\n", r"line 11, column 5: invalid YAML \(duplicate key 'name'\)"),
        ("    <<: *small\n", r"line 11, column 5: invalid YAML \(duplicate key '<<'\)"),
        (
            "  - {<<: {name: x, timesteps: 1, name: y}}\n",
            r"line 11, column 34: invalid YAML \(duplicate key 'name'\)",
        ),
    ],
    ids=["beside-a-merge-key", "two-merge-keys", "in-a-merged-mapping"],
)
def test_a_key_written_twice_is_refused_among_merge_keys(tmp_path, extra, message):
    with pytest.raises(ConfigError, match=message):
        load_config(write(tmp_path, MERGED + extra))


def test_one_key_given_twice_with_set_is_refused():
    with pytest.raises(ConfigError, match=r"--set env\.n_agents is given twice"):
        config_from_dict({}, overrides=["env.n_agents=2", "env.n_agents=3"])


def test_a_mapping_set_on_a_section_keeps_the_sections_other_keys(tmp_path):
    from harness.training.sweep import override

    path = write(
        tmp_path,
        "env: {height: 8, width: 8, n_agents: 2, max_steps: 20, map: {cave: {}},\n"
        "      rewards: {new_cell: 3.0}}\n"
        "phases: [{name: only, timesteps: 5000, batch_size: 16}]\n",
    )
    # --set and a sweep's space-file value (its --set text) take the one rule: merged.
    for text in ("env={n_agents: 3, rewards: {step: -2.0}}",
                 override("env", {"n_agents": 3, "rewards": {"step": -2.0}})):  # fmt: skip
        env = load_config(path, [text]).env
        assert (env.n_agents, env.max_steps, env.height, env.width) == (3, 20, 8, 8)
        assert "cave" in env.map  # not reset to the default `random`
        assert (env.rewards.step, env.rewards.new_cell) == (-2.0, 3.0)  # merged down a level
    phase = load_config(path, ["phases.only={learning_rate: 1.0e-4}"]).phases[0]
    assert (phase.name, phase.timesteps, phase.batch_size) == ("only", 5000, 16)
    # A free-form mapping is replaced whole: another map kind is one map, not two.
    assert load_config(path, ["env={map: {maze: {}}}"]).env.map.keys() == {"maze"}
    # A list is replaced whole.
    assert len(load_config(path, ["phases=[{name: a, timesteps: 4000}]"]).phases) == 1


def test_a_map_file_named_in_an_env_mapping_drops_the_old_files_hash(tmp_path, monkeypatch):
    (tmp_path / "a.txt").write_text("....\n.##.\n....\n")
    (tmp_path / "b.txt").write_text("....\n....\n....\n")
    monkeypatch.chdir(tmp_path)
    saved = tmp_path / "run.yaml"
    saved.write_text(load_config(write(tmp_path, "env: {map: a.txt, n_agents: 2}\n")).to_yaml())
    env = load_config(saved, ["env={map: b.txt}"]).env
    assert env.map == str(tmp_path / "b.txt") and env.n_agents == 2


def test_quoted_set_values_stay_text_and_bare_exponents_are_numbers():
    # `harness run --name 2024` passes name="2024": a name, not a number.
    for name in ("2024", "1e5", "nan"):
        assert config_from_dict({}, overrides=[f'name="{name}"']).name == name
    config = config_from_dict({}, overrides=["phases.0.learning_rate=1e-4"])
    assert config.phases[0].learning_rate == 1e-4


def test_learning_starts_at_or_past_the_runs_end_is_refused():
    phases = "phases: [{name: only, timesteps: 500}]"
    with pytest.raises(ConfigError, match=r"algo.learning_starts: 500 is not below the run's 500"):
        config_from_dict(yaml.safe_load(f"algo: {{learning_starts: 500}}\n{phases}"))
    assert config_from_dict(yaml.safe_load(f"algo: {{learning_starts: 499}}\n{phases}"))


def test_a_map_file_is_held_to_the_cell_limit_of_generated_maps(tmp_path, monkeypatch):
    import harness.config.schema as schema

    monkeypatch.setattr(schema, "MAX_MAP_CELLS", 20)
    small, large = tmp_path / "small.txt", tmp_path / "large.txt"
    small.write_text("....\n....\n" * 2)  # 16 cells
    large.write_text("....\n" * 6)  # 24 cells
    assert config_from_dict({"env": {"map": str(small), "n_agents": 1}}).env.map.endswith(
        "small.txt"
    )
    with pytest.raises(ConfigError, match=r"large.txt' has more than the 20 cells"):
        config_from_dict({"env": {"map": str(large), "n_agents": 1}})


# ---------------------------------------------------------------------- map files' hashes
ROOM = "........\n..##....\n........\n....#...\n........\n........\n........\n........\n"


def with_map(tmp_path: Path, source: str) -> Path:
    """A tiny config on ``room.txt`` given as ``source`` (YAML of ``env.map``)."""
    (tmp_path / "room.txt").write_text(ROOM)
    path = tmp_path / "given.yaml"
    path.write_text(TINY.replace("max_steps: 20}", f"max_steps: 20, map: {source}}}"))
    return path


def saved_config(tmp_path: Path, config_path: Path) -> Path:
    """The config as a run keeps it (``config.yaml``)."""
    path = tmp_path / "config.yaml"
    path.write_text(load_config(config_path).to_yaml())
    return path


FILE_SOURCES = {
    "file": ("{file: {path: room.txt}}", lambda m: m["file"], "env.map: file: "),
    "mix": (
        "{mix: [{weight: 1, cave: {}}, {weight: 2, file: {path: room.txt}}]}",
        lambda m: m["mix"][1]["file"],
        "env.map: mix.1.file: ",
    ),
}


@pytest.mark.parametrize("form", list(FILE_SOURCES))
def test_a_file_source_keeps_its_hash_and_a_changed_file_is_one_line(
    tmp_path, monkeypatch, capsys, form
):
    source, pick, where = FILE_SOURCES[form]
    monkeypatch.chdir(tmp_path)
    path = saved_config(tmp_path, with_map(tmp_path, source))
    room = tmp_path / "room.txt"
    kept = pick(yaml.safe_load(path.read_text())["env"]["map"])
    assert kept["path"] == str(room) and len(kept["sha256"]) == 64
    assert load_config(path).env.map == load_config(path).env.map  # unchanged: loads
    room.write_text(ROOM.replace("#", "."))
    runs = tmp_path / "runs"
    capsys.readouterr()
    assert main(["run", str(path), "--runs-dir", str(runs), "--no-progress"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"{where}map file '{room}' has changed since this config was written" in line
    assert not runs.exists()


def test_a_saved_file_source_without_a_hash_still_loads_and_gets_one(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = with_map(tmp_path, f"{{file: {{path: {tmp_path / 'room.txt'}}}}}")
    source = load_config(path).env.map
    assert source["file"]["path"] == str(tmp_path / "room.txt")
    assert len(source["file"]["sha256"]) == 64


def test_an_override_naming_another_map_file_drops_the_old_hash(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = saved_config(tmp_path, with_map(tmp_path, "{file: {path: room.txt}}"))
    (tmp_path / "hall.txt").write_text("." * 8 + "\n" + "." * 8 + "\n")
    config = load_config(path, ["env.map.file.path=hall.txt"])
    assert config.env.map["file"]["path"] == str(tmp_path / "hall.txt")
    string_form = saved_config(tmp_path, with_map(tmp_path, "room.txt"))
    assert load_config(string_form, ["env.map=hall.txt"]).env.map == str(tmp_path / "hall.txt")


# ---------------------------------------------------------------------- overrides of the map
@pytest.fixture
def run_on_a_map_file(tmp_path: Path) -> Path:
    """A run folder (untrained model) whose map file has since been deleted."""
    from harness.training.adapters import make_vec_env
    from harness.training.train import build_model

    config = load_config(with_map(tmp_path, str(tmp_path / "room.txt")))
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(config.to_yaml())
    venv = make_vec_env(config.env, config.vec.copies, 0, seed=0)
    build_model(config, venv).save(run / "model.zip")
    venv.close()
    (tmp_path / "room.txt").unlink()
    return run


def test_eval_with_another_map_does_not_need_the_runs_map_file(run_on_a_map_file, capsys):
    run = run_on_a_map_file
    capsys.readouterr()
    assert main(["eval", str(run), "--episodes", "1"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"'{run.parent / 'room.txt'}' is not 'random'" in line
    assert main(["eval", str(run), "--episodes", "1", "--set", "env.map=random", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 1
    # A bad replacement still names the override.
    assert main(["eval", str(run), "--set", "env.map=nowhere.txt"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "with --set env.map=nowhere.txt: env.map: 'nowhere.txt' is not 'random'" in line
