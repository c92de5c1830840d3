"""
The paper's Fig. 2: both models fitted to DOP data
==================================================

Fig. 2 of Zhu et al. (2020) fits the six-parameter model and its ref. [7] (the specular term
alone, Thilak et al. 2007) to DOP measurements of aluminum and black paint in the specular
geometry (theta_r = theta_i, phi = 180). Those measurements are not published, so the data here
are synthetic: the six-parameter model at Table 1's true n and k, with the roughness, diffuse
weight and Minnaert exponent of ``pbrdf_cl.analysis.paper.FIG2_SAMPLES`` and Gaussian DOP noise of
sd 0.001. :func:`pbrdf_cl.analysis.paper.fig2` fits both models with
:func:`pbrdf_cl.compare_models` and draws the data, the true curve and both fits.
"""
from pathlib import Path

from pbrdf_cl.analysis import paper

print(paper.FIG2_SAMPLES)

# %%
# Aluminum: a metal (k = 6.6). DOP in one geometry determines n and k only loosely: the best fit
# may land far from the truth (even on a bound), another basin may fit as well, and the summary's
# 95% intervals and notes say so.
fits = paper.fig2("aluminum", Path("."))
print(fits["six-param"].summary())

# %%
# Black paint: a dielectric (k = 0.23). Here ref. [7]'s specular model, without a diffuse term,
# cannot follow the data around the DOP's peak, and AIC/BIC prefer the six-parameter model.
fits = paper.fig2("black paint", Path("."))
print(fits.summary())
