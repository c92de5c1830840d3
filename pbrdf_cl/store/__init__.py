"""Resumable Zarr stores: the one runner of sweeps and image fits (``runner``), the Zarr layer
(``zarr``), the Dask cluster runs (``cluster``), Ctrl-C (``interrupt``)."""
