"""scripts/migrate_models.py: the shipped models are in today's format, an older model is refused
with one line naming the migration, and the migration turns an old-format model (made here from
a shipped one, as older versions saved it) back into today's, playing the same episode."""

from __future__ import annotations

import base64
import io
import json
import runpy
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.save_util import data_to_json

from harness.cli import main
from harness.sb3.dqn import (
    FORMAT_KEY,
    MIGRATE_COMMAND,
    MODEL_FORMAT,
    DoubleDQN,
    OldModelError,
    saved_model_format,
)
from harness.sb3.policies import ACTION_MASK_KEY
from tests.conftest import one_error_line

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = runpy.run_path(str(ROOT / "scripts" / "migrate_models.py"))
#: A goal-action reference: its observations carry an action mask, its policy a harness class.
GOALS = ROOT / "runs" / "reference" / "goals_2agents"


def _decode(entry: dict) -> object:
    import pickle

    return pickle.loads(base64.b64decode(entry[":serialized:"]))  # our own file


def _encode(key: str, value: object) -> dict:
    return json.loads(data_to_json({key: value}))[key]


def _float_mask(space: spaces.Dict) -> spaces.Dict:
    mask = space[ACTION_MASK_KEY]
    box = spaces.Box(0.0, 1.0, mask.shape, np.float32)
    return spaces.Dict({k: box if k == ACTION_MASK_KEY else v for k, v in space.spaces.items()})


def aged(model_zip: bytes) -> bytes:
    """``model_zip`` as a version before model formats saved it: its policy class pickled under
    ``harness.policies`` (the module before ``harness.sb3``), no target network (a compact export
    of then), a float32 action mask, the retired settings stored, none of the later ones."""
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(model_zip)) as zin, zipfile.ZipFile(out, "w") as zout:
        for item in zin.infolist():
            content = zin.read(item.filename)
            if item.filename == "data":
                data = json.loads(content)
                for key in (FORMAT_KEY, "expert_action", "margin", "margin_weight"):
                    del data[key]
                data.update(action_mask=False, same_moves=True)
                name = _decode(data["policy_class"]).__name__
                # A protocol-0 pickle of the class by its old module and name.
                old = b"charness.policies\n" + name.encode() + b"\n."
                data["policy_class"] = {
                    ":type:": "<class 'abc.ABCMeta'>",
                    ":serialized:": base64.b64encode(old).decode(),
                    "__module__": "harness.policies",
                }
                space = _decode(data["observation_space"])
                data["observation_space"] = _encode("observation_space", _float_mask(space))
                for key in ("_last_obs", "_last_original_obs"):
                    obs = _decode(data[key])
                    obs[ACTION_MASK_KEY] = obs[ACTION_MASK_KEY].astype(np.float32)
                    data[key] = _encode(key, obs)
                content = json.dumps(data).encode()
            elif item.filename == "policy.pth":
                state = th.load(io.BytesIO(content), weights_only=True)
                kept = {k: v for k, v in state.items() if not k.startswith("q_net_target.")}
                packed = io.BytesIO()
                th.save(kept, packed)
                content = packed.getvalue()
            zout.writestr(item, content)
    return out.getvalue()


@pytest.fixture
def old_goals(tmp_path: Path) -> Path:
    """A copy of the goal reference's folder whose model is in the old format."""
    run = tmp_path / "goals_2agents"
    run.mkdir()
    (run / "config.yaml").write_bytes((GOALS / "config.yaml").read_bytes())
    (run / "model.zip").write_bytes(aged((GOALS / "model.zip").read_bytes()))
    return run


def test_every_shipped_model_is_in_todays_format() -> None:
    models = SCRIPT["shipped_models"]()
    assert len(models) == 20
    assert {saved_model_format(m) for m in models} == {MODEL_FORMAT}


def test_an_old_model_is_refused_with_one_line_naming_the_migration(old_goals, capsys) -> None:
    assert saved_model_format(old_goals / "model.zip") == 1
    with pytest.raises(OldModelError, match=r"scripts/migrate_models\.py"):
        DoubleDQN.load(old_goals / "model.zip")
    capsys.readouterr()
    assert main(["eval", str(old_goals), "--episodes", "1"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "older version of the harness (model format 1" in line
    assert line.endswith(f"{MIGRATE_COMMAND} {old_goals / 'model.zip'}")


def test_the_migration_gives_back_todays_model_and_its_episode(old_goals, capsys) -> None:
    model = old_goals / "model.zip"
    assert SCRIPT["main"]([str(old_goals)]) == 0
    assert capsys.readouterr().out == f"{model}: migrated\n"
    with zipfile.ZipFile(model) as new, zipfile.ZipFile(GOALS / "model.zip") as ref:
        data, want = json.loads(new.read("data")), json.loads(ref.read("data"))
        state = th.load(io.BytesIO(new.read("policy.pth")), weights_only=True)
        ref_state = th.load(io.BytesIO(ref.read("policy.pth")), weights_only=True)
    assert set(data) == set(want)  # the retired settings gone, the later ones back
    for key in ("expert_action", "margin", "margin_weight", FORMAT_KEY):
        assert data[key] == want[key]
    assert _decode(data["policy_class"]) is _decode(want["policy_class"])
    assert _decode(data["observation_space"]) == _decode(want["observation_space"])
    mask = _decode(data["_last_obs"])[ACTION_MASK_KEY]
    assert mask.dtype == np.int8
    assert np.array_equal(mask, _decode(want["_last_obs"])[ACTION_MASK_KEY])
    assert state.keys() == ref_state.keys()
    for key, value in state.items():
        assert th.equal(value, ref_state[key]), key
        if key.startswith("q_net_target."):  # the online network's tensors, stored once
            online = state["q_net." + key.removeprefix("q_net_target.")]
            assert value.untyped_storage().data_ptr() == online.untyped_storage().data_ptr()
    # Run twice, it leaves the model as it is.
    before = model.read_bytes()
    assert SCRIPT["main"]([str(model)]) == 0
    assert capsys.readouterr().out == f"{model}: already current\n"
    assert model.read_bytes() == before
    # And the migrated model plays the reference's first stored episode.
    committed = json.loads((GOALS / "eval.json").read_text())
    assert main(["eval", str(old_goals), "--episodes", "1", "--json"]) == 0
    saved = json.loads(next(old_goals.glob("eval*.json")).read_text())
    assert saved["coverage"] == committed["coverage"][:1]
    assert saved["wall_hits"] == committed["wall_hits"][:1]


@pytest.mark.parametrize("what", ["missing", "not_a_model"])
def test_the_migration_refuses_what_is_no_model_in_one_line(what, tmp_path, capsys) -> None:
    path = tmp_path / "model.zip"
    if what == "not_a_model":
        path.write_text("not a zip")
    assert SCRIPT["main"]([str(path)]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"migrate_models: error: {path}")
    assert what == "missing" or path.read_text() == "not a zip"  # nothing written
