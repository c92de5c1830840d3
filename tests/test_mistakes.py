"""The mistakes users make (issue: catch the user's mistakes): units, sizes, the command line.
Each gets a correct answer or one line saying what to do, before any work; never a traceback."""
import subprocess
import sys
import warnings

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl import cli, sizes
from pbrdf_cl.analysis import maps, sweeps
from pbrdf_cl.cli import app as cli_app
from pbrdf_cl.compute import pointwise as api

STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "pbrdf_cl", *args], capture_output=True, text=True, timeout=300)


# ---- units and conventions

def test_angles_in_radians_are_flagged():
    with pytest.warns(api.UnitsWarning, match=r"all lie below 1.6 degrees .*are they in radians\?"):
        pbrdf_cl.dop(np.radians(40), np.radians([20.0, 45.0, 65.0]), backend="numpy", **STEEL)
    with warnings.catch_warnings():
        warnings.simplefilter("error", api.UnitsWarning)
        pbrdf_cl.dop(40, [20.0, 45.0, 65.0], backend="numpy", **STEEL)  # degrees
        pbrdf_cl.dop(0.0, 0.0, backend="numpy", **STEEL)  # normal incidence and viewing: not radians
        pbrdf_cl.dop(0.0, [0.5, 30.0], backend="numpy", **STEEL)  # one angle above 1.6
    proc = run_cli("eval", "--theta-i", "0.698", "--theta-r", "0.5", "--n", "1.6", "--k", "2", "--sigma", "0.3",
                   "--backend", "numpy")
    assert proc.returncode == 0
    assert proc.stderr.strip().splitlines() == [
        "pbrdf-cl: warning: theta_i and theta_r all lie below 1.6 degrees (the largest is 0.698): are they in "
        "radians? pbrdf-cl takes degrees (np.degrees(...) converts)"]


def test_radians_of_long_arrays_are_told_from_degrees_across_blocks():
    """Arrays longer than one check block: the radians check stops at the first block holding an
    angle of degrees' size, wherever that block lies, and reads everything only when there is none
    (then the largest angle is told, NaN or a negative angle meaning no warning, as for short arrays)."""
    B = api.CHECK_BLOCK
    small = np.linspace(0.0, 1.5, 3 * B + 5)
    assert api.radians_suspect(small, 0.2) == pytest.approx(1.5)
    assert api.radians_suspect(0.2, small[::-1].copy()) == pytest.approx(1.5)
    for at in (0, B - 1, B, 3 * B + 4):  # one angle of degrees in the first, a middle or the last block
        late = small.copy()
        late[at] = 45.0
        assert api.radians_suspect(late, 0.2) is None and api.radians_suspect(0.2, late) is None
    for bad in (np.nan, -0.1):
        odd = small.copy()
        odd[2 * B] = bad
        assert api.radians_suspect(odd, 0.2) is None
    assert api.radians_suspect(np.zeros(2 * B), 0.0) is None  # normal incidence and viewing
    strided = np.repeat(small, 2)[::2]  # not contiguous
    assert api.radians_suspect(strided, 0.2) == pytest.approx(1.5)
    strided[B + 3] = 80.0
    assert api.radians_suspect(strided, 0.2) is None


def test_radians_are_flagged_on_the_grid_paths_too(tmp_path):
    """grid, reduce_grid, objective, map (once, though its derivative runs more grids) and sweep specs
    warn as eval and fit (once, though its grid stage runs objective) do, whether the zenith angles
    are axes or fixed values; degrees stay silent."""
    rad = np.radians(np.linspace(0, 85, 8))
    for call in (lambda: pbrdf_cl.grid({"theta_r": rad}, dict(theta_i=0.7, **STEEL), backend="numpy"),
                 lambda: pbrdf_cl.grid({"theta_i": rad, "theta_r": rad}, STEEL, backend="numpy"),
                 lambda: pbrdf_cl.reduce_grid({"theta_r": rad, "sigma": [0.3, 0.5]}, dict(theta_i=0.7, n=1.6, k=2.1),
                                              over="theta_r", backend="numpy"),
                 lambda: pbrdf_cl.objective(dict(theta_i=[0.5, 0.7, 0.9], theta_r=[0.3, 0.8, 1.1], dop=[0.1, 0.2, 0.3]),
                                            grid=dict(n=[1.5, 2.0], k=2.0, sigma=0.5), backend="numpy")):
        with pytest.warns(api.UnitsWarning, match=r"all lie below 1.6 degrees .*are they in radians\?"):
            call()
    fixed = {k: v for k, v in STEEL.items() if k != "sigma"}
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        maps.make_map(("theta_r", rad), ("sigma", np.linspace(0.1, 1, 5)), dict(theta_i=0.7, **fixed),
                      derivative="sigma", backend="numpy")
    assert [str(w.message)[:40] for w in seen if issubclass(w.category, api.UnitsWarning)] == [
        "theta_i and theta_r all lie below 1.6 de"]
    with pytest.warns(api.UnitsWarning, match="spec: theta_i and theta_r all lie below 1.6 degrees"):
        sweeps.load_spec(dict(axes=dict(theta_r=rad.tolist()), fixed=dict(theta_i=0.7, **STEEL)))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        pbrdf_cl.fit(dict(theta_i=np.radians([30.0, 40, 50, 30, 40, 50]),
                          theta_r=np.radians([20.0, 45, 65, 40, 60, 30]), dop=[0.05, 0.17, 0.34, 0.1, 0.2, 0.3]),
                     backend="numpy")
    assert sum(issubclass(w.category, api.UnitsWarning) for w in seen) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error", api.UnitsWarning)
        pbrdf_cl.grid({"theta_r": np.linspace(0, 85, 8)}, dict(theta_i=40, **STEEL), backend="numpy")
        pbrdf_cl.grid({"theta_r": rad}, dict(theta_i=40, **STEEL), backend="numpy")  # theta_i in degrees
        sweeps.load_spec(dict(axes=dict(theta_r=np.linspace(0, 85, 8).tolist()), fixed=dict(theta_i=40, **STEEL)))
    proc = run_cli("map", "--x", "theta_r=0:1.4@8", "--y", "sigma=0.1:1@4", "--fix", "theta_i=0.7", "n=1.6", "k=2",
                   "kd=0.1", "--derivative", "sigma", "--backend", "numpy", "--out", str(tmp_path / "m.png"))
    assert proc.returncode == 0 and proc.stderr.count("are they in radians?") == 1, proc.stderr
    spec = tmp_path / "s.toml"
    spec.write_text('quantity = "dop"\n[axes]\ntheta_r = "0:1.4@8"\n[fixed]\ntheta_i = 0.7\nn = 1.6\nk = 2.0\n'
                    'sigma = 0.3\n')
    proc = run_cli("sweep", str(spec), "--out", str(tmp_path / "s.zarr"), "--quiet", "--backend", "numpy")
    assert proc.returncode == 0 and "pbrdf-cl: warning: spec: theta_i and theta_r all lie below" in proc.stderr


def test_a_map_axis_the_quantity_does_not_depend_on_is_noted(tmp_path):
    x, y = ("theta_r", np.linspace(0, 85, 20)), ("sigma", np.linspace(0.05, 1, 12))
    ds = maps.make_map(x, y, dict(theta_i=40, n=1.6, k=2.1), backend="numpy")  # kd = 0
    assert ds.attrs["notes"] == ["dop does not depend on sigma over this map: with kd = 0 the DOP is the "
                                 "specular term's alone, whose scale (sigma, ks, the shadowing) cancels"]
    ds = maps.make_map(x, y, dict(theta_i=40, n=1.6, k=2.1, kd=0.2), backend="numpy")
    assert "notes" not in ds.attrs
    ds = maps.make_map(("n", np.linspace(1.2, 3, 10)), ("theta_r", np.linspace(5, 85, 9)),
                       dict(theta_i=40, phi=120, k=2.1, sigma=0.3), quantity="aop", backend="numpy")
    assert ds.attrs["notes"] == ["aop does not depend on n over this map: the AoP depends on the geometry alone "
                                 "wherever it is defined"]
    proc = run_cli("map", "--x", "theta_r=0:85@20", "--y", "sigma=0.05:1@12", "--fix", "theta_i=40", "n=1.6", "k=2",
                   "--backend", "numpy", "--out", str(tmp_path / "m.png"))
    assert proc.returncode == 0 and "pbrdf-cl: note: dop does not depend on sigma over this map" in proc.stderr


# ---- sizes, checked before any work

def test_outputs_that_cannot_fit_are_refused_first(monkeypatch):
    monkeypatch.setattr(sizes, "available_memory", lambda: 1 << 30)  # 1 GiB
    big = np.broadcast_to(1.6, (20000, 20000))
    with pytest.raises(sizes.TooLargeError, match=r"^the dop of 400000000 points needs 2.98 GiB, but 1 GiB of memory "
                       r"is available; evaluate fewer points per call"):
        pbrdf_cl.dop(40, 30, n=big, k=2, sigma=0.3)
    axes = dict(theta_r=np.linspace(0, 85, 2000), sigma=np.linspace(0.05, 1, 2000), kd=np.linspace(0, 1, 100))
    with pytest.raises(MemoryError, match=r"^the grid of 2000 x 2000 x 100 = 400000000 points needs 1.49 GiB"):
        pbrdf_cl.grid(axes, dict(theta_i=40, n=1.6, k=2.1))
    with pytest.raises(ValueError, match=r"^the map of 20000 x 20000 points needs"):  # also a ValueError
        maps.make_map(("theta_r", np.linspace(0, 85, 20000)), ("sigma", np.linspace(0.05, 1, 20000)),
                      dict(theta_i=40, n=1.6, k=2.1), derivative="sigma")


@pytest.mark.parametrize("args,start", [
    (["eval", "--theta-i", "40", "--theta-r", "0:85:0.0001", "--sigma", "0.01:1:0.0001", "--n", "1.6", "--k", "2"],
     "pbrdf-cl: error: pbrdf-cl eval of 1 x 850001 x 1 x 1 x 1 x 9901 x 1 x 1 x 1 = 8415859901 rows needs"),
    (["map", "--x", "theta_r=0:85@100000", "--y", "sigma=0.05:1@100000", "--fix", "theta_i=40", "n=1.6", "k=2"],
     "pbrdf-cl: error: the map of 100000 x 100000 points needs"),
    (["reproduce", "--resolution", "100000"], "pbrdf-cl: error: --resolution 100000: a map of 100000 x 300000 points"),
])
def test_cli_sizes_refused_in_one_line_before_any_work(tmp_path, args, start):
    out = {"map": ["--out", str(tmp_path / "o.png")], "reproduce": ["--out", str(tmp_path / "o")]}
    proc = run_cli(*args, *out.get(args[0], []))
    assert proc.returncode == 1 and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(start) and "memory is available" in lines[0]
    assert not (tmp_path / "o").exists() and not (tmp_path / "o.png").exists()


@pytest.mark.parametrize("script", ["bench_fit", "bench_sobol", "check_design"])
def test_scripts_check_their_json_before_the_work(script, tmp_path):
    root = __import__("pathlib").Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, str(root / "scripts" / f"{script}.py"), "--json", str(tmp_path / "o.txt")],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 1 and proc.stdout == "" and proc.stderr.count("\n") == 1
    assert proc.stderr.startswith(f"{script}: error: --json ") and "'.txt'" in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_save_npz_writes_the_file_it_names(tmp_path):
    ds = maps.make_map("theta_r=0:85@4", "sigma=0.1:1@3", dict(theta_i=40, n=1.6, k=2.0), backend="numpy")
    with pytest.raises(ValueError, match=r"m.txt: numpy's archive is named .npz; write e.g. .*m.npz"):
        maps.save_npz(ds, tmp_path / "m.txt")
    assert not list(tmp_path.iterdir())  # not m.txt.npz
    maps.save_npz(ds, tmp_path / "m.npz")
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]


@pytest.mark.parametrize("argv, option, suffix", [
    (["fit-image", "stack.npz", "--out", "params.npz"], "--out", "'.npz'"),
    (["fit-image", "stack.npz", "--out", "params.zarr", "--png", "maps.txt"], "--png", "'.txt'"),
    (["sweep", "examples/sweep_sigma_theta.toml", "--out", "sweep.nc"], "--out", "'.nc'"),
    (["map", "--x", "theta_r=0:85@8", "--y", "sigma=0.1:1@4", "--fix", "theta_i=40", "n=1.6", "k=2", "--out", "m.txt"],
     "--out", "'.txt'"),
    (["map", "--x", "theta_r=0:85@8", "--y", "sigma=0.1:1@4", "--fix", "theta_i=40", "n=1.6", "k=2", "--out", "m"],
     "--out", "without one"),
    (["map", "--x", "theta_r=0:85@8", "--y", "sigma=0.1:1@4", "--fix", "theta_i=40", "n=1.6", "k=2", "--out", "m.png",
      "--npz", "m.txt"], "--npz", "'.txt'"),
    (["fit", "examples/steel_435nm.csv", "--json", "fit.csv"], "--json", "'.csv'"),
    (["fit", "examples/steel_435nm.csv", "--plot", "fit.txt"], "--plot", "'.txt'"),
    (["sobol", "examples/sobol.toml", "--png", "sobol.txt"], "--png", "'.txt'"),
    (["design", "--params", "n=1.6,k=2.139,sigma=0.5", "--png", "design.nc"], "--png", "'.nc'"),
    (["bench", "--quick", "--json", "bench.txt"], "--json", "'.txt'"),
])
def test_every_output_suffix_is_checked_before_the_work(argv, option, suffix, capsys, monkeypatch):
    """An output whose suffix names another format (a Zarr store called params.npz, a figure called
    m.txt) is refused in one line naming the option, the suffix and a name that works, before any
    work: the functions that would do it fail the test if called."""
    import os

    from pbrdf_cl.analysis import designs, sensitivity
    from pbrdf_cl.device import engine
    from pbrdf_cl.fitting.images import batch
    from pbrdf_cl.fitting.sample import inversion
    root = __import__("pathlib").Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)

    def no_work(*a, **k):
        raise AssertionError("the work started before the output was checked")
    for module, name in ((batch, "fit_batch"), (sweeps, "sweep"), (maps, "make_map"),
                         (inversion, "fit"), (sensitivity, "sobol"), (designs, "design"), (engine, "resolve_engine")):
        monkeypatch.setattr(module, name, no_work)
    rc = cli.main(argv)
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1 and err.startswith(f"pbrdf-cl: error: {option} "), err
    assert suffix in err and "write e.g." in err
    assert not any(os.path.exists(a) for a in argv if a.endswith((".zarr", ".nc", ".txt", ".csv")) and a != "stack.npz"
                   and not a.startswith("examples"))


def test_sweep_checks_disk_and_extras_before_creating_the_store(tmp_path, monkeypatch, capsys):
    spec = dict(axes=dict(theta_r="0:85@64", sigma="0.05:1@64"), fixed=dict(theta_i=40, n=1.6, k=2.0),
                chunks=dict(points=1024), dtype="float64")
    monkeypatch.setattr(sizes, "free_disk", lambda path: 10000)
    with pytest.raises(sizes.TooLargeError, match=r"^the store would hold up to 32 KiB \(4096 points, uncompressed"):
        pbrdf_cl.sweep(spec, tmp_path / "a.zarr", progress=False)
    assert not (tmp_path / "a.zarr").exists()
    res = pbrdf_cl.sweep(spec, tmp_path / "a.zarr", progress=True, allow_large=True, backend="numpy")
    assert res.complete
    err = capsys.readouterr().err
    assert "sweep: 4096 points in 4 chunks (4 to compute), up to 32 KiB stored uncompressed" in err
    assert "sweep: a chunk takes about" in err and "for the rest" in err
    monkeypatch.undo()
    import importlib.util
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "distributed" else real(name, *a))
    with pytest.raises(RuntimeError, match=r"needs dask.distributed: pip install 'pbrdf-cl\[cluster\]'"):
        sweeps.sweep(spec, tmp_path / "b.zarr", workers=2, progress=False)
    assert not (tmp_path / "b.zarr").exists()


# ---- the command line

def test_cli_basics(capsys):
    assert cli.main([]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: pbrdf-cl") and "COMMAND" in out
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.strip() == f"pbrdf-cl {pbrdf_cl.__version__}"
    with pytest.raises(SystemExit):
        cli.main(["eval", "--theta-i", "40", "--theta-r", "30", "--n", "1.6", "--k", "2", "--sigmaa", "0.3"])
    assert "unrecognized arguments: --sigmaa 0.3; did you mean --sigma?" in capsys.readouterr().err
    for command in ("eval", "map", "fit"):
        with pytest.raises(SystemExit):
            cli.main([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "shadowing function: paper" in text and "(default: paper)" in text, command
        if command != "fit":
            assert "precision (default: float64)" in text and "(default: dop)" in text, command


def test_a_list_option_does_not_swallow_the_data_file():
    parser = cli.build_parser()
    args = parser.parse_args(cli_app._positionals_first(["fit", "--fix", "sigma=0.45", "examples/steel_435nm.csv",
                                                     "--bounds", "n=1:3", "k=0:5"]))
    assert args.data == ["examples/steel_435nm.csv"]
    assert args.fix == ["sigma=0.45"] and args.bounds == ["n=1:3", "k=0:5"]
    # a malformed item is not taken for the file: it gets its own message
    assert cli_app._positionals_first(["map", "--fix", "k"]) == ["map", "--fix", "k"]


def test_eval_rows_are_the_product_in_order(capsys):
    assert cli.main(["eval", "--theta-i", "30,40", "--theta-r", "20:30:5", "--n", "1.6", "--k", "2", "--sigma",
                     "0.3,0.5", "--backend", "numpy", "--json"]) == 0
    import json
    rows = json.loads(capsys.readouterr().out)["rows"]
    import itertools
    want = list(itertools.product([30.0, 40.0], [20.0, 25.0, 30.0], [0.3, 0.5]))
    assert [(r["theta_i"], r["theta_r"], r["sigma"]) for r in rows] == want
    np.testing.assert_allclose([r["dop"] for r in rows],
                               [float(pbrdf_cl.dop(a, b, n=1.6, k=2, sigma=s, backend="numpy")) for a, b, s in want],
                               rtol=1e-12)


# ---- issue #39, item 3: what is held in memory at once is refused before it is allocated

DESIGN_10E8 = ["design", "--params", "n=1.6,k=2.139,sigma=0.5,kd=0.15,c=-0.3", "--candidates", "theta_i=0:89@10000",
               "theta_r=0:89@10000", "--backend", "numpy"]


def test_a_design_over_1e8_candidates_is_refused_in_one_line_before_any_work():
    proc = run_cli(*DESIGN_10E8)
    assert proc.returncode == 1 and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "pbrdf-cl: error: design: 100000000 candidate geometries x 1 material needs 208.6 GiB, "), lines
    assert "give fewer candidates" in lines[0]
    with pytest.raises(sizes.TooLargeError, match=r"^design: 400 candidate geometries x 16 materials needs 13.67 MiB, "
                       r"more than memory_budget = 100 KiB; give fewer candidates \(a coarser grid\), fewer materials "
                       r"or raise memory_budget \(pbrdf-cl design --memory-budget\)$"):
        pbrdf_cl.design(dict(n=(1.2, 2.0), k=2.1, sigma=0.5), dict(theta_i="10:80@20", theta_r="0:85@20"),
                        memory_budget="100 KiB", backend="numpy")


def test_maps_and_grids_beyond_their_limits_are_refused_before_any_work(monkeypatch):
    def no_work(*a, **k):
        raise AssertionError("the work started before the size was checked")
    monkeypatch.setattr(pbrdf_cl.compute.dense, "aligned_empty", no_work)
    with pytest.raises(sizes.TooLargeError, match=r"^the map of 10000 x 10000 points needs 13.41 GiB, more than "
                       r"memory_budget = 1 GiB; use fewer points per axis .* or raise memory_budget \(pbrdf-cl map "
                       r"--memory-budget\)$"):
        maps.make_map(("theta_r", np.linspace(0, 85, 10000)), ("sigma", np.linspace(0.05, 1, 10000)),
                      dict(theta_i=40, n=1.6, k=2.1), backend="numpy")
    axes = dict(theta_r=np.linspace(0, 85, 2000), sigma=np.linspace(0.05, 1, 2000), kd=np.linspace(0, 1, 200))
    with pytest.raises(sizes.TooLargeError, match=r"^the grid of 2000 x 2000 x 200 = 800000000 points needs 2.98 GiB, "
                       r"more than the 2 GiB an in-memory result may take; .*pbrdf-cl sweep .*, or pass allow_large="):
        pbrdf_cl.grid(axes, dict(theta_i=40, n=1.6, k=2.1), backend="numpy")
    monkeypatch.undo()
    monkeypatch.setattr(sizes, "LARGE_RESULT", 1000)
    small = dict(theta_r=np.linspace(0, 85, 30), sigma=np.linspace(0.05, 1, 20))
    with pytest.raises(sizes.TooLargeError, match=r"the grid of 30 x 20 = 600 points needs 4.688 KiB"):
        pbrdf_cl.grid(small, dict(theta_i=40, n=1.6, k=2.1), dtype="float64", backend="numpy")
    assert pbrdf_cl.grid(small, dict(theta_i=40, n=1.6, k=2.1), backend="numpy", allow_large=True).shape == (30, 20)
    proc = run_cli("map", "--x", "theta_r=0:85@4000", "--y", "sigma=0.05:1@4000", "--fix", "theta_i=40", "n=1.6",
                   "k=2", "--memory-budget", "256 MiB", "--out", "never.png")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(lines) == 1 and "more than memory_budget = 256 MiB" in lines[0], lines


def lazy_stack(shape):
    """A lazy (dask) DOP stack of ``shape`` pixels at shared geometry: nothing is computed unless read."""
    da = pytest.importorskip("dask.array")
    import xarray as xr
    ti, tr = np.repeat([30.0, 40.0, 50.0], 10), np.tile(np.arange(20.0, 66.0, 5.0), 3)
    dims = tuple(f"d{i}" for i in range(len(shape)))
    dop = da.full(shape + (30,), 0.3, chunks=tuple(max(1000, s // 100) for s in shape) + (30,))
    return xr.Dataset({"dop": (dims + ("m",), dop), "theta_i": (("m",), ti), "theta_r": (("m",), tr)})


def test_an_image_fit_of_1e12_pixels_is_refused_before_any_pixel_is_read(tmp_path):
    """A 10^12-pixel lazy stack: its blocks' bookkeeping (a list of row ranges, their done marks)
    alone would pass the memory; refused in one line, in memory and into a store (nothing created);
    a row of 10^6 pixels too large for one block likewise."""
    from pbrdf_cl.fitting.images import batch
    for store in (None, tmp_path / "fit.zarr"):
        with pytest.raises(sizes.TooLargeError, match=r"^the bookkeeping of 1000000000000 pixels in 139508929 blocks "
                           r"of 7168 rows needs 33.26 GiB, (but .* of memory is available|more than memory_budget)"):
            batch.fit_batch(lazy_stack((10 ** 12,)), store=store, backend="numpy", progress=False)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match=r"memory_budget=536870912 bytes is too small for one row of 1000000 pixels"):
        batch.fit_batch(lazy_stack((10 ** 6, 10 ** 6)), backend="numpy", progress=False)
    with pytest.raises(sizes.TooLargeError, match=r"^the result of 1000000000 pixels needs .*; write it into a Zarr "
                       r"store block by block \(store=; pbrdf-cl fit-image\)$"):
        batch.fit_batch(lazy_stack((10 ** 5, 10 ** 4)), backend="numpy", progress=False, memory_budget="4 GiB")


# ---- issue #39, item 6: the remaining bad inputs, one line of ours each

C_SPEC = "[axes]\ntheta_r = \"0:85@16\"\n{axis}[fixed]\ntheta_i = 40\nn = 1.6\nk = 2.0\nsigma = 0.3\nkd = 0.1\n{fixed}"


@pytest.mark.parametrize("argv, line", [
    (["eval", "--theta-i", "40", "--theta-r", "30", "--n", "1.6", "--k", "2", "--sigma", "0.3", "--kd", "0.1", "--c",
      "5"], "c must be in [-1, 0], got 5.0"),
    (["eval", "--theta-i", "40", "--theta-r", "30", "--n", "1.6", "--k", "2", "--sigma", "0.3", "--kd", "0.1", "--c",
      "5", "--backend", "numpy"], "c must be in [-1, 0], got 5.0"),
    (["sweep", "{fixed}", "--out", "{tmp}/a.zarr"], "fixed.c: c must be in [-1, 0], got 5.0"),
    (["sweep", "{axis}", "--out", "{tmp}/b.zarr"], "axes.c: c must be in [-1, 0], got 1.0 at index [2]"),
    (["fit", "examples/steel_435nm.csv", "--fix", "c=5"], "--fix c=5: c must be in [-1, 0], got 5.0"),
    (["fit", "examples/steel_435nm.csv", "--bounds", "c=-2:0"],
     "bounds: c low = -2.0 is outside the model's domain (c must be in [-1, 0])"),
    (["fit-image", "{tmp}/stack.npz", "--out", "{tmp}/f.zarr", "--fix", "c=5"], "--fix c=5: c must be in [-1, 0]"),
    (["map", "--x", "theta_r=0:85@8", "--y", "sigma=0.1:1@4", "--fix", "theta_i=40", "n=1.6", "k=2", "kd=0.1", "c=5",
      "--out", "{tmp}/m.png"], "--fix c=5: c must be in [-1, 0], got 5.0"),
    (["design", "--params", "n=1.6,k=2.139,sigma=0.5,kd=0.15,c=5"], "--params c=5: c must be in [-1, 0], got 5.0"),
])
def test_c_outside_the_model_is_refused_on_every_path(argv, line, tmp_path, capsys, monkeypatch):
    """c = 5 (the model defines the Minnaert exponent in (-1, 0]) is refused in one line by eval
    (on the device, whose kernel checks the domain itself, and in numpy), a sweep's fixed value and
    axis, fit's and fit-image's --fix and --bounds, map and design; nothing is written."""
    root = __import__("pathlib").Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)
    (tmp_path / "fixed.toml").write_text(C_SPEC.format(axis="", fixed="c = 5\n"))
    (tmp_path / "axis.toml").write_text(C_SPEC.format(axis="c = \"-1:5@7\"\n", fixed=""))
    np.savez(tmp_path / "stack.npz", dop=np.full((2, 2, 30), 0.3), theta_i=np.repeat([30.0, 40, 50], 10),
             theta_r=np.tile(np.arange(20.0, 66, 5), 3))
    argv = [a.format(tmp=tmp_path, fixed=tmp_path / "fixed.toml", axis=tmp_path / "axis.toml") for a in argv]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("pbrdf-cl: error: ") and line in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["axis.toml", "fixed.toml", "stack.npz"]


@pytest.mark.parametrize("argv, option", [
    (["fit", "examples/steel_435nm.csv", "--plot", "{missing}/fit.png"], "--plot"),
    (["fit", "examples/steel_435nm.csv", "--json", "{missing}/fit.json"], "--json"),
    (["fit-image", "stack.npz", "--out", "{tmp}/params.zarr", "--png", "{missing}/maps.png"], "--png"),
    (["map", "--x", "theta_r=0:85@8", "--y", "sigma=0.1:1@4", "--fix", "theta_i=40", "n=1.6", "k=2", "--out",
      "{missing}/m.png"], "--out"),
    (["map", "--x", "theta_r=0:85@8", "--y", "sigma=0.1:1@4", "--fix", "theta_i=40", "n=1.6", "k=2", "--out",
      "{tmp}/m.png", "--npz", "{missing}/m.npz"], "--npz"),
    (["sobol", "examples/sobol.toml", "--png", "{missing}/sobol.png"], "--png"),
    (["design", "--params", "n=1.6,k=2.139,sigma=0.5", "--png", "{missing}/design.png"], "--png"),
    (["design", "--params", "n=1.6,k=2.139,sigma=0.5", "--out", "{missing}/design.nc"], "--out"),
    (["bench", "--quick", "--json", "{missing}/bench.json"], "--json"),
])
def test_an_output_in_a_folder_that_does_not_exist_is_refused_not_made(argv, option, tmp_path, capsys, monkeypatch):
    """--plot /nonexist/x.png made /nonexist: a file's folder that does not exist is refused in one
    line naming the option and the folder, before any work, and nothing is made."""
    from pbrdf_cl.analysis import designs, sensitivity
    from pbrdf_cl.device import engine
    from pbrdf_cl.fitting.images import batch
    from pbrdf_cl.fitting.sample import inversion
    root = __import__("pathlib").Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)

    def no_work(*a, **k):
        raise AssertionError("the work started before the output was checked")
    for module, name in ((batch, "fit_batch"), (maps, "make_map"), (inversion, "fit"), (sensitivity, "sobol"),
                         (designs, "design"), (engine, "resolve_engine")):
        monkeypatch.setattr(module, name, no_work)
    missing = tmp_path / "nonexist"
    argv = [a.format(tmp=tmp_path, missing=missing) for a in argv]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"pbrdf-cl: error: {option} {missing}/"), err
    assert f"the folder {missing} does not exist; create it first or choose another {option}" in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [
    ["fit", "examples/steel_435nm.csv", "--bounds", "n=1:1e300"],
    ["fit-image", "{tmp}/stack.npz", "--out", "{tmp}/f.zarr", "--bounds", "n=1:1e300"],
    ["design", "--params", "n=1.6,k=2.139,sigma=0.5", "--bounds", "n=1:1e300"],
])
def test_bounds_beyond_what_a_fit_searches_are_refused(argv, tmp_path, capsys, monkeypatch):
    """--bounds n=1:1e300 returned a wrong fit labelled as a model misfit (overflow in the grid and
    the descents): refused in one line with the range a fit searches (the registry's limits)."""
    monkeypatch.chdir(__import__("pathlib").Path(__file__).resolve().parents[1])
    np.savez(tmp_path / "stack.npz", dop=np.full((2, 2, 30), 0.3), theta_i=np.repeat([30.0, 40, 50], 10),
             theta_r=np.tile(np.arange(20.0, 66, 5), 3))
    assert cli.main([a.format(tmp=tmp_path) for a in argv]) == 1
    err = capsys.readouterr().err
    assert err == ("pbrdf-cl: error: bounds: n = (1, 1e+300) reaches beyond what a fit searches (n in [0.01, 100]: "
                   "the model's arithmetic and the search's resolution); give bounds within it\n"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stack.npz"]
    for name, (lo, hi) in {"sigma": (1e-9, 1.0), "k": (0.0, 1e5), "ks": (1e-3, 1e9), "kd": (0.0, 1e4)}.items():
        with pytest.raises(ValueError, match=rf"^bounds: {name} = .* reaches beyond what a fit searches"):
            pbrdf_cl.fitting.setup.FitSetup.check(bounds={name: (lo, hi)})
    pbrdf_cl.fitting.setup.FitSetup.check(bounds=dict(n=(0.01, 100), k=(0, 100), sigma=(1e-3, 10), kd=(0, 1e3)))
