"""Runs on a ``dask.distributed`` cluster (sweeps, image fits into a store): a client for the
length of a run (:func:`connect`), the driver's loops (:func:`run_on_cluster`, results in any
order; :func:`map_in_order`, results in order) and what each worker process builds once and
reuses for every task (:func:`worker_engine`, :func:`per_process`); the engine of a local run
(:func:`local_engine`).

Every task of a store's run writes its own unit of work into the store itself (a path or URL
every worker reaches) and returns a small summary to the driver; nothing large travels back.
The label stage's passes (:mod:`pbrdf_cl.fitting.images.label_workers`) return each block's
sums over its rows and its pixels' own parameters (a few floats per pixel).
"""
from __future__ import annotations

import collections
import contextlib
import itertools
import logging
import os
import tempfile
import threading
import uuid

from ..device.engine import engine_for
from . import interrupt

#: This process's engines, by (device, backend) (:func:`worker_engine`).
_ENGINES = {}
#: Held while a per-process object is looked up or built: a worker may run tasks in threads.
_LOCK = threading.Lock()


def _default_pocl_cache():
    """A cluster's worker processes share one PoCL kernel cache unless ``POCL_CACHE_DIR`` says otherwise."""
    os.environ.setdefault("POCL_CACHE_DIR", os.path.join(tempfile.gettempdir(), "pbrdf-cl-pocl-cache"))


def per_process(cache, key, make):
    """``cache[key]``, built by ``make()`` the first time in this process (under a lock shared by
    every worker thread): a store opened once per worker, then reused by each of its tasks."""
    with _LOCK:
        if key not in cache:
            cache[key] = make()
        return cache[key]


def drop_per_process(cache, key):
    """Drop ``cache[key]`` (built by :func:`per_process`) in this process, under the same lock."""
    with _LOCK:
        cache.pop(key, None)


def worker_engine(device=None, backend="auto"):
    """This process's engine for ``device`` and ``backend`` (built once, then reused by every
    unit of work; see :func:`pbrdf_cl.device.engine.engine_for`)."""
    def make():
        _default_pocl_cache()
        return engine_for(None, device, backend)
    return per_process(_ENGINES, (device, backend), make)


def local_engine(engine=None, backend="auto", device=None):
    """The engine a local run into a store (and an image fit in memory) computes with: ``engine``
    if given, else this process's engine for ``device`` (built once, ``worker_engine``), else
    the default for ``backend`` (both through :func:`pbrdf_cl.device.engine.engine_for`).

    Parameters
    ----------
    engine : pbrdf_cl.Engine or NumpyEngine, optional
        The caller's.
    backend : {"auto", "opencl", "numpy"}, default "auto"
        As for :func:`pbrdf_cl.dop`.
    device : str, optional
        An OpenCL device (see :func:`pbrdf_cl.select_device`).

    Returns
    -------
    pbrdf_cl.Engine or pbrdf_cl.NumpyEngine

    Examples
    --------
    >>> local_engine(backend="numpy")
    NumpyEngine(float64 reference)
    """
    if engine is not None or device is None:
        return engine_for(engine, backend=backend)
    return worker_engine(device, backend)


def require_distributed(what):
    """Refuse a cluster run (``what``: "sweep", "fit") where ``dask.distributed`` is not installed,
    before any work."""
    import importlib.util
    if importlib.util.find_spec("distributed") is None:
        raise RuntimeError(f"a cluster {what} needs dask.distributed: pip install 'pbrdf-cl[cluster]' "
                           "(or run without --workers/--scheduler)")


@contextlib.contextmanager
def connect(workers=None, scheduler=None, client=None):
    """A client of a ``dask.distributed`` cluster for the length of a ``with`` block: ``client``
    itself, or a new client of the scheduler at ``scheduler``, or a new local cluster of
    ``workers`` processes (1 thread each); what is made here is closed at the end of the block,
    also on an error.  None where none of the three is given (a local run).

    Examples
    --------
    >>> with connect(workers=2) as client:  # doctest: +SKIP
    ...     client.nthreads()
    """
    if workers is None and scheduler is None and client is None:
        yield None
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise RuntimeError("a cluster run needs dask.distributed: pip install 'pbrdf-cl[cluster]'") from None
    if client is not None:
        yield client
        return
    cluster = own = None
    try:
        if workers is not None:
            _default_pocl_cache()
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=logging.ERROR)
            own = Client(cluster)
        else:
            own = Client(scheduler, timeout=60)
        yield own
    finally:
        if own is not None:
            own.close()
        if cluster is not None:
            cluster.close()


def in_flight(client):
    """How many tasks a driver keeps submitted at once: two per worker thread, plus two."""
    return 2 * (sum(client.nthreads().values()) or 1) + 2


def map_in_order(client, task, shared_future, items, key):
    """Yield ``task(shared_future, *args)`` for every ``args`` of ``items`` computed on the
    workers of ``client``, in the order of ``items`` (whatever order they finish in), at most
    :func:`in_flight` tasks submitted at once, the next as the oldest is yielded; a Ctrl-C that
    Python swallowed is raised between results (:func:`pbrdf_cl.store.interrupt.check`).  On an
    error, or when the caller stops early, the tasks not yet done are cancelled.  Tasks are named
    ``key``, a token and their place.

    Examples
    --------
    >>> list(map_in_order(client, pow, client.scatter(2), [(3,), (4,)], "pow"))  # doctest: +SKIP
    [8, 16]
    """
    token = uuid.uuid4().hex[:8]
    pending = enumerate(items)
    queue = collections.deque()

    def submit():
        nxt = next(pending, None)
        if nxt is not None:
            i, args = nxt
            queue.append(client.submit(task, shared_future, *args, key=f"{key}-{token}-{i}", pure=False, retries=1))
    try:
        for _ in range(in_flight(client)):
            submit()
        while queue:
            fut = queue.popleft()
            result = fut.result()
            fut.release()
            submit()
            yield result
            interrupt.check()
    finally:
        if queue:
            client.cancel(list(queue))


def run_on_cluster(task, shared, items, args_of, key, finished, *, workers=None, scheduler=None, client=None):
    """Run ``task(shared, *args_of(item))`` for every item on a ``dask.distributed`` cluster:
    ``client``, or a new client of the scheduler at ``scheduler``, or a new local cluster of
    ``workers`` processes (1 thread each), closed again at the end if made here (:func:`connect`).

    ``shared`` is scattered to every worker once; at most two tasks per worker thread (plus two)
    are in flight, the next submitted as one finishes; ``finished(result)`` is called on the
    driver as the results arrive (in any order).  On an error (or Ctrl-C) the tasks not yet done
    are cancelled and the error is raised.  Used by :func:`pbrdf_cl.analysis.sweeps.sweep` and
    :func:`pbrdf_cl.fitting.images.store.write_store`.
    """
    with connect(workers, scheduler, client) as client:
        from distributed import as_completed
        token = uuid.uuid4().hex[:8]
        shared_future = client.scatter(shared, broadcast=True)
        pending = iter(items)

        def submit(item):
            return client.submit(task, shared_future, *args_of(item), key=f"{key}-{token}-{item}", pure=False,
                                 retries=1)
        first = [submit(i) for i in itertools.islice(pending, in_flight(client))]
        queue = as_completed(first)
        try:
            for fut in queue:
                result = fut.result()
                fut.release()
                finished(result)
                interrupt.check()
                nxt = next(pending, None)
                if nxt is not None:
                    queue.add(submit(nxt))
        except BaseException:
            client.cancel(list(queue.futures))
            raise
