"""The image-fit mistakes of issue #26 (pbrdf_cl.fit_batch, pbrdf-cl fit-image) and phi left out
of fit.  Each gets the right answer or one line naming the variable and what to do."""
import os
import subprocess
import sys

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.data import PHI_DEFAULT_NOTE

TI = np.repeat([30.0, 40.0, 50.0], 10)
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
STEEL = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3)
PACKAGE_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def dev(engine):
    if engine is None:
        pytest.skip("no OpenCL device")
    return engine


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "pbrdf_cl", *args], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=PACKAGE_ROOT))


def shared_stack(shape=(3, 4), seed=0):
    """dop (y, x, m) of steel-like pixels (k varying across them) at the paper's shared geometry."""
    rng = np.random.default_rng(seed)
    k = rng.uniform(1.5, 3.0, shape)[..., None]
    dop = pbrdf_cl.dop(TI, TR, **{**STEEL, "k": k}, backend="numpy")
    return np.clip(dop + rng.normal(0, 0.003, dop.shape), 0, 1)


def same_fit(a, b):
    np.testing.assert_array_equal(a.status.values, b.status.values)
    for name in ("n", "k", "sigma", "kd", "c", "sse"):
        np.testing.assert_allclose(a[name].values, b[name].values, rtol=1e-12, atol=0, err_msg=name)


# ---- phi left out (item 7)

def test_phi_left_out_of_fit_is_said(dev, tmp_path):
    """Without phi every point is in plane (phi = 180): a note on fit's result, one line on the
    command line (fit, fit --quiet); none where phi is given."""
    d = pbrdf_cl.dop(TI, TR, **STEEL, backend="numpy")
    res = pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=d), engine=dev)
    assert PHI_DEFAULT_NOTE in res.notes and f"note: {PHI_DEFAULT_NOTE}" in res.summary()
    assert PHI_DEFAULT_NOTE not in pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, phi=180.0, dop=d), engine=dev).notes
    (tmp_path / "nophi.csv").write_text("theta_i,theta_r,dop\n" + "".join(f"{a},{b},{c}\n" for a, b, c in zip(TI, TR, d)))
    (tmp_path / "phi.csv").write_text("theta_i,theta_r,phi,dop\n" + "".join(f"{a},{b},180,{c}\n"
                                                                          for a, b, c in zip(TI, TR, d)))
    for quiet in ([], ["--quiet"]):
        proc = run_cli("fit", str(tmp_path / "nophi.csv"), *quiet)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.count(PHI_DEFAULT_NOTE) == 1, proc.stdout
        proc = run_cli("fit", str(tmp_path / "phi.csv"), *quiet)
        assert proc.returncode == 0 and PHI_DEFAULT_NOTE not in proc.stdout, proc.stderr
