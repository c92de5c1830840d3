"""Inversion: one data set (the staged pipeline), image stacks pixel by pixel, and their stores.

Shared by both (and by :func:`pbrdf_cl.design`):

- ``setup``: :class:`~pbrdf_cl.fitting.setup.FitSetup`, the one setup of a fit (model, shadowing,
  bounds, fixed and free parameters), checked once;
- ``common``: finite differences, the batched Levenberg-Marquardt descent, the noise floor and the
  goodness-of-fit constants.

One data set (:func:`pbrdf_cl.fit`, ``inversion``): ``stages`` (grid, basins, DIRECT-L, BOBYQA,
screen, least squares, intensities), ``basins`` (seeds from the grid), ``uncertainty``
(covariance and intervals), ``result`` (:class:`~pbrdf_cl.fitting.sample.result.FitResult`, the
status table ``FIT_STATUS``, the notes).

Image stacks (:func:`pbrdf_cl.fit_batch`, ``batch``, the front door): ``source`` (the input),
``job`` (the checked job and its blocks), ``pixel_fit`` (one block through the stages),
``pixels`` (what those stages share: :class:`~pbrdf_cl.fitting.images.pixels.BatchSetup`, ``Block``,
``Descent``), ``pixel_stages`` (the device stages and their numpy twins, as engine operations),
``corners`` (the corner stage), ``statistics`` (per-pixel intervals and status), ``dataset`` (the
result, the status table ``PIXEL_STATUS``, the image's goodness of fit), ``batch_store`` (the
resumable Zarr store, on one machine or a dask cluster).
"""
