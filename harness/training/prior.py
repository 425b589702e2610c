"""``harness run`` of a config with a ``prior:`` section: a map prior trained as a run.

The run records its partial maps (:func:`harness.prior.data.record`: training episodes on seeds
apart from the test and validation ones, and ``eval.episodes`` validation episodes), then takes
the phases' gradient steps on them: binary cross-entropy of the U-Net's logits on the unseen
cells, Adam at the phase's learning rate (a ``[start, end]`` pair decays linearly over the
phase), batches of ``batch_size`` partial maps, mirrored at random
(up-down, left-right: the map families have no side).

It is a run like any other (docs/prior.md): its folder holds ``config.yaml``, ``command.txt``,
``tb/`` (TensorBoard: ``prior/train_logloss``, ``eval/unseen_logloss``,
``eval/density_logloss``, ``eval/ratio``), ``checkpoints/step-N/`` (``model.zip`` with the
weights, the optimizer's and the random states; ``state.json``; ``config.yaml``),
``best_model.zip`` (the lowest validation log-loss so far) and, once finished, ``model.zip``:
the prior that scored best on the validation episodes. SIGINT or SIGTERM writes a checkpoint
and stops; ``harness run --resume RUN`` continues from it (the partial maps are recorded again:
the same seeds give the same maps).
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from harness.config.schema import ExperimentConfig, PhaseConfig
from harness.prior.data import UNSEEN, PartialMaps, record
from harness.prior.model import MapPrior, UNet, archive, encode, read_archive
from harness.prior.score import score
from harness.results.rundir import CheckpointDir, RunDir, atomic_write, atomic_write_text
from harness.training.checkpoints import (
    CONFIG_GUARD,
    KEEP,
    STEP_PREFIX,
    CheckpointError,
    TrainingState,
    check_config,
    check_guards,
    check_inside_the_run,
    complete_checkpoints,
    newest_readable,
    read_state,
    set_aside,
)
from harness.training.threads import configure_torch
from harness.training.train import (
    StopOnSignal,
    TrainingFailed,
    TrainingInterrupted,
    make_logger,
    stop_on_signals,
)

#: The training episodes' first seed is ``TRAIN_SEED + seed * SEED_STRIDE`` (modulo 2**31): far
#: from the test (``eval.seed``) and validation (``eval.validation_seed``) episodes' seeds.
TRAIN_SEED, SEED_STRIDE = 10_000_000, 1_000_000
#: Gradient steps between two lines of the training loss (TensorBoard and the progress line).
LOG_EVERY = 100
#: Seconds between two progress lines.
PROGRESS_EVERY_S = 30.0


def training_seed(config: ExperimentConfig) -> int:
    """The seed of the first training episode of a prior run."""
    return (TRAIN_SEED + config.seed * SEED_STRIDE) % 2**31


def learning_rate(phase: PhaseConfig, done: int) -> float:
    """The phase's learning rate after ``done`` of its gradient steps."""
    lr = phase.learning_rate
    if isinstance(lr, (int, float)):
        return float(lr)
    start, end = lr
    return start + (end - start) * min(done / phase.timesteps, 1.0)


class _Batches:
    """Batches of partial maps drawn with ``rng``: a map size with the odds of its share of the
    maps, then ``size`` maps of it, mirrored at random."""

    def __init__(self, sets: Sequence[PartialMaps]) -> None:
        self.sets = [s for s in sets if len(s)]
        counts = np.array([len(s) for s in self.sets], dtype=np.float64)
        self.odds = counts / counts.sum()

    def draw(self, rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
        data = self.sets[int(rng.choice(len(self.sets), p=self.odds))]
        index = rng.integers(len(data), size=size)
        states, walls = data.states[index], data.walls[index]
        for axis in (1, 2):
            if rng.random() < 0.5:
                states, walls = np.flip(states, axis), np.flip(walls, axis)
        return np.ascontiguousarray(states), np.ascontiguousarray(walls)


def logloss(net: UNet, states: np.ndarray, walls: np.ndarray) -> torch.Tensor:
    """Mean binary cross-entropy of the network's logits on the unseen cells of a batch."""
    h, w = states.shape[1:]
    logits = net(encode(states, net.multiple))[:, :h, :w]
    unseen = torch.from_numpy(states == UNSEEN)
    target = torch.from_numpy(walls).to(logits.dtype)
    return F.binary_cross_entropy_with_logits(logits[unseen], target[unseen])


def _save_checkpoint(
    run: RunDir, net: UNet, opt: torch.optim.Optimizer, rng: np.random.Generator,
    state: TrainingState, config: ExperimentConfig, step: int,
) -> Path:  # fmt: skip
    """A complete checkpoint at ``step`` (hidden temporary folder, then a rename; the
    :data:`KEEP` newest kept), as :func:`harness.training.checkpoints.save_checkpoint` writes
    a policy's."""
    folder = run.checkpoints
    folder.mkdir(parents=True, exist_ok=True)
    state.num_timesteps, state.guards = step, [CONFIG_GUARD]
    name = f"{STEP_PREFIX}{step:012d}"
    final, tmp = folder / name, folder / f".{name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    files = CheckpointDir(tmp)
    try:
        weights = {
            "state_dict": net.state_dict(),
            "optimizer": opt.state_dict(),
            "torch_rng": torch.get_rng_state(),
        }
        meta = {"channels": net.channels, "numpy_rng": rng.bit_generator.state}
        files.model.write_bytes(archive(weights, meta))
        files.state.write_text(state.to_json(), encoding="utf-8")
        files.config.write_text(config.to_yaml(), encoding="utf-8")
        if final.exists():
            shutil.rmtree(final)
        tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for old in complete_checkpoints(folder)[:-KEEP]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def _load_checkpoint(
    checkpoint: Path, config: ExperimentConfig
) -> tuple[TrainingState, UNet, torch.optim.Optimizer, np.random.Generator]:
    """A checkpoint read back whole.

    Raises:
        ConfigChangedError: the run's config is not the one the checkpoint was made with.
        CheckpointError: naming the file that cannot be used.
    """
    check_inside_the_run(checkpoint)
    state = read_state(checkpoint)
    check_guards(checkpoint, state)
    check_config(checkpoint, config)
    files = CheckpointDir(checkpoint)
    try:
        weights, meta = read_archive(files.model)
        net = UNet(meta["channels"])
        net.load_state_dict(weights["state_dict"])
        opt = torch.optim.Adam(net.parameters())
        opt.load_state_dict(weights["optimizer"])
        torch.set_rng_state(weights["torch_rng"])
        rng = np.random.default_rng()
        rng.bit_generator.state = meta["numpy_rng"]
    except (ValueError, KeyError, RuntimeError, TypeError) as exc:
        raise CheckpointError(f"{files.model}: unreadable ({exc})") from None
    return state, net, opt, rng


def _resume_point(
    run: RunDir, config: ExperimentConfig
) -> tuple[TrainingState, UNet, torch.optim.Optimizer, np.random.Generator]:
    """The newest checkpoint that reads back whole (older ones are the fallback, and the newer
    unreadable ones are set aside)."""
    checkpoint, point = newest_readable(
        run.checkpoints, lambda checkpoint: _load_checkpoint(checkpoint, config)
    )
    for newer in complete_checkpoints(run.checkpoints):
        if newer.name > checkpoint.name:  # unreadable: passed over
            print(f"harness: set aside {set_aside(newer)}", file=sys.stderr)
    print(f"resuming at step {point[0].num_timesteps} ({checkpoint})", file=sys.stderr)
    return point


def record_sets(config: ExperimentConfig, episodes: int, seed: int, what: str) -> list[PartialMaps]:
    """The partial maps of ``episodes`` episodes from ``seed`` (with a line saying so)."""
    prior = config.prior
    assert prior is not None
    start = time.monotonic()
    sets = record(config.env, prior.planner, episodes, seed, prior.snapshots)
    maps = sum(len(s) for s in sets)
    print(
        f"{what}: {maps:,} partial maps from {episodes} episodes of {prior.planner} "
        f"({time.monotonic() - start:.0f} s)",
        file=sys.stderr,
    )
    if maps == 0:
        raise TrainingFailed(f"{what}: every team map was fully seen; nothing to learn from")
    return sets


def train_prior(
    config: ExperimentConfig,
    run: RunDir,
    progress_bar: bool = True,
    resume: bool = False,
    restart: bool = False,
    command: Sequence[str] | None = None,
    on_evaluation: Callable[[int, dict[str, Any]], None] | None = None,
    on_signal: Callable[[int], None] | None = None,
) -> MapPrior:
    """Train the map prior of ``config`` into ``run`` (the caller holds ``run.lock()``), as
    :func:`harness.training.train.train` trains a policy: ``resume`` continues from the newest
    readable checkpoint, ``restart`` starts again in a folder that has none.
    ``on_evaluation(step, summary)`` hears each validation's score (a sweep's trial reports
    it); ``on_signal(signum)`` each SIGINT/SIGTERM.

    Raises:
        TrainingInterrupted: on SIGINT/SIGTERM, after writing a checkpoint.
        TrainingFailed: on a non-finite loss (the last good checkpoint stays).
        CheckpointError: when resuming without a usable checkpoint.
    """
    prior = config.prior
    if prior is None:
        raise ValueError("train_prior needs a config with a prior: section")
    configure_torch(config.algo.threads)
    if resume:
        state, net, opt, rng = _resume_point(run, config)
        state.resumes += 1
    else:
        if restart:
            run.best_model.unlink(missing_ok=True)
        torch.manual_seed(config.seed)
        rng = np.random.default_rng(config.seed)
        net = UNet(prior.channels)
        opt = torch.optim.Adam(net.parameters())
        state = TrainingState()
        atomic_write_text(run.config, config.to_yaml())
    if command is not None:
        run.write_command(command)
    train_sets = record_sets(config, prior.episodes, training_seed(config), "training")
    # Validated every eval.every steps, and at the end for a caller that hears the scores.
    validating = bool(config.eval.every) or on_evaluation is not None
    validation = (
        record_sets(config, config.eval.episodes, config.eval.validation_seed, "validation")
        if validating
        else []
    )
    batches = _Batches(train_sets)
    logger = make_logger(run, state, restart=restart)
    stop = StopOnSignal()  # the policy run's rule: a second Ctrl-C interrupts at once
    step = state.num_timesteps
    total = config.total_timesteps
    last_line = time.monotonic()
    running: list[float] = []

    def validate() -> None:
        summary = score(MapPrior(net).wall_probability, validation)
        net.train()
        for key in ("unseen_logloss", "density_logloss", "ratio"):
            logger.record(f"eval/{key}", summary[key])
        logger.dump(step)
        if -summary["unseen_logloss"] > state.best_eval:
            state.best_eval = -summary["unseen_logloss"]
            MapPrior(net).save(run.best_model)
            net.train()
        print(  # a line per validation, as a policy's run prints its evaluations
            f"  step {step:,}/{total:,}: validation unseen_logloss "
            f"{summary['unseen_logloss']:.4f} (density {summary['density_logloss']:.4f}, "
            f"ratio {summary['ratio']:.3f})",
            file=sys.stderr,
            flush=True,
        )
        if on_evaluation is not None:
            on_evaluation(step, summary)

    def checkpoint() -> Path:
        with stop.saving():  # a Ctrl-C waits for the write to end
            return _save_checkpoint(run, net, opt, rng, state, config, step)

    try:
        with stop_on_signals(stop, on_signal):
            net.train()
            for index in range(state.phase, len(config.phases)):
                phase = config.phases[index]
                if index != state.phase:
                    state.phase, state.phase_start = index, step
                while step - state.phase_start < phase.timesteps:
                    for group in opt.param_groups:
                        group["lr"] = learning_rate(phase, step - state.phase_start)
                    loss = logloss(net, *batches.draw(rng, phase.batch_size))
                    if not torch.isfinite(loss):
                        found = complete_checkpoints(run.checkpoints)
                        kept = (
                            f"the last good checkpoint is {found[-1]}"
                            if found
                            else "no checkpoint yet"
                        )
                        raise TrainingFailed(
                            f"non-finite loss at step {step}; training stopped, {kept} (try a "
                            "lower learning rate)"
                        )
                    opt.zero_grad()
                    loss.backward()
                    opt.step()
                    step += 1
                    running.append(float(loss.detach()))
                    if step % LOG_EVERY == 0:
                        logger.record("prior/train_logloss", float(np.mean(running)))
                        logger.record("prior/learning_rate", opt.param_groups[0]["lr"])
                        logger.dump(step)
                        if progress_bar and time.monotonic() - last_line >= PROGRESS_EVERY_S:
                            last_line = time.monotonic()
                            print(
                                f"  step {step:,}/{total:,}: train logloss {np.mean(running):.4f}",
                                file=sys.stderr,
                                flush=True,
                            )
                        running.clear()
                    if config.eval.every and step % config.eval.every == 0:
                        validate()
                    if config.checkpoint.every and step % config.checkpoint.every == 0:
                        checkpoint()
                    if stop.signum is not None:
                        raise TrainingInterrupted(stop.signum, checkpoint())
                state.phase, state.phase_start = index + 1, step
                checkpoint()
            if validating and (not config.eval.every or step % config.eval.every != 0):
                validate()
            final = MapPrior(net)
            if run.best_model.is_file():  # the run's prior: the one validation chose
                data = run.best_model.read_bytes()
                atomic_write(run.model, lambda tmp: tmp.write_bytes(data))
                final = MapPrior.load(run.model)
            else:
                final.save(run.model)
            state.finished = True
            checkpoint()
            return final
    finally:
        logger.close()
