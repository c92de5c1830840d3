"""Result files read back: a sensitivity map (:func:`pbrdf_cl.sobol`, :func:`pbrdf_cl.morris`)
written in an older layout, brought into the current one (:func:`compatible`), for its summary
(:func:`pbrdf_cl.analysis.sensitivity.summary`) and its figure
(:func:`pbrdf_cl.plots.sensitivity.plot_sensitivity`) alike."""
from __future__ import annotations


def compatible(ds):
    """A result in the current layout: a Morris result written before ``sigma`` became ``ee_std``
    (the roughness is sigma) renamed; any other returned as is."""
    if "mu_star" in ds and "sigma" in ds.data_vars and "ee_std" not in ds:
        return ds.rename({"sigma": "ee_std"})
    return ds
