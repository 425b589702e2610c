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
"""

from __future__ import annotations

import os
import sys
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
)


def python_command(code: str) -> list[str]:
    """``python -c CODE`` that runs ``code`` without the start folder on ``sys.path``."""
    return [sys.executable, "-c", _SCRUB + code]


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
