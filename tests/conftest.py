import os
import tempfile

import numpy as np
import pytest

os.environ.setdefault("POCL_CACHE_DIR", os.path.join(tempfile.gettempdir(), "pbrdf-cl-pocl-cache"))

import pbrdf_cl  # noqa: E402

PARAMS = ("n", "k", "sigma", "ks", "kd", "c")


def random_inputs(rng, size, in_plane=False):
    """Random valid inputs over the whole domain, angles in degrees, plus hand-picked edge cases."""
    d = dict(
        theta_i=rng.uniform(0, 89.9, size),
        theta_r=rng.uniform(0, 89.9, size),
        phi=np.full(size, 180.0) if in_plane else rng.uniform(0, 360, size),
        n=rng.uniform(0.2, 5, size),
        k=np.where(rng.random(size) < 0.1, 0.0, rng.uniform(0, 10, size)),
        sigma=rng.uniform(0.05, 1.0, size),
        ks=rng.uniform(0.1, 2, size),
        kd=np.where(rng.random(size) < 0.1, 0.0, rng.uniform(0, 5, size)),
        c=rng.uniform(-1, 0, size),
    )
    edges = edge_inputs()
    if in_plane:
        edges["phi"] = np.full_like(edges["phi"], 180.0)
    return {name: np.concatenate([d[name], edges[name]]) for name in d}


def edge_inputs():
    """theta = 0, alpha = 0 (specular), grazing 89.9, retro-reflection, k = 0, tiny sigma, kd = 0."""
    rows = [
        # ti, tr, phi, n, k, sigma, ks, kd, c
        (0, 0, 180, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (0, 0, 37, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (0, 45, 180, 1.6, 0, 0.5, 1, 0.1, -0.3),
        (45, 0, 90, 1.6, 0, 0.5, 1, 0.0, -0.3),
        (40, 40, 180, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (40, 40, 180, 1.6, 2.1, 1e-4, 1, 0.1, -0.3),
        (40, 40, 0, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (89.9, 89.9, 180, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (89.9, 89.9, 0, 1.6, 2.1, 0.5, 1, 0.1, -1.0),
        (89.9, 0, 180, 1.2, 0, 1.0, 1, 0.1, -0.9),
        (89.9, 89.9, 180, 1.0, 0, 0.3, 1, 0.0, 0.0),
        (30, 60, 180, 1.0, 0, 0.3, 1, 0.0, 0.0),
        (30, 60, 180, 0.5, 0, 0.3, 1, 0.2, 0.0),
        (30, 31, 180, 1.5, 0, 1e-3, 1, 0.2, -0.5),
        (30, 70, 180, 1.5, 3, 1e-3, 1, 0.2, -0.5),
        (10, 80, 250, 4.0, 10, 0.05, 2, 5, -1),
    ]
    cols = np.array(rows, dtype=np.float64).T
    return dict(zip(("theta_i", "theta_r", "phi") + PARAMS, cols))


def call(func, inp, **kw):
    return func(inp["theta_i"], inp["theta_r"], inp["phi"], **{p: inp[p] for p in PARAMS}, **kw)


@pytest.fixture(scope="session")
def engine():
    return pbrdf_cl.get_default_engine()


@pytest.fixture
def rng():
    return np.random.default_rng(20200509)
