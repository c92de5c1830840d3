"""Zarr stores: chunked, resumable writing, shared by sweeps and image fits, and the Dask cluster runs."""
