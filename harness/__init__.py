"""coverage-harness: SB3 extensions, SuperSuit adapters and the ``harness`` command.

Packages by layer, each importing only from the ones above it in this list (the architecture
test, ``tests/test_architecture.py``, keeps it so):

* :mod:`harness.sb3`: the Stable-Baselines3 extensions (no ``envs`` import);
* :mod:`harness.config`: the typed config, YAML loading, ``--set``, map sources, migration;
* :mod:`harness.factory`: the one env factory;
* :mod:`harness.evaluation`: the episode loop, test policies, baselines;
* :mod:`harness.results`: the run folder, seed groups, statistics, plots;
* :mod:`harness.training`: the VecEnv adapters, the phase loop, callbacks, checkpoints, sweeps;
* :mod:`harness.cli` (parsing and printing) and :mod:`harness.bench`.
"""

from __future__ import annotations

import contextlib  # (already loaded by Python's start)
import os
import signal
import sys

TYPE_CHECKING = False  # not typing's: nothing is imported before the Ctrl-C handler below

if TYPE_CHECKING:
    from typing import Any

    from harness.sb3.dqn import DoubleDQN
    from harness.sb3.policies import DuelingDQNPolicy
    from harness.sb3.replay import PrioritizedReplayBuffer

__all__ = ["DoubleDQN", "DuelingDQNPolicy", "PrioritizedReplayBuffer"]


def _interrupted_while_loading(signum: int, frame: object) -> None:
    """SIGINT while the ``harness`` command loads its modules (seconds on a busy machine): one
    line and exit code 130, as a Ctrl-C anywhere else gives, instead of the traceback of the
    import under way. Nothing has been written yet."""
    sys.stderr.write("harness: interrupted\n")
    sys.stderr.flush()
    os._exit(128 + signal.SIGINT)


def _started_as_command() -> bool:
    """Whether this process is the ``harness`` command: its console script, or ``python -m
    harness.cli`` (whose ``sys.argv[0]`` is still ``-m`` while this package loads)."""
    if os.path.basename(sys.argv[0]) == "harness":
        return True
    argv = list(getattr(sys, "orig_argv", []))
    return "-m" in argv and argv[argv.index("-m") + 1 :][:1] == ["harness.cli"]


def check_working_folder() -> None:
    """Exit with one line and code 2 when the current folder is gone: deleted after the shell
    entered it, ``os.getcwd()`` fails, and libraries call it while they load (PettingZoo, in a
    default argument), which would end the command in their traceback. Relative paths mean
    nothing there, so the command is refused rather than guessed at. Run first by the command
    and by each process it starts (``harness/processes.py``)."""
    try:
        os.getcwd()
    except OSError as exc:
        problem = (
            "the current folder was deleted"
            if isinstance(exc, FileNotFoundError)
            else f"cannot read the current folder ({exc.strerror or type(exc).__name__})"
        )
        sys.stderr.write(
            f"harness: error: {problem}: cd to an existing folder and run the command again\n"
        )
        sys.stderr.flush()
        raise SystemExit(2) from None


def check_numba_threads() -> None:
    """Exit with one line and code 2 for ``NUMBA_NUM_THREADS`` below 1: numba raises at its
    import, a traceback from deep inside the first module that loads it (the env refuses it as
    well, for the Python API: ``envs.coverage.numba_cache.check_thread_count``)."""
    text = os.environ.get("NUMBA_NUM_THREADS", "").strip()
    if text.lstrip("+-").isdigit() and int(text) < 1:
        sys.stderr.write(
            f"harness: error: NUMBA_NUM_THREADS={text}: numba needs at least 1 thread; unset it "
            "or give a whole number of at least 1\n"
        )
        sys.stderr.flush()
        raise SystemExit(2)


def end_of_loading() -> None:
    """Give Ctrl-C back to Python (``KeyboardInterrupt``, which each command handles); called
    by ``harness.cli.main`` once the modules are loaded."""
    if signal.getsignal(signal.SIGINT) is _interrupted_while_loading:
        signal.signal(signal.SIGINT, signal.default_int_handler)


# First thing the command runs (the package loads before any of its modules): a library that
# imports harness keeps Python's own Ctrl-C, and so does a command started with SIGINT ignored.
if _started_as_command() and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
    # (ValueError: imported from another thread than the main one, not at the command's start)
    with contextlib.suppress(ValueError):
        signal.signal(signal.SIGINT, _interrupted_while_loading)
if _started_as_command():
    check_working_folder()
    check_numba_threads()


def __getattr__(name: str) -> Any:
    # Lazy (PEP 562): `import harness` (e.g. for the CLI's --help) does not import torch.
    if name in __all__:
        import harness.sb3

        return getattr(harness.sb3, name)
    raise AttributeError(f"module 'harness' has no attribute {name!r}")
