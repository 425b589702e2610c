"""The commands of the Python processes the harness starts: seed-group members and their
resumes, sweep workers, the memory benchmark. The one owner of how a child Python is started,
and of how many cores a process may use (:func:`available_cores`).

A child imports only the installed packages and this harness, never a module that happens to lie
in the folder it was started from. ``python -m`` and ``python -c`` put that folder first on
``sys.path``, so a ``yaml.py`` (or ``json.py``, ``numpy.py``, ``resource.py``) beside a
downloaded config would run in every child. Python 3.11's ``-P`` flag leaves it out, but the
project supports 3.10, and ``-I`` would also drop ``PYTHONPATH`` (a source checkout run without
installing); so each child starts from a short bootstrap that removes that first entry before it
imports anything, then appends the folder this harness was imported from at the end of the path
(after every installed package, so it can only supply ``harness`` and ``envs``). A start folder
deleted meanwhile ends the child there, in one line (:func:`harness.check_working_folder`).

A child never outlives the harness command that started it: the bootstrap also starts
:func:`follow_parent`, so that a parent ended by SIGKILL (which it cannot pass on) leaves no
sweep worker or seed run training on as an orphan.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path

#: The folder holding the ``harness`` package this process runs (a checkout or site-packages).
_ROOT = str(Path(__file__).resolve().parents[1])

_SCRUB = (
    "import os, sys\n"
    "try:\n"
    "    _cwd = os.getcwd()\n"
    "except OSError:  # deleted meanwhile: refused below, in one line\n"
    "    _cwd = None\n"
    "if sys.path and sys.path[0] in ('', _cwd):\n"
    "    del sys.path[0]  # the start folder, put first by -c\n"
    f"sys.path.append({_ROOT!r})\n"
    "from harness import check_working_folder\n"
    "check_working_folder()\n"
    "from harness.processes import follow_parent\n"
)

#: Seconds between a child's looks at its parent; and how long a child whose parent is gone
#: has for its clean stop (SIGTERM: a checkpoint, its trial marked failed) before SIGKILL.
PARENT_POLL_S, ORPHAN_GRACE_S = 0.5, 120.0


def python_command(code: str) -> list[str]:
    """``python -c CODE`` that runs ``code`` without the start folder on ``sys.path``, and ends
    when this process ends (:func:`follow_parent`)."""
    return [sys.executable, "-c", f"{_SCRUB}follow_parent({os.getpid()})\n{code}"]


def harness_command(*args: str) -> list[str]:
    """The ``harness ARGS...`` command line of a child process (the same interpreter)."""
    code = "from harness.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    return [*python_command(code), *args]


def available_cores() -> int:
    """The cores this process may run on: its CPU affinity (``taskset``, Slurm, containers
    restrict it), else the machine's count."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0)) or 1
    return os.cpu_count() or 1


def follow_parent(pid: int, poll_s: float = PARENT_POLL_S, grace_s: float = ORPHAN_GRACE_S) -> None:
    """End this process when process ``pid``, the one that started it, ends, however it ends.

    A parent that is gone already ends it at once (exit 143, one line). Otherwise a daemon
    thread looks every ``poll_s`` seconds; once the parent is gone it sends this process SIGTERM,
    which a run or sweep turns into its clean stop, and SIGKILL ``grace_s`` seconds later.

    A thread that polls rather than Linux's ``PR_SET_PDEATHSIG``: that signal follows the parent
    *thread* that started the child, and a parent may start its children from a worker thread
    that ends long before it does. The parent is gone when this process was handed to another
    one (``getppid`` changed), or, for a child started through a wrapper (``sh -c``, a
    debugger), when ``pid`` no longer exists.
    """
    start = os.getppid()

    def gone() -> bool:
        if os.getppid() != start:
            return True
        if start == pid:
            return False
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:  # alive, someone else's: a pid taken again is out of reach
            return False
        return False

    if gone():
        print(
            f"harness: error: the process that started this one ({pid}) has ended", file=sys.stderr
        )
        sys.exit(128 + signal.SIGTERM)

    def watch() -> None:
        while not gone():
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(grace_s)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="harness-follow-parent", daemon=True).start()
