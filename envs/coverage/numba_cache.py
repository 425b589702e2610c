"""The compiled kernels' cache (numba's ``cache=True``): a damaged entry is compiled again.

numba keeps each kernel's machine code in an index (``.nbi``) and data files (``.nbc``) beside
the module (``__pycache__``) or under ``NUMBA_CACHE_DIR``, and unpickles them at the kernel's
first call. A file cut short (a full disk, a killed write on a shared folder, a copied tree)
makes that call raise ``UnpicklingError`` (or another error of the bytes), in every command
until someone finds and deletes the file. Here a cache entry that cannot be loaded is removed
with one line on stderr, and numba compiles the kernel and writes a fresh entry, as it does on
a first run. Installed on import (``envs/coverage/__init__.py`` imports this module first),
before any kernel is called.
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path
from typing import Any


def check_thread_count() -> None:
    """Refuse ``NUMBA_NUM_THREADS`` below 1 in one line: numba raises at its import otherwise,
    a traceback from deep inside it.

    Raises:
        ValueError: naming the variable.
    """
    text = os.environ.get("NUMBA_NUM_THREADS", "").strip()
    try:
        value = int(text) if text else None
    except ValueError:  # numba warns and takes its default: not ours to refuse
        return
    if value is not None and value < 1:
        raise ValueError(
            f"NUMBA_NUM_THREADS={text}: numba needs at least 1 thread; unset it or give a "
            "whole number of at least 1"
        )


#: The cache folders this process has found damaged entries in (each is named once).
_REPORTED: set[Path] = set()


def _discard(cache: Any, error: BaseException) -> None:
    """Remove the index and data files of ``cache`` (a numba ``Cache``); the first time in its
    folder, say so in one line (the kernels of a module share a folder, and a damaged folder
    has many)."""
    index = Path(cache._cache_file._index_path)
    stem = index.name[: -len(".nbi")]
    for path in [index, *index.parent.glob(f"{stem}.*.nbc")]:
        with contextlib.suppress(OSError):  # unwritable: compiled in memory each time, still runs
            path.unlink()
    if index.parent not in _REPORTED:
        _REPORTED.add(index.parent)
        print(
            f"numba cache: a damaged entry in {index.parent} ({index.name}: "
            f"{type(error).__name__}); removed, compiling again",
            file=sys.stderr,
        )


def install() -> None:
    """Make numba treat a cache entry that cannot be loaded (or indexed for saving) as absent."""
    from numba.core import caching

    cache = caching.Cache
    if getattr(cache.load_overload, "_rebuilds_damaged", False):
        return
    load, save = cache.load_overload, cache.save_overload

    def load_overload(self: Any, sig: Any, target_context: Any) -> Any:
        try:
            return load(self, sig, target_context)
        except Exception as exc:  # the bytes of a damaged file raise many kinds
            _discard(self, exc)
            return None  # a miss: numba compiles the kernel and saves a fresh entry

    def save_overload(self: Any, sig: Any, data: Any) -> None:
        try:
            save(self, sig, data)
        except Exception as exc:  # an index that cannot be read back: the next run compiles
            _discard(self, exc)

    load_overload._rebuilds_damaged = True  # type: ignore[attr-defined]
    cache.load_overload = load_overload  # type: ignore[method-assign]
    cache.save_overload = save_overload  # type: ignore[method-assign]


check_thread_count()
install()
