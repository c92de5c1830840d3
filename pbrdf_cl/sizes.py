"""Sizes checked before any work: what an output needs against what the machine has.

Every public call that allocates its result (:func:`pbrdf_cl.dop` and the other per-point
functions, :func:`pbrdf_cl.grid`, maps, ``pbrdf-cl eval``, ``pbrdf-cl reproduce``, synthetic image
stacks) estimates it
first and refuses, with a one-line ``MemoryError`` subclass naming the size, what is available and
what to do, a result that cannot fit in memory; a sweep compares its store with the free disk.
The calls whose whole work is held in memory at once (:func:`pbrdf_cl.design`, maps, the image
fit's bookkeeping of its blocks) also refuse what exceeds their ``memory_budget``
(:func:`check_budget`), and :func:`pbrdf_cl.grid` a result above :data:`LARGE_RESULT` unless
``allow_large=True`` (:func:`check_result`).
"""
from __future__ import annotations

import os
import shutil

from .errors import TooLargeError


def human(nbytes) -> str:
    """``1536`` -> ``"1.5 KiB"``; ``"512 B"`` below a KiB."""
    for unit, size in (("PiB", 1 << 50), ("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if nbytes >= size:
            return f"{nbytes / size:.4g} {unit}"
    return f"{int(nbytes)} B"


def available_memory():
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``; elsewhere the free
    physical pages), or None where it cannot be told."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return None


def check_memory(nbytes, what, advice):
    """Raise :class:`TooLargeError` if ``nbytes`` (an estimate of ``what``) exceeds the available
    memory: ``"<what> needs 74.5 GiB, but 12.1 GiB of memory is available; <advice>"``."""
    avail = available_memory()
    if avail is not None and nbytes > avail:
        raise TooLargeError(f"{what} needs {human(nbytes)}, but {human(avail)} of memory is available; {advice}")


def check_budget(nbytes, what, budget, advice, raise_it="raise memory_budget"):
    """Raise :class:`TooLargeError` if ``nbytes`` (an estimate of ``what``) exceeds the available
    memory (:func:`check_memory`) or ``budget``: ``"<what> needs 206 GiB, more than memory_budget =
    1 GiB; <advice> or <raise_it>"``."""
    check_memory(nbytes, what, advice)
    if nbytes > budget:
        raise TooLargeError(f"{what} needs {human(nbytes)}, more than memory_budget = {human(budget)}; {advice} "
                            f"or {raise_it}")


#: The largest result an in-memory call returns without ``allow_large=True`` (2 GiB): above it the
#: chunked paths (a sweep into a Zarr store, reductions on the device) are the way.
LARGE_RESULT = 2 << 30


def check_result(nbytes, what, advice, allow_large=False):
    """Raise :class:`TooLargeError` if the result ``what`` of ``nbytes`` exceeds the available memory
    (:func:`check_memory`), or :data:`LARGE_RESULT` unless ``allow_large``."""
    check_memory(nbytes, what, advice)
    if nbytes > LARGE_RESULT and not allow_large:
        raise TooLargeError(f"{what} needs {human(nbytes)}, more than the {human(LARGE_RESULT)} an in-memory result "
                            f"may take; {advice}, or pass allow_large=True")


def free_disk(path):
    """Free bytes on the file system that holds ``path`` (or its nearest existing parent); None for
    remote stores."""
    if "://" in str(path) and not str(path).startswith("file://"):
        return None
    p = os.path.abspath(str(path).replace("file://", "", 1))
    while p and not os.path.exists(p):
        parent = os.path.dirname(p)
        if parent == p:
            break
        p = parent
    try:
        return shutil.disk_usage(p).free
    except OSError:
        return None
