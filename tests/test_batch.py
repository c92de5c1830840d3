"""Per-pixel inversion of image stacks (pbrdf_cl.fit_batch): agreement with pbrdf_cl.fitting, both
geometry paths and both backends, missing data and masks, intensities, fixed parameters, the
result's layout, honest intervals, and one-line errors naming the variable and index."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.fitting.images import batch as B
from pbrdf_cl.fitting.images import corners
from pbrdf_cl.fitting.images.dataset import PIXEL_STATUS
from pbrdf_cl.fitting.images.job import BLOCK_BUDGET
from pbrdf_cl.fitting.setup import DEFAULT_BOUNDS

TI = np.repeat([30.0, 40.0, 50.0], 10)            # the paper's geometry
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
TI1, TR1 = np.full(30, 45.0), np.linspace(5, 80, 30)  # one incidence


@pytest.fixture
def dev(engine):
    if engine is None:
        pytest.skip("no OpenCL device")
    return engine


def random_pixels(n, seed, ti=TI, tr=TR, noise=0.01):
    rng = np.random.default_rng(seed)
    truth = dict(n=rng.uniform(1.2, 4, n)[:, None], k=rng.uniform(0.0, 6, n)[:, None],
                 sigma=rng.uniform(0.1, 0.9, n)[:, None], kd=rng.uniform(0.0, 1, n)[:, None],
                 c=rng.uniform(-1, 0, n)[:, None])
    dop = pbrdf_cl.dop(ti, tr, **truth, backend="numpy")
    return np.clip(dop + rng.normal(0, noise, dop.shape), 0, 1), truth


@pytest.mark.parametrize("geometry, share", [("paper", 7 / 8), ("one-incidence", 1.0)])
def test_batched_sse_reaches_the_single_fit(dev, geometry, share):
    """The batched fit's SSE reaches pbrdf_cl.fit's (1e-6 relative, or lower) on 8 random noisy
    pixels: every one with one incidence; in the paper's three-incidence geometry, whose flat
    multi-basin landscape (n = 1, k = 0 corners) defeats the batched starts more often, at least
    7 and the others within 1% (scripts/bench_batch.py measures both shares on 500 pixels; the
    issue's target is 99%)."""
    ti, tr = (TI, TR) if geometry == "paper" else (TI1, TR1)
    dop, _ = random_pixels(8, seed=11, ti=ti, tr=tr)
    res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=ti, theta_r=tr), engine=dev)
    single = np.array([pbrdf_cl.fit(dict(theta_i=ti, theta_r=tr, dop=d), engine=dev).sse for d in dop])
    rel = (res.sse.values - single) / single
    assert np.mean(rel <= 1e-6) >= share and np.all(rel <= 1e-2), rel
    assert res.sse.dims == ("pixel",) and res.sse.shape == (8,)


def test_noise_free_pixels_recover_their_truth(dev):
    truth = dict(n=np.array([1.6, 2.5, 1.3])[:, None], k=np.array([2.139, 0.8, 3.0])[:, None],
                 sigma=np.array([0.5, 0.3, 0.7])[:, None], kd=np.array([0.17, 0.4, 0.05])[:, None],
                 c=np.array([-0.3, -0.6, -0.2])[:, None])
    ti, tr = np.concatenate([TI, TI1]), np.concatenate([TR, TR1])
    dop = pbrdf_cl.dop(ti, tr, **truth, backend="numpy")
    res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=ti, theta_r=tr), engine=dev)
    for name, v in truth.items():
        np.testing.assert_allclose(res[name].values, v[:, 0], rtol=2e-4, atol=2e-4, err_msg=name)
    assert np.all(res.sse.values < 1e-12)


def test_shared_and_per_pixel_geometry_agree(dev):
    dop, _ = random_pixels(6, seed=3)
    dop = dop.reshape(2, 3, 30)
    shared = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI, theta_r=TR), engine=dev)
    full = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=np.broadcast_to(TI, dop.shape),
                                   theta_r=np.broadcast_to(TR, dop.shape), phi=np.full(dop.shape, 180.0)),
                              engine=dev)
    assert shared.attrs["geometry"] == "shared" and full.attrs["geometry"] == "per pixel"
    np.testing.assert_allclose(full.sse.values, shared.sse.values, rtol=1e-6)
    np.testing.assert_array_equal(full.status.values, shared.status.values)


def test_numpy_backend_runs_the_same_stages(dev):
    dop, _ = random_pixels(3, seed=5, ti=TI1, tr=TR1)
    a = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI1, theta_r=TR1), engine=dev)
    b = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI1, theta_r=TR1), backend="numpy")
    np.testing.assert_allclose(b.sse.values, a.sse.values, rtol=1e-6)


def test_missing_measurements_and_masked_pixels(dev):
    dop, _ = random_pixels(4, seed=7, ti=TI1, tr=TR1)
    dop[1, ::3] = np.nan             # a third of pixel 1's measurements are missing
    dop[2, 4:] = np.nan              # pixel 2 keeps 4: too few for 5 free parameters
    mask = np.array([True, True, True, False])
    res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI1, theta_r=TR1, mask=mask), engine=dev)
    assert res.n_valid.values.tolist() == [30, 20, 4, 0]
    status = res.status.values
    assert status[2] == -2 and status[3] == -1 and status[0] >= 0 and status[1] >= 0
    assert np.isnan(res.n.values[2:]).all() and np.isfinite(res.n.values[:2]).all()
    assert "-2: too_few" in res.status.attrs["status_codes"]
    # the pixel with gaps is the fit of its valid measurements alone
    keep = np.isfinite(dop[1])
    alone = pbrdf_cl.fit_batch(dict(dop=dop[1:2, keep], theta_i=TI1[keep], theta_r=TR1[keep]), engine=dev)
    np.testing.assert_allclose(res.sse.values[1], alone.sse.values[0], rtol=1e-9)


def test_intensities_separate_ks_and_kd_like_fit(dev):
    truth = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
    rng = np.random.default_rng(2)
    dop = pbrdf_cl.dop(TI, TR, **truth) + rng.normal(0, 0.003, (2, 30))
    f00 = pbrdf_cl.brdf(TI, TR, **truth) * (1 + rng.normal(0, 0.01, (2, 30)))
    f00_std = 0.01 * pbrdf_cl.brdf(TI, TR, **truth)
    res = pbrdf_cl.fit_batch(dict(dop=dop, f00=f00, theta_i=TI, theta_r=TR, dop_std=0.003, f00_std=f00_std),
                             engine=dev)
    assert "ks" in res and res.attrs["free"].split() == ["n", "k", "sigma", "kd", "c", "ks"]
    single = pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=dop[0], f00=f00[0], dop_std=np.full(30, 0.003),
                               f00_std=f00_std), engine=dev)
    assert res.chi2.values[0] <= single.chi2 * (1 + 1e-6)
    # the reported DOP SSE is that of the reported parameters (kd absolute)
    x = {n: res[n].values[0] for n in ("n", "k", "sigma", "ks", "kd", "c")}
    np.testing.assert_allclose(res.sse.values[0], ((pbrdf_cl.dop(TI, TR, **x) - dop[0]) ** 2).sum(), rtol=1e-9)
    for name in ("n", "k", "sigma", "ks", "kd", "c"):
        np.testing.assert_allclose(res[name].values[0], single.x[name], rtol=1e-3, atol=1e-3, err_msg=name)
    np.testing.assert_allclose(res.ks_stderr.values[0], single.stderr["ks"], rtol=1e-2)


def test_fixed_parameters_and_bounds(dev):
    dop, _ = random_pixels(3, seed=9, ti=TI1, tr=TR1)
    res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI1, theta_r=TR1), fixed={"sigma": 0.45},
                             bounds={"n": (1.2, 3.0)}, engine=dev)
    assert "sigma" not in res and res.attrs["fixed_sigma"] == 0.45
    assert res.attrs["free"] == "n k kd c"
    assert float(res.n.min()) >= 1.2 and float(res.n.max()) <= 3.0
    single = pbrdf_cl.fit(dict(theta_i=TI1, theta_r=TR1, dop=dop[0]), fixed={"sigma": 0.45},
                          bounds={"n": (1.2, 3.0)}, engine=dev)
    assert res.sse.values[0] <= single.sse * (1 + 1e-6)


def test_result_layout_follows_the_input_dataset(dev):
    import xarray as xr
    dop, _ = random_pixels(6, seed=4, ti=TI1, tr=TR1)
    ds = xr.Dataset({"dop": (("row", "col", "meas"), dop.reshape(2, 3, 30)),
                     "theta_i": (("meas",), TI1), "theta_r": (("meas",), TR1), "dop_std": ((), 0.01)},
                    coords={"row": [10, 20], "col": [0.5, 1.5, 2.5]})
    res = pbrdf_cl.fit_batch(ds, engine=dev)
    assert res.n.dims == ("row", "col") and res.n_ci95.dims == ("row", "col", "bound")
    assert res.row.values.tolist() == [10, 20] and res.bound.values.tolist() == ["low", "high"]
    assert res.determined.dims == ("row", "col", "param")
    for name in ("n", "k", "sigma", "kd", "c"):
        lo, hi = res[f"{name}_ci95"].sel(bound="low"), res[f"{name}_ci95"].sel(bound="high")
        # inside the bounds, and (the central 95% of a posterior truncated to them) not always
        # around the value: a best fit on a bound with a wide interval lies outside its interval
        assert bool((hi >= lo).all()) and float(lo.min()) >= DEFAULT_BOUNDS[name][0]
        assert float(hi.max()) <= DEFAULT_BOUNDS[name][1]
        assert res[f"{name}_stderr"].attrs["long_name"].startswith("standard error")
    assert res.attrs["sigma_known"] == 1 and "kd/ks" in res.attrs["note"]
    assert set(res.status.attrs["flag_values"]) == set(PIXEL_STATUS)
    # the per-pixel fields of the fits' one protocol, under its names, and the parameters' units
    # and long names from the registry of the model's inputs (kd relative to ks without intensities)
    from pbrdf_cl.fitting.report import PIXEL_FIELDS
    from pbrdf_cl.model.inputs import LONG_NAMES
    assert all(res[f].dims == ("row", "col") for f in PIXEL_FIELDS)
    assert res.n.attrs["long_name"] == LONG_NAMES["n"] and res.n.attrs["units"] == "1"
    assert res.kd.attrs["long_name"] == LONG_NAMES["kd"] + " relative to ks (kd/ks)"


def test_intervals_cover_the_truth(dev):
    """95% intervals over noisy pixels of a well-determined design cover the truth about 95% of
    the time (scripts/bench_batch.py measures it on the 256 x 256 synthetic image)."""
    ti = np.concatenate([np.full(15, 30.0), np.full(15, 60.0)])
    tr = np.concatenate([np.linspace(5, 80, 15)] * 2)
    rng = np.random.default_rng(21)
    n = 160
    truth = dict(n=rng.uniform(1.4, 2.5, n)[:, None], k=rng.uniform(1.5, 4, n)[:, None],
                 sigma=rng.uniform(0.2, 0.6, n)[:, None], kd=rng.uniform(0.1, 0.5, n)[:, None],
                 c=rng.uniform(-0.7, -0.2, n)[:, None])
    dop = np.clip(pbrdf_cl.dop(ti, tr, **truth, backend="numpy") + rng.normal(0, 0.003, (n, 30)), 0, 1)
    res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=ti, theta_r=tr, dop_std=0.003), engine=dev)
    for name, v in truth.items():
        ci = res[f"{name}_ci95"].values
        covered = np.mean((ci[:, 0] <= v[:, 0]) & (v[:, 0] <= ci[:, 1]))
        assert 0.85 <= covered <= 1.0, (name, covered)


@pytest.mark.parametrize("data, message", [
    (dict(dop=np.full((2, 3, 30), 0.2), theta_i=TI, theta_r=np.where(np.arange(30) == 7, 95.0, TR)),
     r"theta_r must be in \[0, 90\) degrees, got 95.0 at index \[7\]"),
    (dict(dop=np.where(np.arange(180).reshape(2, 3, 30) == 37, 1.5, 0.2), theta_i=TI, theta_r=TR),
     r"dop must be in \[0, 1\] \(NaN for a missing measurement\), got 1.5 at index \[0, 1, 7\]"),
    (dict(dop=np.full((2, 3, 30), 0.2), theta_i=TI, theta_r=TR, dop_std=np.full((2, 3, 30), -1.0)),
     r"dop_std must be > 0 .*got -1.0 at index \[0, 0, 0\]"),
    (dict(dop=np.full((2, 3, 30), 0.2), theta_i=TI), r"no 'theta_r'"),
    (dict(dop=np.full((2, 3, 30), 0.2), theta_i=TI, theta_r=TR, theta=TR), r"unknown variable 'theta'"),
    (dict(dop=np.full(30, 0.2), theta_i=TI, theta_r=TR), r"dop must have shape \(\.\.\., M\)"),
    (dict(dop=np.full((2, 3, 30), 0.2), theta_i=TI, theta_r=TR, mask=np.ones(5, bool)),
     r"mask of shape \(5,\) does not broadcast"),
])
def test_bad_input_is_named_in_one_line(data, message):
    with pytest.raises(ValueError, match=message) as err:
        pbrdf_cl.fit_batch(data, backend="numpy")
    assert "\n" not in str(err.value)


def test_memory_budget_splits_the_image_into_blocks(dev):
    dop, _ = random_pixels(12, seed=8, ti=TI1, tr=TR1)
    data = dict(dop=dop.reshape(6, 2, 30), theta_i=TI1, theta_r=TR1)
    whole = pbrdf_cl.fit_batch(data, engine=dev)
    job = B.BatchJob(data)
    budget = job.fixed_bytes() + job.pixel_bytes() * 4  # the grid's table and two rows
    assert B.BatchJob(data, memory_budget=budget).blocks() == [(0, 2), (2, 4), (4, 6)]
    parts = pbrdf_cl.fit_batch(data, memory_budget=budget, engine=dev)
    np.testing.assert_allclose(parts.sse.values, whole.sse.values, rtol=1e-9)
    with pytest.raises(ValueError, match=r"memory_budget=1000 bytes is too small for one row of 2 pixels"):
        pbrdf_cl.fit_batch(data, memory_budget=1000, engine=dev)


def bench_pixels(which):
    """Pixels ``which`` of scripts/bench_batch.py's 500 random pixels in the paper's geometry
    (parameters uniform in the fit's bounds, DOP noise 0.002)."""
    from pbrdf_cl.fitting.setup import DEFAULT_BOUNDS
    names = ("n", "k", "sigma", "kd", "c")
    lo, hi = (np.array([DEFAULT_BOUNDS[n][i] for n in names]) for i in (0, 1))
    rng = np.random.default_rng(2)
    x = lo + rng.random((500, 5)) * (hi - lo)
    d = pbrdf_cl.dop(TI, TR, backend="numpy", **{n: x[:, j:j + 1] for j, n in enumerate(names)})
    return np.clip(d + rng.normal(0, 0.002, d.shape), 0, 1)[list(which)]


#: Pixels whose optimum is in a corner (bench_pixels numbers): nearly unpolarised light in the
#: index corner n -> 1, k -> 0, kd -> 0 (4 is found only through the table's quarter-decade kd
#: steps); the mirror corner, sigma at its lower bound with kd -> 0 (194 stops short of it in the
#: usual coordinates, 438 is found only through the mirror table).
CORNER_PIXELS = {"index": (4, 199, 297, 396), "mirror": (194, 438)}


@pytest.mark.parametrize("corner", sorted(CORNER_PIXELS))
def test_pixels_reach_the_single_fit_at_the_corners(dev, monkeypatch, corner):
    check_corner_pixels(dev, monkeypatch, corner)


@pytest.mark.parametrize("corner", sorted(CORNER_PIXELS))
def test_corner_pixels_on_the_numpy_backend(monkeypatch, corner):
    check_corner_pixels(pbrdf_cl.NumpyEngine(), monkeypatch, corner)


def check_corner_pixels(eng, monkeypatch, corner):
    """At a corner (batch.CORNERS) a descent in the parameters crawls along a valley: without
    the corner stage these pixels stop short of pbrdf_cl.fit's objective; with it (log(n - 1),
    log k, log kd at the index corner, log kd at the mirror corner) they reach it (1e-6 relative,
    or lower), in the corner."""
    dop = bench_pixels(CORNER_PIXELS[corner])
    data = dict(dop=dop, theta_i=TI, theta_r=TR, dop_std=0.002)
    res = pbrdf_cl.fit_batch(data, engine=eng)
    with monkeypatch.context() as mp:  # this corner's stage switched off
        mp.setattr(corners, "CORNERS", tuple(c for c in corners.CORNERS if c.name != corner))
        off = pbrdf_cl.fit_batch(data, engine=eng)
    single = np.array([pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=d, dop_std=np.full(d.size, 0.002)),
                                    engine=None if eng.is_numpy else eng).chi2 for d in dop])
    rel, rel_off = ((r.chi2.values - single) / single for r in (res, off))
    assert np.all(rel <= 1e-6), rel
    assert np.any(rel_off > 1e-6), rel_off
    (at,) = [c.at for c in corners.CORNERS if c.name == corner]
    for n in at:  # every parameter of the corner within CORNER of its range from its lower bound
        lo, hi = DEFAULT_BOUNDS[n]
        assert np.all(res[n].values - lo < corners.CORNER * (hi - lo)), (n, res[n].values)


#: Pixels of scripts/bench_batch.py's one-incidence geometry (theta_i 45, theta_r 5..80; the
#: bench's random pixels of seed 7) whose optimum lies at the end of a long valley onto the bounds
#: (n = 1 or 5, kd = 5, c = -1): the default schedule's one polished start stops in another basin.
VALLEY_PIXELS = (179, 250, 322, 356, 434, 441, 458)


def test_one_incidence_valleys_reach_the_single_fit(dev, monkeypatch):
    """Pixels of one angle of incidence descend on pixel_fit.ONE_INCIDENCE_SCHEDULE (more starts,
    longer, four polished): on these valley pixels the batched fit reaches pbrdf_cl.fit's objective
    (1e-6 relative, or lower); with the default schedule most of them do not."""
    from pbrdf_cl.fitting.images import pixel_fit
    names = ("n", "k", "sigma", "kd", "c")
    lo, hi = (np.array([DEFAULT_BOUNDS[n][i] for n in names]) for i in (0, 1))
    rng = np.random.default_rng(7)
    x = lo + rng.random((500, 5)) * (hi - lo)
    d = pbrdf_cl.dop(TI1, TR1, backend="numpy", **{n: x[:, j:j + 1] for j, n in enumerate(names)})
    dop = np.clip(d + rng.normal(0, 0.002, d.shape), 0, 1)[list(VALLEY_PIXELS)]
    data = dict(dop=dop, theta_i=TI1, theta_r=TR1, dop_std=0.002)
    res = pbrdf_cl.fit_batch(data, engine=dev)
    with monkeypatch.context() as mp:
        mp.setattr(pixel_fit, "ONE_INCIDENCE_SCHEDULE", pixel_fit.SCREEN_SCHEDULE)
        mp.setattr(pixel_fit, "ONE_INCIDENCE_POLISH_STARTS", pixel_fit.POLISH_STARTS)
        old = pbrdf_cl.fit_batch(data, engine=dev)
    single = np.array([pbrdf_cl.fit(dict(theta_i=TI1, theta_r=TR1, dop=v, dop_std=np.full(v.size, 0.002)),
                                    engine=dev).chi2 for v in dop])
    rel, rel_old = ((r.chi2.values - single) / single for r in (res, old))
    assert np.all(rel <= 1e-6), rel
    assert np.sum(rel_old > 1e-6) >= 4, rel_old


def test_corner_stage_with_sigma_and_c_fixed(dev):
    """With sigma and c fixed the index corner's table has one sigma and one c, and the mirror
    corner (sigma at its lower bound) is not one of this box: two pixels whose optimum is the
    index corner at sigma = 1, c = -1 reach pbrdf_cl.fit's objective with the same values fixed."""
    dop = bench_pixels((4, 220))
    fixed = {"sigma": 1.0, "c": -1.0}
    res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI, theta_r=TR, dop_std=0.002), fixed=fixed, engine=dev)
    assert res.attrs["free"] == "n k kd"
    single = np.array([pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=d, dop_std=np.full(d.size, 0.002)), fixed=fixed,
                                    engine=dev).chi2 for d in dop])
    assert np.all(res.chi2.values <= single * (1 + 1e-6)), (res.chi2.values, single)


def test_corner_coordinates_round_trip():
    names = ["n", "k", "sigma", "kd", "c"]
    X = np.array([[1.0 + 3e-4, 2e-5, 0.4, 7e-6, -0.5], [1.2, 0.3, 0.8, 0.01, -0.1]])
    index, mirror = corners.CORNERS
    for corner in corners.CORNERS:
        U = corners._to_corner(X, names, corner)
        np.testing.assert_allclose(corners._from_corner(U, names, corner), X, rtol=1e-14)
    U = corners._to_corner(X, names, index)
    assert U[0, 0] == np.log(3e-4 + 1.0 - 1.0) and U[0, 2] == 0.4  # sigma and c untouched
    V = corners._to_corner(X, names, mirror)
    assert V[0, 3] == np.log(7e-6) and np.array_equal(V[:, :3], X[:, :3])  # only kd logged


def test_blocks_do_not_change_the_answers(dev):
    """A stack fitted in one block and in blocks of one row gives the same statuses and the same
    values (to float rounding): per-pixel geometry (the synthetic camera stack) and shared
    geometry (random pixels, the corner tables).  Blocks changed them before: the descents'
    lanes went on stepping while another pixel of their vector had not settled, and the
    candidates towards the bounds were those of the block's pixels together."""
    from pbrdf_cl.io import imagestack
    dop, _ = random_pixels(96, seed=3, noise=0.002)
    for data in (imagestack.synthetic_stack(16, seed=1), dict(dop=dop.reshape(12, 8, 30), theta_i=TI, theta_r=TR)):
        job = B.BatchJob(data)
        row = int(np.prod(job.source.shape[1:]))
        budget = job.fixed_bytes() + job.pixel_bytes() * row
        assert len(B.BatchJob(data, memory_budget=budget).blocks()) == job.source.shape[0]
        whole, rows = (pbrdf_cl.fit_batch(data, memory_budget=b, engine=dev) for b in (BLOCK_BUDGET, budget))
        np.testing.assert_array_equal(rows.status.values, whole.status.values)
        for name in ("n", "k", "sigma", "kd", "c", "sse", "chi2", "n_stderr", "kd_ci95"):
            np.testing.assert_allclose(rows[name].values, whole[name].values, rtol=1e-12, atol=0, err_msg=name)


def test_pixels_hold_their_best_values_and_bounds_in_their_intervals(dev, tmp_path, capsys):
    """Issue #34 item 4 for image fits: ``<name>_outside_ci95`` is True exactly where a pixel's
    best value lies outside its own interval, its ``long_name`` says why.  Issue #37 round 8: the
    intervals are the best values +- 1.96 standard errors cut at the bounds, which hold them: on
    this stack (seed 3) 20 best values (n 11, sigma 1, kd 1, c 7) lay outside the central 95% of
    their truncated Gaussians (on a bound, the interval just above it); now none, no count in
    ``attrs`` and no note from fit-image.  A metal's kd = 0 is covered by its pixels' intervals
    (by 2% of them before)."""
    from pbrdf_cl.cli import main
    from pbrdf_cl.fitting.common import OUTSIDE_FOOTNOTE
    dop, _ = random_pixels(24, seed=3, noise=0.003)
    data = dict(dop=dop.reshape(4, 6, 30), theta_i=TI, theta_r=TR, dop_std=np.full((4, 6, 30), 0.003))
    res = pbrdf_cl.fit_batch(data, engine=dev)
    on_bound = 0
    for name in ("n", "k", "sigma", "kd", "c"):
        x, ci = res[name].values, res[f"{name}_ci95"].values
        assert np.all((ci[..., 0] <= x) & (x <= ci[..., 1])), name
        assert not res[f"{name}_outside_ci95"].values.any()
        assert res[f"{name}_outside_ci95"].attrs["long_name"] == OUTSIDE_FOOTNOTE
        lo, hi = pbrdf_cl.fitting.setup.DEFAULT_BOUNDS[name]
        on_bound += int(np.sum((x == lo) & (ci[..., 0] == lo)) + np.sum((x == hi) & (ci[..., 1] == hi)))
    assert on_bound > 0
    assert res.attrs["outside_ci95"] == "" and "outside_ci95_note" not in res.attrs
    np.savez(tmp_path / "stack.npz", **data)
    assert main(["fit-image", str(tmp_path / "stack.npz"), "--out", str(tmp_path / "fit.zarr"), "--no-progress"]) == 0
    assert "outside its own 95% interval" not in capsys.readouterr().out
    rng = np.random.default_rng(950)
    metal = dict(n=1.6, k=2.139, sigma=rng.uniform(0.3, 0.6, (8, 8, 1)), kd=0.0, c=rng.uniform(-0.5, -0.1, (8, 8, 1)))
    dop = np.abs(pbrdf_cl.dop(TI, TR, backend="numpy", **metal) + rng.normal(0, 0.003, (8, 8, 30)))
    res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=TI, theta_r=TR, dop_std=np.full(dop.shape, 0.003)), engine=dev)
    fitted = res.status.values >= 0
    assert np.mean(res.kd_ci95.values[..., 0][fitted] == 0.0) > 0.9


@pytest.mark.parametrize("intensity", [False, True])
def test_forward_differences_by_parts_are_those_of_the_stacked_points(intensity):
    """``fd_jacobian(..., varied=PixelResiduals.varied)`` (the label stage's sums, the numpy
    backend's descents) gives the residuals and Jacobians of the stacked points bit for bit, every
    parameter free (ks as log ks with intensities), on pixels that share their geometry."""
    from pbrdf_cl.fitting.common import fd_jacobian
    from pbrdf_cl.fitting.images.pixels import Block, PixelResiduals, descent_bounds

    truth = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
    rng = np.random.default_rng(3)
    dop = pbrdf_cl.dop(TI, TR, **truth) + rng.normal(0, 0.003, (6, 30))
    data = dict(dop=dop, theta_i=TI, theta_r=TR)
    if intensity:
        data["f00"] = pbrdf_cl.brdf(TI, TR, **truth) * (1 + rng.normal(0, 0.01, (6, 30)))
    job = B.BatchJob(data)
    names = job.names
    blk = Block(job.source.rows(0, 6), job.setup, 1)
    lo, hi = descent_bounds(job.setup, names)
    X = lo + (hi - lo) * rng.uniform(size=(6, len(names)))  # the descent's coordinates (log ks)
    X[0] = hi  # inward steps at the upper bounds
    res = PixelResiduals(job.setup, blk, names, np.arange(6), job.setup.use_f00)
    r0, J0 = fd_jacobian(res.rows, X, lo, hi)
    r1, J1 = fd_jacobian(res.rows, X, lo, hi, varied=res.varied)
    assert r0.tobytes() == r1.tobytes() and J0.tobytes() == J1.tobytes()
    assert J0.shape == (6, len(names), 60 if intensity else 30) and np.all(np.isfinite(J0))
