"""Runs on a ``dask.distributed`` cluster (sweeps, image fits into a store): the driver's loop
(:func:`run_on_cluster`) and what each worker process builds once and reuses for every task
(:func:`worker_engine`, :func:`per_process`); the engine of a local run (:func:`local_engine`).

Every task writes its own unit of work into the store itself (a path or URL every worker
reaches) and returns a small summary to the driver; nothing large travels back.
"""
from __future__ import annotations

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


def run_on_cluster(task, shared, items, args_of, key, finished, *, workers=None, scheduler=None, client=None):
    """Run ``task(shared, *args_of(item))`` for every item on a ``dask.distributed`` cluster:
    ``client``, or a new client of the scheduler at ``scheduler``, or a new local cluster of
    ``workers`` processes (1 thread each), closed again at the end if made here.

    ``shared`` is scattered to every worker once; at most two tasks per worker thread (plus two)
    are in flight, the next submitted as one finishes; ``finished(result)`` is called on the
    driver as the results arrive (in any order).  On an error (or Ctrl-C) the tasks not yet done
    are cancelled and the error is raised.  Used by :func:`pbrdf_cl.analysis.sweeps.sweep` and
    :func:`pbrdf_cl.fitting.images.store.write_store`.
    """
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise RuntimeError("a cluster run needs dask.distributed: pip install 'pbrdf-cl[cluster]'") from None
    cluster = own_client = None
    try:
        if client is None:
            if workers is not None:
                _default_pocl_cache()
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=logging.ERROR)
                own_client = client = Client(cluster)
            else:
                own_client = client = Client(scheduler, timeout=60)
        n_threads = sum(client.nthreads().values()) or 1
        token = uuid.uuid4().hex[:8]
        shared_future = client.scatter(shared, broadcast=True)
        pending = iter(items)

        def submit(item):
            return client.submit(task, shared_future, *args_of(item), key=f"{key}-{token}-{item}", pure=False,
                                 retries=1)
        first = [submit(i) for i in itertools.islice(pending, 2 * n_threads + 2)]
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
    finally:
        if own_client is not None:
            own_client.close()
        if cluster is not None:
            cluster.close()
