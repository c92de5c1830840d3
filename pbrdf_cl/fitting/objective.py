"""The least-squares objective of measurements over many parameter vectors at once
(:func:`objective`, ``pbrdf_cl.objective``): the data read and checked as :func:`pbrdf_cl.fit`
reads them, the sums computed on the device by :func:`pbrdf_cl.compute.dense.objective` (the grid
stage of every fit)."""
from __future__ import annotations

from ..compute import dense, pointwise
from ..io.measurements import as_measurements


def objective(data, grid=None, points=None, *, k_best=10, dtype="float32", shadowing="paper", engine=None,
              backend="auto", memory_budget=dense.DEFAULT_BUDGET, return_sse=True, progress=False):
    """Weighted sum of squared residuals, sum_m w_m (model(p, m) - measured_m)^2, for many parameter
    vectors p over the measurements m, on the device.

    Parameters
    ----------
    data : dict, CSV path, DataFrame, xarray.Dataset or Measurements
        theta_i, theta_r (degrees), dop, optionally phi (default 180) and dop_std (weights
        1/dop_std^2); or any polarimetric quantities (``docs/polarimetry.md``: aop, s0..s3,
        m00..m33 with their ``<name>_std``, the incident state in_s1..in_s3): then the sum is over
        every measured number (an AoP's residual wrapped modulo 180 degrees).
    grid : dict
        Parameter axes (n, k, sigma, ks, kd, c -> 1-d array or scalar) whose Cartesian product is
        searched (factorised: no transcendental function per pair).  ks, kd, c default to 1, 0, 0.
    points : dict
        Or an explicit list: n, k, sigma, ks, kd, c -> equal-length arrays (one full model
        evaluation per pair; DOP data only).
    k_best : int
        How many of the best parameter vectors to return.
    dtype, shadowing, engine, backend, memory_budget, progress
        As for :func:`pbrdf_cl.grid`; the measurements' tables run in blocks within ``memory_budget``
        (on an OpenCL device the same sums as one block's, bit for bit; on the numpy backend the
        blocks' sums added in float64), and a budget below one measurement's tables is refused.
    return_sse : bool, default True
        Keep the SSE of every parameter vector (False: only the best).

    Returns
    -------
    ObjectiveResult
        ``sse`` (a DataArray over the grid's axes, or an array for ``points``), ``best`` (the
        ``k_best`` best vectors and their SSE, best first), ``n_pairs``, ``seconds``.

    Examples
    --------
    >>> import numpy as np, pbrdf_cl
    >>> data = dict(theta_i=[30, 40, 50], theta_r=[20, 45, 65], dop=[0.052, 0.168, 0.338])
    >>> res = pbrdf_cl.objective(data, grid=dict(n=np.linspace(1, 5, 16), k=np.linspace(0, 10, 16), sigma=0.5))
    >>> len(res.best["sse"])
    10
    """
    meas = as_measurements(data)
    pointwise.check_degrees(meas.theta_i, meas.theta_r, f"{meas.source}: ")
    return dense.objective(meas.channels() if meas.polarimetric else meas, grid, points, k_best=k_best, dtype=dtype,
                           shadowing=shadowing, engine=engine, backend=backend, memory_budget=memory_budget,
                           return_sse=return_sse, progress=progress)
