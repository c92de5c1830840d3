"""
A measurement design: where to measure the steel
================================================

:func:`pbrdf_cl.design` chooses the 30 in-plane geometries of a 5 degree grid that make the
predicted 95% intervals of n and k narrowest at DOP noise 0.005, and compares them with the
paper's 30 (theta_i 30/40/50 x theta_r 20..65). :func:`pbrdf_cl.plots.design.plot_design` draws
the information map with both sets and the predicted widths.
"""
import matplotlib.pyplot as plt

import pbrdf_cl
from pbrdf_cl.plots.design import plot_design

r = pbrdf_cl.design(dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3),
                    {"theta_i": "10:80:5", "theta_r": "0:85:5"}, noise=0.005, n_measurements=30,
                    target=("n", "k"))
print(r.summary())

# %%
# The figure, drawn as in a notebook into a figure of one's own (``fig=``; a path writes a PNG
# instead, as ``pbrdf-cl design --png`` does):
plot_design(r, fig=plt.figure(figsize=(13, 5.6), layout="constrained"))
plt.show()
