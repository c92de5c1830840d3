"""The synthetic image stack (pbrdf_cl.io.imagestack, scripts/make_image_stack.py): shapes, the truth
maps, the noise, the geometry and its convention (SPEC.md: phi = 180 is the mirror plane), the seed."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.io import imagestack
from pbrdf_cl.model import reference

SIZE, M = 16, 8


@pytest.fixture(scope="module")
def stack():
    return imagestack.synthetic_stack(SIZE, n_lights=M, seed=3)


def test_shapes_and_dims(stack):
    assert stack.dop.dims == ("y", "x", "m") and stack.dop.shape == (SIZE, SIZE, M)
    for name in ("theta_i", "theta_r", "phi"):
        assert stack[name].dims == ("y", "x", "m") and stack[name].attrs["units"] == "degree"
    for name in ("true_n", "true_k", "true_sigma", "true_kd", "true_c", "material"):
        assert stack[name].dims == ("y", "x")
    assert stack.dop_std.dims == () and float(stack.dop_std) == 0.005 == stack.attrs["noise_std"]
    assert stack.x_mm.shape == stack.y_mm.shape == (SIZE,) and stack.light_x.shape == (M,)
    assert np.all(np.diff(stack.x_mm) > 0) and np.all(np.diff(stack.y_mm) < 0)   # row 0 at the top
    assert "degrees" in stack.attrs["angles"] and "z = 0" in stack.attrs["geometry"]


def test_truth_maps_two_materials_and_a_sigma_gradient(stack):
    params = np.stack([stack[f"true_{p}"].values for p in ("n", "k", "kd", "c")], axis=-1).reshape(-1, 4)
    found = {tuple(row) for row in params}
    expected = {tuple(imagestack.MATERIALS[m][p] for p in ("n", "k", "kd", "c")) for m in ("metal", "dielectric")}
    assert found == expected
    mat = stack.material.values
    assert mat[SIZE // 2, SIZE // 2] == 1 and mat[0, 0] == mat[-1, -1] == mat[0, -1] == 0
    assert 0.15 < mat.mean() < 0.4                                   # a disc of radius 0.3 of the side
    sig = stack.true_sigma.values
    assert np.all(sig == sig[:1]) and np.all(np.diff(sig[0]) > 0)    # constant in y, rising in x
    assert (sig[0, 0], sig[0, -1]) == pytest.approx(imagestack.SIGMA_RANGE)


def clean_dop(ds):
    """The noise-free DOP of a stack from its truth maps, by pbrdf_cl.dop (numpy reference)."""
    tm = {p: ds[f"true_{p}"].values[:, :, None] for p in ("n", "k", "sigma", "kd", "c")}
    return pbrdf_cl.dop(ds.theta_i.values, ds.theta_r.values, phi=ds.phi.values, backend="numpy", **tm)


def test_noise_is_gaussian_of_the_stated_std():
    ds = imagestack.synthetic_stack(SIZE, n_lights=M, noise=0.005, seed=11)
    clean = clean_dop(ds)
    resid = ds.dop.values - clean
    inside = (clean > 0.03) & (clean < 0.97)                         # 6 std from the clipping at 0 and 1
    assert inside.sum() > 500
    r = resid[inside]
    assert np.std(r) == pytest.approx(0.005, rel=0.1) and abs(np.mean(r)) < 0.0015
    assert np.all((ds.dop.values >= 0) & (ds.dop.values <= 1))
    assert ds.attrs["clipped"] == np.count_nonzero((ds.dop.values == 0) | (ds.dop.values == 1))
    exact = imagestack.synthetic_stack(SIZE, n_lights=M, noise=0.0)
    np.testing.assert_array_equal(exact.dop.values, np.clip(clean_dop(exact), 0, 1))


def test_angles_in_range(stack):
    for name in ("theta_i", "theta_r"):
        v = stack[name].values
        assert v.min() >= 0 and v.max() < imagestack.MAX_ZENITH
    assert stack.phi.min() >= 0 and stack.phi.max() < 360
    tr = stack.theta_r.values
    assert np.ptp(tr[:, :, 0]) > 5                                   # the camera is off-axis: theta_r varies
    np.testing.assert_array_equal(tr, tr[:, :, :1].repeat(M, axis=2))  # and is the same for every light


def test_mirror_configuration_is_phi_180():
    """A light at the mirror image of the camera through a surface point: theta_i = theta_r and
    phi = 180, where the model's facet tilt (reference.geometry) is 0, as SPEC.md defines it."""
    p = np.array([12.0, -7.0, 0.0])
    cam = np.array([40.0, 250.0, 300.0])
    light = p + 2.0 * np.array([-(cam - p)[0], -(cam - p)[1], (cam - p)[2]])
    ti, tr, phi = imagestack.angles_from_positions(p, light, cam)
    assert ti == pytest.approx(tr, abs=1e-12) and phi == pytest.approx(180.0, abs=1e-12)
    assert reference.geometry(ti, tr, phi).tan2a == pytest.approx(0.0, abs=1e-20)
    # the same in a stack: a light put at one pixel's mirror position
    cam = np.array(imagestack.synthetic_stack(4, n_lights=1).attrs["camera_mm"])
    ds0 = imagestack.synthetic_stack(4, n_lights=1)
    px = np.array([float(ds0.x_mm[1]), float(ds0.y_mm[2]), 0.0])
    mirror = px + 1.5 * (cam - px) * np.array([-1, -1, 1])
    ds = imagestack.synthetic_stack(4, lights=[mirror], noise=0.0)
    q = ds.isel(y=2, x=1, m=0)
    assert float(q.theta_i) == pytest.approx(float(q.theta_r), abs=1e-9)
    assert float(q.phi) == pytest.approx(180, abs=1e-9)


def test_phi_matches_the_models_geometry():
    """For random positions, the model's facet angles from (theta_i, theta_r, phi) equal those of
    the 3-D vectors: b = half the angle between light and view, a = angle of unit(w_i + w_r) to the
    normal.  This fixes the convention (phi = 0 would be back-scattering)."""
    rng = np.random.default_rng(5)
    surf = np.c_[rng.uniform(-50, 50, (200, 2)), np.zeros(200)]
    light = np.c_[rng.uniform(-300, 300, (200, 2)), rng.uniform(30, 300, 200)]
    cam = np.c_[rng.uniform(-300, 300, (200, 2)), rng.uniform(30, 300, 200)]
    ti, tr, phi = imagestack.angles_from_positions(surf, light, cam)
    unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)   # noqa: E731
    wi, wr = unit(light - surf), unit(cam - surf)
    h = unit(wi + wr)
    g = reference.geometry(ti, tr, phi)
    np.testing.assert_allclose(g.cb, np.sum(wi * h, axis=-1), atol=1e-12)
    np.testing.assert_allclose(np.arctan(np.sqrt(g.tan2a)), np.arccos(np.clip(h[:, 2], -1, 1)), atol=1e-7)
    # a light 90 degrees counter-clockwise of the view (about +z) has phi = 90
    _, _, p90 = imagestack.angles_from_positions([0, 0, 0], [0, 1, 1], [1, 0, 1])
    assert float(p90) == pytest.approx(90.0)


def test_every_pixel_has_near_specular_light():
    ds = imagestack.synthetic_stack(SIZE, noise=0.0)                  # the default 30 lights
    tilt = np.degrees(np.arctan(np.sqrt(reference.geometry(ds.theta_i, ds.theta_r, ds.phi).tan2a)))
    assert np.max(np.min(tilt, axis=-1)) < 9.0                        # facet tilt of the best light
    assert np.ptp(ds.theta_i.values, axis=-1).min() > 50              # and a spread of incidence angles


def test_the_seed_decides_the_noise(stack):
    again = imagestack.synthetic_stack(SIZE, n_lights=M, seed=3)
    np.testing.assert_array_equal(again.dop.values, stack.dop.values)
    other = imagestack.synthetic_stack(SIZE, n_lights=M, seed=4)
    assert not np.array_equal(other.dop.values, stack.dop.values)
    np.testing.assert_array_equal(other.phi.values, stack.phi.values)
    np.testing.assert_array_equal(other.true_sigma.values, stack.true_sigma.values)


def test_light_positions():
    for m in (1, 5, 8, 30, 31):
        lights = imagestack.light_positions(m)
        assert lights.shape == (m, 3)
        assert np.allclose(np.linalg.norm(lights, axis=1), 400.0) and np.all(lights[:, 2] > 0)
    with pytest.raises(ValueError, match="n_lights must be an integer of at least 1, got 0"):
        imagestack.light_positions(0)


def test_refusals():
    with pytest.raises(ValueError, match="size must be an integer of at least 2 pixels, got 1"):
        imagestack.synthetic_stack(1)
    with pytest.raises(ValueError, match="noise must be a finite number >= 0, got -0.1"):
        imagestack.synthetic_stack(4, noise=-0.1)
    with pytest.raises(ValueError, match="zenith angle of 89[0-9.]* degrees"):
        imagestack.synthetic_stack(4, n_lights=4, camera_theta=89.5)
    with pytest.raises(ValueError, match=r"lights must be finite positions of shape \(M, 3\)"):
        imagestack.synthetic_stack(4, lights=[[0.0, 1.0]])


def test_a_stack_too_large_for_memory_is_refused_before_any_work(monkeypatch):
    """The estimate (stack_bytes) lies above the measured peak; a stack above the available memory
    is one line naming its size, before any geometry is computed."""
    import tracemalloc
    tracemalloc.start()
    try:
        imagestack.synthetic_stack(96, n_lights=12)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= imagestack.stack_bytes(96, 12)
    monkeypatch.setattr(pbrdf_cl.sizes, "available_memory", lambda: 8 << 30)

    def no_work(*a, **k):
        raise AssertionError("the geometry was computed before the size check")
    monkeypatch.setattr(imagestack, "angles_from_positions", no_work)
    with pytest.raises(pbrdf_cl.sizes.TooLargeError) as err:
        imagestack.synthetic_stack(20000)
    text = str(err.value)
    assert "20000 x 20000 pixels x 30 lights" in text and "8 GiB" in text and "\n" not in text
    assert isinstance(err.value, ValueError) and isinstance(err.value, MemoryError)
    monkeypatch.setattr(imagestack, "light_positions", no_work)  # many lights: refused before they are placed
    with pytest.raises(pbrdf_cl.sizes.TooLargeError, match="64 x 64 pixels x 1000000000 lights"):
        imagestack.synthetic_stack(64, n_lights=10 ** 9)
    with pytest.raises(pbrdf_cl.sizes.TooLargeError, match="^truth maps of 200000 x 200000 pixels needs"):
        imagestack.truth_maps(200000)


@pytest.mark.parametrize("suffix", [".npz", ".nc"])
def test_save_and_load(tmp_path, suffix):
    ds = imagestack.synthetic_stack(4, n_lights=3)
    path = imagestack.save_stack(ds, tmp_path / f"s{suffix}")
    back = imagestack.load_stack(path)
    for name in ds.variables:
        np.testing.assert_array_equal(back[name].values, ds[name].values)
        assert back[name].dims == ds[name].dims
    assert back.attrs["seed"] == 0 and back.attrs["geometry"] == ds.attrs["geometry"]
    with pytest.raises(ValueError, match="path must end in .nc or .npz"):
        imagestack.save_stack(ds, tmp_path / "s.h5")


def test_script(tmp_path, capsys, monkeypatch):
    spec = importlib.util.spec_from_file_location(
        "make_image_stack", Path(__file__).resolve().parent.parent / "scripts" / "make_image_stack.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = tmp_path / "stack.npz"
    assert script.main(["--size", "6", "--lights", "5", "--noise", "0.01", "--seed", "2", "--out", str(out)]) == 0
    ds = imagestack.load_stack(out)
    assert ds.dop.shape == (6, 6, 5) and ds.attrs["noise_std"] == 0.01 and ds.attrs["seed"] == 2
    assert "stack.npz" in capsys.readouterr().out
    assert script.main(["--size", "1", "--out", str(out)]) == 2
    assert "size must be" in capsys.readouterr().err
    monkeypatch.setattr(pbrdf_cl.sizes, "available_memory", lambda: 8 << 30)
    assert script.main(["--size", "20000", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("make_image_stack: a synthetic stack of 20000 x 20000") and err.count("\n") == 1

    def no_work(*a, **k):
        raise AssertionError("rendered before the output was checked")
    monkeypatch.setattr(imagestack, "synthetic_stack", no_work)
    assert script.main(["--size", "6", "--out", str(tmp_path / "stack.txt")]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "stack.txt" in err and ".npz" in err and err.count("\n") == 1


def test_check_pixels_fits_one_pixel():
    """The script's check (``make_image_stack.py --check``): the stack's columns feed pbrdf_cl.fit as
    they are (one metal pixel, the numpy backend)."""
    spec = importlib.util.spec_from_file_location(
        "make_image_stack", Path(__file__).resolve().parent.parent / "scripts" / "make_image_stack.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    ds = imagestack.synthetic_stack(SIZE, seed=1)
    (row,) = script.check_pixels(ds, [(SIZE // 2, 0)], backend="numpy")
    assert row["material"] == 0 and 0.3 < row["reduced_chi2"] < 3
    for name in imagestack.FIT_PARAMETERS:
        r = row[name]
        assert r["true"] == float(ds[f"true_{name}"][SIZE // 2, 0]) and r["ci95"][0] <= r["ci95"][1]
    assert abs(row["sigma"]["fit"] - row["sigma"]["true"]) < 5 * row["sigma"]["stderr"] < 0.05
    for y, x in script.default_check_pixels(64):
        assert 0 <= y < 64 and 0 <= x < 64
    mats = [int(imagestack.truth_maps(64)["material"][y, x]) for y, x in script.default_check_pixels(64)]
    assert mats == [0, 0, 0, 0, 1, 1, 1]
