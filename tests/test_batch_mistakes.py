"""The image-fit mistakes of issue #26 (pbrdf_cl.fit_batch, pbrdf-cl fit-image): the measurement
axis found from the geometry or refused in one line, a NaN dop_std, the camera path's own
variables, the goodness of fit of an image and phi left out.  Each gets the right answer or one
line naming the variable and what to do."""
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
import xarray as xr

import pbrdf_cl
from pbrdf_cl.fitting.images import batch as B
from pbrdf_cl.io import imagestack
from pbrdf_cl.io.measurements import PHI_DEFAULT_NOTE, DataWarning

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


# ---- the measurement axis (items 2 and 6)

def test_the_measurement_axis_is_the_one_the_shared_angles_run_along(dev, tmp_path):
    """dop with its measurements first or in the middle, the angles shared: a Dataset (as .nc
    too), a dict and a plain .npz give the fit of the (y, x, m) layout, over (y, x)."""
    dop = shared_stack()
    ref = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI, theta_r=TR, dop_std=0.003), engine=dev)
    ds = xr.Dataset({"dop": (("y", "x", "m"), dop), "theta_i": (("m",), TI), "theta_r": (("m",), TR),
                     "dop_std": ((), 0.003)}, coords={"y": [10.0, 20, 30]})
    first = ds.transpose("m", "y", "x")
    first.to_netcdf(tmp_path / "first.nc")
    np.savez(tmp_path / "first.npz", dop=np.moveaxis(dop, -1, 0), theta_i=TI, theta_r=TR, dop_std=0.003)
    for data in (first, ds.transpose("y", "m", "x"), str(tmp_path / "first.nc"), str(tmp_path / "first.npz"),
                 dict(dop=np.moveaxis(dop, -1, 0), theta_i=TI, theta_r=TR, dop_std=0.003),
                 dict(dop=np.moveaxis(dop, -1, 1), theta_i=TI, theta_r=TR, dop_std=np.full((3, 30, 4), 0.003))):
        res = pbrdf_cl.fit_batch(data, engine=dev)
        assert res.n.dims[-2:] in (("y", "x"), ("dim_0", "dim_1")) and res.n.shape == (3, 4), res.n.dims
        same_fit(res, ref)
    assert pbrdf_cl.fit_batch(first, engine=dev).y.values.tolist() == [10.0, 20.0, 30.0]
    proc = run_cli("fit-image", str(tmp_path / "first.npz"), "--out", str(tmp_path / "o.zarr"), "--no-progress")
    assert proc.returncode == 0, proc.stderr
    assert xr.open_zarr(tmp_path / "o.zarr").n.shape == (3, 4)


def test_a_dataset_with_its_measurement_dimension_first_and_per_pixel_angles(dev):
    """The camera stack's dims moved to (m, y, x), every angle per pixel: the dimension named m
    holds the measurements (as open_stack, synthetic_stack and camera_dataset name it)."""
    ds = imagestack.synthetic_stack(6, seed=2)
    same_fit(pbrdf_cl.fit_batch(ds.transpose("m", "y", "x"), engine=dev), pbrdf_cl.fit_batch(ds, engine=dev))


def test_a_stack_whose_angles_contradict_its_measurement_axis_is_refused(tmp_path):
    """Per-pixel angles moved with dop to (m, y, x) without a name to say so (a dict, a plain
    .npz, a Dataset whose dimension is not called m): fitted before as 480 pixels of 16
    measurements; now one line naming the axes and the fix, before any work."""
    ds = imagestack.synthetic_stack(16, seed=0)
    moved = {k: np.moveaxis(ds[k].values, -1, 0) for k in ("dop", "theta_i", "theta_r", "phi")}
    np.savez(tmp_path / "moved.npz", **moved, dop_std=0.005)
    message = (r"^data: dop's axis 2 \((?:'[a-z_]+', )?16 values\) is taken for the measurements, but the per-pixel "
               r"angles change along it as across an image's pixels .* and along axis 0 \((?:'[a-z_]+', )?30 values\) "
               r"as between measurements .*; put the measurements last: np.moveaxis\(a, 0, -1\)")
    for data in (moved, str(tmp_path / "moved.npz"), ds.rename(m="light").transpose("light", "y", "x")):
        with pytest.raises(ValueError, match=message) as err:
            B.BatchJob(data)
        assert "\n" not in str(err.value)
    proc = run_cli("fit-image", str(tmp_path / "moved.npz"), "--out", str(tmp_path / "o.zarr"), "--no-progress")
    assert proc.returncode == 1 and proc.stderr.startswith("pbrdf-cl: error: data: dop's axis 2") and \
        len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not (tmp_path / "o.zarr").exists()
    B.BatchJob(ds)  # the same stack as written, (y, x, m), is not refused


@pytest.mark.parametrize("data, message", [
    (dict(dop=np.full((30, 30, 5), 0.2), theta_i=TI, theta_r=TR),
     r"^data: dop \(30, 30, 5\) has 2 axes of length 30 \(0, 1\), the number of theta_i values: which holds the "
     r"measurements is ambiguous; put them last"),
    (dict(dop=np.full((4, 5, 7), 0.2), theta_i=TI, theta_r=TR),
     r"^data: theta_i has 30 values \(one per measurement\) but no axis of dop \(4, 5, 7\) has 30"),
    (dict(dop=np.full((4, 5, 30), 0.2), theta_i=TI, theta_r=TR[:20]),
     r"^data: the shared angles differ in length \(theta_i 30, theta_r 20\)"),
    (xr.Dataset({"dop": (("y", "x", "m"), np.full((4, 5, 30), 0.2)), "theta_i": (("m",), TI),
                 "theta_r": (("x",), np.full(5, 40.0))}),
     r"^data: the shared angles lie along different dimensions \(theta_i over 'm', theta_r over 'x'\)"),
])
def test_ambiguous_measurement_axes_are_refused_in_one_line(data, message):
    with pytest.raises(ValueError, match=message) as err:
        pbrdf_cl.fit_batch(data, backend="numpy")
    assert "\n" not in str(err.value)


# ---- a NaN dop_std (item 11)

def test_a_nan_std_is_refused_unless_its_measurement_is_missing_too(dev):
    """dop_std = NaN made every pixel too_few without a word: a NaN std of a measured DOP is
    refused naming the index and the fix; NaN in both marks a missing measurement."""
    dop = shared_stack((2, 3))
    with pytest.raises(ValueError, match=r"^data: dop_std is NaN \(one value for every measurement\): give the "
                                         r"noise std \(> 0\), or leave dop_std out"):
        pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI, theta_r=TR, dop_std=np.nan), engine=dev)
    std = np.full(dop.shape, 0.003)
    std[1, 2, 7] = np.nan
    with pytest.raises(ValueError, match=r"^dop_std is NaN at index \[1, 2, 7\] where dop is 0\.\d+: give that "
                                         r"measurement's std \(> 0\), or NaN in dop too to leave it out as missing$"):
        pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI, theta_r=TR, dop_std=std), engine=dev)
    with pytest.raises(ValueError, match=r"^dop_std is NaN at index \[0, 0, 4\]"):
        pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI, theta_r=TR, dop_std=np.where(np.arange(30) == 4, np.nan, 0.003)),
                           engine=dev)
    missing = dop.copy()
    missing[1, 2, 7] = np.nan
    res = pbrdf_cl.fit_batch(dict(dop=missing, theta_i=TI, theta_r=TR, dop_std=std), engine=dev)
    assert res.n_valid.values[1, 2] == 29 and np.all(res.status.values >= 0)


# ---- the camera path's own variables (item 14)

def test_the_camera_datasets_own_variables_are_read_without_a_warning(dev):
    pytest.importorskip("polanalyser")
    from pbrdf_cl.io import camera
    ti, tr = TI[::3], TR[::3]  # 10 geometries
    d = pbrdf_cl.dop(ti, tr, **STEEL, backend="numpy")
    a = np.radians(np.tile(np.array(camera.SUPERPIXEL, float), (4, 4)))
    frames = [np.round(0.5 * 20000 * (1 + dj * np.cos(2 * a))).astype(np.uint16) for dj in d]
    for irradiance in (None, 1.0):
        ds = camera.camera_dataset(frames, ti, tr, dop_std=0.002, irradiance=irradiance)
        assert "intensity" in ds
        with warnings.catch_warnings():
            warnings.simplefilter("error", DataWarning)
            res = pbrdf_cl.fit_batch(ds, fixed={"c": -0.3}, engine=dev)
        assert res.n.shape == (8, 8) and np.all(res.status.values >= 0)
    with pytest.warns(DataWarning, match="variable brightness over the measurements not read"):
        B.BatchJob(ds.assign(brightness=ds.intensity))  # another variable is still named


# ---- the goodness of fit of an image (item 5)

@pytest.fixture(scope="module")
def small_stack():
    return imagestack.synthetic_stack(8, seed=3)


@pytest.mark.parametrize("mistake", ["phi - 180", "phi in radians", "no dop_std, phi - 180"])
def test_a_model_that_does_not_describe_the_image_is_said_so(dev, small_stack, mistake):
    """phi given as phi - 180 (the other convention) or in radians: median chi2 ~7e4 for 25
    degrees of freedom, and fit_batch said nothing; now every pixel's test is kept
    (fits_data, p_value, r2) and the summary says what share fails, with the usual causes."""
    ds = small_stack
    good = pbrdf_cl.fit_batch(ds, engine=dev)
    assert good.attrs["goodness_fits_data"] == 1 and good.attrs["goodness_share_failed"] <= 0.05
    assert good.attrs["goodness"].startswith("goodness of fit: ") and "goodness_warning" not in good.attrs
    assert np.all(good.p_value.values[good.fits_data.values == 1] >= 1e-3)
    phi = np.radians(ds.phi) if mistake == "phi in radians" else (ds.phi - 180) % 360
    bad = ds.assign(phi=phi)
    if mistake.startswith("no dop_std"):
        bad = bad.drop_vars("dop_std")
    res = pbrdf_cl.fit_batch(bad, engine=dev)
    test = "r2" if mistake.startswith("no dop_std") else "chi2"
    assert res.attrs["goodness_test"] == test and res.attrs["goodness_fits_data"] == 0
    assert res.attrs["goodness_share_failed"] > 0.9 and res.attrs["goodness_tested"] == 64
    assert int((res.fits_data.values == 0).sum()) == res.attrs["goodness_failed"]
    if test == "chi2":
        assert float(res.p_value.median()) < 1e-3 and "median chi2" in res.attrs["goodness"]
    else:
        assert np.isnan(res.p_value.values).all() and float(res.r2.median()) < 0.9
    assert res.attrs["goodness_warning"].startswith("WARNING: the model does not describe the data of ")
    assert "the phi convention (180 is in plane" in res.attrs["goodness_warning"]


def test_fit_image_prints_the_goodness_and_keeps_it_in_the_store(small_stack, tmp_path):
    imagestack.save_stack(small_stack.assign(phi=(small_stack.phi - 180) % 360), tmp_path / "bad.npz")
    proc = run_cli("fit-image", str(tmp_path / "bad.npz"), "--out", str(tmp_path / "bad.zarr"), "--no-progress")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    store = xr.open_zarr(tmp_path / "bad.zarr")
    assert lines[2] == store.attrs["goodness"] and "64 of 64 fitted pixels (100.0%) fail the chi2 test" in lines[2]
    assert lines[3] == store.attrs["goodness_warning"] and lines[3].startswith("WARNING: ")
    assert store.attrs["goodness_fits_data"] == 0 and "fits_data" in store and "p_value" in store


# ---- phi left out (item 7)

def test_phi_left_out_of_fit_is_said(dev, tmp_path):
    """Without phi every point is in plane (phi = 180): a note on fit's result, one line on the
    command line (fit, fit --quiet); none where phi is given."""
    d = pbrdf_cl.dop(TI, TR, **STEEL, backend="numpy")
    res = pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=d), engine=dev)
    assert PHI_DEFAULT_NOTE in res.notes and f"note: {PHI_DEFAULT_NOTE}" in res.summary()
    assert PHI_DEFAULT_NOTE not in pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, phi=180.0, dop=d), engine=dev).notes
    (tmp_path / "nophi.csv").write_text("theta_i,theta_r,dop\n" + "".join(f"{a},{b},{c}\n"
                                                                       for a, b, c in zip(TI, TR, d)))
    (tmp_path / "phi.csv").write_text("theta_i,theta_r,phi,dop\n" + "".join(f"{a},{b},180,{c}\n"
                                                                          for a, b, c in zip(TI, TR, d)))
    for quiet in ([], ["--quiet"]):
        proc = run_cli("fit", str(tmp_path / "nophi.csv"), *quiet)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.count(PHI_DEFAULT_NOTE) == 1, proc.stdout
        proc = run_cli("fit", str(tmp_path / "phi.csv"), *quiet)
        assert proc.returncode == 0 and PHI_DEFAULT_NOTE not in proc.stdout, proc.stderr


def test_phi_left_out_of_fit_batch_is_said(dev):
    """The same note in fit_batch's attrs (fit-image prints it: test_batch_store's CLI test)."""
    d = pbrdf_cl.dop(TI, TR, **STEEL, backend="numpy")
    maps = pbrdf_cl.fit_batch(dict(dop=np.broadcast_to(d, (2, 2, 30)), theta_i=TI, theta_r=TR), engine=dev)
    assert maps.attrs["phi_given"] == 0 and maps.attrs["data_notes"].splitlines() == [PHI_DEFAULT_NOTE]
    given = pbrdf_cl.fit_batch(dict(dop=np.broadcast_to(d, (2, 2, 30)), theta_i=TI, theta_r=TR, phi=180.0),
                               engine=dev)
    assert given.attrs["phi_given"] == 1 and "data_notes" not in given.attrs


# ---- coordinates (item 15)

def test_the_stacks_pixel_coordinates_are_kept(dev, tmp_path):
    ds = imagestack.synthetic_stack(6, seed=1)
    res = pbrdf_cl.fit_batch(ds, engine=dev)
    for c in ("x_mm", "y_mm"):
        assert c in res.coords and res[c].attrs["units"] == "mm"
        np.testing.assert_array_equal(res[c].values, ds[c].values)
    assert "light_x" not in res.coords  # over the measurements, not the pixels
    job = B.BatchJob(ds)
    budget = job.fixed_bytes() + job.pixel_bytes() * 12  # blocks of two rows
    stored = pbrdf_cl.fit_batch(ds, store=tmp_path / "s.zarr", memory_budget=budget, engine=dev)
    assert stored.attrs["batch_blocks"] == 3
    for c in ("x_mm", "y_mm"):
        assert c in stored.coords and c not in stored.data_vars
        np.testing.assert_array_equal(stored[c].values, ds[c].values)


# ---- blocks do not change answers (item 12; the device path: test_batch.py)

def test_a_singular_problem_does_not_stop_the_others_of_its_batch():
    """The numpy backend's descent (pbrdf_cl.fitting.common.lm_batch, every pixel x start of a block at once):
    a problem whose Jacobian vanishes made the batched solve raise, and every problem of the
    batch lost its step, so a pixel's answer depended on its block."""
    from pbrdf_cl.fitting.common import lm_batch

    def rows(flat):
        """Problems ``flat`` (bool each) flat (a vanishing Jacobian), the others a valley with its
        minimum at (0.3, 0.09); rows as fd_jacobian lays them out (each problem's point, then its
        two steps)."""
        def f(X):
            r = np.stack([X[:, 0] - 0.3, 10 * (X[:, 1] - X[:, 0] ** 2)], axis=1)
            return np.where(np.repeat(flat, 3)[:, None], 1.0, r)
        return f
    lo, hi = np.array([0.0, 0.0]), np.array([1.0, 1.0])
    X0 = np.array([[0.5, 0.5], [0.9, 0.1]])
    for iterations in (1, 3, 30):
        X, sse, _ = lm_batch(rows(np.array([True, False])), X0, lo, hi, iterations, rows_apart=False)
        Xs, sses, _ = lm_batch(rows(np.array([False])), X0[1:], lo, hi, iterations, rows_apart=False)
        np.testing.assert_array_equal(X[1], Xs[0])
        assert sse[1] == sses[0]
    assert abs(X[1, 0] - 0.3) < 1e-6 and np.array_equal(X[0], X0[0])


def test_a_netcdf_stack_is_read_a_block_of_rows_at_a_time(tmp_path):
    """Issue #39, item 3: a .nc stack opened for a store's fit is read lazily by xarray's own
    indexing, a block of rows at a time, never made one dask chunk that every block reads whole
    (fit-image of a 240 MB stack at 128 MiB: peak RSS 533 MB that way, 377 MB now, as a 4 MB
    stack's), and nothing read is kept."""
    from pbrdf_cl.io.source import Source, open_stack_lazily
    dop = np.broadcast_to(pbrdf_cl.dop(TI, TR, **STEEL, backend="numpy"), (64, 32, 30))
    xr.Dataset({"dop": (("y", "x", "m"), dop), "theta_i": (("m",), TI), "theta_r": (("m",), TR)}).to_netcdf(
        tmp_path / "stack.nc")
    ds = open_stack_lazily(tmp_path / "stack.nc")
    assert ds.dop.chunks is None and not ds.dop.variable._in_memory
    rows = Source(ds).rows(10, 14)
    np.testing.assert_array_equal(rows["dop"], dop[10:14].reshape(-1, 30))
    assert not ds.dop.variable._in_memory  # the rows read are not cached


def _bad_files(tmp_path):
    """Files that are not what their suffix says, and stacks without pixels or measurements."""
    import xarray as xr
    (tmp_path / "empty.npz").write_bytes(b"")
    (tmp_path / "random.npz").write_bytes(np.random.default_rng(0).bytes(2000))
    (tmp_path / "zip.npz").write_bytes(b"PK\x03\x04 not a zip")
    np.save(tmp_path / "lone.npy", np.zeros(3))
    (tmp_path / "lone.npz").write_bytes((tmp_path / "lone.npy").read_bytes())
    (tmp_path / "garbage.nc").write_bytes(np.random.default_rng(1).bytes(2000))
    (tmp_path / "empty.nc").write_bytes(b"")
    (tmp_path / "hdf5.nc").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    xr.Dataset({"a": (("x",), [1.0, 2.0])}).to_netcdf(tmp_path / "whole.nc")
    (tmp_path / "truncated.nc").write_bytes((tmp_path / "whole.nc").read_bytes()[:40])
    for name, shape in (("zero_rows", (0, 4, 30)), ("zero_columns", (4, 0, 30))):
        np.savez(tmp_path / f"{name}.npz", dop=np.zeros(shape), theta_i=TI, theta_r=TR)
    np.savez(tmp_path / "zero_m.npz", dop=np.zeros((4, 4, 0)))


@pytest.mark.parametrize("name, message", [
    ("empty.npz", "empty.npz: the file is empty (0 bytes), not a .npz archive of arrays"),
    ("random.npz", "random.npz: not a .npz archive of arrays (a .npz is a zip file; this one starts with"),
    ("zip.npz", "zip.npz: not a readable .npz archive of arrays (BadZipFile: File is not a zip file)"),
    ("lone.npz", "lone.npz: not a .npz archive of arrays (a .npz is a zip file; this one starts with b'\\x93NUM')"),
    ("garbage.nc", "garbage.nc: not a netCDF file (it starts with"),
    ("empty.nc", "empty.nc: not a netCDF file (the file is empty (0 bytes))"),
    ("hdf5.nc", "hdf5.nc: a netCDF-4 (HDF5) file, which needs the netCDF4 or h5netcdf package to be read"),
    ("truncated.nc", "truncated.nc: a netCDF-3 file that cannot be read ("),
    ("zero_rows.npz", "data: dop has no pixels (shape (0, 4, 30): pixel dimensions (0, 4)); give a stack with at "
                      "least one pixel"),
    ("zero_columns.npz", "data: dop has no pixels (shape (4, 0, 30)"),
    ("zero_m.npz", "data: dop has 0 measurements per pixel; a fit needs several"),
])
def test_a_stack_that_is_no_stack_is_refused_in_one_line_of_ours(name, message, tmp_path, capsys):
    """Issue #39, item 6: a 0-byte or random .npz, a garbage .nc and a zero-pixel stack are refused by
    fit-image in one line naming the file, not a traceback or a library's message; no store is made."""
    from pbrdf_cl import cli
    if name == "hdf5.nc":
        import importlib.util
        if importlib.util.find_spec("h5netcdf") or importlib.util.find_spec("netCDF4"):
            pytest.skip("a netCDF-4 library is installed: the file is read by it")
    _bad_files(tmp_path)
    assert cli.main(["fit-image", str(tmp_path / name), "--out", str(tmp_path / "fit.zarr"), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("pbrdf-cl: error: ") and message in err, err
    assert not (tmp_path / "fit.zarr").exists()


def test_a_label_file_that_is_no_array_is_refused_in_one_line(tmp_path, capsys):
    from pbrdf_cl import cli
    np.savez(tmp_path / "stack.npz", dop=shared_stack(), theta_i=TI, theta_r=TR)
    (tmp_path / "random.npy").write_bytes(np.random.default_rng(0).bytes(300))
    (tmp_path / "empty.npy").write_bytes(b"")
    for name, why in (("random.npy", "it starts with"), ("empty.npy", "the file is empty (0 bytes)")):
        assert cli.main(["fit-image", str(tmp_path / "stack.npz"), "--out", str(tmp_path / "fit.zarr"), "--labels",
                         str(tmp_path / name)]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"--labels {tmp_path / name}: not a .npy file ({why}" in err, err


def test_repeated_measurements_of_a_stack_are_said(tmp_path, capsys):
    """Issue #39, item 6: measurements of a stack that repeat an earlier one exactly (a stack
    appended to itself) were counted as independent without a word; fit-image now says so (as fit
    and fit_joint say of a CSV's repeated rows) and that each pixel's chi2 counts them; a stack
    whose measurements differ in one pixel only is not noted."""
    from pbrdf_cl import cli
    from pbrdf_cl.fitting.images.job import BatchJob
    dop = shared_stack((1, 2))
    twice = dict(dop=np.concatenate([dop, dop], axis=-1), theta_i=np.r_[TI, TI], theta_r=np.r_[TR, TR], dop_std=0.003)
    np.savez(tmp_path / "twice.npz", **twice)
    assert cli.main(["fit-image", str(tmp_path / "twice.npz"), "--out", str(tmp_path / "fit.zarr"), "--no-progress",
                     "--backend", "numpy"]) == 0
    out = capsys.readouterr().out
    assert ("note: 30 of the 60 measurements repeat an earlier one exactly (geometry and the values of every pixel of "
            "the first row; e.g. measurement 30 repeats 0), up to 2 copies: each pixel's fit counts each as an "
            "independent measurement (in its chi2, p-value and intervals)") in out, out
    differ = dict(twice, dop=twice["dop"].copy())
    differ["dop"][0, 1, 30:] += 1e-3
    assert not any("repeat" in n for n in BatchJob(differ).notes)
    assert any("repeat" in n for n in BatchJob(twice).notes)
