"""An installed wheel, away from the source tree, finds its OpenCL kernels through importlib.resources."""
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_wheel_ships_kernels_and_evaluates_outside_the_source_tree(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for name in ("setup.cfg", "pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("pbrdf_cl", "kernels"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(dist), str(src)], check=True, timeout=300)
    wheel = next(dist.glob("pbrdf_cl-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    assert "pbrdf_cl/kernels/pbrdf.h" in names and "pbrdf_cl/kernels/pbrdf_points.cl" in names
    assert "pbrdf_cl/app/page.py" in names and "pbrdf_cl/io/params.py" in names  # the explorer ships too
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target),
                    str(wheel)], check=True, timeout=300)
    work = tmp_path / "elsewhere"
    work.mkdir()
    code = ("import pbrdf_cl, pbrdf_cl.device.engine as e; "
            "print(pbrdf_cl.__file__); print(e.kernel_dir()); "
            "print(repr(float(pbrdf_cl.dop(40, 45, n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3))))")
    env = dict(os.environ, PYTHONPATH=str(target), PYTHONWARNINGS="ignore")
    proc = subprocess.run([sys.executable, "-c", code], cwd=work, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    module_file, kdir, value = proc.stdout.strip().splitlines()
    assert Path(module_file).is_relative_to(target)
    assert Path(kdir).is_relative_to(target) and Path(kdir).name == "kernels"
    assert abs(float(value) - 0.167590) < 5e-7
