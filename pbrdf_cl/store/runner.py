"""The one runner of the resumable stores (a sweep's chunks, an image fit's blocks of rows): the
checks before any work (:func:`check_cluster`, :func:`check_free_disk`), a unit of work computed,
written, then marked done (:class:`Writer`), and the loop over the units not yet done, here or
on a ``dask.distributed`` cluster, with its progress bar and its interrupt checks
(:func:`run_units`).

A job says only what its store is (:mod:`pbrdf_cl.store.zarr` creates and resumes it) and what a
unit computes and writes: a subclass of :class:`Writer` (``compute``, ``write``, ``result``), and
for a cluster a task that runs it on a worker.  :mod:`pbrdf_cl.analysis.sweeps` and
:mod:`pbrdf_cl.fitting.images.store` are the two jobs.
"""
from __future__ import annotations

import contextlib
import errno
import numbers
import os
import shutil
import sys
import time
import warnings

import numpy as np

from .. import sizes
from ..errors import SpecError, StoreError, StoreWarning
from . import cluster, interrupt, verify
from . import zarr as zarr_store


def check_cluster(workers=None, scheduler=None, client=None, engine=None, what="run"):
    """Check the cluster options of a store's run before any work; returns how many were given.

    Parameters
    ----------
    workers : int, optional
        A local cluster of this many processes: a positive integer (Python's or numpy's).
    scheduler, client : optional
        A running cluster's address, or a client of one; at most one of the three.
    engine : pbrdf_cl.Engine or NumpyEngine, optional
        A local run's engine: refused with a cluster, where every worker builds its own
        (``device=``, ``backend=``).
    what : str
        The run, for the message without ``dask.distributed`` ("sweep", "fit").

    Returns
    -------
    int
        0 (a local run) or 1.

    Raises
    ------
    ValueError
        More than one of them, ``workers`` not a positive integer, or ``engine`` with a cluster.
    RuntimeError
        A cluster without ``dask.distributed`` installed.

    Examples
    --------
    >>> check_cluster(workers=np.int64(2), what="sweep")  # doctest: +SKIP
    1
    """
    given = sum(x is not None for x in (workers, scheduler, client))
    if given > 1:
        raise ValueError("give at most one of workers=, scheduler= and client=")
    if workers is not None and (isinstance(workers, (bool, np.bool_)) or not isinstance(workers, numbers.Integral)
                                or workers < 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    if given and engine is not None:
        raise ValueError("engine= is for a local run; every cluster worker builds its own (device=, backend=)")
    if given:
        cluster.require_distributed(what)
    return given


def check_free_disk(store, need, what, allow_large, command, hint=""):
    """Refuse (:class:`pbrdf_cl.TooLargeError`, one line) a store of up to ``need`` bytes where
    less is free, unless ``allow_large``; ``what`` says what it holds ("4096 points,
    uncompressed"), ``command`` the ``pbrdf-cl`` command with ``--allow-large``, ``hint`` another
    way out (ending ", ")."""
    free = sizes.free_disk(store)
    if free is not None and need > free and not allow_large:
        raise sizes.TooLargeError(
            f"the store would hold up to {sizes.human(need)} ({what}) but {sizes.human(free)} is free where it goes; "
            f"free space, choose another store, {hint}or pass allow_large=True (pbrdf-cl {command} --allow-large) "
            "to start anyway")


def progress_bar(enabled, **kw):
    """A tqdm bar on stderr (``kw``: ``total``, ``initial``, ``unit``, ``desc``, ...), or None."""
    if not enabled:
        return None
    from tqdm.auto import tqdm
    return tqdm(dynamic_ncols=True, file=sys.stderr, **kw)


class Writer:
    """Writes the units of work of one job into one store (opened once per process, see
    :func:`pbrdf_cl.store.cluster.per_process`).  A job subclasses it with ``compute(eng, i,
    *args)`` (the unit's values), ``pieces(i, values, *args)`` (what to write: [(array name,
    region, values)], in the order of the store's ``store_units`` variables) and ``result(eng,
    i, values, seconds)`` (the small summary sent back to the driver); :meth:`run` does them in
    order: the unit's values, then their digest and device, and only then its done mark.

    Before writing and again before marking, the store must still hold the job (its root
    attribute ``job_key`` equal to ``job_sha256``): a store deleted and created again by another
    run under a paused one is never written into.

    Parameters
    ----------
    name : str
        The store (a path or URL).
    job_key, job_sha256 : str
        The root attribute naming the job and its value (the spec's or settings' SHA-256).
    error : type
        The exception of a store written by other OpenCL kernels
        (:func:`pbrdf_cl.store.zarr.check_kernels`): a worker with another pbrdf-cl would mix values.
    """

    #: The testing aid's environment variable: seconds per unit, half before its values are
    #: written, half between writing them and marking it done (so that an interrupt lands inside).
    delay_env = None

    def __init__(self, name, job_key, job_sha256, error=SpecError):
        self.name, self.job = name, (job_key, job_sha256)
        self.group = zarr_store.open_group(name, "r+")
        zarr_store.check_kernels(name, self.group.attrs, error=error)
        self.check_job()
        self.done = self.group[zarr_store.DONE]
        self.digest = self.group[zarr_store.DIGEST]
        self.device = self.group[zarr_store.DEVICE]
        self.arrays = {}

    def check_job(self):
        """Refuse (:class:`pbrdf_cl.StoreError`) to go on when the store no longer holds this job."""
        key, want = self.job
        for _ in range(5):  # a root attrs file being replaced reads as absent for an instant
            attrs = zarr_store.read_root_attrs(self.name)
            if attrs is not None:
                break
            time.sleep(0.05)
        have = (attrs or {}).get(key)
        if have != want:
            raise StoreError(f"{self.name} no longer holds this run's job ({key} {str(have)[:12]} now, {want[:12]} "
                             "when the run started: deleted or created again by another run?); this run stopped "
                             "without writing into it")

    def compute(self, eng, i, *args):  # pragma: no cover - every job defines it
        raise NotImplementedError

    def pieces(self, i, values, *args):  # pragma: no cover
        raise NotImplementedError

    def result(self, eng, i, values, seconds):  # pragma: no cover
        raise NotImplementedError

    def write_unit(self, i, pieces):
        """Write the unit's pieces (whole Zarr chunks, each written atomically by zarr), then its digest."""
        hashed = []
        for name, region, a in pieces:
            arr = self.arrays.get(name)
            if arr is None:
                arr = self.arrays[name] = self.group[name]
            a = np.asarray(a).astype(arr.dtype, copy=False)
            arr[region] = a
            hashed.append((name, a))
        self.digest[int(i)] = verify.values_sha256(hashed)

    def run(self, eng, i, *args):
        """Compute unit ``i`` with ``eng``, write it with its digest and device, then mark it done;
        returns :meth:`result`."""
        t0 = time.perf_counter()
        values = self.compute(eng, i, *args)
        delay = float(os.environ.get(self.delay_env) or 0) if self.delay_env else 0.0
        if delay:
            time.sleep(delay / 2)
        pieces = self.pieces(i, values, *args)
        self.check_job()
        self.write_unit(i, pieces)
        self.device[int(i)] = zarr_store.device_key(eng.description)
        if delay:
            time.sleep(delay / 2)
        self.check_job()
        self.done[int(i)] = 1  # ... and only then marked done
        return self.result(eng, i, values, time.perf_counter() - t0)


def disk_message(exc, name):
    """The one line of a full disk or a file-size limit met writing the store ``name`` (None for
    another error)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        code = getattr(exc, "errno", None)
        if code in (errno.ENOSPC, getattr(errno, "EDQUOT", -1)):
            return f"disk full writing {name}; free space and run the same command again to resume"
        if code == errno.EFBIG:
            return (f"a file would pass the file-size limit writing {name} (ulimit -f, or the file system's); "
                    "raise the limit and run the same command again to resume")
        exc = exc.__cause__ or exc.__context__
    return None


@contextlib.contextmanager
def session(store, name):
    """A run into the store ``name``: the store's lock held (:func:`pbrdf_cl.store.lock.holding`;
    a local store only), and a full disk or a file-size limit said in one line naming the store
    and how to resume (:class:`pbrdf_cl.StoreError`)."""
    from . import lock
    with lock.holding(name, zarr_store.is_local(store)):
        try:
            yield
        except Exception as exc:
            msg = disk_message(exc, name)
            if msg is None:
                raise
            raise StoreError(msg) from None


@contextlib.contextmanager
def discard_if_empty(store, name, created, n_units, job):
    """Remove a local store that this run ``created`` when the run fails (an input refused by the
    first unit, a device that fails) before any unit is done: it would block the corrected rerun.
    ``job`` (root attribute, value): a store that holds another job by then is left alone."""
    try:
        yield
    except Exception:
        if created and zarr_store.is_local(store) and not zarr_store.read_done(name, n_units).any() \
                and (zarr_store.read_root_attrs(name) or {}).get(job[0]) == job[1]:
            shutil.rmtree(name, ignore_errors=True)
        raise


def resume_units(name, n_units, variables, what):
    """The done marks of a store being resumed, each done unit checked against its digest
    (:func:`pbrdf_cl.store.verify.check_units`): the damaged ones are un-marked, said in one
    warning line, and computed again by this run."""
    done, bad = verify.check_units(name, n_units, variables)
    if bad:
        warnings.warn(StoreWarning(f"{name}: {len(bad)} of {len(bad) + int(done.sum())} done {what} were damaged "
                                   f"(missing, truncated or altered chunks: {what} {verify.first(bad)}); computing "
                                   "them again"), stacklevel=3)
    return done


def note_device(name, description, what):
    """Record ``description`` among the store's devices; a store resumed on another device is
    said in one warning line (its units' last bits may differ)."""
    before = verify.record_device(name, description)
    if before:
        warnings.warn(StoreWarning(f"{name}: resumed on {description}; its other {what} were computed on "
                                   f"{'; '.join(before)} (the last bits of their values may differ)"), stacklevel=3)


def run_units(todo, writer, finished, *, task, shared, args_of, key, local_args=None, engine=None, device=None,
              backend="auto", workers=None, scheduler=None, client=None, bar=None, started=None):
    """Compute the units ``todo`` of a job, each written into its store then marked done.

    Locally (none of ``workers``, ``scheduler``, ``client``): ``writer()`` (a :class:`Writer`) runs
    each unit on this process's engine (:func:`pbrdf_cl.store.cluster.local_engine` of ``engine``,
    ``device``, ``backend``; ``started(eng)`` is called with it first), with
    ``local_args(i)`` as its extra arguments.  On a cluster
    (:func:`pbrdf_cl.store.cluster.run_on_cluster`): ``task(shared, *args_of(i))`` per unit on the
    workers, tasks named ``key``.  ``finished(result)`` is called on this process as each unit is
    done, and a Ctrl-C that Python swallowed is raised between units
    (:func:`pbrdf_cl.store.interrupt.check`).  The progress ``bar`` is closed at the end, whatever
    happens.
    """
    try:
        if not len(todo):
            return
        if workers is None and scheduler is None and client is None:
            eng = cluster.local_engine(engine, backend, device)
            w = writer()
            if started is not None:
                started(eng)
            for i in todo:
                finished(w.run(eng, i, *(local_args(i) if local_args is not None else ())))
                interrupt.check()
        else:
            cluster.run_on_cluster(task, shared, [int(i) for i in todo], args_of, key, finished,
                                   workers=None if workers is None else int(workers), scheduler=scheduler,
                                   client=client)
    finally:
        if bar is not None:
            bar.close()
