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

import numbers
import os
import sys
import time

import numpy as np

from .. import sizes
from ..errors import SpecError
from . import cluster, interrupt
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
    *args)`` (the unit's values), ``write(i, values, *args)`` (into the store's arrays) and
    ``result(eng, i, values, seconds)`` (the small summary sent back to the driver); :meth:`run`
    does them in order and marks the unit done only after its values are written.

    Parameters
    ----------
    name : str
        The store (a path or URL).
    error : type
        The exception of a store written by other OpenCL kernels
        (:func:`pbrdf_cl.store.zarr.check_kernels`): a worker with another pbrdf-cl would mix values.
    """

    #: The testing aid's environment variable: seconds per unit, half before its values are
    #: written, half between writing them and marking it done (so that an interrupt lands inside).
    delay_env = None

    def __init__(self, name, error=SpecError):
        self.group = zarr_store.open_group(name, "r+")
        zarr_store.check_kernels(name, self.group.attrs, error=error)
        self.done = self.group[zarr_store.DONE]

    def compute(self, eng, i, *args):  # pragma: no cover - every job defines it
        raise NotImplementedError

    def write(self, i, values, *args):  # pragma: no cover
        raise NotImplementedError

    def result(self, eng, i, values, seconds):  # pragma: no cover
        raise NotImplementedError

    def run(self, eng, i, *args):
        """Compute unit ``i`` with ``eng``, write it, then mark it done; returns :meth:`result`."""
        t0 = time.perf_counter()
        values = self.compute(eng, i, *args)
        delay = float(os.environ.get(self.delay_env) or 0) if self.delay_env else 0.0
        if delay:
            time.sleep(delay / 2)
        self.write(i, values, *args)  # whole Zarr chunks, each written atomically by zarr
        if delay:
            time.sleep(delay / 2)
        self.done[int(i)] = 1  # ... and only then marked done
        return self.result(eng, i, values, time.perf_counter() - t0)


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
