"""The ``harness`` command: ``harness run CONFIG.yaml`` and friends (README "Quick start" and
"Commands", docs/ for each). This module parses arguments and prints; the work of each subcommand is
elsewhere:

========  ==========================================================================
run       :func:`harness.training.train.train` (``--seeds``: :mod:`harness.results.groups`)
eval      :func:`harness.commands.evaluate` (a seed group: ``evaluate_group``)
tune      :func:`harness.commands.tune` (a seed group: every run)
compare   :func:`harness.commands.compare`
render    :func:`harness.commands.render`
export    :func:`harness.commands.export_reference`
sweep     :func:`harness.training.sweep.run_sweep`
bench     :func:`harness.bench.run_bench`
========  ==========================================================================

Every user error (a bad config, map, path or argument) ends with one line on stderr and exit
code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import shutil
import signal
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from harness import end_of_loading
from harness.commands import (
    DEFAULT_EPISODES,
    DEFAULT_TEMPERATURES,
    DEFAULT_TUNE_EPISODES,
    PER_EPISODE_KEYS,
    Target,
    TargetError,
    against_config,
    check_against_set,
    check_baseline,
    compare,
    evaluate,
    evaluate_against,
    evaluate_group,
    export_reference,
    format_against,
    format_group_against,
    format_over_seeds,
    format_summary,
    format_tune,
    render,
    resolve_target,
    tune,
)
from harness.config.loading import load_config
from harness.config.pettingzoo import EnvFailed
from harness.config.schema import MAX_SEED, ConfigError, ExperimentConfig, check_name

# The help names the baselines from their registry (its planners' SciPy costs the start nothing
# more: the env, which every command imports, has loaded it already).
from harness.evaluation.baselines import BASELINES
from harness.results.groups import GroupError, GroupInterrupted, Job
from harness.results.rundir import (
    RunDir,
    RunDirError,
    atomic_write_text,
    check_output_file,
    finite_json,
)
from harness.results.stats import REPS
from harness.tasks import TASKS, task_of_summary
from harness.training.checkpoints import CheckpointError
from harness.training.start import StartMode, check_resumable, resume_start, train_run
from harness.training.state import run_state, untrained
from harness.training.sweep import BEST_CONFIG, PRUNERS, SweepError

EXIT_USAGE = 2


class HarnessError(Exception):
    """A user-facing error: printed as one line, exit code 2."""


class _Parser(argparse.ArgumentParser):
    """argparse, with its usage errors on one line (``harness: error: ...``, exit code 2) like
    every other error of the command; ``--help`` shows the usage."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"harness: error: {self.prog}: {message} (see {self.prog} --help)\n")


def _int_in(text: str, low: int, high: int | None, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must be an integer, got {text!r}") from None
    if value < low or (high is not None and value > high):
        bounds = f"in [{low}, {high}]" if high is not None else f">= {low}"
        raise argparse.ArgumentTypeError(f"{what} must be {bounds}, got {value}")
    return value


def seed_arg(text: str) -> int:
    """A ``--seed`` value: an integer in ``[0, MAX_SEED]``."""
    return _int_in(text, 0, MAX_SEED, "seed")


def positive_int(text: str) -> int:
    """An integer >= 1 (episode counts, windows, frame intervals)."""
    return _int_in(text, 1, None, "the value")


#: Most bootstrap resamples of ``harness compare --reps``: 2,000 (the default) gives stable
#: 95 % intervals; a hundred times that takes minutes, beyond it the command would not end.
MAX_REPS = 200_000


def reps_arg(text: str) -> int:
    """A ``--reps`` value: bootstrap resamples in ``[1, MAX_REPS]``."""
    return _int_in(text, 1, MAX_REPS, "--reps")


def temperature_arg(text: str) -> float:
    """A finite temperature >= 0 (0: the greedy policy)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(
            f"temperatures must be finite and >= 0 (0: the greedy policy), got {text}"
        )
    return value


def check_image_output(path: Path, flag: str, suffix: str = ".png") -> None:
    """An output picture: named ``*.png`` (``*.gif`` for ``--gif``) and writable.

    The suffix rule keeps a mistyped path from overwriting a run's ``model.zip``,
    ``episodes.csv`` or ``config.yaml`` with a picture.

    Raises:
        HarnessError: for another suffix; ``RunDirError`` when the place cannot take a file.
    """
    if path.suffix.lower() != suffix:
        raise HarnessError(f"{flag} {path}: expected a {suffix} file name")
    check_output_file(path, flag)


def _add_overrides(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY.PATH=VALUE",
        help="override a config key, e.g. --set env.max_steps=500 (repeatable)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="harness",
        description="Train, evaluate and compare multi-agent coverage policies.",
    )
    sub = parser.add_subparsers(
        dest="command", required=True, metavar="COMMAND", parser_class=_Parser
    )
    _add_run_parser(sub)
    _add_eval_parser(sub)
    _add_tune_parser(sub)
    _add_compare_parser(sub)
    _add_render_parser(sub)
    _add_export_parser(sub)
    _add_sweep_parser(sub)
    _add_bench_parser(sub)
    return parser


def _add_run_parser(sub: Any) -> None:
    """``harness run``: its arguments."""
    run = sub.add_parser("run", help="train an experiment from a YAML config")
    run.add_argument("config", type=Path, nargs="?", help="experiment YAML file (see configs/)")
    run.add_argument(
        "--resume",
        type=Path,
        metavar="RUN_DIR",
        help="continue an interrupted run from its latest checkpoint (uses its config.yaml)",
    )
    _add_overrides(run)
    run.add_argument("--seed", type=seed_arg, help="override the config's seed")
    run.add_argument("--name", help="override the config's name (the run folder's prefix)")
    run.add_argument("--runs-dir", type=Path, default=Path("runs"), help="where runs are written")
    run.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    run.add_argument(
        "--seeds",
        metavar="SEEDS",
        help="a group of runs, one per seed: a list (0,1,2) or a count (3 = 0,1,2)",
    )
    run.add_argument(
        "--jobs",
        type=positive_int,
        help="with --seeds (or --resume GROUP): seeds trained at a time, each on its share of "
        "the cores (default 1; a resumed group: its own)",
    )
    run.add_argument(
        "--into",
        type=Path,
        metavar="RUN_DIR",
        help="train into this new (or empty) folder instead of RUNS_DIR/NAME-TIME",
    )


def _add_eval_parser(sub: Any) -> None:
    """``harness eval``: its arguments."""
    ev = sub.add_parser("eval", help="evaluate a trained model or a baseline on fresh episodes")
    _add_target(ev)
    ev.add_argument(
        "--episodes",
        type=positive_int,
        default=DEFAULT_EPISODES,
        help="test episodes (default 100)",
    )
    ev.add_argument("--json", action="store_true", help="print one JSON object")
    ev.add_argument(
        "--plot",
        type=Path,
        help="coverage/wall hits per episode PNG (Fig. 4.11); a pettingzoo env: the team return",
    )
    ev.add_argument(
        "--against",
        nargs="+",
        default=[],
        metavar="BASELINE",
        help="also play these baselines on the same episodes and compare episode by episode "
        "(mean difference, 95 %% bootstrap interval); saved as against-BASELINE.json",
    )
    ev.add_argument(
        "--against-set",
        dest="against_set",
        action="append",
        default=[],
        metavar="KEY.PATH=VALUE",
        help="an override for the --against baselines alone, on top of the target's config, "
        "e.g. --against-set eval.rollout.prior=null (repeatable; not the episodes' keys: "
        "env.map, env.n_agents, ..., seed); saved as against-BASELINE+KEY.PATH-VALUE.json",
    )


def _add_tune_parser(sub: Any) -> None:
    """``harness tune``: its arguments."""
    tune = sub.add_parser(
        "tune", help="choose the test temperature of a trained model on validation episodes"
    )
    tune.add_argument(
        "target",
        type=Path,
        metavar="RUN_DIR_OR_MODEL",
        help="run folder, zip, or a seed group (every run of it)",
    )
    tune.add_argument(
        "--temperatures",
        type=temperature_arg,
        nargs="+",
        default=list(DEFAULT_TEMPERATURES),
        metavar="T",
        help="temperatures to try (default: %(default)s)",
    )
    tune.add_argument(
        "--episodes",
        type=positive_int,
        default=DEFAULT_TUNE_EPISODES,
        help="validation episodes per temperature (default %(default)s)",
    )
    tune.add_argument(
        "--seed", type=seed_arg, help="seed of the episodes (default: config eval.validation_seed)"
    )
    _add_overrides(tune)
    tune.add_argument(
        "--write",
        action="store_true",
        help="store the chosen temperature as eval.temperature in the run's config.yaml",
    )
    tune.add_argument("--json", action="store_true", help="print one JSON object")


def _add_compare_parser(sub: Any) -> None:
    """``harness compare``: its arguments."""
    cmp_ = sub.add_parser("compare", help="learning curves and eval tables of several runs")
    cmp_.add_argument(
        "runs",
        type=Path,
        nargs="+",
        metavar="RUN_DIR",
        help="runs or seed groups (a group: one curve over its seeds, and intervals over seeds)",
    )
    cmp_.add_argument("--out", type=Path, default=Path("compare.png"), help="PNG to write")
    cmp_.add_argument("--window", type=positive_int, default=20, help="episodes per rolling median")
    cmp_.add_argument(
        "--labels",
        nargs="+",
        metavar="LABEL",
        help="one legend label per run (default: each run's config name; equal labels group)",
    )
    cmp_.add_argument(
        "--reps",
        type=reps_arg,
        default=REPS,
        help=f"bootstrap resamples of the 95 %% intervals over seeds (rliable; default {REPS})",
    )
    cmp_.add_argument(
        "--eval",
        metavar="NAME",
        help="which evaluation of each run: eval (eval.json) or another eval file's stem, e.g. "
        "eval-env.map-random (default: eval.json, else the run's only eval-*.json)",
    )


def _add_render_parser(sub: Any) -> None:
    """``harness render``: its arguments."""
    ren = sub.add_parser("render", help="path pictures (and a GIF) of one episode")
    _add_target(ren)
    ren.add_argument("--out", type=Path, help="paths PNG (default: RUN_DIR/paths.png or paths.png)")
    ren.add_argument("--gif", type=Path, help="also write an animated GIF of the episode")
    ren.add_argument(
        "--every",
        type=positive_int,
        help="GIF: one frame every N steps (default: ceil(max_steps / 200): at most 20 s)",
    )


def _add_export_parser(sub: Any) -> None:
    """``harness export``: its arguments."""
    exp = sub.add_parser("export", help="copy a run's policy into a compact reference folder")
    exp.add_argument("run", type=Path, metavar="RUN_DIR", help="the trained run to export")
    exp.add_argument("--out", type=Path, required=True, help="new folder, e.g. runs/reference/x")
    exp.add_argument(
        "--model",
        default="model",
        help="which model of the run: model (default), best_model or checkpoints/step-N/model",
    )


def _add_sweep_parser(sub: Any) -> None:
    """``harness sweep``: its arguments."""
    sw = sub.add_parser("sweep", help="a hyperparameter sweep on Optuna (one or many machines)")
    sw.add_argument("config", type=Path, help="experiment YAML file")
    sw.add_argument("--space", type=Path, required=True, help="SPACE.yaml: keys and distributions")
    sw.add_argument("--trials", type=positive_int, required=True, help="trials in the whole sweep")
    sw.add_argument("--study", help="study name (default: the config's name)")
    sw.add_argument(
        "--storage",
        help="Optuna storage URL, e.g. postgresql+psycopg://user@host/db for several machines "
        "(default: a journal file in the sweep folder)",
    )
    sw.add_argument("--resume", action="store_true", help="continue a killed sweep of this study")
    sw.add_argument(
        "--pruner",
        choices=PRUNERS,
        default="median",
        help="Optuna pruner that stops weak trials at their evaluations (default: median)",
    )
    sw.add_argument(
        "--jobs",
        type=positive_int,
        default=1,
        help="worker processes on this machine, each on its share of the cores",
    )
    # A worker process started by --jobs: it joins the study as it is and leaves the rest to its
    # parent (refusing an existing study, failing dead trials, writing the best).
    sw.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    sw.add_argument(
        "--sweeps-dir", type=Path, default=Path("runs/sweeps"), help="where sweep folders go"
    )
    sw.add_argument("--quiet", action="store_true", help="no line per finished trial (for scripts)")
    _add_overrides(sw)


def _add_bench_parser(sub: Any) -> None:
    """``harness bench``: its arguments."""
    from harness.bench import SECTION_HELP, SECTIONS

    bench = sub.add_parser(
        "bench",
        help="throughput and memory figures (thesis settings)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Throughput and memory figures, ratios measured in one run "
        "(docs/performance.md).\n\nsections:\n"
        + "\n".join(f"  {name:9} {SECTION_HELP[name]}" for name in SECTIONS)
        + "\n  all       every section (the default)",
    )
    bench.add_argument("what", nargs="?", default="all", choices=[*SECTIONS, "all"])
    bench.add_argument("--json", action="store_true", help="print one JSON object")


def _add_target(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "target", type=Path, nargs="?", metavar="RUN_DIR_OR_MODEL", help="run folder or model zip"
    )
    parser.add_argument("--policy", help="a baseline instead of a model (listed below)")
    width = max(map(len, BASELINES))
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = "baselines (--policy NAME --config CONFIG):\n" + "\n".join(
        f"  {name:{width}}  {entry.summary}" for name, entry in BASELINES.items()
    )
    parser.add_argument("--config", type=Path, help="the experiment config of a --policy")
    parser.add_argument(
        "--seed", type=seed_arg, help="seed of the episodes (default: config eval.seed)"
    )
    _add_overrides(parser)


def resolve_run_config(args: argparse.Namespace) -> ExperimentConfig:
    """The config of ``harness run``: the file, then ``--set``, ``--seed`` and ``--name``."""
    overrides = list(args.overrides)
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    if args.name is not None:
        overrides.append(f"name={json.dumps(args.name)}")
    config = load_config(args.config, overrides)
    from harness.training.checks import checked_config, schedule_warnings  # torch: here

    source = f"{args.config}" + (f" with --set {' '.join(overrides)}" if overrides else "")
    checked_config(config, source)
    # A shortened phase keeps the file's ε and β schedules: said, not changed (SB3 and the
    # reference numbers count them in transitions, as written).
    for line in schedule_warnings(config):
        print(f"harness: warning: {line}", file=sys.stderr)
    try:
        config.env.check_training_map()
    except ValueError as exc:
        raise HarnessError(f"{args.config}: {exc}") from None
    return config


def cmd_run(args: argparse.Namespace) -> int:
    if args.resume is not None:
        return _resume(args)
    if args.config is None:
        raise HarnessError("run needs a CONFIG.yaml (or --resume RUN_DIR)")
    config = resolve_run_config(args)
    if args.seeds is not None:
        return _run_group(args, config)
    if args.jobs not in (None, 1):
        raise HarnessError("--jobs goes with --seeds")
    run = RunDir.create_at(args.into) if args.into else RunDir.create(args.runs_dir, config.name)
    try:
        with run.lock():
            # Before the folder is announced (and before the slow torch import): from here on a
            # kill leaves a folder that `--resume` can start again.
            atomic_write_text(run.config, config.to_yaml())
            print(f"run folder: {run.path}", file=sys.stderr)
            return _train(config, run, args, StartMode.NEW)
    except OSError as exc:  # e.g. a full disk before anything was trained
        if not _remove_unstarted(run):
            raise
        raise HarnessError(
            f"{os_error_text(exc)}; removed the run folder {run.path} (nothing was trained)"
        ) from None


def _remove_unstarted(run: RunDir) -> bool:
    """Remove the folder of a new run that failed before its first checkpoint, if it holds only
    what the start wrote (no episode logged, no checkpoint: :func:`untrained`); whether it was
    removed."""
    try:
        if not untrained(run):
            return False
        shutil.rmtree(run.path)
    except OSError:
        return False
    return True


def os_error_text(exc: OSError) -> str:
    """An ``OSError`` in words, with the file it names (for the one-line error)."""
    where = f": {exc.filename}" if exc.filename else ""
    return f"{exc.strerror or exc}{where}"


def _run_group(args: argparse.Namespace, config: ExperimentConfig) -> int:
    """``harness run CONFIG --seeds ...``: one run per seed in a group folder."""
    from harness.results.groups import parse_seeds, run_group

    if args.seed is not None or args.into is not None:
        raise HarnessError("--seeds makes its own seeds and folders; drop --seed and --into")
    seeds = parse_seeds(args.seeds, MAX_SEED)
    overrides = list(args.overrides) + ([f"name={json.dumps(args.name)}"] if args.name else [])
    try:
        group, jobs = run_group(
            args.config,
            config.name,
            overrides,
            seeds,
            args.jobs or 1,
            args.runs_dir,
            args.argv,
            report=None if args.no_progress else print_progress,
            config_yaml=config.to_yaml(),
            say=lambda line: print(line, file=sys.stderr, flush=True),
        )
    except GroupInterrupted as exc:
        return _group_stopped(exc)
    return _group_done(group, jobs)


def _group_stopped(exc: GroupInterrupted) -> int:
    """The one line of a seed group stopped by a signal (``GroupInterrupted``); its exit code."""
    print(
        f"harness: seed group stopped by {exc} ({exc.summary()}); continue it with: "
        f"harness run --resume {exc.group}",
        file=sys.stderr,
    )
    return 128 + exc.signum


def _group_done(group: Path, jobs: Sequence[Job]) -> int:
    """The end of a seed group's command: each seed's state, the last validations; 0 when every
    seed is done."""
    from harness.results.groups import seed_progress_metric, seed_progress_value

    print(f"group folder: {group}", file=sys.stderr)
    for job in jobs:
        if job.returncode == 0:
            state = "done"
        else:  # its own reason, from its log: nobody has to open the logs to see why
            error = job.error_line()
            state = (
                f"failed (exit {job.returncode}): {error}"
                if error
                else f"failed (exit {job.returncode}, see {job.log})"
            )
        print(f"  seed {job.seed}: {job.run.path.name} {state}", file=sys.stderr)
    finals = [seed_progress_value(job.run) for job in jobs if job.returncode == 0]
    finals = [f for f in finals if f is not None]
    if finals:
        what, fmt = seed_progress_metric(jobs[0].run)
        print(
            f"  last validation over {len(finals)} seed(s): {what} "
            + ", ".join(fmt(f) for f in finals)
            + f" (mean {fmt(sum(finals) / len(finals))}); test them: harness eval {group}",
            file=sys.stderr,
        )
    if any(job.returncode != 0 for job in jobs):
        print(f"  finish the failed seeds with: harness run --resume {group}", file=sys.stderr)
        return 1
    return 0


def print_progress(line: str) -> None:
    """A progress line of long work (seed groups, evaluations), on stderr."""
    print(f"  {line}", file=sys.stderr, flush=True)


#: Seconds between two progress lines of ``harness eval`` (a shorter evaluation prints none).
EVAL_PROGRESS_EVERY_S = 30.0


class EpisodeProgress:
    """``harness eval``'s progress (``run_episodes``' ``progress``): ``WHAT: N/TOTAL episodes,
    M min``, at most one line every :data:`EVAL_PROGRESS_EVERY_S` and none when all are done
    (the summary follows), so only a long evaluation (a search baseline, large maps) says
    where it is."""

    def __init__(self, what: str, total: int) -> None:
        self.what, self.total = what, total
        self.start = self.last = time.monotonic()

    def __call__(self, done: int) -> None:
        now = time.monotonic()
        if done < self.total and now - self.last >= EVAL_PROGRESS_EVERY_S:
            self.last = now
            minutes = (now - self.start) / 60
            print_progress(f"{self.what}: {done}/{self.total} episodes, {minutes:.1f} min")


def _resume(args: argparse.Namespace) -> int:
    from harness.results.groups import is_group

    if (
        args.config is not None
        or args.overrides
        or args.seed is not None
        or args.name
        or args.seeds is not None
        or args.into is not None
    ):
        raise HarnessError(
            "--resume continues a run with its own config.yaml; drop the other options"
        )
    if is_group(args.resume):
        return _resume_group(args)
    if args.jobs is not None:
        raise HarnessError("--jobs goes with --seeds or a seed group's --resume")
    run = RunDir(args.resume)
    check_resumable(run)  # the training layer decides what a resume does; this prints it
    with run.lock():  # a second resume of a live run stops here
        config = load_config(run.config)
        start = resume_start(run, config)
        print(start.message, file=sys.stderr)
        return _train(config, run, args, start.mode) if start.trains else 0


def _resume_group(args: argparse.Namespace) -> int:
    """``harness run --resume GROUP``: resume the seeds that stopped, start those never started,
    leave the finished ones alone (one line per seed says which)."""
    from harness.results.groups import resume_group

    group = Path(args.resume)
    try:
        jobs = resume_group(
            group,
            run_state,
            args.jobs,
            say=print_progress,
            report=None if args.no_progress else print_progress,
        )
    except GroupInterrupted as exc:
        return _group_stopped(exc)
    return _group_done(group, jobs)


def _train(config: ExperimentConfig, run: RunDir, args: argparse.Namespace, mode: StartMode) -> int:
    """Train ``config`` into ``run`` (``train_run``: a policy or a prior) and say how it ended:
    ``mode`` is new, resume or restart."""
    from harness.training.train import TrainingFailed, TrainingInterrupted  # torch, SB3: here

    try:
        train_run(config, run, mode, progress_bar=not args.no_progress, command=args.argv)
    except TrainingInterrupted as exc:
        during = f" {exc.note}" if exc.note else ""
        print(
            f"harness: stopped by {exc}{during} after writing {exc.checkpoint}; "
            f"resume with: harness run --resume {run.path}",
            file=sys.stderr,
        )
        return 128 + exc.signum
    except TrainingFailed as exc:
        print(f"harness: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        newest = run_state(run).checkpoint
        kept = f"the newest checkpoint is {newest}" if newest else "no checkpoint yet"
        print(
            f"harness: interrupted ({kept}); resume with: harness run --resume {run.path}",
            file=sys.stderr,
        )
        return 130
    print(f"done: {run.model}", file=sys.stderr)
    return 0


def _target(args: argparse.Namespace) -> Target:
    target = resolve_target(args.target, args.policy, args.config, args.overrides, args.seed)
    from harness.training.threads import configure_torch

    # One torch thread, whatever algo.threads says (that is for training): the test policy runs
    # the network on a few dozen observations per step, where a second thread only adds
    # synchronisation, and it slowed `harness eval` 4x beside a training run on 2 cores.
    configure_torch(1)
    return target


def cmd_eval(args: argparse.Namespace) -> int:
    from harness.results.groups import is_group

    args.against = list(dict.fromkeys(args.against))  # each baseline once, in the order named
    if args.against_set and not args.against:
        raise HarnessError(
            "--against-set sets the config of the --against baselines: give --against BASELINE"
        )
    check_against_set(args.against_set)  # before anything is played, a group's runs too

    if args.target is not None and is_group(args.target):
        return _eval_group(args)
    from harness.prior.evaluate import is_prior_run

    if args.target is not None and is_prior_run(args.target):
        return _eval_prior(args)
    if args.plot is not None:
        check_image_output(args.plot, "--plot")
    target = _target(args)
    theirs = against_config(target.config, args.against_set)
    for policy in args.against:  # before any episode is played
        check_baseline(policy, theirs, "--against")
    progress = EpisodeProgress(target.label, args.episodes)
    summary, results = evaluate(target, args.episodes, args.overrides, progress)
    if summary["saved"] is not None:
        print(f"saved {summary['saved']}", file=sys.stderr)
    against = [
        evaluate_against(
            target,
            summary,
            p,
            args.overrides,
            EpisodeProgress(p, args.episodes),
            args.against_set,
        )
        for p in args.against
    ]
    for comparison in against:
        if comparison["saved"] is not None:
            print(f"saved {comparison['saved']}", file=sys.stderr)
    if args.plot is not None:
        from harness.results.plots import plot_eval_episodes, plot_eval_returns

        title = f"{target.label}: {len(results)} episodes"
        if "team_return" in summary:  # a PettingZoo env of one's own: no coverage to draw
            plot_eval_returns(summary["team_return"], args.plot, title)
        else:
            plot_eval_episodes(results, None, args.plot, title)
        print(f"saved {args.plot}", file=sys.stderr)
    if args.json:
        hidden = (*PER_EPISODE_KEYS, "saved")
        out = {k: v for k, v in summary.items() if k not in hidden}
        if against:
            out["against"] = [_printable(c) for c in against]
        print(_json(out))
    else:
        print("\n".join([format_summary(summary), *map(format_against, against)]))
    return 0


def _json(data: dict[str, Any]) -> str:
    """``--json``'s line: valid JSON, a non-finite number (an env's NaN info) as null."""
    return json.dumps(finite_json(data), allow_nan=False)


def _eval_prior(args: argparse.Namespace) -> int:
    """``harness eval PRIOR_RUN``: the prior's log-loss on the test episodes' partial maps."""
    from harness.prior.evaluate import evaluate_prior, format_prior

    if args.against or args.plot is not None or args.policy is not None:
        raise HarnessError(
            f"{args.target} is a map prior's run: it is scored by its log-loss (no --against, "
            "--plot or --policy); plan with it: --policy rollout --set eval.rollout.prior=RUN"
        )
    from harness.training.threads import configure_torch

    configure_torch(1)
    try:
        summary = evaluate_prior(Path(args.target), args.overrides, args.episodes, args.seed)
    except ValueError as exc:
        raise HarnessError(str(exc)) from None
    print(f"saved {summary['saved']}", file=sys.stderr)
    print(json.dumps(summary) if args.json else format_prior(summary))
    return 0


def _printable(comparison: dict[str, Any]) -> dict[str, Any]:
    """A comparison of ``--against`` as ``--json`` prints it: without the saved file's path and
    the per-episode lists (the file keeps them, as an evaluation's does)."""
    lists = {"saved", *PER_EPISODE_KEYS, *(f"against_{k}" for k in PER_EPISODE_KEYS)}
    return {k: v for k, v in comparison.items() if k not in lists}


def _eval_group(args: argparse.Namespace) -> int:
    """``harness eval GROUP``: each run as ``harness eval RUN``, then the group's numbers (of
    that evaluation: ``group-eval.json``, ``group-eval-30ep.json`` for ``--episodes 30``). With
    ``--json``, stdout is one JSON object: the group's numbers (when it has them) and each run's
    evaluation under ``"evaluations"``. ``--plot X.png`` draws one picture per seed,
    ``X-seed<k>.png``."""
    from harness.results.groups import group_seeds

    if args.plot is not None:
        check_image_output(args.plot, "--plot")
    seeds = group_seeds(Path(args.target))
    evaluations: dict[str, Any] = {}

    def evaluate_run(run: Path) -> None:
        plot = args.plot
        if plot is not None:  # one picture per seed, not each over the one before
            plot = plot.with_name(f"{plot.stem}-seed{seeds.get(run, run.name)}{plot.suffix}")
        one = argparse.Namespace(**{**vars(args), "target": run, "plot": plot})
        if not args.json:
            print(f"== {run.name}")
            cmd_eval(one)
            return
        text = io.StringIO()
        with contextlib.redirect_stdout(text):
            cmd_eval(one)
        evaluations[run.name] = json.loads(text.getvalue())

    result, saved, missing = evaluate_group(
        Path(args.target),
        evaluate_run,
        args.against,
        args.episodes,
        args.overrides,
        args.seed,
        args.against_set,
    )
    if args.json:
        out = {"group": str(args.target), **(result or {}), "evaluations": evaluations}
        if "against" in out:
            out["against"] = [_printable(c) for c in out["against"]]
    if missing:
        print(
            "harness: no numbers over seeds (group-eval*.json): the group lacks "
            f"{', '.join(missing)} (finish the missing seeds, then evaluate the group again)",
            file=sys.stderr,
        )
    if saved is not None and args.json:
        print(f"saved {saved}", file=sys.stderr)
        for comparison in result.get("against", []):
            print(f"saved {comparison['saved']}", file=sys.stderr)
    elif saved is not None:
        print(format_over_seeds(result))
        print(f"saved {saved}", file=sys.stderr)
        for comparison in result.get("against", []):
            print(format_group_against(comparison))
            print(f"saved {comparison['saved']}", file=sys.stderr)
    if args.json:
        print(_json(out))
    return 0


def cmd_tune(args: argparse.Namespace) -> int:
    from harness.results.groups import group_runs, is_group

    if is_group(args.target):
        # Each seed picks its own temperature on the same validation episodes, as each
        # reference does; `harness eval GROUP` then tests every run at its choice.
        for run in group_runs(args.target):
            print(f"== {run.name}")
            cmd_tune(argparse.Namespace(**{**vars(args), "target": run}))
        return 0
    args.policy = args.config = None
    target = _target(args)
    if args.seed is None:
        # Choices are made on validation episodes, never on the test episodes of harness eval.
        target.seed = target.config.eval.validation_seed
    result, saved = tune(target, args.temperatures, args.episodes, args.overrides, args.write)
    if args.write:
        print(
            f"saved eval.temperature={result['chosen']:g} in {RunDir(target.run_dir).config} "
            f"(was {result['previous_temperature']:g}); eval files made before keep theirs",
            file=sys.stderr,
        )
    print(f"saved {saved}", file=sys.stderr)
    print(_json(result) if args.json else format_tune(result))
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    if args.labels is not None and len(args.labels) != len(args.runs):
        raise HarnessError(f"--labels needs one label per run ({len(args.runs)})")
    for label in args.labels or []:  # a newline or a control character breaks the tables
        if not label.strip() or not label.isprintable():
            raise HarnessError(f"--labels {label[:40]!r}: a label is one line of printable text")
    check_image_output(args.out, "--out")
    labels = args.labels or [None] * len(args.runs)
    result = compare(args.runs, labels, Path(args.out), args.window, args.reps, args.eval)
    wide = max([len(label) for label, _, _ in result.rows] + [len("experiment")]) + 2
    runs = max([len(name) for _, name, _ in result.rows] + [len("run")]) + 2
    # Runs of one task (compare refuses a mix): its headline columns.
    found = [ev for _, _, ev in result.rows if ev is not None]
    task = task_of_summary(found[0]) if found else TASKS[0]
    print(f"{'experiment':<{wide}}{'run':<{runs}}{task.compare_header()}")
    for (label, name, ev), used in zip(result.rows, result.used, strict=True):
        # An evaluation compare chose itself (the run's only one, not eval.json) is named.
        note = f"  ({used}.json)" if args.eval is None and used not in (None, "eval") else ""
        if ev is None:
            others = result.others.get(name, [])
            hint = (
                f"has {', '.join(others)}: pick one with --eval {others[0]}"
                if others
                else "run harness eval"
            )
            print(f"{label:<{wide}}{name:<{runs}}(no {args.eval or 'eval'}.json; {hint})")
        else:
            print(f"{label:<{wide}}{name:<{runs}}{task.compare_row(ev)}{note}")
    if result.over_seeds:
        print()
        print(result.over_seeds)
    for path in result.saved:
        print(f"saved {path}", file=sys.stderr)
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    for path, flag, suffix in ((args.out, "--out", ".png"), (args.gif, "--gif", ".gif")):
        if path is not None:
            check_image_output(path, flag, suffix)
    for path in render(_target(args), args.out, args.gif, args.every):
        print(f"saved {path}", file=sys.stderr)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    out = export_reference(args.run, args.out, args.model)
    print(f"saved {out}", file=sys.stderr)
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from harness.training.sweep import format_best, run_sweep  # Optuna: only here
    from harness.training.train import TrainingInterrupted

    if args.study is not None:
        try:
            check_name(args.study)
        except ValueError as exc:
            raise HarnessError(f"--study {args.study[:40]!r}: a study name {exc}") from None
    study = args.study or load_config(args.config, args.overrides).name
    try:
        result = run_sweep(
            args.config,
            args.overrides,
            args.space,
            args.trials,
            study,
            args.sweeps_dir,
            storage_url=args.storage,
            resume=args.resume,
            pruner=args.pruner,
            jobs=args.jobs,
            worker=args.worker,
            report=None if args.quiet else print_trial,
        )
    except (KeyboardInterrupt, TrainingInterrupted) as exc:  # the trial under way is marked failed
        signum = getattr(exc, "signum", signal.SIGINT)  # SweepInterrupted: SIGTERM
        print(f"harness: sweep stopped by {signal.Signals(signum).name}; continue it with the "
              "same command and --resume", file=sys.stderr)  # fmt: skip
        return 128 + signum
    if args.worker:
        return 0
    print(format_best(result))
    if result is not None:
        print(f"saved {args.sweeps_dir / study / BEST_CONFIG}", file=sys.stderr)
    return 0


def print_trial(line: str) -> None:
    """One finished trial of a sweep, on stderr."""
    print(line, file=sys.stderr, flush=True)


def cmd_bench(args: argparse.Namespace) -> int:
    from harness.bench import format_bench, run_bench

    result = run_bench(args.what)
    print(_json(result) if args.json else format_bench(result))
    return 0


COMMANDS = {
    "run": cmd_run,
    "eval": cmd_eval,
    "tune": cmd_tune,
    "compare": cmd_compare,
    "render": cmd_render,
    "export": cmd_export,
    "sweep": cmd_sweep,
    "bench": cmd_bench,
}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``harness`` console script."""
    _settle_environment()
    try:
        # The modules are loaded: from here on a Ctrl-C is a KeyboardInterrupt, which each
        # command handles (harness/__init__.py turned it into one line while they loaded).
        end_of_loading()
        code = _main(list(sys.argv[1:] if argv is None else argv))
    except KeyboardInterrupt:  # Ctrl-C before a command's own handling (parsing the arguments)
        print("harness: interrupted", file=sys.stderr)
        code = 128 + signal.SIGINT
    if argv is None and code in (128 + signal.SIGINT, 128 + signal.SIGTERM):
        # Stopped by a signal, the message printed: the process only has to exit now. A further
        # Ctrl-C (a terminal sends one to the whole group, and people press it twice) would
        # otherwise land in the interpreter's shutdown (torch's finalizers) with a traceback.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return code


def _settle_environment() -> None:
    """Take from the environment the command starts in only what it means for this command.

    * Paths are printed whatever the terminal's encoding: a character it lacks (``ü`` under
      ``PYTHONIOENCODING=ascii`` or an ASCII locale, a file name that is not UTF-8) is written as
      a backslash escape instead of raising ``UnicodeEncodeError`` after the work is done.
    * Pictures are written with matplotlib's Agg backend: the commands only write files, so the
      user's display backend (``MPLBACKEND``, a matplotlibrc) must not matter, and matplotlib
      rejects an unknown ``MPLBACKEND`` as it is imported (by rliable's dependencies too, for
      mere statistics), so the variable itself is set, before anything imports matplotlib. The
      processes the command starts inherit it.

    (A current folder deleted since the shell entered it is refused earlier, in
    ``harness/__init__.py``: libraries ask for it while they load.)
    """
    for stream in (sys.stdout, sys.stderr):
        if isinstance(stream, io.TextIOWrapper):  # not None, nor a replacement without it
            stream.reconfigure(errors="backslashreplace")
    os.environ["MPLBACKEND"] = "agg"


def _main(argv: list[str]) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, already printed on one line)
        return int(exc.code or 0)
    args.argv = argv
    try:
        with warnings.catch_warnings():
            # Map warnings are worth one line each, not a stack location.
            warnings.simplefilter("default")
            return COMMANDS[args.command](args)
    except (
        ConfigError,
        RunDirError,
        HarnessError,
        CheckpointError,
        TargetError,
        GroupError,
        SweepError,
    ) as exc:
        print(f"harness: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:  # a file the command had to read or write (full disk, permissions)
        print(f"harness: error: {os_error_text(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except EnvFailed as exc:  # an env of one's own, past its check (an evaluation's episode)
        print(f"harness: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C outside training (which stops cleanly by itself)
        print("harness: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT


if __name__ == "__main__":
    sys.exit(main())
