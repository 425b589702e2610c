"""The command line's errors (``harness.cli``): every kind of bad input ends the same way,
exit code 2, one line on stderr naming the problem, no traceback, and no file created, changed
or deleted.

Each case is a row of :data:`CASES`: the ``harness`` arguments (``{cfg}``, ``{run}``, ... are
filled in with paths in a scratch folder), files to write there first, and a fragment the
one-line message must contain (the same placeholders allowed). The scratch folder holds a tiny
valid config, a run folder with an untrained model of that config, and a finished-looking run
folder for ``compare``; every file under it and under ``runs/reference`` keeps its content and
modification time.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from harness.cli import main
from tests.conftest import root_first_env

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
GOOD = "name: tiny\nenv: {height: 8, width: 8, n_agents: 2, max_steps: 20}\nvec: {copies: 1}\n"
GOOD += "algo: {net_arch: [8], buffer_size: 1000, learning_starts: 50}\n"
GOOD += "phases: [{name: only, timesteps: 100}]\neval: {every: 0, episodes: 2}\n"
EPISODES = (
    "episode,phase,timesteps,copy,coverage,reward_mean,wall_hits,new_cells,length\n"
    "0,only,20,0,0.5,1.0,0,3;4,20\n"
)


#: An integer of more digits than Python converts from text (its default limit is 4300).
HUGE_INT = "9" * 5000
TEAMMAP = ["--set", "env.observation=teammap", "--set", "algo.policy=TeamMapPolicy"]


def cfg(extra: str) -> dict[str, str]:
    """Files for a config case: the good config plus ``extra`` YAML lines."""
    return {"bad.yaml": GOOD + extra}


# (id, arguments, files to write first, fragment of the message)
CASES: list[tuple[str, list[str], dict[str, str | bytes], str]] = [
    # ---- config files
    ("missing-config", ["run", "{tmp}/nope.yaml"], {}, "config file not found"),
    ("empty-config", ["run", "{tmp}/bad.yaml"], {"bad.yaml": ""}, "the config file is empty"),
    ("duplicate-key", ["run", "{tmp}/bad.yaml"], {"bad.yaml": GOOD + "name: again\n"},
     "duplicate key 'name'"),
    ("nested-yaml", ["run", "{tmp}/bad.yaml"], {"bad.yaml": "a: " + "[" * 5000},
     "nested too deeply"),
    ("huge-yaml", ["run", "{tmp}/bad.yaml"], {"bad.yaml": GOOD + "#" * (1 << 21) + "\n"},
     "too large for a config file"),
    ("binary-config", ["run", "{tmp}/bad.yaml"], {"bad.yaml": b"\x80\x81\xfe"},
     "cannot read config"),
    ("unknown-key", ["run", "{tmp}/bad.yaml"], cfg("extra_section: 1\n"),
     "extra_section: Extra inputs are not permitted"),
    ("unclosed-yaml", ["run", "{tmp}/bad.yaml"], {"bad.yaml": "env: {n_agents: 2\n"},
     "invalid YAML"),
    ("top-level-list", ["run", "{tmp}/bad.yaml"], {"bad.yaml": "- 1\n- 2\n"},
     "the top level must be a mapping"),
    ("config-endless-stream", ["run", "/dev/zero"], {}, "/dev/zero: not a regular file"),
    ("yaml-int-too-long", ["run", "{tmp}/bad.yaml"], cfg(f"seed: {HUGE_INT}\n"),
     "invalid YAML (Exceeds the limit (4300 digits)"),
    ("override-int-too-long", ["run", "{cfg}", "--set", f"seed={HUGE_INT}"], {},
     "Exceeds the limit (4300 digits)"),
    ("retired-action-mask", ["run", "{cfg}", "--set", "algo.action_mask=true"], {},
     "algo.action_mask: True: this knob was retired"),
    ("n-step-dict-uniform", ["run", "{cfg}", *TEAMMAP, "--set", "algo.n_steps=3",
                             "--set", "algo.prioritized=false"], {},
     "algo.n_steps: 3 needs algo.prioritized: true with env.observation 'teammap'"),
    ("n-steps-zero", ["run", "{cfg}", "--set", "algo.n_steps=0"], {},
     "algo.n_steps: Input should be greater than or equal to 1"),
    ("imitation-without-step", ["run", "{cfg}", "--set", "algo.imitation={{margin: 0.8}}"], {},
     "algo.imitation needs env.frontier.action"),
    ("retired-step-bonus", ["run", "{cfg}", "--set", "eval.step_bonus=1"], {},
     "eval.step_bonus: 1: this knob was retired"),
    ("retired-trail", ["run", "{cfg}", *TEAMMAP, "--set", "env.trail=8"], {},
     "env.trail: 8: this knob was retired"),
    ("imitation-negative-margin", ["run", "{cfg}", "--set", "algo.imitation={{margin: -1}}"], {},
     "algo.imitation.margin: Input should be greater than or equal to 0"),
    ("unknown-policy", ["run", "{cfg}", "--set", "algo.policy=CnnPolicy"], {},
     "algo.policy: unknown policy 'CnnPolicy'"),
    ("epochs-not-increasing", ["run", "{cfg}", "--set", "phases.only.epochs=[[0.5, 1], [0.1, 2]]"],
     {}, "thresholds must be strictly increasing"),
    ("seeds-too-close", ["run", "{cfg}", "--set", "eval.seed=5",
                         "--set", "eval.validation_seed=50"], {},
     "validation_seed must be at least 100000 away from seed"),
    ("map-file-missing", ["run", "{cfg}", "--set", "env.map=nowhere.txt"], {},
     "env.map: 'nowhere.txt' is not 'random'"),
    ("n-agents-zero", ["run", "{cfg}", "--set", "env.n_agents=0"], {},
     "env.n_agents: Input should be greater"),
    # ---- NaN and infinity: the schema takes no non-finite number anywhere
    ("learning-rate-inf", ["run", "{cfg}", "--set", "phases.only.learning_rate=inf"], {},
     "phases.0.learning_rate"),
    ("reward-nan", ["run", "{cfg}", "--set", "env.rewards.new_cell=nan"], {},
     "env.rewards.new_cell: Input should be a finite number"),
    ("per-eps-inf", ["run", "{cfg}", "--set", "algo.per_eps=inf"], {},
     "algo.per_eps: Input should be a finite number"),
    ("temperature-inf", ["run", "{cfg}", "--set", "eval.temperature=inf"], {},
     "eval.temperature: Input should be a finite number"),
    ("eval-temperature-inf", ["eval", "{run}", "--set", "eval.temperature=inf"], {},
     "eval.temperature: Input should be a finite number"),
    ("optimizer-lbfgs", ["run", "{cfg}", "--set", "algo.optimizer=LBFGS"], {},
     "algo.optimizer: torch.optim.LBFGS cannot train"),
    ("optimizer-sparseadam", ["run", "{cfg}", "--set", "algo.optimizer=SparseAdam"], {},
     "algo.optimizer: torch.optim.SparseAdam cannot train"),
    ("optimizer-base", ["run", "{cfg}", "--set", "algo.optimizer=Optimizer"], {},
     "torch's base class"),
    ("optimizer-unknown", ["run", "{cfg}", "--set", "algo.optimizer=Adamm"], {},
     "unknown torch optimizer 'Adamm'"),
    ("optimizer-kwargs-unknown", ["run", "{cfg}", "--set", "algo.optimizer_kwargs={{nope: 1}}"],
     {}, "algo.optimizer_kwargs: RMSprop does not take"),
    ("optimizer-kwargs-negative-lr", ["run", "{cfg}", "--set", "algo.optimizer_kwargs={{lr: -1}}"],
     {}, "algo.optimizer_kwargs"),
    ("optimizer-kwargs-lr", ["run", "{cfg}", "--set", "algo.optimizer_kwargs={{lr: 0.1}}"], {},
     "algo.optimizer_kwargs: lr is set by each phase's learning_rate"),
    ("optimizer-capturable-on-cpu", ["run", "{cfg}", "--set", "algo.optimizer=Adam",
                                     "--set", "algo.optimizer_kwargs={{capturable: true}}",
                                     "--set", "algo.device=cpu"], {},
     "algo.optimizer: torch.optim.Adam cannot train"),
    ("optimizer-differentiable", ["run", "{cfg}", "--set", "algo.optimizer=Adam",
                                  "--set", "algo.optimizer_kwargs={{differentiable: true}}"], {},
     "algo.optimizer: torch.optim.Adam cannot train"),
    ("device-meta", ["run", "{cfg}", "--set", "algo.device=meta"], {},
     "algo.device: cannot train on 'meta'"),
    ("device-unknown", ["run", "{cfg}", "--set", "algo.device=gpu9"], {},
     "algo.device: unknown device 'gpu9'"),
    ("buffer-too-large", ["run", "{cfg}", "--set", "algo.buffer_size=1000000000000"], {},
     "algo.buffer_size: a replay buffer of 1,000,000,000,000 transitions needs"),
    ("buffer-size-astronomical", ["run", "{cfg}", "--set", "algo.buffer_size=" + "9" * 40], {},
     "algo.buffer_size: Input should be less than or equal to 1099511627776"),
    ("batch-larger-than-buffer", ["run", "{cfg}", "--set", "phases.only.batch_size=1000000000000"],
     {}, "phases.only.batch_size: 1,000,000,000,000 is larger than algo.buffer_size (1,000)"),
    ("network-too-large", ["run", "{cfg}", "--set", "algo.net_arch=[1000000, 1000000]"], {},
     "algo.net_arch: a policy of 2,000,040,000,010 weights (online and target network) needs"),
    ("teammap-network-too-large", ["run", "{cfg}", *TEAMMAP, "--set",
                                   "algo.features_dim=1000000000"], {},
     "algo.net_arch, algo.features_dim, algo.cnn_channels: a policy of"),
    ("teammap-crop-huge", ["run", "{cfg}", "--set", "algo.policy=TeamMapPolicy", "--set",
                           "env.observation={{teammap: {{crop: 99999}}}}"],
     {}, "env.observation: crop must be an odd integer in 5..2000"),
    ("teammap-global-size-huge", ["run", "{cfg}", "--set", "algo.policy=TeamMapPolicy", "--set",
                                  "env.observation={{teammap: {{global_size: 99999}}}}"],
     {}, "env.observation: global_size must be an integer in 6..2000"),
    ("old-crop-key-migrates", ["run", "{cfg}", *TEAMMAP, "--set", "env.crop=4"], {},
     "env.observation: crop must be an odd integer in 5..2000, got 4"),
    ("threads-huge", ["run", "{cfg}", "--set", "algo.threads=100000"], {},
     "algo.threads: Input should be less than or equal to 256"),
    ("map-share-out-of-range", ["run", "{cfg}", "--set", "env.map={{cave: {{rock_share: 2}}}}"],
     {}, "rock_share must be in [0.0, 1.0], got 2"),
    ("map-share-nan", ["run", "{cfg}", "--set", "env.map={{cave: {{rock_share: .nan}}}}"], {},
     "rock_share must be in [0.0, 1.0], got nan"),
    ("map-share-negative", ["run", "{cfg}", "--set", "env.map={{maze: {{node_share: -1}}}}"],
     {}, "node_share must be in [0.0, 1.0]"),
    ("map-passes-huge", ["run", "{cfg}", "--set", "env.map={{cave: {{iterations: 100000000}}}}"],
     {}, "iterations must be an integer in [0, 100]"),
    ("map-in-mix-bad", ["run", "{cfg}", "--set",
                        "env.map={{mix: [{{weight: 1, maze: {{n_chambers: 100000000}}}}]}}"], {},
     "n_chambers must be an integer in [0, 10,000]"),
    ("map-too-large", ["run", "{cfg}", "--set", "env.height=100000", "--set", "env.width=100000"],
     {}, "more than the 4,000,000 this harness handles"),
    ("cave-too-slow-to-draw", ["run", "{cfg}", "--set",
                               "env.map={{cave: {{height: 1000, width: 1000}}}}"], {},
     "env.map: cave: a 1000x1000 cave has 1,000,000 cells, over the limit of 62,500"),
    ("cave-too-many-pockets", ["run", "{cfg}", "--set", "env.map={{cave: {{height: 250, width: "
                               "250, iterations: 0, min_region: 1}}}}"], {},
     "env.map: cave: a 250x250 cave with rock_share 0.55, iterations 0 and min_region 1 leaves"),
    ("maze-too-slow-to-draw", ["run", "{cfg}", "--set", "env.height=2000", "--set",
                               "env.width=2000", "--set",
                               "env.map={{mix: [{{weight: 1, maze: }}]}}"],
     {}, "env: map: mix.0.maze: a 2000x2000 maze has 4,000,000 cells, over the limit of 90,000"),
    ("map-too-walled", ["run", "{cfg}", "--set", "env.height=3", "--set", "env.width=3",
                        "--set", "env.wall_fraction=[0.9, 0.95]"], {}, "could not draw a 3x3 map"),
    ("map-too-small", ["run", "{cfg}", "--set", "env.height=1", "--set", "env.width=1"], {},
     "n_agents=2 is more than the 1x1 map's cells"),
    ("maze-too-small", ["run", "{cfg}", "--set", "env.map={{maze: {{}}}}",
                        "--set", "env.height=1", "--set", "env.width=2"], {},
     "a maze needs at least 3x3 cells, got 1x2"),
    ("map-source-unknown-key", ["run", "{tmp}/bad.yaml"],
     {"bad.yaml": GOOD.replace("n_agents: 2", "n_agents: 2, map: {mix: [{weight: 1, "
                               "cave: {rocks: 0.5}}]}")},
     "env.map: mix.0.cave.rocks: Extra inputs are not permitted"),
    ("train-on-test-map", ["run", "{cfg}", "--set", "env.map=cave_100x50",
                           "--set", "env.test_maps=[cave_100x50]"], {},
     "env.map: 'cave_100x50' is a test-only map"),
    ("config-seed-negative", ["run", "{cfg}", "--set", "seed=-1"], {},
     "seed: Input should be greater than or equal to 0"),
    ("config-seed-huge", ["run", "{cfg}", "--set", "seed=1099511627776"], {},
     "seed: Input should be less than or equal to 2147483647"),
    ("eval-seed-negative", ["run", "{cfg}", "--set", "eval.seed=-5"], {},
     "eval.seed: Input should be greater than or equal to 0"),
    ("validation-seed-negative", ["run", "{cfg}", "--set", "eval.validation_seed=-5"], {},
     "eval.validation_seed: Input should be greater than or equal to 0"),
    ("run-seed-negative", ["run", "{cfg}", "--seed", "-1"], {}, "argument --seed"),
    ("run-seed-text", ["run", "{cfg}", "--seed", "x"], {}, "argument --seed"),
    ("seeds-negative", ["run", "{cfg}", "--seeds", "-1"], {}, "must be at least 1"),
    ("seeds-zero", ["run", "{cfg}", "--seeds", "0"], {},
     "a single number is a count of seeds (--seeds 3 trains seeds 0, 1, 2) and must be at least "
     "1; to train one given seed, use --seed N"),
    ("seeds-twice", ["run", "{cfg}", "--seeds", "0,0"], {}, "a seed is given twice"),
    ("seeds-and-threads", ["run", "{cfg}", "--seeds", "2", "--set", "algo.threads=2"], {},
     "--set algo.threads: --seeds gives each seed its seed and algo.threads"),
    ("sweep-jobs-and-threads", ["sweep", "{cfg}", "--space", "{tmp}/space.yaml", "--trials", "2",
                                "--jobs", "2", "--set", "algo.threads=2"],
     {"space.yaml": "algo.gamma: {float: [0.8, 0.99]}\n"},
     "--set algo.threads: --jobs gives each worker its share of the cores"),
    ("seeds-and-seed", ["run", "{cfg}", "--seeds", "2", "--set", "seed=4"], {},
     "--set seed: --seeds gives each seed its seed"),
    ("seeds-count-huge", ["run", "{cfg}", "--seeds", "99999999999999999999"], {},
     "at most 1,000 runs in a group"),
    ("seeds-out-of-range", ["run", "{cfg}", "--seeds", "1,2147483648"], {},
     "seeds must be in [0, 2147483647]"),
    ("name-trailing-newline", ["run", "{cfg}", "--name", "ok\n"], {}, "name: must be 1-64"),
    ("name-traversal", ["run", "{cfg}", "--name", "../up"], {}, "name: must be 1-64"),
    ("override-nested", ["run", "{cfg}", "--set", "seed=" + "[" * 5000], {},
     "nested too deeply"),
    ("override-no-value", ["run", "{cfg}", "--set", "seed"], {}, "expected key.path=value"),
    ("runs-dir-under-file", ["run", "{cfg}", "--runs-dir", "{tmp}/afile/runs"],
     {"afile": "x"}, "cannot create a run folder"),
    # ---- evaluating models
    ("eval-seed-negative", ["eval", "{run}", "--seed", "-3"], {}, "argument --seed"),
    ("eval-episodes-zero", ["eval", "{run}", "--episodes", "0"], {}, "argument --episodes"),
    ("eval-nothing", ["eval", "{tmp}/nowhere"], {}, "no such run folder or model file"),
    ("eval-not-a-run", ["eval", "{tmp}/emptydir"], {"emptydir/.keep": ""},
     "not a run folder (no config.yaml)"),
    ("eval-truncated-zip", ["eval", "{tmp}/trunc/model.zip"], {"trunc/model.zip": b"PK\x03\x04"},
     "cannot load model"),
    ("eval-dangling-symlink", ["eval", "{tmp}/link/model.zip"], {}, "no such run folder"),
    ("eval-other-algorithm", ["eval", "{tmp}/ppo/model.zip"], {}, "cannot load model"),
    ("eval-other-spaces", ["eval", "{tmp}/cartpole/model.zip"], {},
     "observation space Box"),
    ("eval-no-target", ["eval"], {}, "give a run folder or model zip"),
    ("eval-policy-no-config", ["eval", "--policy", "random"], {}, "needs --config"),
    ("eval-no-model-yet", ["eval", "{tmp}/nomodel"], {"nomodel/config.yaml": GOOD},
     "no model.zip yet"),
    ("eval-garbage-zip", ["eval", "{tmp}/trunc/model.zip"], {"trunc/model.zip": b"garbage"},
     "cannot load model"),
    ("eval-plot-over-model", ["eval", "{run}", "--plot", "{run}/model.zip"], {},
     "--plot {run}/model.zip: expected a .png file name"),
    ("eval-plot-over-config", ["eval", "{run}", "--plot", "{run}/config.yaml"], {},
     "expected a .png file name"),
    ("eval-plot-under-file", ["eval", "{run}", "--plot", "{tmp}/afile/p.png"], {"afile": "x"},
     "is a file, not a folder"),
    ("eval-plot-read-only", ["eval", "{run}", "--plot", "/proc/p.png"], {}, "cannot write in"),
    ("eval-plot-is-folder", ["eval", "{run}", "--plot", "{tmp}/d.png"], {"d.png/.keep": ""},
     "is a folder"),
    ("eval-policy-unknown", ["eval", "--policy", "greedy", "--config", "{cfg}"], {},
     "unknown policy 'greedy'"),
    ("render-out-under-file", ["render", "{run}", "--out", "{tmp}/afile/x.png"], {"afile": "x"},
     "is a file, not a folder"),
    ("render-gif-is-folder", ["render", "{run}", "--gif", "{tmp}/d.gif"], {"d.gif/.keep": ""},
     "--gif {tmp}/d.gif: is a folder"),
    ("render-out-over-config", ["render", "{run}", "--out", "{run}/config.yaml"], {},
     "--out {run}/config.yaml: expected a .png file name"),
    ("render-gif-named-png", ["render", "{run}", "--gif", "{tmp}/x.png"], {},
     "--gif {tmp}/x.png: expected a .gif file name"),
    ("render-config-missing", ["render", "--policy", "random", "--config", "{tmp}/nope.yaml"], {},
     "config file not found"),
    ("render-every-zero", ["render", "{run}", "--every", "0"], {}, "argument --every"),
    ("render-seed-huge", ["render", "{run}", "--seed", "4294967296"], {}, "argument --seed"),
    ("export-under-file", ["export", "{run}", "--out", "{tmp}/afile/ref"], {"afile": "x"},
     "is a file, not a folder"),
    ("export-existing", ["export", "{run}", "--out", "{tmp}/emptydir"], {"emptydir/.keep": ""},
     "already exists"),
    ("tune-nan", ["tune", "{run}", "--temperatures", "nan"], {}, "finite and >= 0"),
    ("tune-inf", ["tune", "{run}", "--temperatures", "0.5", "inf"], {}, "finite and >= 0"),
    ("tune-negative", ["tune", "{run}", "--temperatures", "-1"], {}, "finite and >= 0"),
    ("tune-seed-negative", ["tune", "{run}", "--seed", "-1"], {}, "argument --seed"),
    ("tune-temperature-below-zero", ["tune", "{run}", "--temperatures", "-0.1"], {},
     "finite and >= 0"),
    ("tune-write-with-set", ["tune", "{run}", "--write", "--set", "env.max_steps=20"], {},
     "--write stores a choice"),
    ("tune-write-reference", ["tune", "{ref}", "--write", "--episodes", "1"], {},
     "a reference is read-only"),
    # ---- compare
    ("compare-window-zero", ["compare", "{done}", "--window", "0"], {}, "argument --window"),
    ("compare-reps-endless", ["compare", "{done}", "--reps", "100000000"], {},
     "--reps must be in [1, 200000], got 100000000"),
    ("compare-not-a-run", ["compare", "{tmp}/emptydir"], {"emptydir/.keep": ""},
     "not a run folder with episodes.csv"),
    ("compare-empty-csv", ["compare", "{tmp}/c"], {"c/episodes.csv": ""}, "episodes.csv: empty"),
    ("compare-header-only", ["compare", "{tmp}/c"], {"c/episodes.csv": EPISODES.split("\n")[0]
                                                      + "\n"}, "no finished episode yet"),
    ("compare-binary-csv", ["compare", "{tmp}/c"], {"c/episodes.csv": b"\x80\x81garbage"},
     "not a CSV text file"),
    ("compare-garbage-row", ["compare", "{tmp}/c"],
     {"c/episodes.csv": EPISODES + "1,only,forty,0,0.5,1,0,1;1,20\n"}, "line 3"),
    ("compare-nan-coverage", ["compare", "{tmp}/c"],
     {"c/episodes.csv": EPISODES + "1,only,40,0,nan,1,0,1;1,20\n"}, "coverage is nan"),
    ("compare-missing-column", ["compare", "{tmp}/c"], {"c/episodes.csv": "a,b\n1,2\n"},
     "missing column"),
    ("compare-json-list", ["compare", "{tmp}/c"],
     {"c/episodes.csv": EPISODES, "c/eval.json": "[1, 2]"}, "expected a JSON object"),
    ("compare-json-garbage", ["compare", "{tmp}/c"],
     {"c/episodes.csv": EPISODES, "c/eval.json": "{nope"}, "not a readable eval JSON"),
    ("compare-json-wrong-type", ["compare", "{tmp}/c"],
     {"c/episodes.csv": EPISODES, "c/eval.json": '{"coverage_median": "high"}'},
     "coverage_median must be a number"),
    ("compare-out-over-episodes", ["compare", "{done}", "--out", "{done}/episodes.csv"], {},
     "--out {done}/episodes.csv: expected a .png file name"),
    ("compare-labels-count", ["compare", "{done}", "{done}", "--labels", "x"], {},
     "--labels needs one label per run (2)"),
    ("compare-out-under-file", ["compare", "{done}", "--out", "{tmp}/afile/c.png"],
     {"afile": "x"}, "is a file, not a folder"),
    ("compare-bad-evaluations", ["compare", "{tmp}/c"],
     {"c/episodes.csv": EPISODES, "c/evaluations.csv": "timesteps,coverage_median\n5,x\n"},
     "evaluations.csv, line 2"),
    # ---- usage
    ("unknown-command", ["fly"], {}, "invalid choice: 'fly'"),
    ("resume-with-config", ["run", "--resume", "{run}", "{cfg}"], {}, "drop the other options"),
]  # fmt: skip

if not torch.cuda.is_available():
    CASES.append(("device-cuda-missing", ["run", "{cfg}", "--set", "algo.device=cuda"], {},
                  "this machine has no CUDA GPU"))  # fmt: skip


def snapshot(folder: Path) -> dict[str, str]:
    """Every file and folder under ``folder``, with each file's modification time and a hash of
    its content."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_symlink():
            out[str(p.relative_to(folder))] = f"link:{os.readlink(p)}"
        elif p.is_file():
            digest = hashlib.sha256(p.read_bytes()).hexdigest()
            out[str(p.relative_to(folder))] = f"{p.stat().st_mtime_ns}:{digest}"
        else:
            out[str(p.relative_to(folder))] = "dir"
    return out


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Model zips made once: an untrained DoubleDQN of the good config, a PPO model (another
    algorithm) and a DQN for CartPole (other spaces)."""
    import gymnasium as gym
    from stable_baselines3 import PPO

    from harness.config.loading import config_from_dict
    from harness.sb3.dqn import DoubleDQN
    from harness.training.adapters import make_vec_env
    from harness.training.train import build_model

    folder = tmp_path_factory.mktemp("models")
    import yaml

    config = config_from_dict(yaml.safe_load(GOOD))
    venv = make_vec_env(config.env, config.vec.copies, 0, seed=0)
    build_model(config, venv).save(folder / "tiny.zip")
    venv.close()
    (folder / "tiny.yaml").write_text(config.to_yaml())
    PPO("MlpPolicy", gym.make("CartPole-v1"), n_steps=64, batch_size=32).save(folder / "ppo.zip")
    DoubleDQN("MlpPolicy", gym.make("CartPole-v1"), buffer_size=100).save(folder / "cart.zip")
    return folder


@pytest.fixture
def scratch(tmp_path: Path, models: Path) -> dict[str, Path]:
    """The scratch folder: a good config, a run folder with a model, copies of bad models."""
    (tmp_path / "good.yaml").write_text(GOOD)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text((models / "tiny.yaml").read_text())
    (run / "model.zip").write_bytes((models / "tiny.zip").read_bytes())
    done = tmp_path / "done"
    done.mkdir()
    (done / "episodes.csv").write_text(EPISODES)
    for name, zip_name in (("ppo", "ppo.zip"), ("cartpole", "cart.zip"), ("trunc", None)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.yaml").write_text((models / "tiny.yaml").read_text())
        if zip_name:
            (tmp_path / name / "model.zip").write_bytes((models / zip_name).read_bytes())
    (tmp_path / "link").mkdir()
    (tmp_path / "link" / "config.yaml").write_text((models / "tiny.yaml").read_text())
    (tmp_path / "link" / "model.zip").symlink_to(tmp_path / "gone.zip")
    return {"tmp": tmp_path, "cfg": tmp_path / "good.yaml", "run": run, "done": done}


@pytest.mark.parametrize(
    ("args", "files", "message"), [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
def test_bad_input_is_one_line_exit_2_and_changes_nothing(
    scratch, capsys, monkeypatch, args, files, message
):
    tmp = scratch["tmp"]
    for name, content in files.items():
        path = tmp / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
    monkeypatch.chdir(tmp)  # anything written relative to the current folder shows up here
    values = {k: str(v) for k, v in scratch.items()}
    values["ref"] = str(ROOT / "runs" / "reference" / "ddqn_15x15")
    argv = [a.format(**values) for a in args]
    if "--runs-dir" not in argv and argv[0] == "run" and "--resume" not in argv:
        argv += ["--runs-dir", str(tmp / "runs")]
    before, reference_before = snapshot(tmp), snapshot(ROOT / "runs" / "reference")
    capsys.readouterr()
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("harness: error:"), lines
    for key, value in values.items():  # messages may name the scratch paths
        message = message.replace("{" + key + "}", value)
    assert message in lines[0], lines[0]
    assert "Traceback" not in captured.err + captured.out
    assert snapshot(tmp) == before
    assert snapshot(ROOT / "runs" / "reference") == reference_before


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["run", "{cfg}", "--set", "algo.optimizer=LBFGS"], "cannot train"),
        (["eval", "{tmp}/trunc/model.zip"], "cannot load model"),
        (["compare", "{tmp}/c"], "not a run folder"),
        (["run", "/dev/zero"], "not a regular file"),
        (["run", "{cfg}", "--set", "algo.net_arch=[1000000, 1000000]"], "algo.net_arch: a policy"),
    ],
    ids=["config", "model", "compare", "endless-config", "network-too-large"],
)
def test_the_console_script_shows_no_traceback(scratch, args, message):
    values = {k: str(v) for k, v in scratch.items()}
    (scratch["tmp"] / "trunc" / "model.zip").write_bytes(b"PK\x03\x04")
    proc = subprocess.run(
        [sys.executable, "-m", "harness.cli", *[a.format(**values) for a in args]],
        capture_output=True,
        text=True,
        cwd=scratch["tmp"],
        env=root_first_env(),
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def console(args: list[str], cwd: Path, gone: bool = False, **env: str):
    """``harness ARGS`` as a console command started in ``cwd`` with the extra environment
    variables ``env``; ``gone``: ``cwd`` is deleted after the shell entered it, before Python
    starts (``os.getcwd()`` then fails in the command)."""
    cmd = [sys.executable, "-m", "harness.cli", *args]
    if gone:
        cmd = ["sh", "-c", 'cd "$0" && rmdir "$0" && exec "$@"', str(cwd), *cmd]
    return subprocess.run(
        cmd,
        capture_output=True,
        text=True,
        cwd=cwd.parent if gone else cwd,
        env=root_first_env(**env),
    )


def test_paths_the_terminal_cannot_encode_are_printed_escaped(scratch):
    tmp = scratch["tmp"]
    (tmp / "ref ü x").mkdir()
    (tmp / "ref ü x" / "episodes.csv").write_text(EPISODES)
    proc = console(["compare", "ref ü x", "--out", "c.png"], tmp, PYTHONIOENCODING="ascii")
    assert "Traceback" not in proc.stderr
    assert proc.returncode == 0, proc.stderr
    assert "ref \\xfc x" in proc.stdout  # the run's name in the table, escaped
    assert (tmp / "c.png").is_file()


@pytest.mark.parametrize(
    "args",
    [
        ["compare", "{done}", "--out", "{tmp}/c.png"],
        pytest.param(
            ["render", "{run}", "--out", "{tmp}/c.png", "--gif", "{tmp}/c.gif"],
            marks=pytest.mark.slow,  # plays an episode
        ),
    ],
    ids=["compare", "render"],
)
def test_pictures_are_written_whatever_display_backend_the_user_set(scratch, args):
    values = {k: str(v) for k, v in scratch.items()}
    proc = console([a.format(**values) for a in args], scratch["tmp"], MPLBACKEND="bogus")
    assert "Traceback" not in proc.stderr
    assert proc.returncode == 0, proc.stderr
    assert (scratch["tmp"] / "c.png").is_file()


@pytest.mark.parametrize(
    "args",
    [["eval", "{run}"], ["run", "{cfg}", "--runs-dir", "{tmp}/runs"], ["--help"]],
    ids=["eval", "run", "help"],
)
def test_a_deleted_current_folder_is_one_line_and_exit_2(scratch, args):
    values = {k: str(v) for k, v in scratch.items()}
    gone = scratch["tmp"] / "gone"
    gone.mkdir()
    before = snapshot(scratch["tmp"])
    proc = console([a.format(**values) for a in args], gone, gone=True)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        "harness: error: the current folder was deleted: cd to an existing folder and run the "
        "command again"
    ]
    assert not gone.exists()
    assert snapshot(scratch["tmp"]) == {k: v for k, v in before.items() if k != "gone"}


@pytest.mark.parametrize(
    ("policy", "weights"),
    [
        # 13 observation numbers, one hidden layer of 8, 5 actions; online + target network:
        # 2 * ((13 + 1) * 8 + (8 + 1) * 5) = 2 * (112 + 45)
        ("MlpPolicy", 314),
        # dueling: a value stream 13 -> 8 -> 1 and an advantage stream 13 -> 8 -> 5:
        # 2 * ((112 + 9) + (112 + 45))
        ("DuelingMlpPolicy", 556),
    ],
)
def test_the_memory_check_counts_the_networks_weights(policy, weights):
    import yaml

    from harness.config.loading import config_from_dict
    from harness.training.checks import check_network_memory, network_parameters

    config = config_from_dict(yaml.safe_load(GOOD), overrides=[f"algo.policy={policy}"])
    assert network_parameters(config) == weights
    assert check_network_memory(config, available=8 * weights) == 8 * weights  # 4 bytes, twice
    with pytest.raises(ValueError, match=f"algo.net_arch: a policy of {weights} weights"):
        check_network_memory(config, available=8 * weights - 1)


def test_a_config_that_is_a_fifo_is_refused_at_once(tmp_path, capsys):
    fifo = tmp_path / "config.yaml"
    os.mkfifo(fifo)  # opening it for reading would wait for a writer forever
    assert main(["run", str(fifo)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"{fifo}: not a regular file" in line


@pytest.mark.parametrize("kind", ["fifo", "device", "huge"])
def test_a_space_file_that_is_no_regular_small_file_is_refused_at_once(kind, tmp_path, capsys):
    # The sweep's --space is read as a config is: a FIFO would wait for a writer forever,
    # /dev/zero would fill the memory.
    space = tmp_path / "space.yaml"
    if kind == "fifo":
        os.mkfifo(space)
    elif kind == "device":
        space = Path("/dev/zero")
    else:
        space.write_text("algo.gamma: {float: [0.8, 0.99]}\n" + "#" * (1 << 21) + "\n")
    config = tmp_path / "tiny.yaml"
    config.write_text(GOOD)
    args = ["sweep", str(config), "--space", str(space), "--trials", "1"]
    args += ["--sweeps-dir", str(tmp_path / "s")]
    assert main(args) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    expected = "too large for a space file" if kind == "huge" else "not a regular file"
    assert f"{space}: " in line and expected in line
    assert not (tmp_path / "s").exists() or not any((tmp_path / "s").iterdir())
