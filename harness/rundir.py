"""The run directory: the one module that knows where a run's files live.

``runs/<name>-<UTC timestamp>/`` holds::

    config.yaml        the fully resolved config
    command.txt        the command line that started (or resumed) the run
    tb/                TensorBoard events
    checkpoints/       latest checkpoint (model, replay buffer, training state)
    episodes.csv       one row per finished training episode
    evaluations.csv    one row per evaluation during training (validation episodes)
    model.zip          the final model
    best_model.zip     the model with the best periodic evaluation so far
    eval.json          written by ``harness eval`` (eval-*.json: other settings)
    tune.json          written by ``harness tune``
    reference.json     only in a folder made by ``harness export``: marks a reference, whose
                       eval/tune/render results go to ``runs/evals/<name>/`` instead

An existing run directory is never overwritten, and every file that matters is written
atomically (a temporary file in the same folder, then a rename).
"""

from __future__ import annotations

import csv
import os
import shlex
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

#: Columns of ``episodes.csv``, one row per finished training episode (see README).
EPISODE_COLUMNS = (
    "episode",
    "phase",
    "timesteps",
    "copy",
    "coverage",
    "reward_mean",
    "wall_hits",
    "new_cells",
    "length",
)

#: Columns of ``evaluations.csv``, one row per evaluation during training (``eval.every``).
EVALUATION_COLUMNS = (
    "timesteps",
    "episodes",
    "temperature",
    "coverage_median",
    "coverage_q1",
    "coverage_q3",
    "coverage_mean",
    "wall_hits_mean",
)


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


class RunDirError(OSError):
    """A run folder that cannot be created or read, with a one-line message."""


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


@dataclass(frozen=True)
class RunDir:
    """Paths of one run."""

    path: Path

    @property
    def config(self) -> Path:
        return self.path / "config.yaml"

    @property
    def command(self) -> Path:
        return self.path / "command.txt"

    @property
    def tb(self) -> Path:
        return self.path / "tb"

    @property
    def checkpoints(self) -> Path:
        return self.path / "checkpoints"

    @property
    def episodes_csv(self) -> Path:
        return self.path / "episodes.csv"

    @property
    def evaluations_csv(self) -> Path:
        return self.path / "evaluations.csv"

    @property
    def model(self) -> Path:
        return self.path / "model.zip"

    @property
    def best_model(self) -> Path:
        return self.path / "best_model.zip"

    @property
    def eval_json(self) -> Path:
        return self.path / "eval.json"

    @classmethod
    def create(cls, root: str | Path, name: str, now: datetime | None = None) -> RunDir:
        """Make a new ``<root>/<name>-<UTC timestamp>`` folder; never reuse an existing one.

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
                    path.mkdir()  # fails if it exists: two runs in one second get -1, -2, ...
                except FileExistsError:
                    continue
                run = cls(path)
                run.tb.mkdir()
                run.checkpoints.mkdir()
                return run
        except OSError as exc:
            raise RunDirError(
                f"{root}: cannot create a run folder ({exc.strerror or exc})"
            ) from None
        raise RunDirError(f"{root}: too many runs named {name!r} in one second")

    def write_command(self, args: Sequence[str]) -> None:
        """Append the ``harness`` command line with its arguments ``args`` (a resumed run gets a
        second line)."""
        with self.command.open("a", encoding="utf-8") as f:
            f.write(shlex.join(["harness", *args]) + "\n")


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Write a file through ``write(tmp_path)`` then rename it into place.

    A crash leaves either the old file or the new one, never a half-written file.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o644)  # mkstemp makes 0600; a run's files are ordinary readable files
    try:
        write(tmp_path)
        with tmp_path.open("rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp_path, path)
    finally:
        tmp_path.unlink(missing_ok=True)


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


def truncate_csv(path: Path, below: int) -> None:
    """Keep the header and the rows whose first column is below ``below``.

    A resumed run drops what it logged after its checkpoint (episodes from ``next_episode``
    on, evaluations after the checkpoint's timesteps), so nothing appears twice.
    """
    if not path.exists():
        return
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    kept = lines[:1] + [ln for ln in lines[1:] if int(ln.split(",", 1)[0]) < below]
    atomic_write_text(path, "".join(kept))
