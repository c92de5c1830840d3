"""What every figure shares: matplotlib's pyplot on the Agg backend (no display needed) and the
axis labels of the model's inputs."""
from __future__ import annotations

#: Axis labels with units of the model's inputs (the canonical names of ``pbrdf_cl.compute.dense.AXES``).
LABELS = {"theta_i": "incidence zenith angle theta_i (deg)", "theta_r": "reflection zenith angle theta_r (deg)",
          "phi": "relative azimuth phi (deg, 180 = in plane)", "n": "refractive index n",
          "k": "extinction coefficient k", "sigma": "per-axis rms slope sigma", "ks": "specular weight ks",
          "kd": "diffuse weight kd", "c": "Minnaert exponent c"}


def pyplot():
    """``matplotlib.pyplot``, with the Agg backend chosen first: figures are written to files, and no
    display is needed (nor used where there is one)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt
