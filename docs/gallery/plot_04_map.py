"""
A dense map and its derivative
==============================

The DOP of the steel over (theta_r, sigma) at theta_i = 40 deg, and its derivative along sigma by
central differences of device grids (:func:`pbrdf_cl.analysis.maps.make_map`), drawn with labelled
contours by :func:`pbrdf_cl.plots.maps.plot_map`. The same as ``pbrdf-cl map --x theta_r=0:85@128
--y sigma=0.05:1@96 --fix theta_i=40 ... --derivative sigma``.
"""
import matplotlib.pyplot as plt

from pbrdf_cl.analysis.maps import make_map
from pbrdf_cl.plots.maps import plot_map

ds = make_map("theta_r=0:85@128", "sigma=0.05:1@96",
              dict(theta_i=40, n=1.6, k=2.139, ks=0.9, kd=0.15, c=-0.3), derivative="sigma")
print(ds)

# %%
# The figure, drawn as in a notebook into a figure of one's own (``fig=``; a path,
# ``plot_map(ds, "map_sigma_theta_r.png")``, writes the PNG that ``pbrdf-cl map`` writes instead):
fig = plot_map(ds, fig=plt.figure(figsize=(12.4, 5), layout="constrained"))

# %%
# The figure is the caller's: here the DOP and the angle of polarization of the same steel over
# (theta_r, phi), out of the plane of incidence, side by side, each map in a subfigure of one figure.
steel = dict(theta_i=40, n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
dop = make_map("theta_r=0:85@96", "phi=0:360@96", steel)
aop = make_map("theta_r=0:85@96", "phi=0:360@96", steel, quantity="aop")
left, right = plt.figure(figsize=(12.4, 5), layout="constrained").subfigures(1, 2)
plot_map(dop, fig=left, title="DOP of the steel at theta_i = 40 deg")
plot_map(aop, fig=right, title="AoP of the steel at theta_i = 40 deg")
plt.show()
