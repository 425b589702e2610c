"""The ``harness`` command: ``harness run CONFIG.yaml`` and friends (SPEC §5).

Every user error (a bad config, map, path or argument) ends with one line on stderr and exit
code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

from harness.checkpoints import CheckpointError
from harness.config import ConfigError, ExperimentConfig, load_config
from harness.rundir import RunDir, RunDirError

EXIT_USAGE = 2


class HarnessError(Exception):
    """A user-facing error: printed as one line, exit code 2."""


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
    parser = argparse.ArgumentParser(
        prog="harness",
        description="Train, evaluate and compare multi-agent coverage policies.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="train an experiment from a YAML config")
    run.add_argument("config", type=Path, nargs="?", help="experiment YAML file (see configs/)")
    run.add_argument(
        "--resume",
        type=Path,
        metavar="RUN_DIR",
        help="continue an interrupted run from its latest checkpoint (uses its config.yaml)",
    )
    _add_overrides(run)
    run.add_argument("--seed", type=int, help="override the config's seed")
    run.add_argument("--name", help="override the config's name (the run folder's prefix)")
    run.add_argument("--runs-dir", type=Path, default=Path("runs"), help="where runs are written")
    run.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser


def resolve_run_config(args: argparse.Namespace) -> ExperimentConfig:
    """The config of ``harness run``: the file, then ``--set``, ``--seed`` and ``--name``."""
    overrides = list(args.overrides)
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    if args.name is not None:
        overrides.append(f"name={json.dumps(args.name)}")
    return load_config(args.config, overrides)


def cmd_run(args: argparse.Namespace) -> int:
    if args.resume is not None:
        return _resume(args)
    if args.config is None:
        raise HarnessError("run needs a CONFIG.yaml (or --resume RUN_DIR)")
    config = resolve_run_config(args)
    run = RunDir.create(args.runs_dir, config.name)
    run.write_command(args.argv)
    print(f"run folder: {run.path}", file=sys.stderr)
    return _train(config, run, args, resume=False)


def _resume(args: argparse.Namespace) -> int:
    if args.config is not None or args.overrides or args.seed is not None or args.name:
        raise HarnessError(
            "--resume continues a run with its own config.yaml; drop the other options"
        )
    run = RunDir(args.resume)
    if not run.config.is_file():
        raise HarnessError(f"{run.path}: not a run folder (no config.yaml)")
    config = load_config(run.config)
    from harness.checkpoints import latest_checkpoint, read_state

    state = read_state(latest_checkpoint(run.checkpoints))
    if state.finished:
        print(
            f"{run.path}: this run already finished ({state.num_timesteps} steps)", file=sys.stderr
        )
        return 0
    run.write_command(args.argv)
    print(f"resuming {run.path} at step {state.num_timesteps}", file=sys.stderr)
    return _train(config, run, args, resume=True)


def _train(config: ExperimentConfig, run: RunDir, args: argparse.Namespace, resume: bool) -> int:
    from harness.train import TrainingFailed, TrainingInterrupted, train  # torch, SB3: only here

    try:
        train(config, run, progress_bar=not args.no_progress, resume=resume)
    except TrainingInterrupted as exc:
        print(
            f"harness: stopped by {exc} after writing {exc.checkpoint}; "
            f"resume with: harness run --resume {run.path}",
            file=sys.stderr,
        )
        return 128 + exc.signum
    except TrainingFailed as exc:
        print(f"harness: error: {exc}", file=sys.stderr)
        return 1
    print(f"done: {run.model}", file=sys.stderr)
    return 0


COMMANDS = {"run": cmd_run}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``harness`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.argv = argv
    try:
        with warnings.catch_warnings():
            # Map warnings are worth one line each, not a stack location.
            warnings.simplefilter("default")
            return COMMANDS[args.command](args)
    except (ConfigError, RunDirError, HarnessError, CheckpointError) as exc:
        print(f"harness: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
