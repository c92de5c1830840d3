"""Per-pixel inversion of polarization image stacks: :func:`fit_batch`, the front door (in memory,
or block by block into a resumable Zarr store with ``store=``, on ``dask.distributed`` workers
with ``workers=``/``scheduler=``/``client=``).

Every pixel of a stack has its own M measurements of DOP (and optionally intensity), or of
polarimetric quantities (normalised Stokes parameters s1, s2, s3 under the source's polarization
state per measurement, Mueller elements, DOP, AoP: :mod:`pbrdf_cl.model.measurables`' channels), and is
fitted on its own, by the stages of :func:`pbrdf_cl.fit` reshaped for many pixels at once
(:mod:`pbrdf_cl.fitting.images.pixel_fit`):

(a) the objective on a coarse grid for every pixel, on the device, keeping the minimum of each
    region of the grid (the grid split in halves along every free parameter): with shared
    geometry the DOP table of the grid is computed once and each pixel's SSE is its product with
    the pixel's data; with per-pixel geometry the factor tables of ``pbrdf_tables.cl`` are built
    per pixel and combined (``kernels/pbrdf_batch.cl``);
(b) a bounded Levenberg-Marquardt run on the device from each pixel's best region minima, the
    algorithm of :func:`pbrdf_cl.fitting.common.lm_batch` (float32), the best of them polished
    in float64, derivatives by forward differences of the device functions of
    ``kernels/pbrdf.h``; with intensities (``f00``/``s0``) a last float64 run adds ks (as log
    ks) and the intensity residuals, as :func:`pbrdf_cl.fit`'s intensity stage;
(c) the best start per pixel, covariance from J^T J, 95% intervals (the best values +- 1.96
    standard errors, Student's t without known noise, cut at the bounds), and a status per pixel.

On the numpy backend the same stages run with ``reference.py`` (the grid from
``dense.NumpyTables``, the descent by ``lm_batch`` itself): slower, for machines without a
usable OpenCL driver and for tests.  The input is :mod:`pbrdf_cl.io.source`'s, the job
:mod:`pbrdf_cl.fitting.images.job`'s, the result :mod:`pbrdf_cl.fitting.images.dataset`'s and the store
:mod:`pbrdf_cl.fitting.images.store`'s.
"""
from __future__ import annotations

import os
import time

import numpy as np

from ... import sizes
from ...io.source import open_stack_lazily
from ...store import cluster
from ..setup import FitSetup
from . import store as image_store
from .dataset import goodness_summary, interval_summary
from .job import BLOCK_BUDGET, N_STARTS, BatchJob, choose_quantities
from .labels import LabelJob, UnsharedLabelJob, label_shared, read_labels


def fit_batch(data, model="six-param", bounds=None, fixed=None, shadowing="paper", *, memory_budget=BLOCK_BUDGET,
              progress=False, n_starts=N_STARTS, grid_shape=None, engine=None, backend="auto", device=None, store=None,
              workers=None, scheduler=None, client=None, allow_large=False, labels=None, shared=None, quantities=None):
    """Fit the model to every pixel of a polarization image stack, batched on the device.

    Parameters
    ----------
    data : xarray.Dataset, dict of arrays or path
        ``dop`` of shape ``(..., M)`` (pixel dimensions, then M measurements; NaN marks a missing
        measurement of that pixel); ``theta_i``, ``theta_r`` and optionally ``phi`` (degrees,
        default 180) shared, shape ``(M,)``, or per pixel, broadcastable to ``dop``; optional
        ``dop_std`` (broadcastable; NaN only where ``dop`` is NaN), ``f00`` or ``s0``
        intensities (then ks and kd are separated, as in :func:`pbrdf_cl.fit`), ``f00_std`` and
        a boolean ``mask`` over the pixel dimensions (False: skip the pixel).  A path to a
        ``.npz``, ``.nc`` or ``.zarr`` stack with those variables.  The measurements may lie
        along another axis where the geometry says which (the shared angles' axis or
        dimension, or a Dataset dimension named ``m``; see ``pbrdf_cl.io.source.Source``); ambiguous layouts
        are refused.  Without ``phi`` every measurement is in plane (``attrs["data_notes"]``).
        Polarimetric stacks hold, like ``dop`` (instead of it or beside it), ``s1``, ``s2``, ``s3``
        (the reflected Stokes vector normalised by S0, in the psps frame of the outgoing beam),
        ``aop`` (degrees), normalised Mueller elements ``m01`` .. ``m33`` and their optional
        ``<name>_std`` (for every fitted quantity or none; an AoP among others needs its own), and
        the source's normalised Stokes vector per measurement ``in_s1``, ``in_s2``, ``in_s3``
        (shared, shape ``(M,)``, or per pixel; absent: unpolarised light); NaN marks a value not
        measured.  Intensities (``f00``, ``s0``) are not fitted with polarimetric quantities (a note
        says so).
    model, bounds, fixed, shadowing
        As for :func:`pbrdf_cl.fit`.
    memory_budget : int or str, default "512 MiB"
        Bounds the memory of one block of pixels (host and device); larger stacks are fitted
        block by block.
    progress : bool, default False
        A progress bar in pixels, with pixels/s and the time left.
    n_starts : int, default 32
        Descents per pixel, from the best region minima of the grid stage.
    grid_shape : dict, optional
        Grid nodes per free parameter (default ``pbrdf_cl.fitting.images.pixels.BATCH_GRID``).
    engine, backend
        Where to compute (as for :func:`pbrdf_cl.dop`); the numpy backend runs the same stages
        with the float64 reference, much slower.
    device : str, optional
        The OpenCL device (see :func:`pbrdf_cl.select_device`) where no ``engine`` is given, and
        that of every cluster worker.
    store : str or path, optional
        Write the result to this Zarr store block by block (a local path, or the URL of an fsspec
        store every worker reaches), resumable: a store that holds this job (same settings, input
        and kernels) is resumed, one started with others is refused with a one-line
        :class:`pbrdf_cl.StoreError` naming what differs (see
        :func:`pbrdf_cl.fitting.images.store.write_store`); the result is then opened from it
        (lazily), its ``attrs`` adding ``seconds``, ``blocks_computed`` and ``blocks_skipped``.  A
        path to a ``.nc`` stack is then read lazily (dask), a block at a time.
    workers, scheduler, client : optional, with ``store`` only
        Fit the blocks on a local ``dask.distributed`` cluster of this many processes, on the
        cluster of this scheduler address, or through this client (each worker builds its own
        engine and writes its blocks into the store); at most one of them.
    allow_large : bool, default False, with ``store`` only
        Start even if the store (uncompressed) would not fit on the free disk.
    labels : array-like or str, optional
        An integer label image over the pixel dimensions (0: not fitted), or the name of such a
        variable of the stack: the pixels of a label share the ``shared`` parameters, one value
        per label found from all its pixels (``pbrdf_cl.fitting.images.labels``, docs/joint_images.md);
        the label stage, then the per-pixel pass (with ``workers``, ``scheduler`` or ``client``
        the passes of both over the blocks run on the workers of one cluster).
    shared : sequence of str or str, optional, with ``labels``
        The parameters the pixels of a label share (free parameters, not all of them), as a
        sequence or one string (``"n,k"``, ``"n k"``); by default ("n", "k"), less a fixed one;
        empty (``()``, ``""``): nothing, every pixel is fitted on its own.
    quantities : sequence of str or str, optional
        The measured quantities fitted, names of the stack's (``"s1,s2"``, ``("dop",)``). Default:
        the stack's polarimetric quantities where it gives the source's state (``in_s1`` ..
        ``in_s3``) or has no ``dop``, else its ``dop`` (as for unpolarised light); the quantities
        left out are named in ``attrs["data_notes"]``.  With ``labels`` only the DOP.

    Returns
    -------
    xarray.Dataset
        Over the pixel dimensions: one variable per fitted parameter (``n``, ``k``, ``sigma``,
        ``kd``, ``c``, and ``ks`` with intensities; kd is kd/ks without them), ``sse`` (sum of
        squared DOP residuals), ``chi2`` (weighted), ``<name>_stderr``, ``<name>_ci95`` (a
        trailing ``bound`` dimension: low, high), ``<name>_outside_ci95`` (the best value lies
        outside its own 95% interval: a parameter the pixel's data do not determine, its best
        fit at a bound; the variable's ``long_name`` says why), ``determined`` (per parameter:
        the 95% interval is narrower than half the bounds), ``r2``, ``p_value`` and
        ``fits_data`` (the goodness-of-fit test of each pixel, as :func:`pbrdf_cl.fit`'s),
        ``n_valid`` (measurements used), ``nfev`` and ``status`` (codes in
        ``attrs["status_codes"]``); the stack's coordinates over the pixels; units, settings,
        the image's goodness of fit (:func:`goodness_summary`: ``attrs["goodness"]``, and
        ``attrs["goodness_warning"]`` where too many pixels fail) and the count of best values
        outside their intervals (:func:`interval_summary`: ``attrs["outside_ci95"]``, with
        ``attrs["outside_ci95_note"]`` where any) in ``attrs``.  With ``labels``: the pixels'
        ``labels``; the shared parameters' per-pixel values, stderr and intervals are their
        label's (the other parameters' intervals hold the shared ones at the label's values);
        over a ``label`` dimension ``label_<name>``, ``label_<name>_stderr``,
        ``label_<name>_ci95``, ``label_<name>_outside_ci95``, ``label_corr`` (the shared
        parameters' correlations, valid or NaN), ``label_pixels``, ``label_chi2``,
        ``label_sse``, ``label_dof``, ``label_p_value`` and ``label_fits_data`` (each label's
        goodness-of-fit test: chi2 with dop_std, else an F test against the pixels' own fits;
        ``attrs["label_goodness"]``, and ``attrs["label_goodness_warning"]`` naming the labels
        that fail) and ``label_status`` (codes in its attrs); pixels of label 0 are masked
        (status -1).  ``attrs["quantities"]`` names the quantities
        fitted (``sse``, ``r2`` and ``n_valid`` are of them).

    Raises
    ------
    ValueError
        For bad input, naming the variable and the first offending index.
    StoreError
        With ``store``: it holds another job, or another input.

    Examples
    --------
    >>> import numpy as np, pbrdf_cl
    >>> ti, tr = np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)
    >>> truth = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3)
    >>> dop = np.broadcast_to(pbrdf_cl.dop(ti, tr, **truth), (2, 3, 30))
    >>> res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=ti, theta_r=tr))
    >>> res.n.shape, bool(abs(res.n - 1.6).max() < 1e-3)
    ((2, 3), True)
    """
    settings = dict(memory_budget=memory_budget, n_starts=n_starts, grid_shape=grid_shape)
    if quantities is not None:
        settings["quantities"] = quantities
    if shared is not None and labels is None:
        raise ValueError("shared= needs labels= (the label image that says which pixels share them)")
    if store is not None:
        image_store.check_cluster(workers, scheduler, client, engine)
        if isinstance(data, (str, os.PathLike)):
            data = open_stack_lazily(data)
        job = _job(data, model, bounds, fixed, shadowing, settings, labels, shared)
        if not job.prepares:
            return image_store.write_store(job, store, progress=progress, engine=engine, backend=backend,
                                           device=device, workers=workers, scheduler=scheduler, client=client,
                                           allow_large=allow_large)
        # a label job: its label stage's passes and the per-pixel pass where the blocks go, on one cluster;
        # what the store refuses whatever the label stage finds, refused before it
        image_store.check_before_stage(job, store, allow_large)
        with cluster.connect(workers, scheduler, client) as client:
            job.prepare(image_store.local_engine(engine, backend, device), progress, client=client, device=device,
                        backend=backend)
            return image_store.write_store(job, store, progress=progress, engine=engine, backend=backend,
                                           device=device, client=client, allow_large=allow_large)
    if workers is not None or scheduler is not None or client is not None:
        raise ValueError("workers=, scheduler= and client= need store= (the workers write their blocks into it)")
    if allow_large:
        raise ValueError("allow_large= needs store= (it allows a store larger than the free disk)")
    job = _job(data, model, bounds, fixed, shadowing, settings, labels, shared)
    sizes.check_memory(job.result_bytes(), f"the result of {job.source.n_pixels} pixels",
                       "write it into a Zarr store block by block (store=; pbrdf-cl fit-image)")
    eng = image_store.local_engine(engine, backend, device)
    t0 = time.perf_counter()
    job.prepare(eng, progress)
    parts = []
    bar = _bar(job.source.n_pixels, progress)
    for r0, r1 in job.blocks():
        parts.append(job.fit_rows(eng, r0, r1))
        if bar is not None:
            bar.update(parts[-1]["sse"].size)
    if bar is not None:
        bar.close()
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    ds = job.dataset(out, seconds=time.perf_counter() - t0)
    ds.attrs.update(goodness_summary(ds))
    ds.attrs.update(interval_summary(ds))
    return ds


def _job(data, model, bounds, fixed, shadowing, settings, labels, shared):
    """The checked job: a :class:`~pbrdf_cl.fitting.images.labels.LabelJob` with ``labels`` and something
    to share, else a :class:`~pbrdf_cl.fitting.images.job.BatchJob` (with ``labels`` and nothing shared,
    every labelled pixel on its own, label 0 not fitted, as a note says)."""
    if labels is None:
        return BatchJob(data, model, bounds, fixed, shadowing, **settings)
    quantities = settings.pop("quantities", None)
    data, given = read_labels(data, labels)
    if label_shared(FitSetup.check(model, bounds, fixed, shadowing), shared):
        job = LabelJob(data, model, bounds, fixed, shadowing, labels=given, shared=shared, **settings)
    else:
        job = UnsharedLabelJob(data, model, bounds, fixed, shadowing, labels=given, **settings)
    if job.setup.channels or (quantities is not None and choose_quantities(job.source, quantities)[0] != ("dop",)):
        raise ValueError("labels=: image fits with labels fit the DOP under unpolarised light only, not polarimetric "
                         "quantities or incident states; fit those without labels (every pixel on its own)")
    return job


def _bar(total, enabled):
    if not enabled:
        return None
    from tqdm.auto import tqdm
    return tqdm(total=total, desc="fit_batch", unit="px", unit_scale=True, smoothing=0.1)
