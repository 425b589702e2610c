"""Checkpoints: everything needed to continue a run exactly where it stopped.

A checkpoint is a folder ``checkpoints/step-<num_timesteps>/`` holding:

* ``model.zip``: the SB3 model (weights, optimizer state, step counters, ``ep_info_buffer``);
* ``replay_buffer.pkl``: the replay buffer with its priorities (the rows it has not filled
  yet left out: :func:`save_replay_buffer`), and
  ``replay_buffer.pkl.sha256``, its SHA-256 as written: a resume refuses a buffer that changed
  since (:func:`check_replay_buffer`; a flipped byte could otherwise load as NaN observations);
* ``rng.pkl``: the numpy, Python and torch random states;
* ``state.json``: the harness's own position (:class:`TrainingState`), with the list of the
  checkpoint's guard files (``guards``: the ``.sha256``, ``config.yaml``);
* ``config.yaml``: the run's config it was made with; a resume refuses a run whose
  ``config.yaml`` has been edited since (:func:`check_config`).

A guard file that ``state.json`` lists but the folder lacks makes the checkpoint damaged
(:func:`check_guards`): deleting it must not switch its check off. Checkpoints written before
``state.json`` listed them (no ``guards``) are checked with what they have: the ``.sha256`` and
``config.yaml`` when there, nothing when not, as they were written.

It is written into a hidden temporary folder and renamed into place only when complete, and older
checkpoints are deleted only after that, so the last good checkpoint survives a crash or a
``kill -9`` at any moment. The newest complete folder is the one a resume loads.
"""

from __future__ import annotations

import hashlib
import json
import pickle
import random
import shutil
import sys
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from harness.config.loading import config_from_dict, parse_yaml
from harness.config.schema import ConfigError, ExperimentConfig
from harness.results.rundir import CheckpointDir, RunDir, RunDirError

T = TypeVar("T")

STEP_PREFIX = "step-"
KEEP = 2  # checkpoints kept: the newest and the one before it

#: The guard files of a checkpoint, as ``state.json`` lists them (:attr:`TrainingState.guards`).
SHA256_GUARD = CheckpointDir(Path()).replay_buffer_sha256.name
CONFIG_GUARD = CheckpointDir(Path()).config.name
GUARDS = (SHA256_GUARD, CONFIG_GUARD)


class CheckpointError(RuntimeError):
    """A missing or unreadable checkpoint, with a one-line message."""


class ConfigChangedError(CheckpointError):
    """The run's config is not the one its checkpoint was made with: no checkpoint of the run
    can be resumed with it (an older one is no fallback)."""


#: Fields of ``state.json`` that checkpoints written before them lack, with their value then.
OPTIONAL_STATE_FIELDS: dict[str, Any] = {"pending_eval": None, "guards": None}


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
    pending_eval: int | None = None
    """The step of an in-training evaluation that a signal abandoned (a resume runs it first);
    ``None`` when none was. Optional in ``state.json`` (older checkpoints lack it)."""
    guards: list[str] | None = None
    """The files of the checkpoint that guard the others, as :func:`save_checkpoint` wrote them
    (``replay_buffer.pkl.sha256``, ``config.yaml``): a resume treats a missing one as damage
    (:func:`check_guards`). ``None`` in checkpoints written before ``state.json`` listed them
    (optional in ``state.json``)."""

    def to_json(self) -> str:
        data = asdict(self)
        data["best_eval"] = None if not np.isfinite(self.best_eval) else self.best_eval
        return json.dumps(data, indent=2)

    @classmethod
    def from_json(cls, text: str) -> TrainingState:
        """Parse ``state.json``; every field must be there with its type (but those of
        :data:`OPTIONAL_STATE_FIELDS`, which older checkpoints lack).

        Raises:
            ValueError: naming the field.
        """
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError("not a JSON object")
        if data.get("best_eval") is None:
            data["best_eval"] = float("-inf")
        for name, default in OPTIONAL_STATE_FIELDS.items():
            data.setdefault(name, default)
        types = {
            "best_eval": (int, float),
            "finished": (bool,),
            "pending_eval": (int, type(None)),
            "guards": (list, type(None)),
        }
        for name in cls.__dataclass_fields__:
            value = data.get(name)
            expected = types.get(name, (int,))
            if name not in data or not isinstance(value, expected):
                raise ValueError(f"{name} is {value!r}")
            if name == "guards" and value is not None and any(g not in GUARDS for g in value):
                raise ValueError(f"{name} is {value!r}")
            counter = int in expected and float not in expected and value is not None
            if counter and (isinstance(value, bool) or value < 0):
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


def save_checkpoint(
    model: Any, folder: Path, state: TrainingState, config: str | None = None
) -> Path:
    """Write a complete checkpoint of ``model`` and ``state`` under ``folder`` (``checkpoints/``),
    with ``config`` (the run's config as YAML, :meth:`ExperimentConfig.to_yaml`) when given.

    Returns:
        The new checkpoint's folder.
    """
    folder.mkdir(parents=True, exist_ok=True)
    state.num_timesteps = int(model.num_timesteps)
    # Listed in state.json, so that a guard file deleted later reads as damage, not as a
    # checkpoint written before it existed.
    state.guards = [SHA256_GUARD] + ([CONFIG_GUARD] if config is not None else [])
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
            save_replay_buffer(model, f)
        files.replay_buffer_sha256.write_text(
            f"{file_sha256(files.replay_buffer)}  {files.replay_buffer.name}\n", encoding="utf-8"
        )
        with files.rng.open("wb") as f:
            pickle.dump(rng_states(), f)
        files.state.write_text(state.to_json(), encoding="utf-8")
        if config is not None:
            files.config.write_text(config, encoding="utf-8")
        if final.exists():  # same step written twice (e.g. a periodic and a phase-end checkpoint)
            shutil.rmtree(final)
        tmp.rename(final)
    except BaseException:  # an error or an interrupt: leave no temporary folder behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for old in complete_checkpoints(folder)[:-KEEP]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def _row_arrays(state: dict[str, Any]) -> list[tuple[str, Any, Any, int]]:
    """``(attribute, key, array, rows kept)`` for each array (numpy or torch) of a buffer's
    pickled ``state`` indexed by its rows (first length ``buffer_size``) or by its flat slots
    (``buffer_size * n_envs``, the priorities), directly or in a dict attribute."""
    rows, envs, pos = state["buffer_size"], state["n_envs"], state["pos"]
    found = []
    for name, value in state.items():
        items = value.items() if isinstance(value, dict) else [(None, value)]
        for key, array in items:
            shape = getattr(array, "shape", None)
            if not shape or not hasattr(array, "__getitem__"):
                continue
            if shape[0] == rows:
                found.append((name, key, array, pos))
            elif shape[0] == rows * envs:
                found.append((name, key, array, pos * envs))
    return found


def _all_equal(rows: Any, value: Any, chunk: int = 1024) -> bool:
    """Whether every entry of ``rows`` (numpy or torch) equals ``value``, compared ``chunk``
    rows at a time (a whole comparison would allocate a mask as large as the buffer)."""
    return all(bool((rows[i : i + chunk] == value).all()) for i in range(0, rows.shape[0], chunk))


class _BufferPickler(pickle.Pickler):
    """Pickles ``buffer`` as :func:`restore_replay_buffer` of its state without the rows it has
    not filled (see :func:`save_replay_buffer`); everything else as pickle does."""

    def __init__(self, file: Any, buffer: Any) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self._buffer = buffer

    def reducer_override(self, obj: Any) -> Any:
        if obj is not self._buffer:
            return NotImplemented
        # A harness buffer (harness.sb3.replay.Replay) gives its state with the
        # tensors where they are, and moves them to the host after the cut: only kept rows travel.
        on_device = hasattr(obj, "stored_state")
        if on_device:
            state = obj.stored_state()
        else:
            reduced = obj.__reduce_ex__(pickle.HIGHEST_PROTOCOL)
            state = dict(reduced[2])  # the attributes, as the buffer's class pickles them
        cut = []
        if not state["full"]:
            for name, key, array, keep in _row_arrays(state):
                tail = array[keep:]
                if tail.shape[0] == 0 or not _all_equal(tail, tail.reshape(-1)[0]):
                    continue  # nothing to leave out, or rows written before a reset
                head = array[:keep]
                if hasattr(head, "clone") and head.device.type == "cpu":
                    head = head.clone()  # torch pickles a view's whole storage
                # (A view on a GPU is copied alone to the host by host_state.)
                # (A numpy view pickles its own bytes, written from where they are: protocol 5.)
                if key is None:
                    state[name] = head
                else:
                    state[name] = {**state[name], key: head}
                cut.append((name, key, array.shape[0], tail.reshape(-1)[0].item()))
        if on_device:
            state = obj.host_state(state)
        return restore_replay_buffer, (type(obj), state, cut)


def save_replay_buffer(model: Any, file: Any) -> None:
    """Pickle ``model``'s replay buffer as SB3's ``save_replay_buffer`` does, without the rows it
    has not filled yet: a 200k-transition team-map buffer is 1.7 GiB allocated, written whole
    however few transitions it holds. An array is cut only where every row past the stored ones
    holds one value (what it was made with: zeros, or the -1 of unlabelled decisions), and the
    pickle rebuilds it whole on loading (:func:`restore_replay_buffer`): SB3's
    ``load_replay_buffer`` and a plain ``pickle.load`` give a buffer equal to the saved one."""
    _BufferPickler(file, model.replay_buffer).dump(model.replay_buffer)


def restore_replay_buffer(
    cls: type, state: dict[str, Any], cut: list[tuple[str, Any, int, Any]]
) -> Any:
    """A buffer of class ``cls`` from the ``state`` :func:`save_replay_buffer` pickled, each cut
    array ``(attribute, key, length, value)`` made whole again with the value its left-out rows
    held. (Named in checkpoint files: keep its name and arguments.)"""
    for name, key, length, fill in cut:
        head = state[name] if key is None else state[name][key]
        shape = (length, *head.shape[1:])
        if hasattr(head, "clone"):  # a tensor (on the CPU, as the device buffer pickles them)
            import torch

            whole = torch.full(shape, fill, dtype=head.dtype, device=head.device)
        elif fill == 0:  # pages the system maps only when written, as SB3 allocates them
            whole = np.zeros(shape, dtype=head.dtype)
        else:
            whole = np.full(shape, fill, dtype=head.dtype)
        whole[: head.shape[0]] = head
        if key is None:
            state[name] = whole
        else:
            state[name][key] = whole
    buffer = cls.__new__(cls)
    setstate = getattr(buffer, "__setstate__", None)  # the device buffer's moves its tensors
    if setstate is not None:
        setstate(state)
    else:
        buffer.__dict__.update(state)
    return buffer


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, in hex (read in 1 MiB pieces: a buffer may be gigabytes)."""
    digest = hashlib.sha256()
    with path.open("rb") as f:
        while piece := f.read(1 << 20):
            digest.update(piece)
    return digest.hexdigest()


def check_guards(checkpoint: Path, state: TrainingState) -> None:
    """Refuse a checkpoint that lacks a guard file its ``state.json`` says was written (a
    deleted ``.sha256`` would load the buffer unchecked, a deleted ``config.yaml`` would let an
    edited config through).

    Raises:
        CheckpointError: one line naming the missing file (the damaged-checkpoint path: a
            resume falls back to the older checkpoint, or refuses).
    """
    files = CheckpointDir(checkpoint)
    paths = {SHA256_GUARD: files.replay_buffer_sha256, CONFIG_GUARD: files.config}
    for guard in state.guards or ():
        if not paths[guard].is_file():
            raise CheckpointError(
                f"{paths[guard]}: missing (written with the checkpoint, as its state.json "
                "says; damaged)"
            )


def check_inside_the_run(checkpoint: Path) -> None:
    """Refuse a checkpoint whose folder or any of its files lead out of its run folder (a link
    in a downloaded run; :meth:`CheckpointDir.check_inside`, the rule of every folder's files):
    its pickles, state and config are read only from the folder named on the command line.

    Raises:
        CheckpointError: one line naming the file (a resume falls back to the older
            checkpoint, or refuses).
    """
    try:
        CheckpointDir(checkpoint).check_inside()  # rundir's rule, for each of its files
    except RunDirError as exc:  # a link out, or a link loop
        raise CheckpointError(str(exc)) from None


def check_replay_buffer(checkpoint: Path) -> None:
    """Check ``replay_buffer.pkl`` against the SHA-256 stored beside it when the checkpoint was
    written; a checkpoint without the stored hash passes (one written before checkpoints kept
    it: :func:`check_guards` refuses the others first).

    Raises:
        CheckpointError: one line naming the file, when the hash differs or cannot be read.
    """
    files = CheckpointDir(checkpoint)
    stored_file = files.replay_buffer_sha256
    if not stored_file.exists():
        return
    try:
        fields = stored_file.read_text(encoding="utf-8").split()
        actual = file_sha256(files.replay_buffer)
    except (OSError, ValueError) as exc:  # UnicodeDecodeError is a ValueError
        raise CheckpointError(f"{files.replay_buffer}: unreadable ({exc})") from None
    stored = fields[0].lower() if fields else ""
    if len(stored) != 64 or any(c not in "0123456789abcdef" for c in stored):
        raise CheckpointError(f"{stored_file}: unreadable (not a SHA-256)")
    if actual != stored:
        raise CheckpointError(
            f"{files.replay_buffer}: unreadable (damaged: its SHA-256 is not the one stored in "
            f"{stored_file.name} when the checkpoint was written)"
        )


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


def newest_readable(folder: Path, load: Callable[[Path], T]) -> tuple[Path, T]:
    """The newest complete checkpoint under ``folder`` that ``load`` reads back whole, with what
    it read; when the newest cannot be used, the line says why and which older one is used.

    Raises:
        CheckpointError: when none reads back whole (the reasons of each).
        ConfigChangedError: at once (an older checkpoint is no fallback for an edited config).
    """
    found = complete_checkpoints(folder)
    if not found:
        raise CheckpointError(f"{folder}: no complete checkpoint to resume from")
    problems: list[str] = []
    for checkpoint in reversed(found):
        try:
            value = load(checkpoint)
        except ConfigChangedError:
            raise
        except CheckpointError as exc:
            problems.append(str(exc))
            continue
        if problems:
            print(
                f"harness: {'; '.join(problems)}; resuming from the older {checkpoint.name}",
                file=sys.stderr,
            )
        return checkpoint, value
    raise CheckpointError("; ".join(problems))


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
    """The training state of a checkpoint folder (none of whose files leads out of its run:
    :func:`check_inside_the_run`)."""
    check_inside_the_run(checkpoint)
    try:
        return TrainingState.from_json(CheckpointDir(checkpoint).state.read_text(encoding="utf-8"))
    except (OSError, ValueError, TypeError) as exc:
        raise CheckpointError(f"{CheckpointDir(checkpoint).state}: unreadable ({exc})") from None


def read_rng(checkpoint: Path) -> dict[str, Any]:
    """The random states of a checkpoint folder (as :func:`read_state`, inside its run)."""
    check_inside_the_run(checkpoint)
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


#: Keys of a run's config that may change between a checkpoint and its resume: how the run uses
#: this machine, not what it trains.
MAY_CHANGE = frozenset(
    {"algo.device", "algo.threads", "vec.backend", "vec.num_cpus", "checkpoint.every"}
)


def read_checkpoint_config(checkpoint: Path) -> dict[str, Any] | None:
    """The config a checkpoint was made with, defaults filled in as today's schema fills them
    (as written when today's schema no longer takes it); ``None`` for a checkpoint written
    before checkpoints kept their config.

    Raises:
        CheckpointError: when the file is there but unreadable, or a checkpoint file leads out
            of the run (:func:`check_inside_the_run`).
    """
    check_inside_the_run(checkpoint)
    path = CheckpointDir(checkpoint).config
    if not path.is_file():
        return None
    try:
        raw = parse_yaml(path.read_text(encoding="utf-8"), str(path))
    except (OSError, ValueError) as exc:  # ConfigError and UnicodeDecodeError are ValueErrors
        raise CheckpointError(f"{path}: unreadable ({exc})") from None
    if not isinstance(raw, dict):
        raise CheckpointError(f"{path}: unreadable (not a mapping)")
    try:
        with warnings.catch_warnings():  # the run's own config.yaml has said them already
            warnings.simplefilter("ignore")
            return config_from_dict(raw, str(path)).model_dump(mode="json")
    except ConfigError:
        return raw


def config_changes(old: Any, new: Any, key: str = "") -> list[tuple[str, Any, Any]]:
    """``(key, old value, new value)`` for each key of two config dumps that differs, dotted as
    ``--set`` writes it (phases by name); keys of :data:`MAY_CHANGE` are left out. Phases added,
    removed, renamed or reordered are one change of ``phases`` (their names)."""
    named = [
        isinstance(v, list) and all(isinstance(i, dict) and "name" in i for i in v)
        for v in (old, new)
    ]
    if all(named):
        old_names, new_names = [i["name"] for i in old], [i["name"] for i in new]
        if old_names != new_names:
            return [(key, old_names, new_names)]
        return [
            change
            for o, n in zip(old, new, strict=True)
            for change in config_changes(o, n, f"{key}.{o['name']}")
        ]
    if isinstance(old, dict) and isinstance(new, dict):
        changes = []
        for name in dict.fromkeys([*old, *new]):
            sub = f"{key}.{name}" if key else str(name)
            if sub not in MAY_CHANGE:
                changes += config_changes(old.get(name), new.get(name), sub)
        return changes
    return [] if old == new else [(key, old, new)]


def _short(value: Any, limit: int = 40) -> str:
    text = "(none)" if value is None else json.dumps(value, separators=(", ", ": "))
    return text if len(text) <= limit else text[: limit - 3] + "..."


def check_config(checkpoint: Path, config: ExperimentConfig) -> None:
    """Refuse ``config`` (the run's ``config.yaml`` now) unless it is the one ``checkpoint`` was
    made with, but for :data:`MAY_CHANGE`; a checkpoint without its config passes (one written
    before checkpoints kept it: :func:`check_guards` refuses the others first).

    Raises:
        ConfigChangedError: one line naming the keys that differ, with both values.
        CheckpointError: when the checkpoint's copy of the config is unreadable.
    """
    stored = read_checkpoint_config(checkpoint)
    if stored is None:
        return
    changes = config_changes(stored, config.model_dump(mode="json"))
    if not changes:
        return
    shown = "; ".join(f"{key}: {_short(old)} -> {_short(new)}" for key, old, new in changes[:6])
    more = f"; and {len(changes) - 6} more" if len(changes) > 6 else ""
    run = RunDir(checkpoint.parent.parent)
    raise ConfigChangedError(
        f"{run.config}: changed since {checkpoint.name} was written ({shown}{more}); a run "
        "resumes only with the config it was made with: put it back, or start a new run"
    )
