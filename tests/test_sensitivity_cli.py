"""Issue 15, part 3: the sensitivity spec (load_sobol_spec), `pbrdf-cl sobol`, write_result and the
figures (plot_sensitivity)."""
import inspect
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import pbrdf_cl
from pbrdf_cl import cli
from pbrdf_cl.analysis.sensitivity import load_sobol_spec, sobol, summary, write_result
from pbrdf_cl.analysis.sweeps import SpecError
from pbrdf_cl.plots.sensitivity import plot_sensitivity

ROOT = Path(__file__).resolve().parents[1]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

TINY = """
quantity = "dop"
method = "sobol"
N = 64
seed = 7
dtype = "float32"
shadowing = "paper"
memory_budget = "64 MiB"
[ranges]
n = [1.2, 2.5]
k = [0.01, 3.0, "log"]
sigma = [0.1, 0.6]
kd = [0.0, 0.5]
[geometry]
theta_i = "0:80@4"
theta_r = [10, 30, 50, 70, 85]
[fixed]
ks = 1.0
c = -0.3
"""
TINY_SETTINGS = dict(ranges={"n": (1.2, 2.5), "k": (0.01, 3.0, "log"), "sigma": (0.1, 0.6), "kd": (0.0, 0.5)},
                     geometry={"theta_i": "0:80@4", "theta_r": [10, 30, 50, 70, 85]}, fixed={"ks": 1.0, "c": -0.3},
                     N=64, seed=7, memory_budget="64 MiB")


def assert_png(path):
    data = Path(path).read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 5_000, f"{path} is not a (non-trivial) PNG"


@pytest.fixture(scope="module")
def tiny():
    """The tiny spec's result from pbrdf_cl.sobol directly (the reference of the CLI's output)."""
    return sobol(**TINY_SETTINGS)


# ---- the spec ---------------------------------------------------------------------------------

def test_example_spec_parses_into_sobols_arguments():
    settings = load_sobol_spec(ROOT / "examples" / "sobol.toml")
    assert settings["ranges"] == {"n": (1.2, 2.5), "k": (0.01, 3.0, "log"), "sigma": (0.1, 0.6), "kd": (0.0, 0.5),
                                  "c": (-1.0, 0.0)}
    assert settings["geometry"] == {"theta_i": "0:80@64", "theta_r": "0:85@64"}
    assert settings["fixed"] == {"ks": 1.0}
    assert (settings["quantity"], settings["method"], settings["N"], settings["seed"]) == ("dop", "sobol", 4096, 1)
    assert settings["second_order"] is False and settings["memory_budget"] == "512 MiB"
    inspect.signature(sobol).bind(**settings)  # every key is one of sobol's arguments


def test_text_path_and_dict_give_the_same_settings(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(TINY)
    from_text, from_path = load_sobol_spec(TINY), load_sobol_spec(str(path))
    assert from_text == from_path == load_sobol_spec(path)
    assert {k: from_text[k] for k in TINY_SETTINGS} == TINY_SETTINGS
    import tomllib
    assert load_sobol_spec(tomllib.loads(TINY)) == from_text


def _with(text, old, new):
    assert old in text
    return text.replace(old, new)


BAD = [  # (the change to TINY, the field the message starts with, a phrase it holds)
    (("N = 64", "N = 1"), "N:", ">= 2"),
    (("N = 64", "N = 6.5"), "N:", "integer"),
    (("seed = 7", "seed = 0"), "seed:", ">= 1"),
    (("seed = 7", "sead = 7"), "unknown key 'sead'", "did you mean 'seed'"),
    (('method = "sobol"', 'method = "sobel"'), "method:", "did you mean 'sobol'"),
    (('quantity = "dop"', 'quantity = "aop"'), "quantity:", "no sensitivity map"),
    (('quantity = "dop"', 'quantity = "dpo"'), "quantity:", "unknown quantity"),
    (('dtype = "float32"', 'dtype = "float16"'), "dtype:", "float32 or float64"),
    (('shadowing = "paper"', 'shadowing = "papr"'), "shadowing:", "did you mean 'paper'"),
    (('memory_budget = "64 MiB"', 'memory_budget = "lots"'), "memory_budget:", "size"),
    (('method = "sobol"', 'method = "sobol"\nnum_levels = 4'), "num_levels:", "morris"),
    (('method = "sobol"', 'method = "morris"\nsecond_order = true'), "second_order:", "Morris"),
    (('method = "sobol"', 'second_order = "yes"'), "second_order:", "true or false"),
    (('k = [0.01, 3.0, "log"]', 'k = [0.0, 3.0, "log"]'), "ranges.k:", "low > 0"),
    (('k = [0.01, 3.0, "log"]', 'k = [0.01, 3.0, "lg"]'), "ranges.k:", "'linear' or 'log'"),
    (('n = [1.2, 2.5]', 'n = [2.5, 1.2]'), "ranges.n:", "low must be below high"),
    (('n = [1.2, 2.5]', 'n = [1.2, "a"]'), "ranges.n", "not a number"),
    (('n = [1.2, 2.5]', 'n = [0.0, 2.5]'), "ranges.n:", "n must be > 0"),
    (('n = [1.2, 2.5]', 'n = 1.5'), "ranges.n:", "(low, high)"),
    (('n = [1.2, 2.5]', 'nn = [1.2, 2.5]'), "ranges.nn:", "did you mean 'n'"),
    (('sigma = [0.1, 0.6]\n', ''), "ranges:", "sigma needs a range"),
    (('ks = 1.0', 'ks = -1.0'), "fixed.ks:", "ks must be"),
    (('ks = 1.0', 'kss = 1.0'), "fixed.kss:", "did you mean 'ks'"),
    (('ks = 1.0', 'n = 1.5'), "fixed.n:", "also has a range"),
    (('theta_i = "0:80@4"', 'theta_i = "0:80@x"'), "geometry.theta_i", "count"),
    (('theta_i = "0:80@4"', 'theta_i = [10, 95]'), "geometry.theta_i:", "[0, 90)"),
    (('theta_i = "0:80@4"', 'theta_ii = "0:80@4"'), "geometry.theta_ii:", "did you mean 'theta_i'"),
    (('theta_i = "0:80@4"\n', ''), "geometry:", "theta_i is required"),
]


@pytest.mark.parametrize("change, field, phrase", BAD, ids=[b[1] + b[2] for b in BAD])
def test_each_bad_field_is_one_line_naming_it(change, field, phrase):
    with pytest.raises(SpecError) as info:
        load_sobol_spec(_with(TINY, *change))
    text = str(info.value)
    assert "\n" not in text and text.startswith(field) and phrase in text, text


def test_toml_syntax_error_names_its_line_and_a_missing_file_is_named(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(_with(TINY, "seed = 7", "seed = "))
    with pytest.raises(SpecError, match=r"bad\.toml: not valid TOML: .*line 5"):
        load_sobol_spec(bad)
    with pytest.raises(SpecError, match="cannot read the spec .*nothere.toml"):
        load_sobol_spec(tmp_path / "nothere.toml")
    with pytest.raises(SpecError, match="ranges: a table"):
        load_sobol_spec("N = 64\n")


# ---- pbrdf-cl sobol ---------------------------------------------------------------------------

def test_cli_end_to_end_equals_pbrdf_cl_sobol(tmp_path, capsys, tiny):
    spec = tmp_path / "tiny.toml"
    spec.write_text(TINY)
    nc, png, store = tmp_path / "r.nc", tmp_path / "maps.png", tmp_path / "r.zarr"
    assert cli.main(["sobol", str(spec), "--out", str(nc), "--png", str(png), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert cli.main(["sobol", str(spec), "--out", str(store), "--no-progress"]) == 0
    assert_png(png)
    # the summary: the work done and, per parameter, its mean indices and where it dominates
    runs = 64 * (4 + 2)
    assert f"{runs} runs per geometry, {runs * 20} model runs in " in out
    for p in ("n", "k", "sigma", "kd"):
        line = next(ln for ln in out.splitlines() if ln.split()[:1] == [p])
        mean_s1, mean_st = (float(v) for v in line.split()[1:3])
        assert mean_s1 == pytest.approx(float(tiny.S1.sel(parameter=p).mean()), rel=2e-3, abs=1e-3)
        assert mean_st == pytest.approx(float(tiny.ST.sel(parameter=p).mean()), rel=2e-3, abs=1e-3)
    assert f"wrote {nc} and {png}" in out
    for ds in (xr.load_dataset(nc), xr.open_zarr(store).load()):
        assert ds.S1.dims == ("parameter", "theta_i", "theta_r") and ds.S1.shape == (4, 4, 5)
        assert list(ds.parameter.values) == ["n", "k", "sigma", "kd"]
        np.testing.assert_array_equal(ds.theta_r.values, [10, 30, 50, 70, 85])
        assert float(ds.phi) == 180.0
        np.testing.assert_array_equal(ds.samples.values, tiny.samples.values)
        for var in ("S1", "ST", "S1_conf", "ST_conf"):
            np.testing.assert_array_equal(ds[var].values, tiny[var].values)
        np.testing.assert_array_equal(ds.attrs["range_k"], [0.01, 3.0])
        assert ds.attrs["scale_k"] == "log" and ds.attrs["fixed_c"] == -0.3 and ds.attrs["seed"] == 7
        assert ds.attrs["model_runs"] == runs * 20 and ds.attrs["method"] == "sobol"
    # a second run replaces the store
    assert cli.main(["sobol", str(spec), "--out", str(store), "--no-progress"]) == 0


def test_morris_through_the_spec(tmp_path, capsys):
    text = _with(_with(TINY, 'method = "sobol"', 'method = "morris"\nnum_levels = 6'), "N = 64", "N = 16")
    spec = tmp_path / "m.toml"
    spec.write_text(text)
    nc, png = tmp_path / "m.nc", tmp_path / "m.png"
    assert cli.main(["sobol", str(spec), "--out", str(nc), "--png", str(png), "--no-progress"]) == 0
    assert "dominates (largest mu*)" in capsys.readouterr().out
    assert_png(png)
    got = xr.load_dataset(nc)
    want = sobol(**{**TINY_SETTINGS, "N": 16}, method="morris", num_levels=6)
    assert got.attrs["num_levels"] == 6 and got.attrs["method"] == "morris"
    for var in ("mu", "mu_star", "ee_std", "mu_star_conf", "constant"):
        np.testing.assert_array_equal(got[var].values, want[var].values)
    assert (got.mu_star.values >= np.abs(got.mu.values) - 1e-12).all()


def test_cli_errors_are_one_line(tmp_path, capsys):
    spec = tmp_path / "s.toml"
    spec.write_text(_with(TINY, 'k = [0.01, 3.0, "log"]', 'k = [0.0, 3.0, "log"]'))
    assert cli.main(["sobol", str(spec)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("pbrdf-cl: error: ranges.k: ") and "Traceback" not in err
    spec.write_text(TINY)
    blocker = tmp_path / "afile"
    blocker.write_text("")
    for argv, message in [(["--out", str(blocker / "r.nc")], "--out"),
                          (["--png", str(blocker / "m.png")], "--png"),
                          (["--out", str(tmp_path / "r.txt")], ".nc (netCDF) or .zarr"),
                          ([], "cannot read the spec")]:
        target = str(spec) if argv else str(tmp_path / "missing.toml")
        assert cli.main(["sobol", target, *argv]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("pbrdf-cl: error: ") and message in err, err
    # a figure of three geometry axes is refused before any work (nothing written)
    spec.write_text(_with(TINY, 'theta_r = [10, 30, 50, 70, 85]', 'theta_r = [10, 30]\nphi = [170, 180]'))
    nc = tmp_path / "never.nc"
    assert cli.main(["sobol", str(spec), "--out", str(nc), "--png", str(tmp_path / "x.png")]) == 1
    err = capsys.readouterr().err
    assert "--png: draws one or two geometry axes, got 3" in err and "ds.sel(phi=" in err
    assert not nc.exists()
    # a .zarr path that is something else is not overwritten
    other = tmp_path / "other.zarr"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    spec.write_text(TINY)
    assert cli.main(["sobol", str(spec), "--out", str(other), "--no-progress"]) == 1
    assert "is not a Zarr store" in capsys.readouterr().err and (other / "keep.txt").exists()


def test_help(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["sobol", "--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    assert "usage: pbrdf-cl sobol" in text and "examples/sobol.toml" in text
    for option in ("--out", "--png", "--device", "--backend", "--no-progress"):
        assert option in text
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    assert "sobol" in capsys.readouterr().out


# ---- write_result and the figures ---------------------------------------------------------------

def test_write_result_makes_attributes_storable(tmp_path, tiny):
    ds = tiny.copy()
    ds.attrs.update(flag=True, big=np.int64(3) << 40, nothing=None, pair=(1, 2))
    for path in (tmp_path / "a.nc", tmp_path / "a.zarr"):
        write_result(ds, path)
        back = xr.open_zarr(path) if path.suffix == ".zarr" else xr.open_dataset(path)
        assert back.attrs["flag"] == 1 and back.attrs["big"] == float(3 << 40) and back.attrs["nothing"] == ""
        np.testing.assert_array_equal(back.attrs["pair"], [1.0, 2.0])
        back.close()
    assert tiny.attrs.get("flag") is None  # the caller's dataset is left alone
    with pytest.raises(ValueError, match=r"\.nc \(netCDF\) or \.zarr"):
        write_result(tiny, tmp_path / "a.h5")


def test_figures_of_one_and_two_axes_and_refusals(tmp_path, tiny):
    fig = plot_sensitivity(tiny, tmp_path / "two.png")
    assert len(fig.axes) == 2 * 4 + 2  # S1 and ST of 4 parameters, a colour bar per row
    assert_png(tmp_path / "two.png")
    one = tiny.isel(theta_i=2)  # theta_i becomes a scalar coordinate: one axis left
    assert plot_sensitivity(one, tmp_path / "one.png", title="one axis").get_suptitle() == "one axis"
    assert_png(tmp_path / "one.png")
    m = sobol(**{**TINY_SETTINGS, "N": 8, "geometry": {"theta_i": 40, "theta_r": "0:85@6"}}, method="morris")
    plot_sensitivity(m, tmp_path / "morris.png")
    assert_png(tmp_path / "morris.png")
    three = xr.concat([tiny.assign_coords(phi=p) for p in (170.0, 180.0)], dim="phi")
    with pytest.raises(ValueError,
                       match=r"got 3 \(phi, theta_i, theta_r\); select a value of phi first, e.g. ds.sel\(phi=170\)"):
        plot_sensitivity(three, tmp_path / "three.png")
    plot_sensitivity(three.sel(phi=180.0), tmp_path / "selected.png")
    assert_png(tmp_path / "selected.png")
    with pytest.raises(ValueError, match="got 0"):
        plot_sensitivity(tiny.isel(theta_i=0, theta_r=1), tmp_path / "zero.png")
    with pytest.raises(ValueError, match="neither S1/ST nor mu_star/ee_std"):
        plot_sensitivity(tiny[["samples"]], tmp_path / "none.png")
    assert not (tmp_path / "three.png").exists() and not (tmp_path / "zero.png").exists()


def test_figures_mark_constant_geometries_and_name_kd_as_the_ratio(tmp_path, capsys):
    """A geometry where the DOP does not vary over the box (theta_i = theta_r = 0) is hatched in every
    panel and named in a legend (2-d maps and 1-d lines); kd is labelled kd/ks with ks fixed at 1,
    and with its kd/ks range for another ks; a Morris result of the old layout (sigma) still draws."""
    settings = {**TINY_SETTINGS, "N": 16, "geometry": {"theta_i": "0:80@4", "theta_r": "0:85@5"}}
    ds = sobol(**settings)
    assert ds.constant.sel(theta_i=0, theta_r=0).item() == 1 and int(ds.constant.sum()) == 1
    fig_path = tmp_path / "s.png"
    import matplotlib
    from matplotlib.collections import PatchCollection
    captured = {}
    real = matplotlib.figure.Figure.savefig

    def keep(self, *a, **k):
        captured["fig"] = self
        return real(self, *a, **k)
    matplotlib.figure.Figure.savefig = keep
    try:
        plot_sensitivity(ds, fig_path)
        fig = captured["fig"]
        panels = [ax for ax in fig.axes if ax.get_title()]
        assert len(panels) == 8
        for ax in panels:
            hatched = [c for c in ax.collections if isinstance(c, PatchCollection) and c.get_hatch()]
            assert len(hatched) == 1 and len(hatched[0].get_paths()) == 1, ax.get_title()
        assert any("constant over the box" in t.get_text() for leg in fig.legends for t in leg.get_texts())
        assert [ax.get_title().split("\n")[0] for ax in panels if "kd" in ax.get_title()] == [
            "kd/ks in [0, 0.5] (ks = 1)"] * 2
        ks2 = sobol(**{**settings, "fixed": {"ks": 2.0, "c": -0.3}})
        plot_sensitivity(ks2, tmp_path / "ks2.png")
        assert any("kd in [0, 0.5]: kd/ks in [0, 0.25]" in ax.get_title() for ax in captured["fig"].axes)
        m = sobol(**{**settings, "geometry": {"theta_i": 0, "theta_r": "0:85@6"}}, method="morris")
        plot_sensitivity(m, tmp_path / "m.png")
        left = captured["fig"].axes[0]
        assert any("constant over the box" in t.get_text() for t in left.get_legend().get_texts())
        assert any(p.get_hatch() for p in left.patches)
        plot_sensitivity(m.rename({"ee_std": "sigma"}), tmp_path / "old.png")  # a file of the old layout
    finally:
        matplotlib.figure.Figure.savefig = real
    assert_png(fig_path)
    spec = tmp_path / "both.toml"
    spec.write_text(TINY.replace("ks = 1.0\n", "").replace("kd = [0.0, 0.5]", "kd = [0.0, 0.5]\nks = [0.5, 2.0]")
                    .replace("N = 64", "N = 8"))
    assert cli.main(["sobol", str(spec), "--no-progress"]) == 0
    out = capsys.readouterr()
    assert "note: ks and kd both have a range" in out.out and "warning" not in out.err


def test_summary_names_the_dominant_parameter(tiny):
    text = summary(tiny)
    st = tiny.ST.values.reshape(4, -1)
    varies = np.abs(st).max(axis=0) > 0
    best = np.argmax(st[:, varies], axis=0)
    for i, p in enumerate(tiny.parameter.values):
        line = next(ln for ln in text.splitlines() if ln.split()[:1] == [p])
        assert line.rstrip().endswith(f"{np.mean(best == i):.1%} of geometries")
    assert pbrdf_cl.sobol is sobol
