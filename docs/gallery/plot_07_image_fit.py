"""
An image fit: every pixel of a synthetic camera stack
=====================================================

A synthetic stack (:func:`pbrdf_cl.io.imagestack.synthetic_stack`): a sample of two materials
with a roughness gradient, imaged by a polarization camera under 30 light positions, with DOP
noise 0.005. :func:`pbrdf_cl.fit_batch` fits every pixel on the device, with intervals and a
status per pixel; :func:`pbrdf_cl.plots.images.plot_batch_maps` draws the truth, the fitted maps
and the interval widths. A 24 x 24 stack here, to keep the build quick.
"""
import matplotlib.pyplot as plt

import pbrdf_cl
from pbrdf_cl.io import imagestack
from pbrdf_cl.plots.images import plot_batch_maps

stack = imagestack.synthetic_stack(size=24, seed=0)
maps = pbrdf_cl.fit_batch(stack)
print(maps.attrs["goodness"])
for name in ("n", "k", "sigma", "kd", "c"):
    low, high = maps[f"{name}_ci95"].sel(bound="low"), maps[f"{name}_ci95"].sel(bound="high")
    covered = float(((low <= stack[f"true_{name}"]) & (stack[f"true_{name}"] <= high)).mean())
    print(f"{name}: the 95% intervals cover the truth at {covered:.0%} of the pixels")

# %%
# Drawn as in a notebook into a figure of one's own (``fig=``: it is sized to fit the panels); a
# path, ``plot_batch_maps(maps, "image_fit.png", truth=stack)``, writes the PNG instead.
plot_batch_maps(maps, truth=stack, fig=plt.figure())
plt.show()
