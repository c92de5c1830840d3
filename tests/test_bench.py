"""scripts/bench.py runs (quick sizes) and reports every path with a small error; speed is
measured by running the script, never asserted in tests."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import pbrdf_cl

from conftest import requires_opencl

ROOT = Path(__file__).resolve().parent.parent


@requires_opencl
def test_bench_quick_reports_every_path(tmp_path):
    out = tmp_path / "bench.json"
    env = dict(os.environ, PYTHONPATH=str(Path(pbrdf_cl.__file__).resolve().parent.parent), PYTHONWARNINGS="ignore")
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench.py"), "--quick", "--json", str(out)],
                          capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(out.read_text())
    assert report["device"] == pbrdf_cl.get_default_engine().description
    paths = {(r["path"].split(" (")[0], r["dtype"]) for r in report["rows"]}
    for path in ("per-point kernel", "factorised grid", "pbrdf_cl.grid -> host DataArray",
                 "objective, grid x 30 measurements"):
        assert (path, "float32") in paths and (path, "float64") in paths, path
    assert ("numpy reference", "float64") in paths
    assert any(p.startswith("sweep -> Zarr store") for p, _ in paths), paths
    for r in report["rows"]:
        assert r["rate"] > 0
        if r["path"].startswith("objective"):
            assert r["max_abs_err"] <= (1e-12 if r["dtype"] == "float64" else 1e-4), r
        else:
            assert r["max_abs_err"] <= (1e-12 if r["dtype"] == "float64" else 2e-5), r
    for line in ("per-point kernel", "factorised grid", "objective"):
        assert line in proc.stdout
    # end-to-end rows beside the kernel rows, with their peak memory and, with a C compiler, their
    # fractions of the C loop (pbrdf.h compiled as C) and of the memory roofline, both measured
    rows = {(r["path"], r["dtype"]): r for r in report["rows"]}
    for dtype in ("float32", "float64"):
        e2e = rows[(f"pbrdf_cl.dop, {dtype} inputs (end-to-end)", dtype)]
        assert e2e["peak_extra_mb"] <= 2 * e2e["output_mb"] + 64
        if dtype == "float32":  # the broadcast call, its inputs sent once and gathered as before (#12)
            bc = {r["path"].split(" broadcast, ")[1]: r for r in report["rows"] if " broadcast, " in r["path"]}
            assert set(bc) == {"sent once (end-to-end)", "gathered (end-to-end)"}, bc
            assert all(r["n"] == 1 << 16 and r["peak_extra_mb"] <= r["output_mb"] + 8 for r in bc.values()), bc
        grid = rows[("pbrdf_cl.grid -> host DataArray (end-to-end)", dtype)]
        assert grid["peak_extra_mb"] <= 2 * grid["output_mb"] + 64
        if shutil.which("cc") or shutil.which("gcc"):
            c = rows[("C loop, pbrdf.h compiled by the host's cc (limit)", dtype)]
            assert c["rate"] > 0 and "pbrdf_host.c" in c["compiled"]
            assert 0 < e2e["of_c_loop"] and 0 < e2e["of_roofline"] and 0 < grid["of_roofline"]
            assert e2e["of_c_loop"] == pytest.approx(e2e["rate"] / c["rate"])


@pytest.mark.parametrize("args", [["--help"], ["--quick", "--json", "out.json", "--sweep-workers", "0"]])
def test_cli_bench_takes_the_documented_options(tmp_path, args):
    env = dict(os.environ, PYTHONPATH=str(Path(pbrdf_cl.__file__).resolve().parent.parent), PYTHONWARNINGS="ignore")
    proc = subprocess.run([sys.executable, "-m", "pbrdf_cl", "bench", *args], capture_output=True, text=True,
                          timeout=600, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    if args == ["--help"]:
        assert "--quick" in proc.stdout and "--backend" in proc.stdout
    else:
        assert json.loads((tmp_path / "out.json").read_text())["rows"]


def test_bench_skips_the_cluster_row_without_dask_distributed(monkeypatch, capsys):
    import numpy as np

    from pbrdf_cl import bench
    monkeypatch.setitem(sys.modules, "distributed", None)  # as after a plain `pip install .`
    rows = []
    bench.bench_sweep(pbrdf_cl.NumpyEngine(), None, rows, np.random.default_rng(0), 0.25, 1, workers=2)
    assert [r["path"] for r in rows] == ["sweep -> Zarr store, here, numpy backend (end-to-end)"]
    assert "dask.distributed is not installed" in capsys.readouterr().out


def test_interleaved_rates_turn_the_order_so_that_no_call_always_follows_the_same_one():
    """An end-to-end call slowed the call after it; in a fixed order that was always the same row."""
    from pbrdf_cl import bench
    calls = []
    funcs = {name: (lambda name=name: calls.append(name) or sum(range(10000))) for name in "abc"}
    rates = bench.interleaved_rates(funcs, 1.0, 6, settle=0.0)
    assert set(rates) == set("abc") and all(w > 0 and c > 0 for w, c in rates.values())
    timed = calls[3:]  # after one warm-up call each
    assert len(timed) == 18 and all(timed.count(n) == 6 for n in "abc")
    before = {n: {timed[i - 1] for i in range(1, len(timed)) if timed[i] == n} for n in "abc"}
    assert all(len(prev) == 2 for prev in before.values()), before  # each follows both others
    assert [timed[3 * r] for r in range(6)] == list("abcabc")  # each leads in turn


@requires_opencl
def test_bench_skips_the_mitsuba_rows_without_mitsuba(monkeypatch, capsys):
    import numpy as np

    from pbrdf_cl import bench
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # mitsuba is never a dependency
    rows = []
    bench.bench_mitsuba(pbrdf_cl.get_default_engine(), rows, np.random.default_rng(0), 1 << 12, 1)
    assert rows == []
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and "Mitsuba rows are skipped: mitsuba is not installed" in out


@requires_opencl
def test_bench_mitsuba_rows_agree_with_the_model(tmp_path):
    """Where mitsuba (and a libLLVM) is installed: its rough conductor and our DOP side by side, both
    ways, agreeing where kd = 0 makes the two models the same DOP; speed is not asserted."""
    pytest.importorskip("mitsuba")
    import numpy as np

    from pbrdf_cl import bench
    mi, _ = bench.mitsuba_setup(1)
    if mi is None:
        pytest.skip("Mitsuba's LLVM variant is unavailable here")
    rows = []
    bench.bench_mitsuba(pbrdf_cl.get_default_engine(), rows, np.random.default_rng(0), 1 << 14, 1)
    assert len(rows) == 6 and all(r["rate"] > 0 and r["cpu_rate"] > 0 for r in rows)
    assert sum("kd 0.2" in r["path"] for r in rows) == 1  # the whole kernel, beside the conductor's short path
    assert sum("resident degrees" in r["path"] for r in rows) == 1 and rows[0]["ours_over_mitsuba_degrees"] > 0
    assert {r["path"].split(" (")[-1] for r in rows} == {"kernel)", "end-to-end)"}
    assert all(r["max_abs_err"] <= 2e-5 for r in rows), rows


def test_bench_joint_image_stacks_hold_their_materials_in_their_label_maps():
    """scripts/bench_joint_image.py's ``--stack`` images: every label of the map holds its own
    (n, k), and the noise-free DOP of the stack is the model's at those values, pixel by pixel."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import bench_joint_image as bench
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    for kind, (ti, tr, truth, ranges) in bench.STACKS.items():
        data, lab, got = bench.stack(12, 0.0, 3, kind)
        assert got == truth and sorted(np.unique(lab)) == sorted(truth), kind
        assert data["dop"].shape == (12, 12, ti.size) and np.all(data["dop_std"] == 0.0)
        rng = np.random.default_rng(3)  # the stack's own parameters, drawn as it draws them
        own = {a: rng.uniform(lo, hi, (12, 12, 1)) for a, lo, hi in ranges}
        for L, (n, k) in truth.items():
            where = np.argwhere(lab == L)
            i, j = where[len(where) // 2]
            want = np.abs(pbrdf_cl.dop(ti, tr, n=n, k=k, **{a: v[i, j] for a, v in own.items()}, backend="numpy"))
            np.testing.assert_allclose(data["dop"][i, j], want, rtol=0, atol=1e-15, err_msg=f"{kind} label {L}")
