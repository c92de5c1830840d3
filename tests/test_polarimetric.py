"""Polarimetric quantities as data (issue #36, part 1): the Stokes vector for polarized incidence
(SPEC's check values, SCATMECH's Mueller matrix times S_in), the channels of every measurable
quantity against the Mueller matrix they come from, the device objective of channels against the
float64 reference on every device, and the one-line refusals of bad polarimetric input."""
import warnings

import numpy as np
import pySCATMECH.brdf as scatmech  # a test extra
import pytest

import pbrdf_cl
from pbrdf_cl.compute import dense
from pbrdf_cl.io.measurements import as_measurements, read_csv
from pbrdf_cl.model import measurables, reference

STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)


@pytest.mark.parametrize("phi, m00, s", [
    (180.0, 1.733459e-01, (0.16759, -0.60201, -0.238702)),
    (150.0, 1.728435e-01, (-0.569087, -0.200527, -0.181051)),
])
def test_spec_check_values_source_at_45_degrees(phi, m00, s):
    assert pbrdf_cl.mueller(40, 45, phi, **STEEL, backend="numpy")[0, 0] == pytest.approx(m00, rel=1e-6)
    got = pbrdf_cl.stokes(40, 45, phi, **STEEL, incident=(0, 1, 0), backend="numpy")
    np.testing.assert_allclose(got[1:] / got[0], s, atol=1e-6)
    dev = pbrdf_cl.stokes(40, 45, phi, **STEEL, incident=(0, 1, 0))
    np.testing.assert_allclose(dev, got, rtol=1e-12)


def test_stokes_for_polarized_incidence_matches_scatmech():
    """F S_in against SCATMECH's psps Mueller matrix times S_in (its conventions: s = sqrt(2) sigma,
    phi_s = 180 - phi, n - ik written as our k > 0): every component within 1e-12 of S0, for
    random out-of-plane geometries and random incident states."""
    rng = np.random.default_rng(36)
    model = scatmech.BRDF_Model("Facet_BRDF_Model")
    worst, done = 0.0, 0
    while done < 60:
        ti, tr, phi = rng.uniform(5, 80), rng.uniform(5, 80), rng.uniform(0, 360)
        if reference.geometry(ti, tr, phi).sb < np.sin(np.radians(5)):
            continue
        n, k, sigma = rng.uniform(1.1, 4), rng.uniform(0, 6), rng.uniform(0.1, 0.8)
        v = rng.normal(size=3)
        s_in = v / np.linalg.norm(v) * rng.uniform(0, 1)
        model.setParameters({"lambda": 0.5, "substrate": f"({n!r},{k!r})",
                             "sdf": "Gaussian_Slope_Distribution_Function", "sdf.s": repr(float(np.sqrt(2) * sigma))})
        M = np.array(model.MuellerBRDF(np.radians(ti), np.radians(tr), np.radians(180 - phi), 0, "psps"))
        theirs = M @ np.concatenate([[1.0], s_in])
        ours = pbrdf_cl.stokes(ti, tr, phi, n=n, k=k, sigma=sigma, shadowing="none", incident=s_in)
        worst = max(worst, np.max(np.abs(ours - theirs)) / abs(theirs[0]))
        done += 1
    assert worst < 1e-12, worst


def _points(rng, size):
    ti, tr, phi = rng.uniform(5, 80, size), rng.uniform(5, 80, size), rng.uniform(0, 360, size)
    par = dict(n=rng.uniform(1.1, 4, size), k=rng.uniform(0, 6, size), sigma=rng.uniform(0.1, 0.8, size),
               ks=rng.uniform(0.5, 2, size), kd=rng.uniform(0, 0.5, size), c=rng.uniform(-1, 0, size))
    v = rng.normal(size=(size, 3))
    inc = v / np.linalg.norm(v, axis=1)[:, None] * rng.uniform(0, 1, (size, 1))
    return ti, tr, phi, par, inc


def test_every_channel_is_its_number_of_the_mueller_matrix():
    """dop, aop, s1..s3 (normalised), s0..s3 (absolute), m_ij (normalised and absolute), f00: each
    channel's model value equals what the Mueller matrix F and the incident state say."""
    rng = np.random.default_rng(3)
    ti, tr, phi, par, inc = _points(rng, 40)
    F = pbrdf_cl.mueller(ti, tr, phi, **par, backend="numpy")
    S = np.einsum("pij,pj->pi", F, np.column_stack([np.ones(40), inc]))
    expect = {"dop": np.linalg.norm(S[:, 1:], axis=1) / S[:, 0], "aop": 0.5 * np.degrees(np.arctan2(S[:, 2], S[:, 1])),
              **{f"s{i}": S[:, i] / S[:, 0] for i in (1, 2, 3)},
              **{f"m{i}{j}": F[:, i, j] / F[:, 0, 0] for i in range(4) for j in range(4) if i or j}}
    absolute = {**{f"s{i}": S[:, i] for i in range(4)}, **{f"m{i}{j}": F[:, i, j] for i in range(4) for j in range(4)},
                "f00": F[:, 0, 0]}
    for cols, want in ((expect, expect), (absolute, absolute)):
        ch = measurables.channels(ti, tr, phi, {k: np.zeros(40) for k in cols}, incident=inc)
        g = reference.geometry(ch.theta_i, ch.theta_r, ch.phi)
        p = {k: v[ch.row] for k, v in par.items()}
        f = reference.fresnel(p["n"], p["k"], g.cb, g.sb)
        logK = reference.log_specular_scale(g, p["sigma"], p["ks"], reference.shadowing_factor(g, p["sigma"], 1))
        got = ch.values(f, reference.frame_rotations(g, ch.phi), logK, reference.diffuse(g, p["kd"], p["c"]))
        for name in cols:
            sel = ch.name == name
            w = want[name][ch.row[sel]]
            if name == "aop":
                np.testing.assert_allclose(np.cos(np.radians(2 * (got[sel] - w))), 1.0, atol=1e-12)
            else:
                np.testing.assert_allclose(got[sel], w, rtol=1e-10, atol=1e-14 * np.abs(F[:, 0, 0]).max(), err_msg=name)


def test_aop_residuals_wrap_modulo_180():
    r = reference.channel_residual(np.array([89.0, -89.0, 10.0, np.nan]), np.array([-89.0, 89.0, 10.0, 0.0]),
                                   np.array([True, True, True, True]))
    np.testing.assert_allclose(r, [-2.0, 2.0, 0.0, 90.0])
    assert reference.channel_residual(np.array([89.0]), np.array([-89.0]), np.array([False]))[0] == 178.0


def _mixed_channels(rng, M=24):
    ti, tr, phi, par, inc = _points(rng, M)
    cols = dict(dop=rng.uniform(0, 1, M), aop=rng.uniform(-90, 90, M), s1=rng.uniform(-0.5, 0.5, M),
                s2=rng.uniform(-0.5, 0.5, M), m01=rng.uniform(-0.5, 0.5, M), m23=rng.uniform(-0.5, 0.5, M),
                f00=rng.uniform(0, 1, M))
    cols["s1"][::3] = np.nan  # not measured at those rows
    stds = {k: np.full(M, 0.01 if k != "aop" else 1.0) for k in cols}
    return measurables.channels(ti, tr, phi, cols, stds, inc)


def test_channel_terms_per_distinct_geometry_equal_the_spread_ones():
    """``channel_terms(at=)`` (P per distinct geometry, each channel taking its own) gives the
    numbers of P spread to every channel first, bit for bit, for every kind of channel."""
    rng = np.random.default_rng(7)
    ch = _mixed_channels(rng)
    geo = np.column_stack([ch.theta_i, ch.theta_r, ch.phi])
    first, at = np.unique(geo, axis=0, return_index=True, return_inverse=True)[1:]
    at = at.reshape(-1)
    g = reference.geometry(ch.theta_i[first], ch.theta_r[first], ch.phi[first])
    f = reference.fresnel(np.array([[1.4], [2.5]]), np.array([[0.3], [3.0]]), g.cb, g.sb)
    P = reference.mueller_at(f, reference.frame_rotations(g, ch.phi[first]), 1.0, 0.0)  # (2, G, 4, 4)
    assert len(first) < len(ch) and set(ch.kind.tolist()) == {0, 1, 2}
    spread = reference.channel_terms(P[:, at], ch.u, ch.v, ch.comp, ch.kind)
    gathered = reference.channel_terms(P, ch.u, ch.v, ch.comp, ch.kind, at=at)
    for a, b in zip(spread, gathered):
        assert a.shape == b.shape == (2, len(ch))
        np.testing.assert_array_equal(a, b)


def test_channel_objective_on_every_device_equals_the_reference(engine):
    """The device objective of mixed channels (objective_channel_rows at both row levels and
    objective_channels) equals the float64 reference's to 1e-12 in float64, 1e-4 in float32."""
    if engine is None:
        pytest.skip("no OpenCL device")
    ch = _mixed_channels(np.random.default_rng(11))
    assert np.isnan(ch.obs).sum() == 0 and len(ch) == 24 * 7 - 8
    for grid in (dict(n=np.linspace(1.1, 3, 5), k=np.linspace(0, 4, 6), sigma=0.4, kd=np.linspace(0, 0.5, 21)),
                 dict(n=np.linspace(1.1, 3, 5), k=[0.0, 2.0], sigma=np.linspace(0.1, 0.8, 8), kd=[0.0, 0.2],
                      c=[-0.5, 0]),
                 dict(n=[1.5, 2.5], k=[0.5, 3.0], sigma=0.3)):
        ref = dense.objective(ch, grid=grid, dtype="float64", backend="numpy").sse.values
        got = dense.objective(ch, grid=grid, dtype="float64", engine=engine).sse.values
        np.testing.assert_allclose(got, ref, rtol=1e-12)
        got32 = dense.objective(ch, grid=grid, dtype="float32", engine=engine).sse.values
        np.testing.assert_allclose(got32, ref, rtol=1e-4)


def test_polarimetric_columns_are_read_from_csv_dict_and_dataset(tmp_path):
    """s1, s2 under a 45-degree source from a CSV (empty cells: not measured), a dict and an xarray
    Dataset give the same channels."""
    ti, tr = np.repeat([30.0, 50.0], 3), np.tile([20.0, 40.0, 60.0], 2)
    S = pbrdf_cl.stokes(ti, tr, 150, **STEEL, incident=(0, 1, 0), backend="numpy")
    s1, s2 = S[:, 1] / S[:, 0], S[:, 2] / S[:, 0]
    lines = ["theta_i,theta_r,phi,s1,s1_std,s2,s2_std,in_s1,in_s2,in_s3"]
    lines += [f"{a},{b},150,{'' if i == 2 else repr(float(c))},0.005,{float(d)!r},0.005,0,1,0"
              for i, (a, b, c, d) in enumerate(zip(ti, tr, s1, s2))]
    (tmp_path / "cam.csv").write_text("\n".join(lines) + "\n")
    m = read_csv(tmp_path / "cam.csv")
    assert m.polarimetric and m.dop is None and np.isnan(m.quantities["s1"][2]) and len(m.channels()) == 11
    d = as_measurements(dict(theta_i=ti, theta_r=tr, phi=150.0, s1=np.where(np.arange(6) == 2, np.nan, s1), s2=s2,
                             s1_std=0.005, s2_std=0.005, in_s1=0.0, in_s2=1.0, in_s3=0.0))
    import xarray as xr
    cols = dict(theta_i=ti, theta_r=tr, phi=150.0, s1=d.quantities["s1"], s2=s2, s1_std=0.005, s2_std=0.005, in_s2=1.0)
    ds = xr.Dataset({k: ("m", np.broadcast_to(v, 6)) for k, v in cols.items()})
    x = as_measurements(ds)
    for other in (d, x):
        a, b = m.channels(), other.channels()
        np.testing.assert_array_equal(a.obs, b.obs)
        np.testing.assert_array_equal(a.u, b.u)
    assert list(m.channels().name[:3]) == ["s1", "s2", "s1"]


@pytest.mark.parametrize("columns, words", [
    (dict(s1=[0.9, 0.1], s2=[0.9, 0.1]), ["row 0", "longer than 1", "sqrt(s1^2 + s2^2) = 1.273"]),
    (dict(s0=[0.1, 0.1], s1=[0.08, 0.2], s2=[0.0, 0.05]), ["row 1", "longer than s0", "> s0 = 0.1"]),
    (dict(m01=[0.2, -1.4]), ["row 1", "m01 = -1.4 is outside [-1, 1]"]),
    (dict(m00=[0.2, 0.2], m12=[0.1, 0.3]), ["row 1", "|m12| = 0.3 exceeds m00 = 0.2"]),
    (dict(s0=[0.1, -0.1], s1=[0.0, 0.0]), ["row 1", "s0 = -0.1 is not >= 0 (an intensity)"]),
    (dict(m00=[-0.2, 0.2], m12=[0.1, 0.1]), ["row 0", "m00 = -0.2 is not >= 0 (the BRDF)"]),
    (dict(s1=[0.1, 0.2], in_s1=[0.8, 0.0], in_s2=[0.8, 0.0]), ["row 0", "is not a Stokes vector", "1.28 > 1"]),
    (dict(s1=[0.1, 0.2], in_s1=[0.0, np.nan]), ["row 1", "in_s1 is empty", "incident state of every row"]),
    (dict(s1_1=[0.1, 0.2]), ["column 's1_1'", "did you mean 's1'"]),
    (dict(aop=[10.0, np.nan], aop_std=[0.0, 1.0]), ["row 0", "aop_std = 0.0 is not > 0"]),
    (dict(dop=[np.nan, np.nan], s1=[np.nan, np.nan]), ["row 0", "nothing measured"]),
])
def test_bad_polarimetric_input_is_refused_in_one_line(columns, words):
    data = dict(theta_i=[40.0, 40.0], theta_r=[20.0, 45.0], **columns)
    with pytest.raises(ValueError) as err:
        as_measurements(data)
    text = str(err.value)
    assert "\n" not in text and all(w in text for w in words), text


def test_stokes_of_several_states_at_one_geometry_need_their_state():
    """s1 measured twice at one geometry with different values and no incident state: different
    source states, refused in one line; with in_s columns, read."""
    ti, tr = np.array([40.0, 40.0]), np.array([45.0, 45.0])
    S = pbrdf_cl.stokes(ti, tr, 150, **STEEL, incident=[(1, 0, 0), (0, 1, 0)], backend="numpy")
    cols = dict(theta_i=ti, theta_r=tr, phi=150.0, s1=S[:, 1] / S[:, 0])
    with pytest.raises(ValueError, match=r"row 0 and row 1: s1 = .* at one geometry: measured under different "
                                         r"incident states\? give the incident state of every row"):
        as_measurements(cols)
    assert as_measurements(dict(cols, in_s1=[1.0, 0.0], in_s2=[0.0, 1.0])).polarimetric


def test_aop_in_radians_is_warned_of_and_incident_checked_in_stokes():
    ti, tr = np.repeat([30.0, 50.0], 3), np.tile([20.0, 40.0, 60.0], 2)
    a = pbrdf_cl.aop(ti, tr, 150.0, **STEEL)
    with pytest.warns(pbrdf_cl.UnitsWarning, match=r"aop: every value lies within \+-1.571 .* radians"):
        as_measurements(dict(theta_i=ti, theta_r=tr, phi=150.0, aop=np.radians(a)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        as_measurements(dict(theta_i=ti, theta_r=tr, phi=150.0, aop=a))
    with pytest.raises(ValueError, match=r"incident must be the normalised Stokes vector \(s1, s2, s3\)"):
        pbrdf_cl.stokes(40, 45, **STEEL, incident=(1, 0, 0, 0))
    with pytest.raises(ValueError, match=r"is not a Stokes vector: s1\^2 \+ s2\^2 \+ s3\^2 = 1.28 > 1"):
        pbrdf_cl.stokes(40, 45, **STEEL, incident=(0.8, 0.8, 0))


TI = np.repeat([30.0, 40.0, 50.0], 10)   # the paper's geometry
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
TRUTH = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)


def test_fit_recovers_the_truth_from_noise_free_camera_and_mueller_data():
    """s1, s2 under a 45-degree source (in plane) and normalised Mueller elements (out of plane):
    the fit reaches the truth (kd as kd/ks, ks held), and its report names what it fitted."""
    S = pbrdf_cl.stokes(TI, TR, 180.0, **TRUTH, incident=(0, 1, 0), backend="numpy")
    cam = dict(theta_i=TI, theta_r=TR, phi=180.0, s1=S[:, 1] / S[:, 0], s2=S[:, 2] / S[:, 0], in_s1=0.0, in_s2=1.0)
    r = pbrdf_cl.fit(cam)
    for p, v in dict(TRUTH, kd=TRUTH["kd"] / TRUTH["ks"], ks=1.0).items():
        assert r.x[p] == pytest.approx(v, rel=1e-6, abs=1e-8), p
    assert r.observed == "s1, s2" and "SSE" in r.summary() and "(s1, s2)" in r.summary()
    M = pbrdf_cl.mueller(TI[::3], TR[::3], 150.0, **TRUTH, backend="numpy")
    mue = dict(theta_i=TI[::3], theta_r=TR[::3], phi=150.0,
               **{f"m{i}{j}": M[:, i, j] / M[:, 0, 0] for i in range(4) for j in range(4) if i or j})
    r = pbrdf_cl.fit(mue)
    assert r.x["n"] == pytest.approx(1.6, rel=1e-6) and r.x["k"] == pytest.approx(2.139, rel=1e-6)
    assert r.n_points == 10 * 15


def test_absolute_stokes_separate_ks_and_kd():
    """Absolute S0, S1, S2 under a 45-degree source: ks is fitted (the intensity stage), kd is kd
    itself, and both come back."""
    S = pbrdf_cl.stokes(TI, TR, 180.0, **TRUTH, incident=(0, 1, 0), backend="numpy")
    d = dict(theta_i=TI, theta_r=TR, phi=180.0, s0=S[:, 0], s1=S[:, 1], s2=S[:, 2], in_s1=0.0, in_s2=1.0,
             s0_std=0.01 * S[:, 0], s1_std=0.01 * S[:, 0], s2_std=0.01 * S[:, 0])
    r = pbrdf_cl.fit(d)
    assert "ks" in r.free and r.x["ks"] == pytest.approx(0.9, rel=1e-4) and r.x["kd"] == pytest.approx(0.15, rel=1e-4)
    assert r.sigma_known and r.fits_data


def test_noisy_camera_data_determine_n_and_k_far_better_than_dop():
    """Camera data under a 45-degree source at noise 0.005 (std given): the 95% intervals of n and k
    cover the truth and are several times narrower than a DOP fit's on the same geometry."""
    rng = np.random.default_rng(2)
    S = pbrdf_cl.stokes(TI, TR, 180.0, **TRUTH, incident=(0, 1, 0), backend="numpy")
    cam = dict(theta_i=TI, theta_r=TR, phi=180.0, s1=S[:, 1] / S[:, 0] + rng.normal(0, 0.005, 30),
               s2=S[:, 2] / S[:, 0] + rng.normal(0, 0.005, 30), s1_std=0.005, s2_std=0.005, in_s1=0.0, in_s2=1.0)
    dop = pbrdf_cl.dop(TI, TR, **TRUTH, backend="numpy") + rng.normal(0, 0.005, 30)
    r, d = pbrdf_cl.fit(cam), pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=dop, dop_std=np.full(30, 0.005)))
    for p in ("n", "k"):
        lo, hi = r.ci95[p]
        assert lo <= TRUTH[p] <= hi, (p, lo, hi)
        assert 5 * (hi - lo) < d.ci95[p][1] - d.ci95[p][0], p
    assert r.fits_data and r.p_value > 1e-3


@pytest.mark.parametrize("extra, words", [
    (dict(s1_std=0.005), "standard deviations are given for s1 but not for s2; give <name>_std for every quantity"),
    (dict(aop=20.0), "aop_std is needed where the AoP is fitted with other quantities (s1, s2)"),
])
def test_fit_refuses_mixed_weights_in_one_line(extra, words):
    S = pbrdf_cl.stokes(TI, TR, 180.0, **TRUTH, incident=(0, 1, 0), backend="numpy")
    cam = dict(theta_i=TI, theta_r=TR, phi=180.0, s1=S[:, 1] / S[:, 0], s2=S[:, 2] / S[:, 0], in_s1=0.0, in_s2=1.0)
    with pytest.raises(ValueError) as err:
        pbrdf_cl.fit(dict(cam, **extra))
    assert words in str(err.value) and "\n" not in str(err.value)


def test_cli_eval_prints_stokes_for_an_incident_state(capsys):
    """``pbrdf-cl eval --quantity stokes --incident 0,1,0`` prints pbrdf_cl.stokes(incident=) (text and
    JSON); another quantity with --incident, a state that is not a Stokes vector and a state that
    is not three numbers are refused in one line."""
    import json

    from pbrdf_cl.cli import main
    args = ["eval", "--theta-i", "40", "--theta-r", "45", "--phi", "150", "--n", "1.6", "--k", "2.139", "--sigma",
            "0.5", "--ks", "0.9", "--kd", "0.15", "--c", "-0.3", "--quantity", "stokes", "--incident", "0,1,0"]
    assert main(args + ["--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    want = pbrdf_cl.stokes(40, 45, 150, **STEEL, incident=(0, 1, 0))
    np.testing.assert_allclose(got["rows"][0]["stokes"], want, rtol=1e-12)
    assert got["incident"] == [0.0, 1.0, 0.0]
    assert main(args) == 0 and "for incident (0,1,0)" in capsys.readouterr().out
    for bad, words in ((["--quantity", "dop"], "use --quantity stokes, not dop"),
                       (["--incident", "0.9,0.9,0"], "is not a Stokes vector"),
                       (["--incident", "45"], "give the normalised Stokes vector S1,S2,S3")):
        assert main(args + bad) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err, err
