"""
Fit polarization-camera data under polarized light
==================================================

Unpolarized light and a DOP measurement barely determine the complex index: on the paper's
geometry the DOP fit of ``examples/steel_435nm.csv`` leaves n and k across most of their bounds.
A polarizer in front of the lamp (here at +45 degrees from s towards p) and a linear polarization
camera measure s1 = S1/S0 and s2 = S2/S0 of the reflected light at the same geometries, and these
carry the phase between r_s and r_p that ellipsometry measures. ``examples/steel_camera_45.csv``
holds such data for the same steel (its header states the parameters and the noise);
:func:`pbrdf_cl.fit` fits them with the same global search and intervals as DOP data, and
:func:`pbrdf_cl.plots.fit.plot_fit` draws each quantity with the fit and its residuals (what
``pbrdf-cl fit examples/steel_camera_45.csv --plot fit.png`` writes).
"""
from pathlib import Path

import matplotlib.pyplot as plt

import pbrdf_cl
from pbrdf_cl.plots.fit import plot_fit

examples = Path("../../examples")
camera = pbrdf_cl.read_csv(examples / "steel_camera_45.csv")
res = pbrdf_cl.fit(camera)
print(res.summary())

# %%
# The DOP of the same steel, geometries and noise, under unpolarized light: the widths of the 95%
# intervals of n and k side by side.
dop = pbrdf_cl.fit(examples / "steel_435nm.csv")
for p in ("n", "k"):
    w_cam, w_dop = (r.ci95[p][1] - r.ci95[p][0] for r in (res, dop))
    print(f"{p}: camera under a 45-degree source {res.ci95[p][0]:.3f} .. {res.ci95[p][1]:.3f} "
          f"(width {w_cam:.3f}); DOP {dop.ci95[p][0]:.3f} .. {dop.ci95[p][1]:.3f} (width {w_dop:.3f}, "
          f"{w_dop / w_cam:.0f} times wider)")

# %%
# A panel and its residuals per quantity (s1 and s2, the source's state in the title), drawn as
# in a notebook into a figure of one's own (``fig=``).
fig = plt.figure(figsize=(10.4, 5.6), layout="constrained")
plot_fit(camera, {"six-param": res}, fig=fig)
plt.show()
