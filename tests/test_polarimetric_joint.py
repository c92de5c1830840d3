"""Joint fits of polarimetric sets (issue #36, item 2: ``fit_joint`` fits any mix of quantities):
camera data under a 45-degree source at two wavelengths (truth covered, the global optimum
against least squares from the truth, intervals far narrower than the DOP's), a DOP set and a
Mueller set of one sample sharing n and k, one-line refusals, the figure."""
import numpy as np
import pytest
from scipy.optimize import least_squares

import pbrdf_cl
from pbrdf_cl.fitting.sets import joint

TI = np.repeat([30.0, 40.0, 50.0], 10)   # the paper's geometry
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
NOISE = 0.005
#: One sample at two wavelengths: n, k and kd/ks change, sigma and c (shared) do not.
OWN = {"435": dict(n=1.6, k=2.139, kd=0.17), "633": dict(n=2.5, k=3.4, kd=0.06)}
SHARED = dict(sigma=0.5, c=-0.3)


def camera(truth, rng, phi=180.0):
    """s1, s2 under a source polarized at 45 degrees, noise NOISE (given)."""
    S = pbrdf_cl.stokes(TI, TR, phi, ks=1.0, **truth, incident=(0, 1, 0), backend="numpy")
    return dict(theta_i=TI, theta_r=TR, phi=phi, s1=S[:, 1] / S[:, 0] + rng.normal(0, NOISE, TI.size),
                s2=S[:, 2] / S[:, 0] + rng.normal(0, NOISE, TI.size), s1_std=NOISE, s2_std=NOISE,
                in_s1=0.0, in_s2=1.0)


def dop_set(truth, rng):
    d = pbrdf_cl.dop(TI, TR, ks=1.0, **truth, backend="numpy") + rng.normal(0, NOISE, TI.size)
    return dict(theta_i=TI, theta_r=TR, dop=d, dop_std=np.full(TI.size, NOISE))


@pytest.fixture(scope="module")
def cameras():
    rng = np.random.default_rng(3)
    sets = {s: camera({**o, **SHARED}, rng) for s, o in OWN.items()}
    return sets, pbrdf_cl.fit_joint(sets)


def test_joint_camera_fit_covers_the_truth_and_reaches_the_optimum(cameras):
    sets, res = cameras
    assert res.success and res.fits_data and res.shared == ["sigma", "c"]
    assert res.n_points == 2 * 2 * TI.size  # s1 and s2 at every geometry of both sets
    for s, own in OWN.items():
        for p, v in {**own, **SHARED}.items():
            lo, hi = res.ci95[s][p]
            assert lo <= v <= hi, (s, p, v, (lo, hi))
        assert res.separate[s].observed == "s1, s2"
    assert any("normalised Stokes parameters" in n for n in res.notes)
    # no better point near the truth: least squares on the stacked residuals from the truth
    setup = joint.check_joint_args(sets, None, "six-param", None, None, "paper")
    resid = joint.JointResiduals(setup)
    truth = np.array([SHARED[p] for p in setup.shared]
                     + [OWN[s][p] for s in setup.names for p in setup.own(s)])
    ls = least_squares(lambda x: resid.rows(x[None])[0], truth, bounds=(setup.lo, setup.hi), x_scale="jac")
    assert res.chi2 <= 2 * ls.cost * (1 + 1e-6) + 1e-9
    assert res.chi2 >= sum(r.chi2 for r in res.separate.values()) - 1e-6  # sharing fits no better


def test_joint_camera_intervals_are_far_narrower_than_the_dop_s(cameras):
    """The same sample, geometry and noise measured as DOP: the joint camera fit's k is at least 10
    times narrower and its n at least 3 times (in plane, a 45-degree source alone determines n
    about 7 times better than the DOP by Fisher information: the issue's table)."""
    _, res = cameras
    rng = np.random.default_rng(3)
    dop = pbrdf_cl.fit_joint({s: dop_set({**o, **SHARED}, rng) for s, o in OWN.items()})
    for s in OWN:
        width = {p: res.ci95[s][p][1] - res.ci95[s][p][0] for p in ("n", "k")}
        dop_width = {p: dop.ci95[s][p][1] - dop.ci95[s][p][0] for p in ("n", "k")}
        assert 10 * width["k"] < dop_width["k"], (s, width, dop_width)
        assert 3 * width["n"] < dop_width["n"], (s, width, dop_width)


def test_a_dop_set_and_a_mueller_set_of_one_sample_share_n_and_k():
    """Two instruments, one sample: the DOP of the paper's geometry and normalised Mueller matrices
    out of plane (noise-free), n and k shared: the truth, every number counted."""
    truth = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3)
    M = pbrdf_cl.mueller(TI[::3], TR[::3], 150.0, ks=1.0, **truth, backend="numpy")
    mue = dict(theta_i=TI[::3], theta_r=TR[::3], phi=150.0,
               **{f"m{i}{j}": M[:, i, j] / M[:, 0, 0] for i in range(4) for j in range(4) if i or j})
    d = pbrdf_cl.dop(TI, TR, ks=1.0, **truth, backend="numpy")
    res = pbrdf_cl.fit_joint({"dop": dict(theta_i=TI, theta_r=TR, dop=d), "mueller": mue}, shared="n, k")
    assert res.n_points == TI.size + 10 * 15
    assert res.shared_x["n"] == pytest.approx(1.6, rel=1e-5) and res.shared_x["k"] == pytest.approx(2.139, rel=1e-5)
    assert res.x["mueller"]["sigma"] == pytest.approx(0.5, rel=1e-5)
    assert res.set_sse["dop"] < 1e-12 and res.set_sse["mueller"] < 1e-12


def test_stds_for_some_sets_only_are_refused_in_one_line():
    rng = np.random.default_rng(0)
    a = camera({**OWN["435"], **SHARED}, rng)
    b = {k: v for k, v in camera({**OWN["633"], **SHARED}, rng).items() if not k.endswith("_std")}
    with pytest.raises(ValueError) as err:
        pbrdf_cl.fit_joint({"a": a, "b": b})
    msg = str(err.value)
    assert "standard deviations (<name>_std): given for set a but not for b" in msg and "\n" not in msg
    few = dict(a, theta_i=TI[:2], theta_r=TR[:2], s1=a["s1"][:2], s2=a["s2"][:2])
    with pytest.raises(ValueError, match=r"^set 'a': .*4 measured numbers for 5 free parameters"):
        pbrdf_cl.fit_joint({"a": few, "b": a})


def test_joint_figure_of_polarimetric_sets(cameras, tmp_path):
    from pbrdf_cl.plots.joint import plot_joint
    _, res = cameras
    fig = plot_joint(res, tmp_path / "joint.png")
    assert (tmp_path / "joint.png").stat().st_size > 10_000
    ax = fig.axes[0]
    assert ax.get_xlabel().startswith("measured") and ax.get_ylabel() == "model"
    assert {t.get_text() for t in ax.get_legend().get_texts()} == {"s1, source linear +45 (0, 1, 0)",
                                                                   "s2, source linear +45 (0, 1, 0)"}


def test_cli_joint_fit_of_camera_csvs(cameras, tmp_path, capsys):
    """``pbrdf-cl fit a.csv b.csv`` on camera data written by write_csv (s1, s2, their stds and the
    source's state): the joint fit of fit_joint, its data line names the quantities and states."""
    import json

    from pbrdf_cl import cli
    from pbrdf_cl.io.measurements import as_measurements, read_csv, write_csv
    sets, res = cameras
    paths = []
    for s, d in sets.items():
        paths.append(str(tmp_path / f"{s}.csv"))
        write_csv(paths[-1], as_measurements(d))
        back = read_csv(paths[-1])
        assert back.incident.tolist() == [[0.0, 1.0, 0.0]] * TI.size and set(back.stds) == {"s1", "s2"}
    out = tmp_path / "joint.json"
    assert cli.main(["fit", *paths, "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "435: " in text and "60 measured numbers: s1, s2 under 1 incident state: linear +45 (0, 1, 0)" in text
    got = json.loads(out.read_text())["joint"]
    assert got["shared_x"]["sigma"] == pytest.approx(res.shared_x["sigma"], rel=1e-4)
    assert got["x"]["633"]["k"] == pytest.approx(res.x["633"]["k"], rel=1e-4)
