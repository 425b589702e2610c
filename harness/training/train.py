"""Training an experiment, top to bottom: config → VecEnv → model → phases → run directory.

``train(config, run)`` is what ``harness run`` calls:

1. seed everything and set torch's thread count;
2. build the VecEnv (``harness.training.adapters``) and the ``DoubleDQN`` (``build_model``);
3. for each phase in order, on the same model and replay buffer: apply the phase's settings
   (learning rate, batch size, train_freq, PER alpha) and call ``model.learn`` with the phase's
   callbacks (ε and β schedules, epochs by coverage, episode log, evaluation, checkpoints);
4. save ``model.zip``.
"""

from __future__ import annotations

import contextlib
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import (
    CSVOutputFormat,
    Logger,
    TensorBoardOutputFormat,
)
from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import set_random_seed
from stable_baselines3.common.vec_env import VecEnv

from harness.config.pettingzoo import EnvFailed
from harness.config.schema import (
    ConfigError,
    ExperimentConfig,
    PhaseConfig,
)
from harness.evaluation.episodes import (
    EpisodesStopped,
    model_policy,
    run_episodes,
)
from harness.processes import available_cores
from harness.results.rundir import (
    CheckpointDir,
    LogMismatchError,
    RunDir,
    append_csv_rows,
    atomic_write,
    atomic_write_text,
    rewind_logs,
)
from harness.sb3.dqn import (
    DoubleDQN,
    LossOptions,
    NonFiniteLossError,
    OldModelError,
)
from harness.sb3.replay import replay_for
from harness.sb3.schedules import PhaseLinearSchedule
from harness.tasks import task_of
from harness.training.adapters import make_vec_env
from harness.training.callbacks import (
    EpisodeLogCallback,
    EpochsByCoverageCallback,
    PeriodicCallback,
    PhaseProgressBar,
)
from harness.training.checkpoints import (
    CheckpointError,
    ConfigChangedError,
    TrainingState,
    check_config,
    check_guards,
    check_inside_the_run,
    check_replay_buffer,
    complete_checkpoints,
    newest_readable,
    read_rng,
    read_state,
    save_checkpoint,
    set_aside,
    set_rng_states,
)
from harness.training.checks import (
    check_device,
    check_replay_memory,
    format_bytes,
    network_groups,
    policy_class_name,
    policy_kwargs,
)
from harness.training.teacher import TeacherLabeller
from harness.training.threads import configure_torch


def build_model(config: ExperimentConfig, venv: VecEnv) -> DoubleDQN:
    """Make the ``DoubleDQN`` of ``config.algo`` with the first phase's settings."""
    algo, first = config.algo, config.phases[0]
    kwargs = policy_kwargs(algo, config.env.id_width, algo.device, network_groups(config))
    # On CUDA the buffer lives there (no host round trip per gradient step; its sample joins
    # the recorded step), per-decision replay on the host; uniform replay on the host is SB3's
    # own buffer (n-step returns: its NStepReplayBuffer).
    buffer_class, buffer_kwargs = replay_for(algo.device, algo.prioritized, algo.per_decision)
    if buffer_class is not None:  # n-step returns, as SB3 asks of a custom buffer
        buffer_kwargs.update(n_steps=algo.n_steps, gamma=algo.gamma)
    if algo.prioritized:
        buffer_kwargs.update(alpha=first.alpha, beta=first.beta.start, eps=algo.per_eps)
    if algo.per_decision:  # with a teacher, each decision keeps its label (training.teacher)
        buffer_kwargs["labels"] = algo.teacher is not None
    return DoubleDQN(
        policy_class_name(algo),
        venv,
        learning_rate=_lr_start(first),
        buffer_size=algo.buffer_size,
        learning_starts=algo.learning_starts,
        batch_size=first.batch_size,
        gamma=algo.gamma,
        train_freq=(first.train_freq, "step"),
        gradient_steps=first.epochs[0][1],
        replay_buffer_class=buffer_class,
        replay_buffer_kwargs=buffer_kwargs or None,
        # SB3 builds its NStepReplayBuffer from this when no buffer class is given.
        n_steps=algo.n_steps if buffer_class is None else 1,
        target_update_interval=algo.target_update_interval,
        # ε, β and the learning rate's schedules are installed by apply_phase, in one place.
        max_grad_norm=algo.max_grad_norm,
        loss=LossOptions(double_q=algo.double_q, **_imitation_kwargs(config)),
        cuda_graph=algo.cuda_graph,
        # Enough finished episodes for the epochs table's median (one entry per slot).
        stats_window_size=max(
            100, max(p.epochs_window for p in config.phases) * config.env.n_agents
        ),
        policy_kwargs=kwargs,
        device=algo.device,
        seed=None,  # SuperSuit's VecEnv has no seed(); train() seeds torch/numpy and the env copies
        verbose=0,
    )


def _imitation_kwargs(config: ExperimentConfig) -> dict[str, Any]:
    """The :class:`LossOptions` of ``algo.imitation``: DQfD's margin loss with the env's
    planner-backed action as the expert's; for ``algo.teacher`` the loss's margin and weight
    (the samples carry the teacher's labels); none (DoubleDQN's defaults) without either."""
    teacher = config.algo.teacher
    if teacher is not None:
        return {"margin": teacher.margin, "margin_weight": teacher.weight}
    imitation, options = config.algo.imitation, config.env.frontier_options
    if imitation is None or options is None:
        return {}
    return {
        "expert_action": options.expert_action,
        "margin": imitation.margin,
        "margin_weight": imitation.weight,
    }


def _labeller(config: ExperimentConfig, state: TrainingState) -> TeacherLabeller | None:
    """``algo.teacher``'s labeller, its draws seeded by the run's seed and its resumes (as the
    episodes are, :func:`_env_seed`), its copies labelled on the run's CPU threads
    (``algo.threads``, else every core the process may use: the labels come between the
    gradient steps); ``None`` without a teacher."""
    teacher = config.algo.teacher
    if teacher is None:
        return None
    threads = config.algo.threads or available_cores()
    return TeacherLabeller(teacher, seed=[config.seed, state.resumes], threads=threads)


def _lr_start(phase: PhaseConfig) -> float:
    lr = phase.learning_rate
    return lr[0] if isinstance(lr, tuple) else lr


def apply_phase(model: DoubleDQN, phase: PhaseConfig, phase_start: int) -> None:
    """Set what changes between phases on the live model, schedules included (Table 4.1).

    This is the one place where the learning rate, ε and β schedules are installed. Each is a
    :class:`PhaseLinearSchedule` of the transitions done in the phase, which
    ``DoubleDQN.start_phase`` makes SB3's ``progress_remaining`` measure: a phase starts at its
    start values whether it is the first phase, a later one, or resumed mid-way.

    Args:
        model: The model, built or loaded.
        phase: The phase's settings.
        phase_start: ``model.num_timesteps`` when the phase started (earlier than now when a
            run resumes mid-phase).
    """
    model.start_phase(phase.timesteps, phase_start)
    lr = phase.learning_rate
    lr_start, lr_end = lr if isinstance(lr, tuple) else (lr, lr)
    # The learning rate moves over the whole phase; ε and β over their own `steps`.
    model.learning_rate = lr_start
    model.lr_schedule = PhaseLinearSchedule(lr_start, lr_end, phase.timesteps, phase.timesteps)
    eps = phase.exploration
    model.exploration_schedule = PhaseLinearSchedule(eps.start, eps.end, eps.steps, phase.timesteps)
    if model.prioritized:
        beta = phase.beta
        model.beta_schedule = PhaseLinearSchedule(beta.start, beta.end, beta.steps, phase.timesteps)
        model.replay_buffer.alpha = phase.alpha
    model.batch_size = phase.batch_size
    model.train_freq = TrainFreq(phase.train_freq, TrainFrequencyUnit.STEP)


def phase_callbacks(ctx: RunContext, index: int) -> tuple[list[BaseCallback], EpisodeLogCallback]:
    """The callbacks of (the rest of) phase ``index``, in the order they run, and its episode log
    (the schedules are not callbacks: :func:`apply_phase` installs them). The run's evaluator,
    checkpointer and stopper are the same objects in every phase."""
    config, phase = ctx.config, ctx.config.phases[index]
    n_agents = config.env.n_agents
    episode_log = EpisodeLogCallback(
        ctx.run.episodes_csv, task_of(config.env), phase.name, ctx.state.next_episode
    )
    ctx.checkpointer.episode_log = episode_log  # the checkpoints store its episode counter
    callbacks: list[BaseCallback] = [
        EpochsByCoverageCallback(phase.epochs, phase.epochs_window, n_agents),
        episode_log,
        ctx.evaluator,
        ctx.checkpointer,
        ctx.stopper,
    ]
    if ctx.progress_bar:
        done = int(ctx.model.num_timesteps) - ctx.state.phase_start
        callbacks.append(PhaseProgressBar(phase.name, phase.timesteps - done, n_agents))
    return callbacks, episode_log


class Evaluator(PeriodicCallback):
    """Evaluation on validation episodes every ``eval.every`` transitions (a callback of every
    phase); keeps the best model.

    The episodes come from ``eval.validation_seed``, never the test seed of ``harness eval``, so
    ``best_model.zip`` is chosen without seeing the test maps. The same maps and start cells are
    used at every evaluation, so the curve is comparable over training. "Best": see
    :func:`harness.evaluation.episodes.selection_score`.

    ``should_stop`` (training's: a signal arrived) is asked at every step of the evaluation's
    episodes: when it says so, the evaluation is abandoned, nothing of it is logged, and
    :attr:`pending` keeps its step, which the checkpoint stores and a resume evaluates first
    (:meth:`evaluate` with that step, outside ``learn()``).
    """

    def __init__(
        self,
        config: ExperimentConfig,
        run: RunDir,
        best: float = -np.inf,
        on_evaluation: Callable[[int, dict[str, Any]], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        pending: int | None = None,
    ) -> None:
        super().__init__(config.eval.every)
        self.config, self.run = config, run
        self.best = best
        # Called with (timesteps, summary) after each evaluation: a sweep reports to Optuna here
        # (and may raise optuna.TrialPruned to stop the run).
        self.on_evaluation = on_evaluation
        self.should_stop = should_stop
        self.pending = pending

    def _on_period(self) -> None:
        self.evaluate()

    def evaluate(self, timesteps: int | None = None) -> None:
        """Evaluate the model and log it at ``timesteps`` (default: the model's step counter; a
        resume passes the step of the evaluation it runs again)."""
        model = self.model
        step = int(model.num_timesteps) if timesteps is None else int(timesteps)
        cfg = self.config.eval
        policy = model_policy(model, cfg.temperature, cfg.shield)
        try:
            results = run_episodes(
                policy,
                self.config.env,
                cfg.episodes,
                cfg.validation_seed,
                should_stop=self.should_stop,
            )
        except EpisodesStopped:
            self.pending = step
            return
        except EnvFailed as exc:  # (training names the step it stopped at and the checkpoint)
            raise EnvFailed(exc.step, f"{exc.error} (an evaluation episode)", exc.during) from None
        self.pending = None
        task = task_of(self.config.env)
        summary = task.summarize(results)
        task.record_evaluation(summary, model.logger.record)
        model.logger.dump(step)
        self._append_row(step, summary)
        score = task.selection_score(summary)
        if score > self.best:
            self.best = score
            save_model(model, self.run.best_model)
        if self.on_evaluation is not None:
            self.on_evaluation(step, summary)

    def _append_row(self, timesteps: int, summary: dict[str, Any]) -> None:
        # The test policy's learning curve, next to episodes.csv (the training episodes'):
        # a plain file that `harness export` keeps and `harness compare` draws.
        row = {
            **summary,
            "timesteps": timesteps,
            "episodes": self.config.eval.episodes,
            "temperature": self.config.eval.temperature,
        }
        columns = log_columns(self.config)[1]
        append_csv_rows(self.run.evaluations_csv, columns, [[row[c] for c in columns]])


def log_columns(config: ExperimentConfig) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The columns of a run's ``episodes.csv`` and ``evaluations.csv``: its task's."""
    task = task_of(config.env)
    return task.episode_columns, task.evaluation_columns


def save_model(model: DoubleDQN, path: Path) -> None:
    """Atomically save an SB3 model zip."""

    def write(tmp: Path) -> None:
        with tmp.open("wb") as f:
            model.save(f)

    atomic_write(path, write)


class StopOnSignal(BaseCallback):
    """Ends ``learn()`` once SIGINT or SIGTERM arrived (see :func:`train`), at the end of the
    current collection round (at most ``train_freq`` env steps later), so that the checkpoint
    resumes on the uninterrupted run's rounds (``DoubleDQN.at_round_boundary``).

    While :meth:`saving` is active (a checkpoint or model being written), a further Ctrl-C is
    ignored with a note, so that it cannot tear a save in two.

    A training call (``gradient_steps`` updates after a round) does not wait for the end of the
    round either: :meth:`before_gradient_step`, an optimizer step pre-hook that the callback puts
    on the model's optimizer for the length of each ``learn()``, ends it before its next update
    (:class:`GradientStepsStopped`) once a signal arrived.
    """

    def __init__(self) -> None:
        super().__init__()
        self.signum: int | None = None
        self.saving_now = False
        self.gradient_steps_done = 0  # of the training call under way
        self._hook: Any = None  # the optimizer hook's handle while learn() runs

    def stop_requested(self) -> bool:
        """Whether SIGINT or SIGTERM arrived."""
        return self.signum is not None

    def before_gradient_step(self, optimizer: Any, args: Any, kwargs: Any) -> None:
        """A torch optimizer step pre-hook: raise :class:`GradientStepsStopped` before the
        update once a signal arrived, so that the model holds whole gradient steps only."""
        if self.signum is not None:
            raise GradientStepsStopped(self.gradient_steps_done)
        self.gradient_steps_done += 1

    def _on_training_start(self) -> None:
        # A signal ends a long training call (a large epochs table) before its next update.
        self._remove_hook()  # one left by a learn() that raised
        self._hook = self.model.policy.optimizer.register_step_pre_hook(self.before_gradient_step)

    def _on_training_end(self) -> None:
        self._remove_hook()

    def _remove_hook(self) -> None:
        if self._hook is not None:
            self._hook.remove()
            self._hook = None

    def _on_rollout_end(self) -> None:
        self.gradient_steps_done = 0  # SB3 calls the training after the rollout's end

    @contextlib.contextmanager
    def saving(self) -> Iterator[None]:
        self.saving_now = True
        try:
            yield
        finally:
            self.saving_now = False

    def _on_step(self) -> bool:
        return self.signum is None or not self.model.at_round_boundary()


class GradientStepsStopped(Exception):
    """A signal ended a training call before its next gradient step (``done`` were made)."""

    def __init__(self, done: int) -> None:
        super().__init__(f"stopped after {done} gradient steps")
        self.done = done


class Checkpointer(PeriodicCallback):
    """Writes checkpoints with the live training state (episode counter, best evaluation, an
    abandoned evaluation) and the run's config (YAML) that a resume compares the run's
    ``config.yaml`` with: every ``checkpoint.every`` transitions (a callback of every phase), at
    the first round boundary at or past each multiple, so that a resumed run trains on the same
    transitions; and when :meth:`save` is called (a phase's end, a stop, the run's end)."""

    def __init__(
        self,
        config: ExperimentConfig,
        run: RunDir,
        state: TrainingState,
        evaluator: Evaluator,
        stopper: StopOnSignal,
    ) -> None:
        super().__init__(config.checkpoint.every, when=DoubleDQN.at_round_boundary)
        self.run, self.state, self.evaluator, self.stopper = run, state, evaluator, stopper
        self.config_yaml = config.to_yaml()
        self.episode_log: EpisodeLogCallback | None = None  # the phase's (phase_callbacks)

    def _on_period(self) -> None:
        self.save()

    def save(self) -> Path:
        """Write a checkpoint of the model now; its folder."""
        if self.episode_log is not None:
            self.state.next_episode = self.episode_log.next_episode
        self.state.best_eval = self.evaluator.best
        self.state.pending_eval = self.evaluator.pending
        with self.stopper.saving():
            return save_checkpoint(self.model, self.run.checkpoints, self.state, self.config_yaml)


@dataclass
class RunContext:
    """What the steps of one training run share, in one object (as SB3's callbacks reach the
    model through ``self.model``): the model, the config, the run folder, the training state,
    the callbacks that live as long as the run (evaluation, checkpoints, the signal stop) and
    whether phases show a progress bar. :meth:`start` makes it for a built or loaded model."""

    config: ExperimentConfig
    run: RunDir
    model: DoubleDQN
    state: TrainingState
    stopper: StopOnSignal
    evaluator: Evaluator
    checkpointer: Checkpointer
    progress_bar: bool = True

    @classmethod
    def start(
        cls,
        config: ExperimentConfig,
        run: RunDir,
        model: DoubleDQN,
        state: TrainingState,
        progress_bar: bool = True,
        on_evaluation: Callable[[int, dict[str, Any]], None] | None = None,
    ) -> RunContext:
        """The run's context, its evaluator and checkpointer taking up ``state`` (the best
        evaluation, an abandoned one) and bound to ``model``: they also run outside
        ``learn()`` (an abandoned evaluation on resuming, a checkpoint at a phase's end)."""
        stopper = StopOnSignal()
        evaluator = Evaluator(
            config, run, state.best_eval, on_evaluation, stopper.stop_requested, state.pending_eval
        )
        checkpointer = Checkpointer(config, run, state, evaluator, stopper)
        evaluator.init_callback(model)
        checkpointer.init_callback(model)
        return cls(config, run, model, state, stopper, evaluator, checkpointer, progress_bar)


class TrainingInterrupted(Exception):
    """Training stopped on a signal after writing a checkpoint; ``note`` says what the signal
    cut short, if anything (an evaluation, a training call), else it is empty."""

    def __init__(self, signum: int, checkpoint: Path, note: str = "") -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum, self.checkpoint, self.note = signum, checkpoint, note


class TrainingFailed(Exception):
    """Training cannot go on (a non-finite loss, an env of one's own that failed); the last good
    checkpoint is kept."""


def _env_failure(exc: EnvFailed, run: RunDir, timesteps: int) -> TrainingFailed:
    """The one line of an env that failed mid-training (:class:`EnvFailed`): where, the newest
    checkpoint (the run resumes from it; with none yet, a resume starts it again)."""
    found = complete_checkpoints(run.checkpoints)
    kept = f"the newest checkpoint is {found[-1]}" if found else "no checkpoint yet"
    return TrainingFailed(
        f"{exc} (after {timesteps:,} transitions); training stopped, {kept}; once the env is "
        f"fixed, resume with: harness run --resume {run.path}"
    )


@contextlib.contextmanager
def stop_on_signals(
    stopper: StopOnSignal, on_signal: Callable[[int], None] | None = None
) -> Iterator[None]:
    """Turn the first SIGINT/SIGTERM into a clean stop; a second SIGINT interrupts at once,
    unless a checkpoint is being written (then it waits for the write to end). ``on_signal``
    (called in the handler: it may only take note) hears of every signal, also one that comes
    after the last point where training asks (its final save), which would be lost otherwise."""

    def handler(signum: int, frame: Any) -> None:
        if on_signal is not None:
            on_signal(signum)
        if stopper.signum is not None and signum == signal.SIGINT:
            if stopper.saving_now:
                print("harness: still writing the checkpoint, one moment", file=sys.stderr)
                return
            raise KeyboardInterrupt
        stopper.signum = signum

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def _env_seed(config: ExperimentConfig, state: TrainingState) -> int:
    # A resumed run continues on new episodes rather than replaying the first maps again.
    return config.seed + 100_000 * state.resumes


class _ResumedTensorBoardFormat(TensorBoardOutputFormat):
    """SB3's TensorBoard writer with ``purge_step``: TensorBoard then hides the events that an
    earlier session logged from that step on, which the resumed run logs again."""

    def __init__(self, folder: str, purge_step: int) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(log_dir=folder, purge_step=purge_step)
        self._is_closed = False


def make_logger(run: RunDir, state: TrainingState, restart: bool = False) -> Logger:
    """SB3's logger for a run: TensorBoard events and the scalars as CSV in ``run.tb``.

    A resumed run (``state.resumes > 0``) neither repeats nor loses what was logged before its
    checkpoint: its TensorBoard events purge the earlier session's steps after the checkpoint,
    and its CSV goes to a file of its own (:meth:`RunDir.progress_csv`). A restarted run (no
    checkpoint to resume from) purges every earlier step.
    """
    folder = str(run.tb)
    run.tb.mkdir(parents=True, exist_ok=True)
    if restart or state.resumes:
        purge_step = 0 if restart else state.num_timesteps + 1
        events: TensorBoardOutputFormat = _ResumedTensorBoardFormat(folder, purge_step)
    else:
        events = TensorBoardOutputFormat(folder)
    csv_log = CSVOutputFormat(str(run.progress_csv(0 if restart else state.resumes)))
    return Logger(folder=folder, output_formats=[events, csv_log])


def check_training_device(config: ExperimentConfig, run: RunDir) -> None:
    """Refuse an ``algo.device`` this machine does not have (SB3 would train on the CPU without
    a word). Every path that trains asks it (:func:`train`: a new run, a resume of an edited
    ``config.yaml``, a sweep's trial of a sampled device): one rule, as for ``--set``.

    Raises:
        ConfigError: naming the run's config and the device.
    """
    try:
        check_device(config.algo.device)
    except ValueError as exc:
        raise ConfigError(f"{run.config}: {exc}") from None


def train(
    config: ExperimentConfig,
    run: RunDir,
    progress_bar: bool = True,
    resume: bool = False,
    restart: bool = False,
    command: Sequence[str] | None = None,
    on_evaluation: Callable[[int, dict[str, Any]], None] | None = None,
    on_signal: Callable[[int], None] | None = None,
) -> DoubleDQN:
    """Train ``config`` into ``run``; with ``resume``, continue from its newest readable
    checkpoint; with ``restart``, start again from step 0 in a run folder that has no checkpoint
    yet (what it logged before is dropped). The caller holds ``run.lock()``. ``command`` (the
    ``harness`` arguments) is appended to ``command.txt`` once the run is ready to go: a resume
    refused for a damaged checkpoint changes no file. ``on_evaluation(timesteps, summary)`` is
    called after each in-training evaluation (see :class:`Evaluator`); ``on_signal(signum)``
    hears of each SIGINT/SIGTERM that reaches training (:func:`stop_on_signals`).

    Raises:
        TrainingInterrupted: on SIGINT/SIGTERM, after writing a checkpoint.
        TrainingFailed: on a non-finite loss, or an env of one's own that failed (the last good
            checkpoint stays).
        CheckpointError: when resuming without a usable checkpoint, or when the run's logs
            disagree with it (nothing is changed then).
        ConfigError: for an ``algo.device`` this machine does not have, before anything is
            changed (SB3 would train on the CPU without a word).
    """
    check_training_device(config, run)
    configure_torch(config.algo.threads)
    if resume:
        point = find_resume_point(run, config)
        state, model = point.state, point.model
        try:
            rewind_logs(run, state.next_episode, state.num_timesteps, log_columns(config))
        except LogMismatchError as exc:
            raise CheckpointError(f"cannot resume from {point.checkpoint.name}: {exc}") from None
        for newer in complete_checkpoints(run.checkpoints):
            if newer.name > point.checkpoint.name:  # unreadable: find_resume_point passed it over
                print(f"harness: set aside {set_aside(newer)}", file=sys.stderr)
        set_rng_states(point.rng)
        state.resumes += 1
        if command is not None:
            run.write_command(command)
    else:
        if restart:  # first, so that a log it cannot read stops it before any file changes
            try:
                rewind_logs(run, 0, 0, log_columns(config))
            except LogMismatchError as exc:
                raise CheckpointError(f"cannot start the run again: {exc}") from None
            run.best_model.unlink(missing_ok=True)
        set_random_seed(config.seed)
        atomic_write_text(run.config, config.to_yaml())
        state = TrainingState()
        if command is not None:
            run.write_command(command)

    print(
        f"replay buffer: {config.algo.buffer_size:,} transitions, about "
        f"{format_bytes(check_replay_memory(config))} when full",
        file=sys.stderr,
    )
    try:
        venv = make_vec_env(
            config.env,
            config.vec.copies,
            config.vec.num_cpus,
            seed=_env_seed(config, state),
            backend=config.vec.backend,
            labeller=_labeller(config, state),
        )
    except EnvFailed as exc:  # an env of one's own, at its first reset
        raise _env_failure(exc, run, state.num_timesteps) from None
    logger = make_logger(run, state, restart=restart)
    try:
        if resume:
            model.set_env(venv)  # fresh episodes: the saved env state is gone with the process
        else:
            try:
                model = build_model(config, venv)
            except MemoryError:  # a limit the checks could not see: one line, not numpy's
                raise TrainingFailed(
                    f"out of memory building the model and its replay buffer of "
                    f"{config.algo.buffer_size:,} transitions: lower algo.buffer_size, or raise "
                    "the memory limit"
                ) from None
            model.action_space.seed(config.seed)
        model.set_logger(logger)
        ctx = RunContext.start(config, run, model, state, progress_bar, on_evaluation)
        with stop_on_signals(ctx.stopper, on_signal):
            if ctx.evaluator.pending is not None:
                _evaluate_pending(ctx)
            for index in range(state.phase, len(config.phases)):
                _run_phase(ctx, index)
            with ctx.stopper.saving():
                save_model(model, run.model)
            state.finished = True
            ctx.checkpointer.save()
        return model
    except EnvFailed as exc:  # an env of one's own, stepped by training or its evaluation
        raise _env_failure(exc, run, int(model.num_timesteps)) from None
    finally:
        logger.close()
        venv.close()


def _evaluate_pending(ctx: RunContext) -> None:
    """Run the evaluation that a signal abandoned before the checkpoint a run resumes from: the
    model is the one it was to evaluate (no training call came between), logged at its step."""
    step = ctx.evaluator.pending
    print(f"evaluating step {step} again (abandoned when the run stopped)", file=sys.stderr)
    ctx.evaluator.evaluate(timesteps=step)
    if ctx.stopper.signum is not None:
        checkpoint = ctx.checkpointer.save()
        raise TrainingInterrupted(ctx.stopper.signum, checkpoint, _stop_note(ctx.evaluator))


def _stop_note(
    evaluator: Evaluator, cut: GradientStepsStopped | None = None, planned: int = 0
) -> str:
    """What a signal cut short, for the line that says the run stopped ("" when nothing)."""
    notes = []
    if evaluator.pending is not None:
        notes.append(
            f"during the evaluation at step {evaluator.pending} (abandoned; the resume runs it)"
        )
    if cut is not None:
        notes.append(
            f"during a training call (cut short after {cut.done:,} of its {planned:,} gradient "
            "steps)"
        )
    return "; ".join(notes)


def _run_phase(ctx: RunContext, index: int) -> None:
    """Run (the rest of) phase ``index``, then checkpoint at its end."""
    model, state, stopper = ctx.model, ctx.state, ctx.stopper
    phase = ctx.config.phases[index]
    if index != state.phase:  # a new phase starts here
        state.phase, state.phase_start = index, int(model.num_timesteps)
    done = int(model.num_timesteps) - state.phase_start
    if done < phase.timesteps:
        apply_phase(model, phase, state.phase_start)
        callbacks, episode_log = phase_callbacks(ctx, index)
        callback = CallbackList(callbacks)
        cut: GradientStepsStopped | None = None
        try:
            model.learn(
                total_timesteps=phase.timesteps - done,
                callback=callback,
                log_interval=ctx.config.n_slots,  # dump logs once per round of finished episodes
                reset_num_timesteps=False,
            )
        except GradientStepsStopped as exc:  # at a round's end: the training call after it
            cut = exc
            # What learn() skipped: closes the progress bar, takes off the stopper's hook.
            callback.on_training_end()
        except NonFiniteLossError as exc:
            found = complete_checkpoints(ctx.run.checkpoints)
            kept = f"the last good checkpoint is {found[-1]}" if found else "no checkpoint yet"
            raise TrainingFailed(
                f"{exc}; training stopped, {kept} (try a lower learning rate or max_grad_norm)"
            ) from None
        state.next_episode = episode_log.next_episode
        if stopper.signum is not None:
            note = _stop_note(ctx.evaluator, cut, int(model.gradient_steps))
            raise TrainingInterrupted(stopper.signum, ctx.checkpointer.save(), note)
    state.phase, state.phase_start = index + 1, int(model.num_timesteps)
    ctx.checkpointer.save()


@dataclass
class ResumePoint:
    """A checkpoint read back whole: the model with its replay buffer, the training state and
    the random states."""

    checkpoint: Path
    state: TrainingState
    rng: dict[str, Any]
    model: DoubleDQN


def find_resume_point(run: RunDir, config: ExperimentConfig) -> ResumePoint:
    """The newest checkpoint of ``run`` that reads back whole, saying which one when the newest
    cannot be used (the older one kept is the fallback).

    Raises:
        CheckpointError: when no checkpoint reads back whole (the reasons of each).
        ConfigChangedError: when the run's config is not the one a checkpoint was made with
            (at once: an older checkpoint is no fallback for an edited ``config.yaml``).
    """
    checkpoint, point = newest_readable(
        run.checkpoints, lambda checkpoint: load_resume_point(checkpoint, config)
    )
    print(f"resuming at step {point.state.num_timesteps} ({checkpoint})", file=sys.stderr)
    return point


def load_resume_point(checkpoint: Path, config: ExperimentConfig) -> ResumePoint:
    """Read a checkpoint's state, random states, model and replay buffer, and check that they
    belong together.

    Raises:
        ConfigChangedError: when ``config`` is not the one the checkpoint was made with.
        CheckpointError: naming the file that cannot be used.
    """
    files = CheckpointDir(checkpoint)
    check_inside_the_run(checkpoint)  # before anything of it is read
    state = read_state(checkpoint)
    check_guards(checkpoint, state)  # a deleted guard must not switch its check off
    check_config(checkpoint, config)  # before the slow loads
    rng = read_rng(checkpoint)
    try:
        model = DoubleDQN.load(files.model, device=config.algo.device)
    except OldModelError as exc:  # its own line: it names the command that migrates the model
        raise CheckpointError(str(exc)) from None
    except Exception as exc:  # SB3 raises many kinds on a damaged zip
        raise CheckpointError(f"{files.model}: unreadable ({exc})") from None
    check_replay_buffer(checkpoint)  # a flipped byte could load as NaN observations
    try:
        with files.replay_buffer.open("rb") as f:
            model.load_replay_buffer(f)
    except Exception as exc:  # a damaged pickle raises many kinds
        raise CheckpointError(f"{files.replay_buffer}: unreadable ({exc})") from None
    if model.n_envs != config.n_slots:  # a checkpoint without its config: what it can tell
        raise ConfigChangedError(
            f"{RunDir(checkpoint.parent.parent).config}: env.n_agents x vec.copies is "
            f"{config.n_slots}, but {files.model} was made with {model.n_envs} (changed since "
            "the checkpoint was written); put them back, or start a new run"
        )
    if model.num_timesteps != state.num_timesteps or not 0 <= state.phase <= len(config.phases):
        raise CheckpointError(
            f"{files.state}: says step {state.num_timesteps}, phase "
            f"{state.phase}, but the model is at step {model.num_timesteps} of a "
            f"{len(config.phases)}-phase run"
        )
    pending = state.pending_eval
    if (
        not 0 <= state.phase_start <= state.num_timesteps
        or state.next_episode < 0
        or (pending is not None and not 0 < pending <= state.num_timesteps)
    ):
        raise CheckpointError(f"{files.state}: inconsistent counters")
    return ResumePoint(checkpoint, state, rng, model)
