"""
A dense map and its derivative
==============================

The DOP of the steel over (theta_r, sigma) at theta_i = 40 deg, and its derivative along sigma by
central differences of device grids (:func:`pbrdf_cl.explore.maps.make_map`), drawn with labelled
contours by :func:`pbrdf_cl.plots.maps.plot_map`. The same as ``pbrdf-cl map --x theta_r=0:85@128
--y sigma=0.05:1@96 --fix theta_i=40 ... --derivative sigma``.
"""
from pbrdf_cl.explore.maps import make_map
from pbrdf_cl.plots.maps import plot_map

ds = make_map("theta_r=0:85@128", "sigma=0.05:1@96",
              dict(theta_i=40, n=1.6, k=2.139, ks=0.9, kd=0.15, c=-0.3), derivative="sigma")
print(ds)

# %%
# The figure:
plot_map(ds, "map_sigma_theta_r.png")
