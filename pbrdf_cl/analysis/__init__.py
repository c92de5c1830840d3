"""The analyses of the parameter space: global sensitivity (``sensitivity``: Sobol', Morris),
measurement design (``designs``, ``design_result``, ``instruments``: which geometries and which
instrument determine the parameters best), two-axis maps (``maps``), sweeps larger than memory into
Zarr stores (``sweeps``), and the paper's figures and Table 1 (``paper``).  (The interactive
explorer is :mod:`pbrdf_cl.app`; ``pbrdf_cl.explore()`` opens it.)"""
