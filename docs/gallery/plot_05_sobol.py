"""
A Sobol' map: which parameter controls the DOP where
====================================================

Sobol' indices of the DOP over (theta_i, theta_r) for a box of materials (:func:`pbrdf_cl.sobol`):
S1 is the share of the DOP's variance a parameter explains alone, ST its share with all its
interactions. ks is fixed at 1 (the DOP sees kd/ks only). A small map here (16 x 16 geometries,
N = 256) to keep the build quick; ``pbrdf-cl reproduce`` draws a finer one.
"""
import matplotlib.pyplot as plt

import pbrdf_cl
from pbrdf_cl.analysis.sensitivity import summary
from pbrdf_cl.plots.sensitivity import plot_sensitivity

ds = pbrdf_cl.sobol({"n": (1.2, 1.7), "k": (0.2, 7.0, "log"), "sigma": (0.2, 0.7), "kd": (0.0, 0.25),
                     "c": (-0.6, 0.0)},
                    {"theta_i": "0:80@16", "theta_r": "0:85@16"}, fixed={"ks": 1.0}, N=256, seed=1)
print(summary(ds))

# %%
# The figure, drawn as in a notebook into a figure of one's own (``fig=``; a path writes a PNG
# instead, as ``pbrdf-cl sobol --png`` does):
plot_sensitivity(ds, fig=plt.figure(figsize=(17, 6.8), layout="constrained"))
plt.show()
