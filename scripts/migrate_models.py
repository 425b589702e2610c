"""Rewrite saved models into today's layout (``harness.sb3.dqn.MODEL_FORMAT``), once, in place, so
that the harness reads every model one way and keeps no loading shims for older ones.

    python scripts/migrate_models.py [PATH ...]   # default: every shipped model

A PATH is a model zip or a folder (its ``*.zip`` files, at any depth: a run folder with its
checkpoints, say). The default is the shipped ones: ``runs/reference/*/model.zip`` and any
``docs/seeds/**/*.zip``. A model already in today's format is left as it is, so running the
script twice changes nothing. Prints one line per model; exits 2 with one line for a path that
is no model zip (nothing is written for it), 0 otherwise.

What format 1 (models saved before formats were stated) becomes:

* classes pickled under their modules from before they moved into ``harness.sb3``
  (``harness.policies``, ``harness.buffers``, ``harness.dqn``, ``harness.schedules``) are named
  by their module now;
* the target network, which compact exports (``harness export``) left out, is stored as the
  online network's tensors, once (how exports store it now);
* an action mask entry of the observation space that is not the env's int8 (the goal-action
  references were saved with a float32 one) becomes int8, with the same bounds, and so do the
  masks of the saved last observations: the harness feeds models the env's mask as it is;
* the retired settings ``action_mask`` and ``same_moves`` (stored by older runs as attributes that
  nothing read) are dropped, and ``expert_action``, ``margin`` and ``margin_weight`` are stored
  with the values models from before the imitation loss were trained with (no expert action);
* the format is stated.

Nothing else changes: the online network's weights, the settings and the counters are the file's
own, so a migrated model plays the same actions (``scripts/check_references.py`` checks the
shipped ones on all their stored episodes).
"""

from __future__ import annotations

import base64
import io
import json
import os
import pickle
import sys
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.save_util import data_to_json

from harness.results.rundir import RunDir
from harness.sb3.dqn import FORMAT_KEY, MODEL_FORMAT, saved_model_format, target_as_online
from harness.sb3.policies import ACTION_MASK_KEY

ROOT = Path(__file__).resolve().parents[1]
EXIT_USAGE = 2

#: Modules of the harness's SB3 classes before they moved into ``harness.sb3``.
MOVED_MODULES = {
    "harness.policies": "harness.sb3.policies",
    "harness.buffers": "harness.sb3.buffers",
    "harness.dqn": "harness.sb3.dqn",
    "harness.schedules": "harness.sb3.schedules",
}
#: Settings older runs stored that no version reads any more.
RETIRED = ("action_mask", "same_moves")
#: Settings added since, with the values every model saved without them was trained with.
ADDED = {"expert_action": None, "margin": 0.8, "margin_weight": 1.0}
#: Saved observations (SB3's ``data``) whose action mask follows the observation space's.
SAVED_OBSERVATIONS = ("_last_obs", "_last_original_obs")
#: The dtype an action mask has in the env, and so in the models (PettingZoo's convention).
MASK_DTYPE = np.int8


class _RenamingUnpickler(pickle.Unpickler):
    """Unpickles with the classes of :data:`MOVED_MODULES` found in their new module, and notes
    whether it had to."""

    renamed = False

    def find_class(self, module: str, name: str) -> Any:
        if module in MOVED_MODULES:
            self.renamed = True
            module = MOVED_MODULES[module]
        return super().find_class(module, name)


def shipped_models() -> list[Path]:
    """The models the repository ships: every reference's and any under ``docs/seeds`` (a map
    prior's reference holds no SB3 model: docs/prior.md)."""
    from harness.prior.evaluate import is_prior_run

    folders = (ROOT / "runs" / "reference").iterdir()
    references = [RunDir(p).model for p in folders if not is_prior_run(p)]
    references = [model for model in references if model.is_file()]
    return sorted({*references, *(ROOT / "docs" / "seeds").rglob("*.zip")})


def _int8_mask_space(space: Any) -> Any:
    """``space`` with its action mask ``Box`` as an int8 one (the same object when it is)."""
    if not (isinstance(space, spaces.Dict) and ACTION_MASK_KEY in space.spaces):
        return space
    mask = space.spaces[ACTION_MASK_KEY]
    if not isinstance(mask, spaces.Box) or mask.dtype == MASK_DTYPE:
        return space
    low, high = mask.low.astype(MASK_DTYPE), mask.high.astype(MASK_DTYPE)
    entry = spaces.Box(low, high, mask.shape, MASK_DTYPE)
    return spaces.Dict({k: entry if k == ACTION_MASK_KEY else v for k, v in space.spaces.items()})


def _int8_mask_obs(obs: Any) -> Any:
    """Saved observations (a dict of arrays) with their action mask as int8 (the same object
    when it is, or when they carry none)."""
    if not isinstance(obs, dict) or ACTION_MASK_KEY not in obs:
        return obs
    mask = obs[ACTION_MASK_KEY]
    if not isinstance(mask, np.ndarray) or mask.dtype == MASK_DTYPE:
        return obs
    return {**obs, ACTION_MASK_KEY: mask.astype(MASK_DTYPE)}


def migrated_data(data: dict[str, Any]) -> dict[str, Any]:
    """SB3's ``data`` (the JSON of a model zip) in today's format: the entries that change are
    decoded, changed and encoded again as SB3 encodes them; every other entry is kept as it is."""
    out: dict[str, Any] = {}
    for key, entry in data.items():
        if key in RETIRED:
            continue
        if not (isinstance(entry, dict) and ":serialized:" in entry):
            out[key] = entry
            continue
        unpickler = _RenamingUnpickler(io.BytesIO(base64.b64decode(entry[":serialized:"])))
        value = unpickler.load()
        if key == "observation_space":
            changed = _int8_mask_space(value)
        elif key in SAVED_OBSERVATIONS:
            changed = _int8_mask_obs(value)
        else:
            changed = value
        if unpickler.renamed or changed is not value:
            out[key] = json.loads(data_to_json({key: changed}))[key]
        else:
            out[key] = entry
    for key, value in ADDED.items():
        out.setdefault(key, value)
    out[FORMAT_KEY] = MODEL_FORMAT
    return out


def migrated_policy(policy_pth: bytes) -> bytes:
    """A saved policy ``state_dict`` with its target network: the one it holds, or else the
    online network's tensors (stored once)."""
    state = th.load(io.BytesIO(policy_pth), map_location="cpu", weights_only=True)
    if any(k.startswith("q_net_target.") for k in state):
        return policy_pth
    packed = io.BytesIO()
    th.save(target_as_online(state), packed)
    return packed.getvalue()


def migrate(path: Path) -> bool:
    """Rewrite the model zip ``path`` in today's format (into a temporary file beside it, then
    renamed over it: an interrupted migration leaves the old file whole).

    Returns:
        ``True`` when it was rewritten, ``False`` when it already was in today's format.

    Raises:
        ValueError: ``path`` is no model zip.
    """
    found = saved_model_format(path)
    if found is None:
        raise ValueError(f"{path}: not a model zip (no SB3 data in it)")
    if found == MODEL_FORMAT:
        return False
    if found > MODEL_FORMAT:
        raise ValueError(f"{path}: model format {found} is newer than this harness's")
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        with zipfile.ZipFile(path) as zin, zipfile.ZipFile(name, "w", zipfile.ZIP_DEFLATED) as zout:
            for item in zin.infolist():
                content = zin.read(item.filename)
                if item.filename == "data":
                    content = json.dumps(migrated_data(json.loads(content)), indent=4).encode()
                elif item.filename == "policy.pth":
                    content = migrated_policy(content)
                zout.writestr(item, content)
        os.replace(name, path)
    except BaseException:
        Path(name).unlink(missing_ok=True)
        raise
    return True


def models_under(paths: list[str]) -> list[Path]:
    """The model zips the command line names: files as they are, folders' ``*.zip`` files.

    Raises:
        ValueError: a path that does not exist.
    """
    out: list[Path] = []
    for arg in paths:
        path = Path(arg)
        if path.is_dir():
            out.extend(sorted(path.rglob("*.zip")))
        elif path.is_file():
            out.append(path)
        else:
            raise ValueError(f"{arg}: no such file or folder")
    return out


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in args):
        print(__doc__)
        return 0
    try:
        models = models_under(args) if args else shipped_models()
        for model in models:
            print(f"{model}: {'migrated' if migrate(model) else 'already current'}", flush=True)
    except ValueError as exc:
        print(f"migrate_models: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    return 0


if __name__ == "__main__":
    sys.exit(main())
