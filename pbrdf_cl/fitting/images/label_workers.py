"""The label stage's block passes on ``dask.distributed`` workers (:class:`WorkerBlocks`), what
``pbrdf_cl.fit_batch(stack, labels=L, store=..., workers=N)`` (or ``scheduler=``, ``client=``)
runs before its per-pixel pass, on the same cluster.

Each block of a pass (``<pass>_block`` of :class:`pbrdf_cl.fitting.images.label_stage.Passes`:
the profile on the grid, the start, the refinement's descents, the subsample's rows) is one task
(:func:`run_label_block`); a worker builds the job's ``Passes`` once, with its own engine
(:func:`pbrdf_cl.store.cluster.worker_engine`, the one the per-pixel pass's tasks use), and
reuses them for every block of every pass.  The driver gets the blocks' results in block order
(:func:`pbrdf_cl.store.cluster.map_in_order`) and adds their sums per row in row order, so the
label stage's result is the in-memory one bit for bit, whatever the number of workers (on the
same device).  What comes back per block: its sums per row and label, and its pixels' own
parameters (a few floats per pixel); the stack stays with the workers.
"""
from __future__ import annotations

import uuid

from ...store import cluster
from .label_stage import Passes

#: This process's label-stage passes, by run (one run's at a time: :func:`run_label_block`).
_PASSES = {}


def run_label_block(job, token, kind, device, backend, r0, r1, *args):
    """Dask task: ``Passes.<kind>_block(r0, r1, *args)`` of ``job``'s label stage with this
    worker's engine.

    Parameters
    ----------
    job : pbrdf_cl.fitting.images.labels.LabelJob
        The job (scattered to every worker once per label stage).
    token : str
        The label stage's run: the worker builds its ``Passes`` once per run (dropping another
        run's, so that a long-lived worker keeps one stack).
    kind : {"profile", "evaluate", "gather"}
        The pass.
    device, backend
        The engine each worker builds once (``pbrdf_cl.store.cluster.worker_engine``).
    r0, r1 : int
        The block's rows.
    *args
        The pass's inputs for the block.

    Returns
    -------
    tuple or list
        What the block function returns.

    Examples
    --------
    >>> client.submit(run_label_block, job_future, token, "profile", None, "auto", 0, 8)  # doctest: +SKIP
    """
    eng = cluster.worker_engine(device, backend)  # (built under the lock per_process holds: not inside make)

    def make():
        _PASSES.clear()  # another run's passes (and its stack) go
        return Passes(job, eng)
    passes = cluster.per_process(_PASSES, token, make)
    try:
        import dask
    except ImportError:  # pragma: no cover - a worker has dask
        return getattr(passes, f"{kind}_block")(r0, r1, *args)
    with dask.config.set(scheduler="synchronous"), passes.eng.lock:  # one block in flight per engine
        return getattr(passes, f"{kind}_block")(r0, r1, *args)


def forget(token):
    """Run on every worker at the end of a label stage: drop its passes (and the stack they hold)."""
    cluster.drop_per_process(_PASSES, token)


class WorkerBlocks:
    """Where a label stage's blocks run with a cluster: ``map(kind, items)`` yields
    ``Passes.<kind>_block(*item)`` of every item, computed on the workers of ``client``, in the
    order of ``items``.

    Parameters
    ----------
    client : distributed.Client
        The cluster's client (kept open by the caller for the label stage and the per-pixel pass).
    job : pbrdf_cl.fitting.images.labels.LabelJob
        The job, sent to every worker once.
    device, backend
        What every worker builds its engine for.

    Examples
    --------
    >>> with WorkerBlocks(client, job) as blocks:  # doctest: +SKIP
    ...     result = run_label_stage(job, engine, workers=blocks)
    """

    def __init__(self, client, job, device=None, backend="auto"):
        self.client, self.device, self.backend = client, device, backend
        self.token = uuid.uuid4().hex
        self.job = client.scatter(job, broadcast=True)

    def map(self, kind, items):
        """The results of the pass ``kind`` on the blocks ``items`` ((r0, r1, *args) each), in order."""
        return cluster.map_in_order(self.client, run_label_block, self.job,
                                    ((self.token, kind, self.device, self.backend, *item) for item in items),
                                    f"pbrdf-labels-{kind}")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        """The workers drop the job and its passes (after an error, only the job: the workers may
        be gone; a worker's next label stage drops the old passes)."""
        try:
            if exc[0] is None:
                self.client.run(forget, self.token)
        finally:
            self.job.release()
