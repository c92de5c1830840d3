"""The pbrdf-cl command line: devices and eval."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl import cli

from conftest import requires_opencl

PACKAGE_ROOT = str(Path(pbrdf_cl.__file__).resolve().parent.parent)  # run the pbrdf_cl under test
STEEL = ["--n", "1.6", "--k", "2.139", "--sigma", "0.5", "--ks", "0.9", "--kd", "0.15", "--c", "-0.3"]


def run_cli(*args):
    """Run the CLI as a user would, in a subprocess (python -m pbrdf_cl == the pbrdf-cl script)."""
    return subprocess.run([sys.executable, "-m", "pbrdf_cl", *args], capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=PACKAGE_ROOT))


@requires_opencl
def test_devices_lists_every_device_with_its_probe_and_marks_the_default():
    proc = run_cli("devices", "--json")
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)
    default = pbrdf_cl.get_default_engine()
    assert sum(r["default"] for r in rows) == 1
    (mark,) = [r for r in rows if r["default"]]
    assert f"{mark['platform']} / {mark['device']}" == default.description and mark["usable"]
    assert mark["fp64"] is default.fp64 and "check values" in mark["probe"]
    assert all(r["simulator"] == ("Oclgrind" in r["platform"]) for r in rows)
    text = run_cli("devices").stdout
    assert default.description in text and "usable: " in text and text.count("*") >= 2


def test_eval_json_matches_api():
    proc = run_cli("eval", "--theta-i", "30,40,50", "--theta-r", "20:65:5", *STEEL, "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    rows = out["rows"]
    assert len(rows) == 30 and out["quantity"] == "dop" and out["shadowing"] == "paper"
    ti = np.array([r["theta_i"] for r in rows])
    tr = np.array([r["theta_r"] for r in rows])
    want = pbrdf_cl.dop(ti, tr, n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3, backend="numpy")
    np.testing.assert_allclose([r["dop"] for r in rows], want, atol=1e-12)
    assert rows[0]["theta_i"] == 30 and rows[0]["theta_r"] == 20 and abs(rows[0]["dop"] - 0.051841) < 5e-7


def test_eval_table_mueller_and_f00(capsys):
    assert cli.main(["eval", "--theta-i", "40", "--theta-r", "45", "--phi", "130", *STEEL,
                     "--quantity", "mueller"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1].split()
    m = np.array([float(v) for v in line[-16:]]).reshape(4, 4)
    want = pbrdf_cl.mueller(40, 45, 130, n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3, backend="numpy")
    np.testing.assert_allclose(m, want, rtol=1e-6, atol=1e-12)
    assert cli.main(["eval", "--theta-i", "40", "--theta-r", "45", *STEEL, "--quantity", "brdf",
                     "--backend", "numpy", "--shadowing", "smith", "--dtype", "float32"]) == 0
    out = capsys.readouterr().out
    assert "brdf (1/sr)" in out.splitlines()[0]
    assert float(out.splitlines()[-1].split()[-1]) == pytest.approx(
        pbrdf_cl.brdf(40, 45, n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3, shadowing="smith"), rel=1e-6)


def test_eval_specular_model_needs_no_sigma(capsys):
    assert cli.main(["eval", "--theta-i", "40", "--theta-r", "45", "--n", "1.6", "--k", "2.1",
                     "--model", "specular", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert rows[0]["dop"] == pytest.approx(float(pbrdf_cl.dop(40, 45, n=1.6, k=2.1, model="specular")), abs=1e-12)


@pytest.mark.parametrize("args,message", [
    (["--theta-i", "95", "--theta-r", "20", *STEEL], "theta_i must be in [0, 90) degrees, got 95.0"),
    (["--theta-i", "40", "--theta-r", "20:x:5", *STEEL], "--theta-r 20:x:5: stop 'x' is not a number"),
    (["--theta-i", "40", "--theta-r", "60:20:5", *STEEL],
     "--theta-r 60:20:5: the step 5 goes up from 60 but the stop 20 is below it; write 60:20:-5 to count down, "
     "or 20:60:5"),
    (["--theta-i", "40", "--theta-r", "20", "--n", "1.6", "--k", "2"], "--sigma is required"),
    (["--theta-i", "40", "--theta-r", "20", *STEEL[:6], "--kd", "-1"], "kd must be >= 0, got -1.0"),
    (["--theta-i", "40", "--theta-r", "20", *STEEL, "--device", "no-such-device"], "matches no OpenCL"),
])
def test_eval_errors_name_the_option(args, message):
    proc = run_cli("eval", *args)
    assert proc.returncode != 0
    assert message in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
