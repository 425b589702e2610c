"""The run directory: the one module that knows where a run's files live.

``runs/<name>-<UTC timestamp>/`` holds::

    config.yaml        the fully resolved config
    command.txt        the command line that started (or resumed) the run
    tb/                TensorBoard events (and progress.csv, SB3's CSV of the same scalars)
    checkpoints/       latest checkpoint (model, replay buffer, training state)
    episodes.csv       one row per finished training episode
    evaluations.csv    one row per evaluation during training (validation episodes)
    model.zip          the final model
    best_model.zip     the model with the best periodic evaluation so far
    eval.json          written by ``harness eval`` (eval-*.json: other models, a checkpoint's
                       too, and settings, see :func:`result_filename`)
    tune.json          written by ``harness tune``
    reference.json     only in a folder made by ``harness export``: marks a reference, whose
                       eval/tune/render results go to ``runs/evals/<name>/`` instead

An existing run directory is never overwritten, and every file that matters is written
atomically (a temporary file in the same folder, then a rename). Every file read from or written
into a run (or a checkpoint, group, sweep or reference folder) lies inside it, links resolved:
:func:`inside` is the one rule, and :class:`RunDir`'s paths ask it.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import hashlib
import io
import json
import math
import os
import re
import shlex
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from harness.config.schema import ExperimentConfig


def log_header(path: str | Path) -> tuple[str, ...]:
    """The columns that a CSV log's header line names (none when it has none or cannot be
    read: the reader then names the problem). Each task logs its own columns
    (:attr:`harness.tasks.base.Task.episode_columns`): the header says whose a log is."""
    try:
        with Path(path).open(encoding="utf-8", newline="") as f:
            return tuple(next(csv.reader([f.readline()]), []))
    except (OSError, UnicodeDecodeError, csv.Error):
        return ()


#: Marks a folder made by ``harness export`` (a shipped reference policy): commands read it but
#: never write into it (see :func:`results_folder`).
REFERENCE_MARKER = "reference.json"

#: Where ``harness eval``/``tune``/``render`` write the results of a reference policy, per
#: reference name (relative to the current directory, like ``runs/``).
REFERENCE_RESULTS = Path("runs") / "evals"


def is_reference(folder: Path) -> bool:
    """Whether ``folder`` is an exported reference (it holds :data:`REFERENCE_MARKER`)."""
    return (Path(folder) / REFERENCE_MARKER).is_file()


def results_folder(run_dir: Path) -> Path:
    """Where results about a run's policy go: the run folder itself, or for a reference
    ``runs/evals/<name>/``, so that evaluating a shipped reference never changes its files."""
    if is_reference(run_dir):
        return REFERENCE_RESULTS / Path(run_dir).resolve().name
    return Path(run_dir)


def leads_outside(path: Path, root: Path) -> bool:
    """Whether ``path``, links resolved, lies outside ``root``: pickles are loaded only from
    inside the folder named on the command line, and a link in a downloaded folder would name
    another file. A path that does not exist yet counts too: a folder above it may be a link out
    (``tb/`` linked elsewhere), and a dangling link would create its target.

    Raises:
        RunDirError: for a link loop, naming the path.
    """
    try:
        return not Path(path).resolve().is_relative_to(Path(root).resolve())
    except (OSError, RuntimeError) as exc:  # a link loop
        raise RunDirError(f"{path}: not a usable file ({exc})") from None


class RunDirError(OSError):
    """A run folder that cannot be created or read, with a one-line message."""


class LinkOutError(RunDirError):
    """A file of a run, checkpoint, group, sweep or reference folder that leads out of it (it, or
    a folder above it inside the folder, is a link elsewhere): refused, never read or written."""


def inside(path: Path, root: Path, what: str = "the run folder") -> Path:
    """The one rule for every file the harness reads from or writes into one of its folders (a
    run, a checkpoint, a seed group, a sweep, a reference, ``runs/evals/<name>/``): ``path``,
    links resolved, lies inside ``root``. A link whose target is inside is fine; one leading out
    would make a command load a pickle or a config (code) nobody named, or write over a file
    elsewhere, so it is refused before anything is read or written. Only what the user names on
    the command line is taken from elsewhere.

    Args:
        path: The file (or folder) of ``root`` about to be read or written.
        root: The folder it belongs to.
        what: ``root`` in words, for the message (``"the group folder"``).

    Returns:
        ``path``, unchanged.

    Raises:
        LinkOutError: one line naming the file and where it leads.
        RunDirError: for a link loop.
    """
    path = Path(path)
    if leads_outside(path, root):
        raise LinkOutError(
            f"{path} leads outside {what} {root} (to {os.path.realpath(path)}): a folder's "
            "files live inside it; nothing was read from it or written to it"
        )
    return path


def check_output_file(path: Path, flag: str) -> None:
    """Fail early, before any work, if a file cannot be written at ``path``.

    Checks that no part of the path is an existing file, that ``path`` is not a folder, and that
    the nearest existing folder accepts a new file (by creating and removing a temporary one: it
    also catches read-only file systems, which permission bits do not show to root). Nothing is
    left behind; missing folders are created only when the file is written.

    Raises:
        RunDirError: naming ``flag`` and the path.
    """
    path = Path(path)
    if path.is_dir():
        raise RunDirError(f"{flag} {path}: is a folder, not a file name")
    ancestor = path.parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise RunDirError(f"{flag} {path}: {ancestor} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=ancestor):
            pass
    except OSError as exc:
        raise RunDirError(f"{flag} {path}: cannot write in {ancestor} ({exc.strerror})") from None


#: Episodes of a standard evaluation (the thesis tested on 100).
STANDARD_EPISODES = 100

#: Files a reference made by ``harness export`` copies from its run (besides its model).
REFERENCE_FILES = ("config.yaml", "command.txt", "episodes.csv", "evaluations.csv", "tune.json")


#: Longest readable part of a result's file name (a file name may take 255 bytes).
READABLE_LIMIT = 100

#: The readable name of a checkpoint's model in a result's name: ``step-N`` for the model
#: ``checkpoints/step-N/model``.
_CHECKPOINT_MODEL = re.compile(r"checkpoints/(step-[0-9]+)/model")


def result_filename(
    kind: str,
    overrides: Sequence[str],
    model: str = "model",
    episodes: int = STANDARD_EPISODES,
    seed_changed: str | None = None,
) -> str:
    """The file ``harness eval`` (``kind="eval"``) or ``harness tune`` (``"tune"``) saves to.

    ``eval.json`` is the standard evaluation: the run's ``model.zip``, :data:`STANDARD_EPISODES`
    episodes with the config's ``eval.seed`` (``tune.json``: the run's ``model.zip``). Anything
    else gets its own file, e.g. ``eval-best_model.json``, ``eval-10ep.json``,
    ``eval-seed7.json``, ``eval-step-000000001000.json`` (the checkpoint's model
    ``checkpoints/step-000000001000/model``) or ``eval-env.max_steps-500.json`` (``--set
    env.max_steps=500``), so no result replaces another. That readable name is the whole name
    only when it reads back as exactly what was evaluated (:func:`_read_back`); when it does
    not (e.g. a ``/`` or ``-`` in a value, a name over :data:`READABLE_LIMIT` characters cut short),
    ``~`` and a short hash of the exact model, episodes, seed and overrides follow it, e.g.
    ``eval-env.map-maps-a-b.txt~904d8dba.json``: ``maps/a-b.txt`` and ``maps/a/b.txt`` read
    the same but are two files. (A readable name without the hash has no ``~``, and two
    settings that read back the same are the same setting, so neither kind of name can stand
    for two settings.)

    Args:
        kind: ``"eval"``, ``"tune"`` or ``"against-POLICY"`` (:func:`against_filename`).
        overrides: The ``--set`` overrides.
        model: The model's path inside the run folder without ``.zip`` (``"model"``,
            ``"best_model"``, ``"checkpoints/step-000000001000/model"``).
        episodes: Number of episodes evaluated (``eval`` only).
        seed_changed: The seed, when it is not the config's ``eval.seed`` (``eval`` only).
    """
    checkpoint = _CHECKPOINT_MODEL.fullmatch(model)
    parts = [] if model == "model" else [checkpoint[1] if checkpoint else model]
    if episodes != STANDARD_EPISODES:
        parts.append(f"{episodes}ep")
    if seed_changed is not None:
        parts.append(f"seed{seed_changed}")
    parts += list(overrides)
    if not parts:
        return f"{kind}.json"
    return f"{kind}-{_slug(parts, (model, episodes, seed_changed, list(overrides)))}.json"


def _slug(
    parts: Sequence[str],
    exact: tuple[str, int, str | None, list[str]],
    limit: int = READABLE_LIMIT,
) -> str:
    """The readable name of ``parts`` (see :func:`result_filename`), with ``~`` and a short hash
    of ``exact`` (what was evaluated) after it unless it reads back as exactly that within
    ``limit`` characters."""
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "-", "_".join(parts)).strip("-")
    if len(slug) <= limit and _read_back(slug) == exact:
        return slug
    digest = hashlib.sha256(json.dumps(exact).encode("utf-8")).hexdigest()[:8]
    return f"{slug[:limit]}~{digest}"


#: The ``+`` before an ``--against-set`` part of a comparison's file name: no slug, no policy
#: name, no ``kind`` holds one, so the part after it is the baseline's settings and nothing else.
AGAINST_SET_MARK = "+"
#: Longest readable part of the ``--against-set`` part: with the evaluation's own (at most
#: :data:`READABLE_LIMIT` and a hash) and a seed group's ``group-`` before the name, a file name
#: stays well under the 255 bytes a file system takes.
AGAINST_SET_LIMIT = READABLE_LIMIT // 2


def against_filename(
    policy: str,
    overrides: Sequence[str],
    model: str = "model",
    episodes: int = STANDARD_EPISODES,
    seed_changed: str | None = None,
    against_set: Sequence[str] = (),
) -> str:
    """The file of ``harness eval --against POLICY``: the episode-by-episode comparison of a
    model with a written planner on the evaluation's episodes, named as that evaluation is
    (:func:`result_filename`) with ``against-POLICY`` for ``eval``: ``against-frontier_pocket.json``
    beside ``eval.json``, ``against-frontier_pocket-10ep.json`` beside ``eval-10ep.json``.

    ``against_set`` (``--against-set``: the overrides the baseline alone played under) follows
    after a ``+``, as a slug of its own (read back, or hashed, as the evaluation's ``--set``s
    are): ``against-rollout+eval.rollout.after-0.6.json``,
    ``against-rollout-10ep+eval.rollout.after-0.6.json``. The ``+`` keeps it apart from the
    evaluation's own ``--set``s (``--set X --against P`` is not ``--against P --against-set X``),
    and never replaces the plain ``against-POLICY*.json``."""
    name = result_filename(f"against-{policy}", overrides, model, episodes, seed_changed)
    if not against_set:
        return name
    exact = ("model", STANDARD_EPISODES, None, list(against_set))
    slug = _slug(against_set, exact, AGAINST_SET_LIMIT)
    return f"{name.removesuffix('.json')}{AGAINST_SET_MARK}{slug}.json"


def _read_back(slug: str) -> tuple[str, int, str | None, list[str]] | None:
    """What a readable name (:func:`result_filename`'s, without ``kind-`` and ``.json``) says
    was evaluated: ``(model, episodes, seed_changed, overrides)``, ``None`` when it cannot say.

    One fixed reading: a leading ``step-N_`` is a checkpoint's model; each ``-`` parts a key
    from its value; a value and the next key part at the ``_`` after which a top-level config
    key (``env``, ``eval``, ``seed``, ...) begins; before the first key,
    ``_``-separated, come the model, ``Nep`` and ``seedS``. A name is used bare only when this
    reading gives back its own setting, so that no two settings share a bare name.
    """
    model = "model"
    checkpoint = re.match(r"(step-[0-9]+)(?:_|$)", slug)
    if checkpoint:
        model, slug = f"checkpoints/{checkpoint[1]}/model", slug[checkpoint.end() :]
    head, *pieces = slug.split("-")
    overrides: list[str] = []
    prefix = head
    if pieces:
        prefix, key = _split_at_key(head) or ("", head)
        for piece in pieces[:-1]:
            split = _split_at_key(piece)
            if split is None:
                return None
            value, following = split
            overrides.append(f"{key}={value}")
            key = following
        overrides.append(f"{key}={pieces[-1]}")
    tokens = prefix.split("_") if prefix else []
    seed = None
    episodes = STANDARD_EPISODES
    if tokens and re.fullmatch(r"seed[0-9]+", tokens[-1]):
        seed = tokens.pop()[len("seed") :]
    if tokens and re.fullmatch(r"[0-9]+ep", tokens[-1]):
        episodes = int(tokens.pop()[: -len("ep")])
    if tokens:
        if model != "model":
            return None
        model = "_".join(tokens)
    return model, episodes, seed, overrides


def _split_at_key(text: str) -> tuple[str, str] | None:
    """``text`` parted at its first ``_`` after which a config key begins (its first part is a
    top-level key of the config), as ``(before, key)``; ``None`` when there is no such ``_``."""
    for at in (i for i, c in enumerate(text) if c == "_"):
        key = text[at + 1 :]
        if key.split(".", 1)[0] in ExperimentConfig.model_fields:
            return text[:at], key
    return None


@dataclass(frozen=True)
class CheckpointDir:
    """Paths of one checkpoint, ``checkpoints/step-<num_timesteps>/``."""

    path: Path

    @property
    def model(self) -> Path:
        return self.path / "model.zip"

    @property
    def replay_buffer(self) -> Path:
        return self.path / "replay_buffer.pkl"

    @property
    def replay_buffer_sha256(self) -> Path:
        """The SHA-256 of ``replay_buffer.pkl`` as written (none in checkpoints written before
        checkpoints kept it), in ``sha256sum``'s format."""
        return self.path / "replay_buffer.pkl.sha256"

    @property
    def rng(self) -> Path:
        return self.path / "rng.pkl"

    @property
    def state(self) -> Path:
        return self.path / "state.json"

    @property
    def config(self) -> Path:
        """The run's config as it was when the checkpoint was written (none in checkpoints
        written before checkpoints kept it)."""
        return self.path / "config.yaml"

    def check_inside(self) -> None:
        """Ask :func:`inside` of the checkpoint's folder and each of its files, against its run
        folder (``RUN/checkpoints/step-N/``: two folders up): a checkpoint is read only when
        all of it lies in its run.

        Raises:
            LinkOutError: naming the first file that leads out.
            RunDirError: for a link loop.
        """
        run = self.path.parent.parent
        for path in (
            self.path,
            self.model,
            self.replay_buffer,
            self.replay_buffer_sha256,
            self.rng,
            self.state,
            self.config,
        ):
            inside(path, run)


def unique_folder(root: str | Path, name: str, now: datetime | None = None) -> Path:
    """Make a new folder ``<root>/<name>-<UTC timestamp>`` (a run, a seed group, a sweep); two
    made in the same second get ``-1``, ``-2``, ... suffixes; an existing one is never reused.

    Raises:
        RunDirError: when ``root`` cannot be created or written.
    """
    stamp = (now or datetime.now(timezone.utc)).strftime("%Y%m%dT%H%M%SZ")
    root = Path(root)
    try:
        root.mkdir(parents=True, exist_ok=True)
        for attempt in range(1000):
            suffix = "" if attempt == 0 else f"-{attempt}"
            path = root / f"{name}-{stamp}{suffix}"
            try:
                path.mkdir()  # fails if it exists
            except FileExistsError:
                continue
            return path
    except OSError as exc:
        raise RunDirError(f"{root}: cannot create a run folder ({exc.strerror or exc})") from None
    raise RunDirError(f"{root}: too many runs named {name!r} in one second")


@dataclass(frozen=True)
class RunDir:
    """Paths of one run."""

    path: Path

    def inside(self, path: Path) -> Path:
        """``path`` once :func:`inside` allows it for this folder: every file of the folder that
        a command reads or writes is asked for here (the properties below ask for theirs).

        Raises:
            LinkOutError: for a path that leads outside the folder, in one line.
        """
        return inside(path, self.path)

    def _file(self, name: str) -> Path:
        """The folder's file ``name``, asked for through :meth:`inside`."""
        return self.inside(self.path / name)

    @property
    def config(self) -> Path:
        return self._file("config.yaml")

    @property
    def is_run(self) -> bool:
        """Whether the folder is a run's: it holds the run's ``config.yaml``, the first file a
        run writes (where the run stands: ``harness.training.state.run_state``), and is no
        checkpoint of one (:attr:`is_checkpoint`: a checkpoint keeps a copy of that file)."""
        return self.config.is_file() and not self.is_checkpoint

    @property
    def is_checkpoint(self) -> bool:
        """Whether the folder is a checkpoint of a run, ``RUN/checkpoints/step-N/``: its
        results and config belong to ``RUN`` (:attr:`checkpoint_of`)."""
        run = self.checkpoint_of
        return os.path.abspath(self.path.parent) == os.path.abspath(run.checkpoints) and (
            run.config.is_file()
        )

    @property
    def checkpoint_of(self) -> RunDir:
        """The run this folder would be a checkpoint of (two folders up)."""
        return RunDir(Path(os.path.normpath(self.path / os.pardir / os.pardir)))

    @property
    def command(self) -> Path:
        return self._file("command.txt")

    @property
    def tb(self) -> Path:
        return self._file("tb")

    @property
    def checkpoints(self) -> Path:
        return self._file("checkpoints")

    @property
    def episodes_csv(self) -> Path:
        return self._file("episodes.csv")

    @property
    def evaluations_csv(self) -> Path:
        return self._file("evaluations.csv")

    @property
    def model(self) -> Path:
        return self._file("model.zip")

    @property
    def best_model(self) -> Path:
        return self._file("best_model.zip")

    @property
    def eval_json(self) -> Path:
        """The standard evaluation (see :func:`result_filename`)."""
        return self._file("eval.json")

    @property
    def paths_png(self) -> Path:
        return self._file("paths.png")

    @property
    def reference_marker(self) -> Path:
        return self._file(REFERENCE_MARKER)

    def result(self, name: str) -> Path:
        """A file of this folder by its name: a result named by :func:`result_filename`, or
        one of :data:`REFERENCE_FILES`."""
        return self._file(name)

    def loaded_files(self) -> tuple[Path, ...]:
        """The files ``eval`` and ``tune`` load from the run (its config, model and best
        model), not yet asked for: a folder holding the run (a seed group) asks its own
        :func:`inside` of them first."""
        return tuple(self.path / name for name in ("config.yaml", "model.zip", "best_model.zip"))

    def check_files(self) -> None:
        """Ask :meth:`inside` of every file that training reads or writes in the run (its
        config, command, logs, models, ``.lock``, ``tb/`` and what it holds, ``checkpoints/``;
        each checkpoint is asked for its own files when it is read): ``harness run --resume``
        asks this first, so that a link out of the run stops it before any file changes.

        Raises:
            LinkOutError: naming the first file that leads out.
        """
        for name in (
            *("config.yaml", "command.txt", "episodes.csv", "evaluations.csv"),
            *("model.zip", "best_model.zip", ".lock", "checkpoints", "tb"),
        ):
            self._file(name)
        if self.tb.is_dir():
            for path in self.tb.iterdir():  # SB3's progress CSVs and TensorBoard's events
                self.inside(path)

    def model_named(self, name: str) -> Path:
        """A model zip of the run by its path without ``.zip`` (``"model"``, ``"best_model"``,
        ``"checkpoints/step-N/model"``: the names :func:`result_filename` takes).

        Raises:
            RunDirError: for a name that leaves the run folder (absolute, ``..``, or a link out
                of it): a model zip is a pickle, loaded only from inside the run named.
        """
        relative = Path(f"{name}.zip")
        if relative.is_absolute() or ".." in relative.parts:
            raise RunDirError(
                f"model {name!r}: not a model of {self.path} (model, best_model or "
                "checkpoints/step-N/model)"
            )
        return self.inside(self.path / relative)

    def progress_csv(self, resumes: int = 0) -> Path:
        """SB3's CSV log of the scalars (beside the TensorBoard events): ``progress.csv``, and
        ``progress-resume<N>.csv`` after the N-th resume (SB3's writer empties the file it
        opens)."""
        name = "progress.csv" if resumes == 0 else f"progress-resume{resumes}.csv"
        return self.inside(self.tb / name)

    def write_result(self, name: str, data: dict[str, Any]) -> Path:
        """Save a result JSON of this folder (:func:`result_filename`'s ``name``), atomically."""
        return write_json(self.result(name), data)

    def eval_file(self, name: str = "eval") -> Path:
        """An evaluation by its file stem: ``eval`` (the standard ``eval.json``) or another of
        :func:`result_filename`'s names, e.g. ``eval-env.map-random``.

        Raises:
            RunDirError: for a stem that is not an evaluation's name (no folders, no other file).
        """
        if name != "eval" and not (name.startswith("eval-") and "/" not in name):
            raise RunDirError(
                f"{name!r} is not an evaluation's name: 'eval' (eval.json) or 'eval-...' "
                "(eval-env.map-random.json and the like, as harness eval names them)"
            )
        return self._file(f"{name}.json")

    def eval_names(self) -> list[str]:
        """The evaluations this folder holds, by the stem :meth:`eval_file` takes (sorted)."""
        return sorted(
            p.stem for p in self.path.glob("eval*.json") if p.stem == "eval" or p.stem[4:5] == "-"
        )

    def read_eval(self, name: str = "eval") -> dict[str, Any] | None:
        """An evaluation (by default the standard ``eval.json``; see :meth:`eval_file`) as a
        JSON object, or ``None`` if there is none.

        Raises:
            RunDirError: when the file is there but is not a JSON object, naming it.
        """
        path = self.eval_file(name)
        if not path.is_file():
            return None
        try:
            data = json.loads(path.read_text(encoding="utf-8"), parse_int=_float_sized_int)
        except _NumberTooLarge as exc:
            raise RunDirError(f"{path}: the number {exc} is too large for an evaluation") from None
        except (OSError, ValueError) as exc:
            raise RunDirError(f"{path}: not a readable eval JSON ({exc})") from None
        if not isinstance(data, dict):
            raise RunDirError(f"{path}: expected a JSON object, got {type(data).__name__}")
        return data

    def read_curves(
        self, episode_column: str = "coverage", evaluation_column: str = "coverage_median"
    ) -> tuple[Curve, Curve | None]:
        """The training episodes' curve (``episodes.csv``: timesteps, ``episode_column``) and
        the in-training evaluations' (``evaluations.csv``: timesteps, ``evaluation_column``;
        ``None`` for a run made without them). The columns are the run's task's (the coverage
        env's by default).

        Raises:
            RunDirError: for a folder without ``episodes.csv``, or an empty one.
            ValueError: naming the file and line of anything that is not a curve.
        """
        episodes = self.episodes_csv
        if not episodes.is_file():
            raise RunDirError(f"{self.path}: not a run folder with episodes.csv")
        try:
            with episodes.open(newline="", encoding="utf-8") as f:
                if next(csv.reader(f), None) is None:
                    raise RunDirError(f"{episodes}: empty")
        except (UnicodeDecodeError, csv.Error):
            raise RunDirError(f"{episodes}: not a CSV text file") from None
        curve = read_episodes_csv(episodes, episode_column)
        if len(curve[0]) == 0:
            raise RunDirError(f"{episodes}: no finished episode yet")
        evals = self.evaluations_csv
        return curve, read_evaluations_csv(evals, evaluation_column) if evals.is_file() else None

    def write_reference_marker(self, origin: Path, model: str) -> None:
        """Mark this folder as a reference exported from run ``origin``'s model ``model``."""
        marker = {"exported_from": str(origin), "model": f"{model}.zip"}
        atomic_write_text(self.reference_marker, json.dumps(marker, indent=2) + "\n")

    @classmethod
    def create(cls, root: str | Path, name: str, now: datetime | None = None) -> RunDir:
        """Make a new ``<root>/<name>-<UTC timestamp>`` run folder; never reuse an existing one.

        Raises:
            RunDirError: when ``root`` cannot be created or written.
        """
        run = cls(unique_folder(root, name, now))
        try:
            run.tb.mkdir()
            run.checkpoints.mkdir()
        except OSError as exc:
            shutil.rmtree(run.path, ignore_errors=True)  # made just now: nothing else is in it
            raise RunDirError(
                f"{run.path}: cannot create a run folder ({exc.strerror}); removed it"
            ) from None
        return run

    @property
    def lock_file(self) -> Path:
        return self._file(".lock")

    @classmethod
    def made_names(cls) -> frozenset[str]:
        """The names a run folder holds from its making on, before anything is written into
        it: ``tb/`` and ``checkpoints/`` (:meth:`create`, :meth:`create_at`) and ``.lock``
        (:meth:`lock`)."""
        # Under "/" every path lies inside: no file of the current folder is asked about.
        blank = cls(Path(os.sep))
        return frozenset(p.name for p in (blank.tb, blank.checkpoints, blank.lock_file))

    @contextlib.contextmanager
    def lock(self, holder: str = "a run or resume") -> Iterator[None]:
        """Hold the run folder for this process: a second ``harness run --resume`` (or any other
        process training into this folder) is refused while this one lives.

        An OS lock (``flock``) on ``.lock``: the kernel releases it when the process ends, however
        it ends, so a lock left by a dead process is simply taken over. The file holds the
        holder's pid, for the message; ``holder`` says what holds such a folder (a sweep folder
        is held the same way: ``a sweep of this study``).

        Raises:
            RunDirError: when another live process holds the folder.
        """
        try:
            fd = os.open(self.lock_file, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise RunDirError(f"{self.path}: cannot lock the run folder ({exc.strerror})") from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "?"
                raise RunDirError(
                    f"{self.path}: in use by process {pid} ({holder} still going); "
                    "wait for it to end or stop it first"
                ) from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
            yield
        finally:
            os.close(fd)  # releases the lock

    @classmethod
    def create_at(cls, path: str | Path) -> RunDir:
        """Make the run folder ``path`` itself (a seed of a group, a trial of a sweep); it must not
        exist yet, or be empty.

        Raises:
            RunDirError: when it exists with files in it, or cannot be created.
        """
        path = Path(path)
        try:
            if path.exists() and (not path.is_dir() or any(path.iterdir())):
                raise RunDirError(f"{path}: already exists (a run folder is never reused)")
            path.mkdir(parents=True, exist_ok=True)
            run = cls(path)
            run.tb.mkdir()
            run.checkpoints.mkdir()
        except OSError as exc:
            if isinstance(exc, RunDirError):
                raise
            raise RunDirError(f"{path}: cannot create the run folder ({exc.strerror})") from None
        return run

    def note_command(self, note: str) -> None:
        """Append a ``# note`` line to ``command.txt`` (making it if it is missing)."""
        command = self.command
        before = command.read_text().rstrip("\n") + "\n" if command.is_file() else ""
        atomic_write_text(command, f"{before}# {note}\n")

    def write_command(self, args: Sequence[str]) -> None:
        """Append the ``harness`` command line with its arguments ``args`` (a resumed run gets a
        second line)."""
        with self.command.open("a", encoding="utf-8") as f:
            f.write(shlex.join(["harness", *args]) + "\n")


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Write a file through ``write(tmp_path)`` then rename it into place.

    A crash, an error in ``write`` or a full disk leaves either the old file or the new one,
    never a half-written file, and no temporary file. Every picture, JSON and CSV the harness
    writes goes through here. A ``path`` that is a link is replaced by the new file, never
    written through (the file it named is left as it was).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp_path = Path(tmp)
    try:  # from the file's creation on, so that a Ctrl-C at any point leaves no temporary file
        os.close(fd)
        os.chmod(tmp_path, 0o644)  # mkstemp makes 0600; a run's files are ordinary readable files
        write(tmp_path)
        with tmp_path.open("rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp_path, path)
    except OSError as exc:  # a full disk: named by the file being written, not the temporary one
        if exc.filename in (tmp, str(tmp_path)):
            exc.filename = str(path)
        raise
    finally:
        tmp_path.unlink(missing_ok=True)


def write_figure(figure: Any, path: Path, **savefig: Any) -> Path:
    """Save a matplotlib figure whole or not at all (:func:`atomic_write`): ``savefig`` to a
    temporary file beside ``path``, then renamed over it, so a full disk or an error while
    drawing leaves the old picture as it was. The format comes from ``path``'s suffix unless
    ``savefig`` names one (the temporary file's own suffix is ``.tmp``).

    Returns:
        ``path``.
    """
    path = Path(path)
    savefig.setdefault("format", path.suffix.lstrip(".").lower() or "png")
    atomic_write(path, lambda tmp: figure.savefig(tmp, **savefig))
    return path


def append_csv_rows(path: Path, columns: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    """Append ``rows`` to a run's CSV log, writing the ``columns`` header first if it is new.

    The file is opened per call (once per round of episodes or per evaluation): nothing stays
    open if training dies, and every row written is on disk.
    """
    new = not path.exists() or path.stat().st_size == 0
    with path.open("a", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        if new:
            writer.writerow(columns)
        writer.writerows(rows)


def atomic_write_text(path: Path, text: str) -> None:
    """Atomically write a text file."""
    atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


class LogMismatchError(ValueError):
    """A run's CSV log that disagrees with the checkpoint a resume restores."""


def read_csv_log(path: Path, columns: Sequence[str]) -> tuple[list[list[str]], int]:
    """The rows of a run's CSV log, without a torn last line.

    A kill while a row was being appended leaves a last line without its newline (or with fewer
    fields): that row is after any checkpoint (checkpoints are written between appends), so it
    is left out. Anything else that is not a row of ``columns`` is an error.

    Returns:
        The rows (as text fields) and the number of torn lines dropped (0 or 1).

    Raises:
        LogMismatchError: naming the file and line.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise LogMismatchError(f"{path}: not a text file") from None
    lines = text.splitlines(keepends=True)
    torn = 0
    if lines and not lines[-1].endswith("\n"):
        lines, torn = lines[:-1], 1
    try:
        rows = list(csv.reader(lines))
    except csv.Error as exc:
        raise LogMismatchError(f"{path}: not a CSV log ({exc})") from None
    if not rows:
        return [], torn
    if tuple(rows[0]) != tuple(columns):
        raise LogMismatchError(f"{path}: line 1: expected the header {','.join(columns)}")
    for number, row in enumerate(rows[1:], start=2):
        if len(row) != len(columns):
            raise LogMismatchError(f"{path}: line {number}: {len(row)} fields, not {len(columns)}")
    return rows[1:], torn


def rewind_logs(
    run: RunDir,
    next_episode: int,
    num_timesteps: int,
    columns: tuple[Sequence[str], Sequence[str]] | None = None,
) -> tuple[int, int]:
    """Drop from ``episodes.csv`` and ``evaluations.csv`` what was logged after a checkpoint.

    ``columns``: the logs' columns (the run's task's, ``episodes.csv``'s and
    ``evaluations.csv``'s: another header is a damaged log); ``None``: the headers they have.

    Only rows provably after the checkpoint go: episodes numbered ``next_episode`` or later whose
    ``timesteps`` exceed ``num_timesteps``, and evaluations after ``num_timesteps``. If the logs
    disagree with the checkpoint (rows missing before it, or a row that should go but finished
    before it: a damaged log or ``state.json``), nothing is changed and an error says why.

    Returns:
        Episode and evaluation rows dropped.

    Raises:
        LogMismatchError: with one line naming the file, the row and the checkpoint.
    """
    plans: list[tuple[Path, Sequence[str], list[list[str]], int]] = []
    # (each task logs its own columns: the caller says which)
    episode_columns, evaluation_columns = columns or (
        log_header(run.episodes_csv),
        log_header(run.evaluations_csv),
    )
    episodes, torn = (
        read_csv_log(run.episodes_csv, episode_columns) if run.episodes_csv.exists() else ([], 0)
    )
    keep = []
    for row in episodes:
        try:
            number, steps = int(row[0]), int(row[2])
        except ValueError:
            raise LogMismatchError(
                f"{run.episodes_csv}: episode {row[0]!r} is not a number"
            ) from None
        if number < next_episode:
            if steps > num_timesteps:
                raise LogMismatchError(
                    f"{run.episodes_csv}: episode {number} finished at step {steps}, after the "
                    f"checkpoint's step {num_timesteps} that counts it; nothing was changed"
                )
            keep.append(row)
        elif steps <= num_timesteps:
            raise LogMismatchError(
                f"{run.episodes_csv}: episode {number} finished at step {steps}, before the "
                f"checkpoint (step {num_timesteps}, next episode {next_episode}): the log and "
                "the checkpoint disagree; nothing was changed"
            )
    if len(keep) != next_episode or [int(r[0]) for r in keep] != list(range(next_episode)):
        raise LogMismatchError(
            f"{run.episodes_csv}: the checkpoint counts {next_episode} episodes but the log has "
            f"{len(keep)} of them; nothing was changed"
        )
    plans.append((run.episodes_csv, episode_columns, keep, len(episodes) - len(keep) + torn))
    evaluations, torn = (
        read_csv_log(run.evaluations_csv, evaluation_columns)
        if run.evaluations_csv.exists()
        else ([], 0)
    )
    try:
        kept_evals = [r for r in evaluations if int(r[0]) <= num_timesteps]
    except ValueError:
        raise LogMismatchError(
            f"{run.evaluations_csv}: a timesteps value is not a number"
        ) from None
    plans.append(
        (
            run.evaluations_csv,
            evaluation_columns,
            kept_evals,
            len(evaluations) - len(kept_evals) + torn,
        )
    )
    for path, columns, rows, dropped in plans:
        if dropped and path.exists():
            atomic_write(path, lambda p, c=columns, r=rows: _write_csv(p, c, r))
    return plans[0][3], plans[1][3]


def _write_csv(path: Path, columns: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        writer.writerows(rows)


# ---------------------------------------------------------------------- curves and results
#: A run's curve: ``(timesteps, values)``, int64 and float64 arrays in order of timesteps.
Curve = tuple[np.ndarray, np.ndarray]


def read_episodes_csv(path: str | Path, column: str = "coverage") -> Curve:
    """Read a run's ``episodes.csv``.

    Args:
        path: The file (the coverage env's columns ``episode, phase, timesteps, copy, coverage,
            reward_mean, wall_hits, new_cells, length``; only ``timesteps`` and ``column`` are
            used).
        column: The curve's column (the task's headline: a PettingZoo env's ``team_return``).

    Returns:
        ``(timesteps, coverage)``: int64 and float64 arrays, one entry per finished episode,
        in order of timesteps (a PettingZoo env's log: ``team_return``).

    Raises:
        ValueError: When a column is missing or a value is not a number (naming file and line).
    """
    # Copies finish out of order only within a step; the sort puts them back.
    return _read_columns(path, "timesteps", column)


def read_evaluations_csv(path: str | Path, column: str = "coverage_median") -> Curve:
    """Read a run's ``evaluations.csv`` (the in-training evaluations of the test policy).

    Returns:
        ``(timesteps, column)`` arrays (a PettingZoo env's column: ``return_median``), one
        entry per evaluation, in order.

    Raises:
        ValueError: When a column is missing or a value is not a number (naming file and line).
    """
    return _read_columns(path, "timesteps", column)


#: The range of a curve's ``x`` column (int64, as numpy stores it).
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1


def _read_columns(path: str | Path, x: str, y: str) -> Curve:
    """Columns ``x`` (int64) and ``y`` (float64) of a CSV file, sorted stably by ``x``."""
    path = Path(path)
    xs: list[int] = []
    ys: list[float] = []
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a CSV text file") from None
    reader = csv.DictReader(io.StringIO(text, newline=""))
    try:
        missing = {x, y} - set(reader.fieldnames or ())
        if missing:
            raise ValueError(f"{path}: missing column(s) {', '.join(sorted(missing))}")
        for row in reader:
            try:
                xs.append(int(float(row[x])))
                ys.append(float(row[y]))
            except (TypeError, ValueError, OverflowError):
                raise ValueError(f"{path}, line {reader.line_num}: {x}/{y} not a number") from None
            if not _INT64_MIN <= xs[-1] <= _INT64_MAX:  # 1e300 is a float, but no step count
                raise ValueError(f"{path}, line {reader.line_num}: {x} {row[x]} is out of range")
            if not math.isfinite(ys[-1]):
                raise ValueError(f"{path}, line {reader.line_num}: {y} is {row[y]}")
    except csv.Error as exc:
        raise ValueError(f"{path}, line {reader.line_num}: not CSV ({exc})") from None
    xa = np.asarray(xs, dtype=np.int64)
    order = np.argsort(xa, kind="stable")
    return xa[order], np.asarray(ys, dtype=np.float64)[order]


class _NumberTooLarge(ValueError):
    """A JSON integer beyond the float range (every number of a result is used as a float)."""


def _float_sized_int(text: str) -> int:
    """``json.loads``'s ``parse_int``: the integer, if a float can hold it.

    Raises:
        _NumberTooLarge: with the number shortened (``1000000000...`` (401 digits)).
    """
    value = int(text)
    try:
        float(value)
    except OverflowError:
        shown = text if len(text) <= 20 else f"{text[:12]}... ({len(text.lstrip('-'))} digits)"
        raise _NumberTooLarge(shown) from None
    return value


def finite_json(data: Any) -> Any:
    """``data`` with every non-finite float (NaN, inf: an env's info can be one) as ``None``,
    JSON's null: JSON has no NaN, and ``json.dumps`` would write one that no reader takes."""
    if isinstance(data, (float, np.floating)):
        return float(data) if math.isfinite(data) else None
    if isinstance(data, dict):
        return {key: finite_json(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [finite_json(value) for value in data]
    return data


def write_json(path: Path, data: dict[str, Any]) -> Path:
    """Write a result JSON atomically, non-finite numbers as null (:func:`finite_json`)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(finite_json(data), indent=2, allow_nan=False))
    return path
