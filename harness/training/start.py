"""What ``harness run`` does with a run folder, and the one function that trains a config.

A ``--resume`` of a run acts on its state (:func:`harness.training.state.run_state`):

=================  ===========================================================================
state              what :func:`resume_start` returns (or raises)
=================  ===========================================================================
``NEW``            refused (:func:`check_resumable`): not a run folder
``NO_CHECKPOINT``  :attr:`StartMode.RESTART`: trained again from step 0 in the same folder
``RESUMABLE``      :attr:`StartMode.RESUME`: continued from its newest checkpoint, once its
                   ``config.yaml`` is the one the checkpoint was written with
``FINISHED``       :attr:`StartMode.FINISHED`: nothing to do (exit 0); refused without a
                   checkpoint
=================  ===========================================================================

Each answer comes with the line the command prints; :func:`train_run` then trains the config, a
policy or a map prior (``prior:``). The command line parses, calls these and prints.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass

from harness.config.schema import ExperimentConfig
from harness.results.rundir import RunDir, RunDirError
from harness.training.checkpoints import CheckpointError
from harness.training.state import RunState, check_resume_config, run_state


class StartMode(enum.Enum):
    """How a run folder is trained (or not)."""

    NEW = "new"
    """A new run in a folder made for it."""
    RESTART = "restart"
    """A run stopped before its first checkpoint: again from step 0, same folder."""
    RESUME = "resume"
    """A run stopped after a checkpoint: from the newest one that reads back whole."""
    FINISHED = "finished"
    """A finished run: nothing is trained."""


@dataclass(frozen=True)
class Start:
    """What a ``--resume`` of a run does (:attr:`mode`), and the line that says so."""

    mode: StartMode
    message: str

    @property
    def trains(self) -> bool:
        return self.mode is not StartMode.FINISHED


def check_resumable(run: RunDir) -> None:
    """Refuse, before the run is locked or anything read, a folder that ``--resume`` cannot
    continue: one with a file linked out of it, a checkpoint of a run (its lock would go into
    the checkpoint), a folder that holds no run.

    Raises:
        LinkOutError: naming the first file that leads out of the run.
        RunDirError: for a checkpoint or a folder that is no run, in one line.
    """
    run.check_files()  # a file linked out of the run: refused before anything is read or written
    if run.is_checkpoint:
        raise RunDirError(
            f"{run.path} is a checkpoint of {run.checkpoint_of.path}: resume the run "
            f"(harness run --resume {run.checkpoint_of.path}), which continues from its newest "
            "checkpoint"
        )
    if run_state(run).never_started:
        raise RunDirError(
            f"{run.path}: not a run folder (no config.yaml) nor a seed group (no group.json)"
        )


def resume_start(run: RunDir, config: ExperimentConfig) -> Start:
    """What ``harness run --resume`` does with ``run`` (its :func:`run_state`) and its
    ``config``, read under the lock the caller holds: every refusal comes before anything is
    said or changed.

    Raises:
        CheckpointError: for a finished run without a checkpoint (its model is kept), or a
            ``config.yaml`` changed since the newest checkpoint (``ConfigChangedError``).
        ConfigError: for an ``algo.device`` this machine does not have.
    """
    status = run_state(run)
    if status.finished:
        if status.training is None:  # its checkpoints deleted since: nothing to resume
            raise CheckpointError(
                f"{run.path}: this run is finished (it has its model.zip) and has no "
                "checkpoint to resume from; nothing was trained and its model.zip is kept"
            )
        return Start(
            StartMode.FINISHED,
            f"{run.path}: this run already finished ({status.training.num_timesteps} steps)",
        )
    from harness.training.train import check_training_device  # torch: here

    check_training_device(config, run)  # (train asks too) before anything is said or done
    if status.state is RunState.NO_CHECKPOINT:
        return Start(
            StartMode.RESTART,
            f"{run.path}: no checkpoint yet (stopped before the first one): starting the run "
            "again from step 0 in the same folder",
        )
    check_resume_config(status, config)  # before the slow start: one line, nothing changed
    return Start(StartMode.RESUME, f"resuming {run.path}")


def train_run(
    config: ExperimentConfig,
    run: RunDir,
    mode: StartMode,
    progress_bar: bool = True,
    command: Sequence[str] | None = None,
) -> None:
    """Train ``config`` into ``run`` (the caller holds ``run.lock()``), new, restarted or
    resumed (``mode``): a policy (:func:`harness.training.train.train`) or, for a config with a
    ``prior:`` section, a map prior (:func:`harness.training.prior.train_prior`).

    Raises:
        ValueError: for :attr:`StartMode.FINISHED` (nothing to train).
        TrainingInterrupted, TrainingFailed, CheckpointError, ConfigError: as ``train`` does.
    """
    if mode is StartMode.FINISHED:
        raise ValueError(f"{run.path}: a finished run is not trained")
    # Imported here: torch and SB3 load only when something trains, and prior.py imports
    # train.py (train.py must not import it back).
    if config.prior is not None:  # a map prior's run (docs/prior.md)
        from harness.training.prior import train_prior as train
    else:
        from harness.training.train import train  # type: ignore[assignment]
    train(
        config,
        run,
        progress_bar=progress_bar,
        resume=mode is StartMode.RESUME,
        restart=mode is StartMode.RESTART,
        command=command,
    )
