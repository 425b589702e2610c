"""What state a run folder is in: the one owner of the rules that ``harness run --resume`` (of a
run, and of each seed of a group), the start of a new run and ``harness tune --write`` act on.

A run's state follows from three facts of its folder: its ``config.yaml``, its complete
checkpoints (the newest one's ``state.json`` says whether the run finished) and its
``model.zip`` (written once every phase is done):

=================  ==================================================  ======================
:class:`RunState`  when                                                ``--resume`` then
=================  ==================================================  ======================
``NEW``            no ``config.yaml``: nothing of the run written yet  a run: refused (not a
                                                                       run); a seed: started
``NO_CHECKPOINT``  a config, no complete checkpoint, no ``model.zip``  starts it again from
                   (stopped before its first checkpoint)               step 0, same folder
``RESUMABLE``      a complete checkpoint, the run not finished (or     resumes from the newest
                   the newest ``state.json`` unreadable: the resume    checkpoint that reads
                   falls back to the older checkpoint)                 back whole
``FINISHED``       ``model.zip``, and the newest checkpoint says the   says so, exit 0; with
                   run finished, or no checkpoint is left              no checkpoint: refused
=================  ==================================================  ======================

The command line and seed groups ask :func:`run_state` and act on its answer; file names come
from :class:`~harness.results.rundir.RunDir`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path

from harness.config.schema import ExperimentConfig
from harness.results.rundir import RunDir
from harness.training.checkpoints import (
    CheckpointError,
    ConfigChangedError,
    TrainingState,
    check_config,
    complete_checkpoints,
    read_state,
)


class RunState(enum.Enum):
    """Where a run folder stands (see the module's table)."""

    NEW = "never started"
    NO_CHECKPOINT = "stopped before its first checkpoint"
    RESUMABLE = "stopped"
    FINISHED = "finished"


@dataclass(frozen=True)
class RunStatus:
    """A run's :class:`RunState` with the checkpoint it was read from."""

    state: RunState
    checkpoint: Path | None = None
    """The newest complete checkpoint; ``None`` when there is none."""
    training: TrainingState | None = None
    """That checkpoint's training state; ``None`` without a checkpoint, or when its
    ``state.json`` is unreadable."""

    @property
    def never_started(self) -> bool:
        return self.state is RunState.NEW

    @property
    def finished(self) -> bool:
        return self.state is RunState.FINISHED

    @property
    def words(self) -> str:
        """How the run stands, in the words of ``harness run --resume GROUP``'s line per seed:
        ``finished``, ``stopped at step 1,200``, ``stopped before its first checkpoint``,
        ``stopped (its newest checkpoint is unreadable)``, ``never started``."""
        if self.state is not RunState.RESUMABLE:
            return self.state.value
        if self.training is None:
            return f"{self.state.value} (its newest checkpoint is unreadable)"
        return f"{self.state.value} at step {self.training.num_timesteps:,}"


def run_state(run: RunDir) -> RunStatus:
    """The state of ``run`` (the rules: this module's table).

    A newest checkpoint whose ``state.json`` cannot be read leaves the run ``RESUMABLE``, even
    beside a ``model.zip``: the resume falls back to the older checkpoint and says so.
    """
    if not run.is_run:
        return RunStatus(RunState.NEW)
    found = complete_checkpoints(run.checkpoints)
    if not found:
        # model.zip without a checkpoint: finished, its checkpoints deleted since; a resume
        # has nothing to continue from, and the model is kept.
        done = run.model.is_file()
        return RunStatus(RunState.FINISHED if done else RunState.NO_CHECKPOINT)
    try:
        newest: TrainingState | None = read_state(found[-1])
    except CheckpointError:
        newest = None
    if newest is not None and newest.finished and run.model.is_file():
        return RunStatus(RunState.FINISHED, found[-1], newest)
    return RunStatus(RunState.RESUMABLE, found[-1], newest)


def check_resume_config(status: RunStatus, config: ExperimentConfig) -> None:
    """Refuse, before the slow start, to resume a ``RESUMABLE`` run whose ``config.yaml``
    (``config``) changed since its newest checkpoint was written; a checkpoint whose copy of the
    config is unreadable passes (the resume falls back to the older checkpoint and says so).

    Raises:
        ConfigChangedError: one line naming the keys that differ; nothing was changed.
    """
    if status.checkpoint is None:
        return
    try:
        check_config(status.checkpoint, config)
    except ConfigChangedError:
        raise
    except CheckpointError:
        pass


def untrained(run: RunDir) -> bool:
    """Whether ``run`` holds only what a new run writes before it trains (what its making
    leaves, :meth:`RunDir.made_names`, then its ``config.yaml`` and ``command.txt``) and no
    complete checkpoint: a start that failed there (a full disk) loses nothing with it.

    Raises:
        OSError: when the folder cannot be listed.
    """
    start = RunDir.made_names() | {run.config.name, run.command.name}
    if not {p.name for p in run.path.iterdir()} <= start:
        return False
    return not complete_checkpoints(run.checkpoints)
