"""Image fits of polarimetric stacks (issue #36, part 3): fit_batch and fit-image on a linear
polarization camera's s1, s2 under a polarized source (and any mix of s1..s3, AoP, Mueller elements,
DOP), the device's batch stages of channels against their numpy twins in float64, the truth from
noise-free stacks with shared and per-pixel geometry, the shipped example stacks against the truth
and a DOP-only fit of the same pixels, camera_dataset's S1, S2 and the source's state, and the
one-line refusals."""
import numpy as np
import pytest
import xarray as xr

import pbrdf_cl
from pbrdf_cl.cli import main
from pbrdf_cl.device.engine import NumpyEngine
from pbrdf_cl.fitting.images import pixel_stages
from pbrdf_cl.fitting.images.job import BatchJob
from pbrdf_cl.fitting.images.pixels import Block
from pbrdf_cl.io import camera, imagestack

from conftest import requires_opencl

TI, TR = imagestack.PAPER_THETA_I, imagestack.PAPER_THETA_R
TRUTH = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3)
PARAMS = ("n", "k", "sigma", "kd", "c")
SMALL_GRID = dict(n=4, k=4, sigma=3, kd=3, c=2)


def cam(par, ti=TI, tr=TR, phi=180.0, incident=(0.0, 1.0, 0.0), noise=0.0, seed=0, aop=False):
    """s1, s2 (and the AoP) of the model under ``incident`` (shared (3,), per measurement or per pixel)
    for parameters ``par`` (scalars or (p, 1) arrays), with Gaussian noise of std ``noise``."""
    inc = np.broadcast_to(np.asarray(incident, float), np.broadcast_shapes(np.shape(incident), (np.size(ti), 3)))
    S = pbrdf_cl.stokes(ti, tr, phi, **par, incident=inc, backend="numpy")
    rng = np.random.default_rng(seed)
    out = {f"s{j}": S[..., j] / S[..., 0] + rng.normal(0, noise, S.shape[:-1]) for j in (1, 2)}
    if aop:
        out["aop"] = 0.5 * np.degrees(np.arctan2(S[..., 2], S[..., 1])) + rng.normal(0, 50 * noise, S.shape[:-1])
    shape = S.shape[:-1]
    out.update({f"in_s{j + 1}": inc[..., j] for j in range(3)})
    out.update(theta_i=ti if np.ndim(phi) < 2 else np.broadcast_to(ti, shape),
               theta_r=tr if np.ndim(phi) < 2 else np.broadcast_to(tr, shape), phi=phi)
    return out


def random_params(rng, p):
    return dict(n=rng.uniform(1.2, 3, (p, 1)), k=rng.uniform(0.2, 4, (p, 1)), sigma=rng.uniform(0.2, 0.7, (p, 1)),
                kd=rng.uniform(0.02, 0.4, (p, 1)), c=rng.uniform(-0.8, -0.1, (p, 1)))


def shared_stack(noise=0.01):
    """6 pixels at 20 out-of-plane geometries under two source states: s1, s2 and an AoP (stds given)."""
    rng = np.random.default_rng(5)
    ti, tr = np.repeat(TI[::3], 2), np.repeat(TR[::3], 2)
    inc = np.tile([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], (10, 1))
    d = cam(random_params(rng, 6), ti, tr, 150.0, inc, noise, aop=True)
    return dict(d, s1_std=noise, s2_std=noise, aop_std=50 * noise)


def per_pixel_stack(noise=0.01):
    """4 pixels, each its own azimuth and source state (per-pixel geometry and incident states)."""
    rng = np.random.default_rng(6)
    phi = np.array([180.0, 150.0, 120.0, 170.0])[:, None] * np.ones(TI.size)
    inc = np.zeros((4, TI.size, 3))
    inc[:2, :, 1] = 1.0
    inc[2:, :, 0], inc[2:, :, 2] = 0.5, np.sqrt(0.75)
    d = cam(random_params(rng, 4), TI, TR, phi, inc, noise, aop=True)
    return dict(d, s1_std=noise, s2_std=noise, aop_std=50 * noise)


def blocks(data, lanes):
    job = BatchJob(data, grid_shape=SMALL_GRID)
    raw = job.read_rows(0, job.source.shape[0])
    return job, Block(raw, job.setup, lanes), Block(raw, job.setup, 1)


@pytest.mark.parametrize("make", [shared_stack, per_pixel_stack])
def test_channel_grid_stages_on_the_device_equal_the_numpy_twins_in_float64(engine, monkeypatch, make):
    """batch_grid of channels (the value table and each pixel's weighted residuals, an AoP's wrapped;
    per-pixel tables) and, shared, the corner stage's ranking table and its minima: the device's
    float64 builds give the numpy backend's values and the same region minima."""
    if not engine.fp64:
        pytest.skip("no float64 on this device")
    monkeypatch.setattr(pixel_stages, "GRID_DTYPE", "float64")
    job, dev, ref = blocks(make(), engine.call("batch_lanes"))
    assert job.setup.channels and dev.spec is not None and dev.shared == (make is shared_stack)
    numpy = NumpyEngine()
    best, arg = engine.call("batch_grid", job.setup, dev, job.order, job.rstart)
    best_np, arg_np = numpy.call("batch_grid", job.setup, ref, job.order, job.rstart)
    np.testing.assert_allclose(best, best_np, rtol=1e-10)
    np.testing.assert_array_equal(arg, arg_np)
    if dev.shared:
        rng = np.random.default_rng(1)
        sets = dict(n=rng.choice([1.2, 2.0], 40), k=rng.choice([0.0, 1.0, 3.0], 40), sigma=np.full(40, 0.3),
                    ks=np.ones(40), kd=rng.choice([0.0, 0.1, 0.3], 40), c=np.full(40, -0.5))
        T = engine.call("batch_ranking_table", dev, sets, "paper")
        T_np = numpy.call("batch_ranking_table", ref, sets, "paper")
        np.testing.assert_allclose(T, T_np, rtol=1e-11, atol=1e-12)
        rstart = np.array([0, 13, 40], np.int32)
        b, a = engine.call("batch_table_minima", dev, T_np, rstart)
        b_np, a_np = numpy.call("batch_table_minima", ref, T_np, rstart)
        np.testing.assert_allclose(b, b_np, rtol=1e-10)
        np.testing.assert_array_equal(a, a_np)


@pytest.mark.parametrize("make", [shared_stack, per_pixel_stack])
def test_channel_descents_on_the_device_equal_the_numpy_twins_in_float64(engine, make):
    """batch_lm of channels (the PB_CHANNELS build) at given points: the objective and J^T J of the
    device's float64 build are the numpy twin's (reference.py through ChannelModel); and the
    descents of both from the same starts reach the same minimum."""
    if not engine.fp64:
        pytest.skip("no float64 on this device")
    job, dev, ref = blocks(make(), engine.call("batch_lanes"))
    setup, numpy = job.setup, NumpyEngine()
    rng = np.random.default_rng(2)
    X = np.clip(np.array([[TRUTH[n] for n in setup.free]]) * rng.uniform(0.8, 1.2, (2, dev.p, 5)),
                setup.lo, setup.hi)
    d = engine.call("batch_lm", setup, dev, X, setup.free, "float64", 0, False)
    r = numpy.call("batch_lm", setup, ref, X, setup.free, "float64", 0, False)
    np.testing.assert_allclose(d.sse, r.sse, rtol=1e-11)
    scale = np.abs(r.jtj).max(axis=(-2, -1), keepdims=True)
    assert np.all(np.abs(d.jtj - r.jtj) <= 1e-5 * np.abs(r.jtj) + 1e-6 * scale)
    d = engine.call("batch_lm", setup, dev, X[:1], setup.free, "float64", 60, False)
    r = numpy.call("batch_lm", setup, ref, X[:1], setup.free, "float64", 60, False)
    done = d.settled[0] & (np.abs(d.sse[0] - r.sse[0]) < 1e-6 * r.sse[0])
    assert done.sum() >= dev.p - 1  # a descent may end in another basin, not most
    np.testing.assert_allclose(d.x[0][done], r.x[0][done], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("backend", [pytest.param("opencl", marks=requires_opencl), "numpy"])
@pytest.mark.parametrize("which", ["shared", "per pixel"])
def test_noise_free_stacks_give_the_truth(backend, which):
    """Noise-free s1, s2 under a 45-degree source at the paper's geometry (shared), and s1, s2 and the
    AoP with per-pixel azimuths and source states: every pixel's fit is the truth (kd as kd/ks)."""
    if which == "shared":
        data = cam(TRUTH)
        data = {k: (np.broadcast_to(v, (2, 3) + np.shape(v)) if k in ("s1", "s2") else v) for k, v in data.items()}
    else:
        data = per_pixel_stack(noise=0.0)
        data.update(s1_std=0.01, s2_std=0.01, aop_std=0.5)
        data = {k: (v[:2] if np.ndim(v) >= 2 else v) for k, v in data.items()}
        truth = random_params(np.random.default_rng(6), 4)
    r = pbrdf_cl.fit_batch(data, backend=backend)
    assert r.attrs["quantities"] == ("s1 s2" if which == "shared" else "aop s1 s2")
    assert r.attrs["geometry"] == which
    for n in PARAMS:
        want = TRUTH[n] if which == "shared" else truth[n][:2, 0]
        np.testing.assert_allclose(r[n].values, np.broadcast_to(want, r[n].shape), rtol=2e-5, atol=1e-6, err_msg=n)
    assert (r.status.values > 0).all()


def _widths(ds):
    return {n: float(np.median(ds[f"{n}_ci95"].values[..., 1] - ds[f"{n}_ci95"].values[..., 0])) for n in PARAMS}


def _coverage(ds, truth):
    ci = {n: ds[f"{n}_ci95"].values for n in PARAMS}
    true = {n: truth[f"true_{n}"].values for n in PARAMS}
    return {n: float(np.mean((ci[n][..., 0] <= true[n]) & (true[n] <= ci[n][..., 1]))) for n in PARAMS}


@pytest.mark.parametrize("name, n_ratio", [("camera_45deg_16", 5), ("camera_four_states_16", 10)])
def test_fit_image_on_the_example_stacks(tmp_path, capsys, name, n_ratio):
    """fit-image on each shipped camera stack (s1, s2, noise 0.005, the source at 45 degrees or in
    four states): the 95% intervals cover the truth maps on most pixels, and the n and k intervals
    are much narrower than those of a DOP-only fit of the same pixels at the same frames and noise
    (a single 45-degree state leaves n's only ~7 times narrower, SPEC's Fisher information says)."""
    path = f"examples/{name}.npz"
    assert main(["fit-image", path, "--out", str(tmp_path / "fit.zarr"), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "fitted: s1, s2 (source: the incident states in_s1, in_s2, in_s3 of the stack)" in out, out
    ds, truth = xr.open_zarr(tmp_path / "fit.zarr"), imagestack.load_stack(path)
    assert ds.attrs["quantities"] == "s1 s2"
    covered = _coverage(ds, truth)
    assert min(covered.values()) >= 0.8, covered
    par = {n: truth[f"true_{n}"].values[:, :, None] for n in PARAMS}
    dop = pbrdf_cl.dop(truth.theta_i.values, truth.theta_r.values, truth.phi.values, backend="numpy", **par)
    dop = np.clip(dop + np.random.default_rng(0).normal(0, 0.005, dop.shape), 0, 1)
    only = pbrdf_cl.fit_batch(dict(dop=dop, dop_std=0.005, theta_i=truth.theta_i.values,
                                   theta_r=truth.theta_r.values, phi=truth.phi.values))
    cam_w, dop_w = _widths(ds), _widths(only)
    assert cam_w["n"] * n_ratio < dop_w["n"] and cam_w["k"] * 10 < dop_w["k"], (cam_w, dop_w)


def test_fitted_quantities_and_notes():
    """By default the polarimetric quantities where the source's state is given (dop, a camera's
    DoLP of the same frames, left out with a note), the DOP as before where it is not (s1, s2 left
    out with a note); quantities= chooses; intensities are not fitted with channels (a note)."""
    d = cam(TRUTH)
    d = {k: (np.broadcast_to(v, (1, 2, 30)) if k in ("s1", "s2") else v) for k, v in d.items()}
    dop = np.broadcast_to(pbrdf_cl.dop(TI, TR, **TRUTH, backend="numpy"), (1, 2, 30))
    kw = dict(grid_shape=SMALL_GRID, n_starts=4)
    with_state = BatchJob(dict(d, dop=dop), **kw)
    assert with_state.setup.quantities == ("s1", "s2") and with_state.setup.channels
    assert any(n.startswith("dop not fitted: s1, s2 are fitted") for n in with_state.notes)
    plain = {k: v for k, v in d.items() if not k.startswith("in_")}
    unpolarised = BatchJob(dict(plain, dop=dop), **kw)
    assert unpolarised.setup.quantities == ("dop",) and not unpolarised.setup.channels
    assert any(n.startswith("s1, s2 not fitted: the source's state is not given") for n in unpolarised.notes)
    assert BatchJob(dict(plain, dop=dop), quantities="s1, s2", **kw).setup.quantities == ("s1", "s2")
    f00 = np.broadcast_to(pbrdf_cl.brdf(TI, TR, **TRUTH, backend="numpy"), (1, 2, 30))
    job = BatchJob(dict(d, f00=f00), **kw)
    assert not job.setup.use_f00 and any("intensities (f00 or s0) are not fitted" in n for n in job.notes)
    r = pbrdf_cl.fit_batch(dict(plain, dop=dop), quantities=("dop", "s2"), **kw)
    assert r.attrs["quantities"] == "dop s2" and "sum of squared residuals of dop, s2" in r.sse.attrs["long_name"]


def _bad(**change):
    d = cam(TRUTH)
    d = {k: (np.broadcast_to(v, (2, 3, 30)).copy() if k in ("s1", "s2") else np.array(v, float)) for k, v in d.items()}
    d.update(change)
    return {k: v for k, v in d.items() if v is not None}


BAD = np.zeros((2, 3, 30))


@pytest.mark.parametrize("data, kw, words", [
    (_bad(s1_std=0.01), {}, "data: standard deviations are given for s1 but not for s2; give <name>_std for every "
                            "fitted quantity or for none"),
    (_bad(aop=np.zeros((2, 3, 30))), {}, "data: aop_std is needed where the AoP is fitted with other quantities "
                                         "(s1, s2)"),
    (_bad(in_s1=np.full(30, 0.8), in_s2=np.full(30, 0.8)), {},
     "the incident state at index [0] (in_s1 = 0.8, in_s2 = 0.8, in_s3 = 0) is not a Stokes vector: "
     "in_s1^2 + in_s2^2 + in_s3^2 = 1.28 > 1"),
    (_bad(in_s2=np.where(np.arange(30) == 4, np.nan, 1.0)), {}, "in_s2 must be finite (the incident state of every "
                                                                "measurement; 0, 0, 0 for unpolarised light), got nan "
                                                                "at index [4]"),
    (_bad(s1=BAD + 0.9, s2=BAD + 0.9), {}, "data at index [0, 0, 0]: the Stokes vector is longer than 1 (normalised) "
                                           "beyond its noise: sqrt(s1^2 + s2^2) = 1.273 > 1"),
    (_bad(m01=BAD + 1.5), {"quantities": "m01"}, "data at index [0, 0, 0]: m01 = 1.5 is outside [-1, 1] beyond its "
                                                 "noise"),
    (_bad(s1_std=np.where(np.arange(30) == 7, np.nan, 0.01) + BAD, s2_std=0.01), {},
     "s1_std is NaN at index [0, 0, 7] where s1 is"),
    (_bad(s1=None, s1_std=0.01), {}, "data: s1_std is given without s1"),
    (_bad(aop=np.where(np.arange(30) == 2, np.inf, 0.0) + BAD, aop_std=1.0, s1_std=0.01, s2_std=0.01), {},
     "aop must be finite (degrees; NaN for a missing measurement), got inf at index [0, 0, 2]"),
    (_bad(), {"quantities": "s_1"}, "quantities: 's_1' is not a measured quantity; did you mean 's1'?"),
    (_bad(), {"quantities": "dop"}, "quantities: 'dop' is not in the stack, which has s1, s2"),
    (_bad(), {"labels": np.ones((2, 3), int)}, "labels=: image fits with labels fit the DOP under unpolarised light "
                                               "only"),
])
def test_bad_polarimetric_stacks_are_refused_in_one_line(data, kw, words):
    with pytest.raises(ValueError) as err:
        pbrdf_cl.fit_batch(data, backend="numpy", **kw)
    text = str(err.value)
    assert words in text and "\n" not in text, text


# ---------------------------------------------------------------------------------------------
# the camera: raw mosaics of the model's light under a polarized source

@pytest.fixture(scope="module")
def pa():
    pytest.importorskip("cv2", reason="polanalyser needs OpenCV (pip install 'pbrdf-cl[camera]')")
    return pytest.importorskip("polanalyser", reason="pip install 'pbrdf-cl[camera]'")


def mosaics(S, side=8, counts=60000.0, roll=0.0):
    """Raw IMX250MZR frames (uint16) of uniform Stokes vectors S (M, 3: S0, S1, S2 in the beam's
    frame) seen by a sensor whose x axis is ``roll`` degrees from the beam's s axis."""
    a = np.radians(np.tile(np.array(camera.SUPERPIXEL), (side // 2, side // 2)) + roll)
    scale = counts / S[:, 0].max()
    return [np.round(0.5 * (s0 + s1 * np.cos(2 * a) + s2 * np.sin(2 * a)) * scale).astype(np.uint16)
            for s0, s1, s2 in S]


def test_camera_dataset_keeps_s1_s2_and_the_sources_state(pa):
    """Frames of the model's light under a 45-degree source: camera_dataset's s1, s2 are the model's
    S1/S0, S2/S0 (to the counts' quantisation), in the beam's frame where the sensor is rolled and
    roll= says by how much; the source's state is kept per frame, and fit_batch takes s1, s2 to the
    truth."""
    ti, tr = TI[::3], TR[::3]
    S = pbrdf_cl.stokes(ti, tr, 180.0, **TRUTH, incident=(0, 1, 0), backend="numpy")
    want1, want2 = S[:, 1] / S[:, 0], S[:, 2] / S[:, 0]
    mask = np.zeros((8, 8), bool)
    mask[3:5, 3:5] = True
    ds = camera.camera_dataset(mosaics(S[:, :3]), ti, tr, incident=(0, 1, 0), s_std=1e-3, mask=mask)
    assert ds.s1.dims == ("y", "x", "m") and ds.in_s2.values.tolist() == [1.0] * 10 and ds.in_s1.dims == ("m",)
    np.testing.assert_allclose(ds.s1.values[3, 3], want1, atol=1e-4)
    np.testing.assert_allclose(ds.s2.values[3, 3], want2, atol=1e-4)
    np.testing.assert_allclose(np.hypot(ds.s1, ds.s2).values[3, 3], ds.dop.values[3, 3], atol=1e-12)
    assert "taken as the outgoing beam's" in ds.attrs["stokes_frame"]
    rolled = camera.camera_dataset(mosaics(S[:, :3], roll=25.0), ti, tr, incident=(0, 1, 0), roll=25.0)
    np.testing.assert_allclose(rolled.s1.values[3, 3], want1, atol=2e-4)
    np.testing.assert_allclose(rolled.s2.values[3, 3], want2, atol=2e-4)
    assert "rotated by roll" in rolled.attrs["stokes_frame"]
    unrolled = camera.camera_dataset(mosaics(S[:, :3], roll=25.0), ti, tr, incident=(0, 1, 0))
    assert np.abs(unrolled.s2.values[3, 3] - want2).max() > 0.1   # the sensor's frame is not the beam's
    r = pbrdf_cl.fit_batch(ds)
    assert r.attrs["quantities"] == "s1 s2" and (r.status.values[mask] > 0).all()
    for n in ("n", "k"):
        np.testing.assert_allclose(r[n].values[mask], TRUTH[n], rtol=2e-3)
        assert ((r[f"{n}_ci95"].values[mask][:, 0] <= TRUTH[n]) & (TRUTH[n] <= r[f"{n}_ci95"].values[mask][:, 1])).all()
    assert "in_s1" not in camera.camera_dataset(mosaics(S[:, :3]), ti, tr)   # unpolarised: no state, dop fitted


@pytest.mark.parametrize("kw, words", [
    (dict(incident=(0.8, 0.8, 0.0)),
     "incident[0] = (0.8, 0.8, 0) is not a Stokes vector: s1^2 + s2^2 + s3^2 = 1.28 > 1"),
    (dict(incident=np.zeros((2, 3))), "incident must be the source's normalised Stokes vector (s1, s2, s3), shape "
                                      "(3,), or one per frame, shape (3, 3), got shape (2, 3)"),
    (dict(roll=[0.0, np.nan, 0.0]), "roll must be finite (degrees), got nan"),
    (dict(s_std=-1.0), "s_std must be finite and > 0, got -1.0"),
])
def test_bad_camera_states_are_refused_in_one_line(kw, words):
    with pytest.raises(ValueError) as err:
        camera.camera_dataset([np.zeros((4, 4), np.uint16)] * 3, [30, 40, 50], 45, **kw)
    assert words in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_a_state_given_partly_shared_partly_per_pixel():
    """in_s1 shared (M,) beside in_s2 per pixel: every pixel's channels take their own state (the
    block is per pixel), checked and fitted as if both were per pixel."""
    d = cam(TRUTH, incident=(0.0, 1.0, 0.0))
    d = {k: (np.broadcast_to(v, (2, 30)) if k in ("s1", "s2") else v) for k, v in d.items()}
    mixed = dict(d, in_s2=np.broadcast_to(d["in_s2"], (2, 30)))
    job = BatchJob(mixed, grid_shape=SMALL_GRID, n_starts=4)
    blk = Block(job.read_rows(0, 2), job.setup, 1)
    assert not blk.shared and blk.spec.u.shape == (2, 60, 4)
    np.testing.assert_array_equal(blk.spec.u[:, :, 2], 1.0)
    r = pbrdf_cl.fit_batch(mixed, backend="numpy")
    np.testing.assert_allclose(r.n.values, TRUTH["n"], rtol=1e-5)


def test_narrow_vectors_change_no_channel_value(engine):
    """The channel kernels at 256-bit vectors (PB_VW, PB_VECTOR_REAL 8 / 4) give every value of the
    512-bit builds, bit for bit: each lane computes alone (shared and per-pixel stacks)."""
    from pbrdf_cl.device import engine as E
    from pbrdf_cl.device import sources
    if E.narrow_reason(engine.device):
        pytest.skip(f"this device builds 256-bit vectors only: {E.narrow_reason(engine.device)}")
    narrow = E.Engine(engine.device)
    narrow.vector_width, narrow.lm_lanes = dict(sources.NARROW_VECTOR_WIDTH), dict(sources.NARROW_LM_LANES)
    for data in (shared_stack(), per_pixel_stack()):
        a, b = (pbrdf_cl.fit_batch(data, engine=eng, grid_shape=SMALL_GRID, n_starts=8) for eng in (engine, narrow))
        for v in ("n", "k", "sigma", "kd", "c", "chi2", "status"):
            np.testing.assert_array_equal(a[v].values, b[v].values, err_msg=v)
