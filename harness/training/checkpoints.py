"""Checkpoints: everything needed to continue a run exactly where it stopped.

A checkpoint is a folder ``checkpoints/step-<num_timesteps>/`` holding:

* ``model.zip``: the SB3 model (weights, optimizer state, step counters, ``ep_info_buffer``);
* ``replay_buffer.pkl``: the replay buffer with its priorities;
* ``rng.pkl``: the numpy, Python and torch random states;
* ``state.json``: the harness's own position (:class:`TrainingState`).

It is written into a hidden temporary folder and renamed into place only when complete, and older
checkpoints are deleted only after that, so the last good checkpoint survives a crash or a
``kill -9`` at any moment. The newest complete folder is the one a resume loads.
"""

from __future__ import annotations

import json
import pickle
import random
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.results.rundir import CheckpointDir

STEP_PREFIX = "step-"
KEEP = 2  # checkpoints kept: the newest and the one before it


class CheckpointError(RuntimeError):
    """A missing or unreadable checkpoint, with a one-line message."""


@dataclass
class TrainingState:
    """Where a run stands, beyond what the SB3 model knows."""

    phase: int = 0
    """Index of the phase in progress (``len(phases)`` when all are done)."""
    phase_start: int = 0
    """``num_timesteps`` when that phase started."""
    next_episode: int = 0
    """Number of the next row of ``episodes.csv``."""
    best_eval: float = float("-inf")
    """Best evaluation score so far (for ``best_model.zip``)."""
    finished: bool = False
    """True once ``model.zip`` of the whole run is written."""
    resumes: int = 0
    """How often the run was resumed (new env seeds each time)."""
    num_timesteps: int = 0
    """The model's step counter when the checkpoint was written (for reading only)."""

    def to_json(self) -> str:
        data = asdict(self)
        data["best_eval"] = None if not np.isfinite(self.best_eval) else self.best_eval
        return json.dumps(data, indent=2)

    @classmethod
    def from_json(cls, text: str) -> TrainingState:
        """Parse ``state.json``; every field must be there with its type.

        Raises:
            ValueError: naming the field.
        """
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError("not a JSON object")
        if data.get("best_eval") is None:
            data["best_eval"] = float("-inf")
        types = {"best_eval": (int, float), "finished": (bool,)}
        for name in cls.__dataclass_fields__:
            value = data.get(name)
            expected = types.get(name, (int,))
            if name not in data or not isinstance(value, expected):
                raise ValueError(f"{name} is {value!r}")
            if expected == (int,) and (isinstance(value, bool) or value < 0):
                raise ValueError(f"{name} is {value!r}")
        extra = set(data) - set(cls.__dataclass_fields__)
        if extra:
            raise ValueError(f"unknown field(s) {', '.join(sorted(extra))}")
        return cls(**data)


def rng_states() -> dict[str, Any]:
    """The global random states SB3 training draws from."""
    import torch  # here, not at the top: the command line imports this module without torch

    return {
        "numpy": np.random.get_state(),  # noqa: NPY002 (SB3 seeds and uses the global state)
        "python": random.getstate(),
        "torch": torch.get_rng_state(),
    }


def set_rng_states(states: dict[str, Any]) -> None:
    """Restore what :func:`rng_states` returned."""
    import torch

    np.random.set_state(states["numpy"])  # noqa: NPY002
    random.setstate(states["python"])
    torch.set_rng_state(states["torch"])


def save_checkpoint(model: Any, folder: Path, state: TrainingState) -> Path:
    """Write a complete checkpoint of ``model`` and ``state`` under ``folder`` (``checkpoints/``).

    Returns:
        The new checkpoint's folder.
    """
    folder.mkdir(parents=True, exist_ok=True)
    state.num_timesteps = int(model.num_timesteps)
    name = f"{STEP_PREFIX}{state.num_timesteps:012d}"
    final = folder / name
    tmp = folder / f".{name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    files = CheckpointDir(tmp)
    try:
        with files.model.open("wb") as f:
            model.save(f)
        with files.replay_buffer.open("wb") as f:
            model.save_replay_buffer(f)
        with files.rng.open("wb") as f:
            pickle.dump(rng_states(), f)
        files.state.write_text(state.to_json(), encoding="utf-8")
        if final.exists():  # same step written twice (e.g. a periodic and a phase-end checkpoint)
            shutil.rmtree(final)
        tmp.rename(final)
    except BaseException:  # an error or an interrupt: leave no temporary folder behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for old in complete_checkpoints(folder)[:-KEEP]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def complete_checkpoints(folder: Path) -> list[Path]:
    """Complete checkpoint folders, oldest first (temporary folders are hidden, never listed)."""
    if not folder.is_dir():
        return []
    found = [p for p in folder.iterdir() if p.name.startswith(STEP_PREFIX) and p.is_dir()]
    return sorted(p for p in found if CheckpointDir(p).state.is_file())


#: Prefix of a checkpoint that a resume could not read and passed over: kept to look at, never
#: loaded nor counted among the :data:`KEEP` newest again.
UNUSABLE_PREFIX = "unusable-"


def set_aside(checkpoint: Path) -> Path:
    """Rename an unreadable checkpoint that a resume passed over to ``unusable-step-N``: the
    resumed run's timeline no longer goes through it, and it must not take the place of one of
    the two usable checkpoints kept."""
    target = checkpoint.with_name(UNUSABLE_PREFIX + checkpoint.name)
    if target.exists():
        shutil.rmtree(target)
    return checkpoint.rename(target)


def latest_checkpoint(folder: Path) -> Path:
    """The newest complete checkpoint.

    Raises:
        CheckpointError: when there is none.
    """
    found = complete_checkpoints(folder)
    if not found:
        raise CheckpointError(f"{folder}: no complete checkpoint to resume from")
    return found[-1]


def read_state(checkpoint: Path) -> TrainingState:
    """The training state of a checkpoint folder."""
    try:
        return TrainingState.from_json(CheckpointDir(checkpoint).state.read_text(encoding="utf-8"))
    except (OSError, ValueError, TypeError) as exc:
        raise CheckpointError(f"{CheckpointDir(checkpoint).state}: unreadable ({exc})") from None


def read_rng(checkpoint: Path) -> dict[str, Any]:
    """The random states of a checkpoint folder."""
    try:
        with CheckpointDir(checkpoint).rng.open("rb") as f:
            states = pickle.load(f)
        # Check by setting them on a copy of the current states, then putting those back.
        current = rng_states()
        set_rng_states(states)
        set_rng_states(current)
        return states
    except Exception as exc:  # a damaged pickle raises many kinds
        raise CheckpointError(f"{CheckpointDir(checkpoint).rng}: unreadable ({exc})") from None
