"""
The paper's Fig. 4 and Fig. 5: the steel fit
============================================

The paper's fit to 45# steel at 435 nm (n = 1.6, k = 2.139, sigma = 0.5, ks = 0.9, kd = 0.15,
c = -0.3): the DOP against the reflection angle at three incidence angles (Fig. 4), and at
theta_i = 40 deg for three roughness values (Fig. 5). The curves are :func:`pbrdf_cl.dop`
evaluated in the plane of incidence.
"""
from pathlib import Path

import numpy as np

import pbrdf_cl
from pbrdf_cl.analysis import paper

steel = paper.STEEL
print(np.round(pbrdf_cl.dop(40, [20, 45, 65], **steel), 6))   # SPEC's check values: 0.051841 ...

# %%
# Fig. 4: DOP against theta_r at theta_i = 30, 40 and 50 deg (markers: the paper's measured
# geometries).
paper.fig4(Path("."))

# %%
# Fig. 5: the DOP falls as the roughness sigma grows.
paper.fig5(Path("."))
