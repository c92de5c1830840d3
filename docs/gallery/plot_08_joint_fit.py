"""
A joint fit: three wavelengths, shared roughness
================================================

The same sample at three wavelengths shares its roughness sigma and Minnaert exponent c, while n,
k and kd/ks change. :func:`pbrdf_cl.fit_joint` fits the three synthetic data sets together, sigma
and c one value for all, and reports each set's separate fit beside the joint one;
:func:`pbrdf_cl.plots.joint.plot_joint` draws the data with both fits.
"""
import matplotlib.pyplot as plt
import numpy as np

import pbrdf_cl
from pbrdf_cl.plots.joint import plot_joint

ti, tr = np.repeat([30.0, 40.0, 50.0], 10), np.tile(np.arange(20.0, 66.0, 5.0), 3)
rng = np.random.default_rng(1)
sets = {}
for name, own in {"435 nm": dict(n=1.6, k=2.139, kd=0.17), "532 nm": dict(n=2.0, k=2.8, kd=0.1),
                  "633 nm": dict(n=2.5, k=3.4, kd=0.06)}.items():
    dop = pbrdf_cl.dop(ti, tr, sigma=0.5, c=-0.3, **own) + rng.normal(0, 0.003, ti.size)
    sets[name] = dict(theta_i=ti, theta_r=tr, dop=np.clip(dop, 0, 1), dop_std=np.full(ti.size, 0.003))
joint = pbrdf_cl.fit_joint(sets, shared=("sigma", "c"))
print(joint.summary())

# %%
# Drawn as in a notebook into a figure of one's own (``fig=``); a path, ``plot_joint(joint,
# "joint_fit.png")``, writes the file instead, as ``pbrdf-cl fit a.csv b.csv --plot`` does.
plot_joint(joint, fig=plt.figure(figsize=(12.6, 4.6), layout="constrained"))
plt.show()
