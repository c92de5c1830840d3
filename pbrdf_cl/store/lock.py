"""One writer at a time: the lock a run into a local store holds from before the store is created
(or resumed) until the run ends (:func:`holding`).

The lock is ``NAME.lock`` beside the store ``NAME`` (a ``filelock.FileLock``: an OS lock on the
file, which the OS drops when its process dies; deleting the store does not release it).  Its
holder writes a record into it (``pid``, ``host``, ``started``) and empties it again on a normal
release, so that:

- a second run into the same store is refused at once (:class:`pbrdf_cl.StoreError`, one line
  naming the holder's pid, host and start);
- a record left in a lock that can be taken is that of a run that died (SIGKILL, a crash, a
  machine that went down): the lock is taken over and this is said in one warning line
  (:class:`pbrdf_cl.StoreWarning`).

Under the lock the ``NAME.creating-*`` folders of creations that were killed
(:func:`pbrdf_cl.store.zarr.create_in_place`) are removed: no other run can be creating the store.

Stores given by URL (fsspec: ``s3://``, ``memory://``, ...) are not locked: no OS lock spans an
object store; one writer at a time is then the caller's to ensure.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import time
import warnings
from pathlib import Path

from ..errors import StoreError, StoreWarning


def lock_path(name):
    """The lock file of the local store ``name`` (an absolute path): ``NAME.lock`` beside it."""
    return Path(f"{os.fspath(name).rstrip(os.sep)}.lock")


def _read_record(path):
    try:
        text = path.read_text()
    except OSError:
        return None
    try:
        rec = json.loads(text) if text.strip() else None
    except ValueError:
        return {"pid": "?", "host": "?", "started": text.strip()[:40]}
    return rec if isinstance(rec, dict) else None


def _who(rec):
    return f"pid {rec.get('pid', '?')} on {rec.get('host', '?')}, started {rec.get('started', '?')}"


def remove_stale_creations(name):
    """Remove the ``NAME.creating-*`` folders beside the store ``name`` (creations killed before
    their rename); called under the lock, where no other run can be creating it.  Returns how
    many were removed."""
    path = Path(name)
    removed = 0
    if not path.parent.is_dir():
        return 0
    for p in path.parent.glob(f"{path.name}.creating-*"):
        shutil.rmtree(p, ignore_errors=True)
        removed += not p.exists()
    return removed


@contextlib.contextmanager
def holding(name, local=True):
    """Hold the lock of the store ``name`` for the block (nothing for a store given by URL,
    ``local`` False).

    Raises
    ------
    StoreError
        Another run holds it: ``"NAME is being written by another run (pid P on HOST, started T;
        lock NAME.lock); ..."``.
    """
    if not local:
        yield
        return
    import filelock
    path = lock_path(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    before = _read_record(path)  # read first: an older filelock truncates the file on trying
    lock = filelock.FileLock(str(path), timeout=0)
    try:
        lock.acquire()
    except filelock.Timeout:
        rec = _read_record(path) or before or {}
        raise StoreError(f"{name} is being written by another run ({_who(rec)}; lock {path}); wait for it to "
                         "end, or choose another --out") from None
    try:
        if before:
            warnings.warn(StoreWarning(f"{name}: took over the lock of a run that is no longer running "
                                       f"({_who(before)}); resuming"), stacklevel=3)
        record = {"pid": os.getpid(), "host": socket.gethostname(),
                  "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        with open(path, "w") as f:
            f.write(json.dumps(record) + "\n")
        n = remove_stale_creations(name)
        if n:
            warnings.warn(StoreWarning(f"{name}: removed {n} folder(s) {Path(name).name}.creating-* left by a "
                                       "creation that was killed"), stacklevel=3)
        yield
    finally:
        with contextlib.suppress(OSError):
            with open(path, "w"):
                pass  # an empty record: released normally
        lock.release()
