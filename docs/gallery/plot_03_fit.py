"""
Fit one sample, and compare with ref. [7]
=========================================

The bundled example ``examples/steel_435nm.csv`` holds synthetic DOP measurements of the steel at
theta_i = 30, 40, 50 deg (its header states the parameters and the noise).
:func:`pbrdf_cl.compare_models` fits the six-parameter model and ref. [7]'s specular model and
compares them by AIC/BIC; :func:`pbrdf_cl.plots.fit.plot_fit` draws the data, both fits and the
residuals (what ``pbrdf-cl fit --compare --plot`` writes).
"""
from pathlib import Path

import matplotlib.pyplot as plt

import pbrdf_cl
from pbrdf_cl.plots.fit import plot_fit

csv = Path("../../examples/steel_435nm.csv")
data = pbrdf_cl.read_csv(csv)
both = pbrdf_cl.compare_models(data)
print(both.summary())

# %%
# Drawn as in a notebook, into a figure of one's own (``fig=``; no file is written);
# ``plot_fit(data, both.fits, "fit_steel.png")`` writes the file instead, as the command does.
fig = plt.figure(figsize=(8, 7.5), layout="constrained")
plot_fit(data, both.fits, fig=fig)
plt.show()
