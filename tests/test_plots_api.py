"""Plots that live in notebooks (issue #35, item 7): every public plot function draws into the
caller's axes (``ax=``) or figure (``fig=``, a subfigure too) and returns it, makes a figure of its
own otherwise, and writes a file only when given a path; the package never chooses matplotlib's
backend; ``plots`` imports no room that draws through it (item 5: no plots <-> explore circle)."""
import ast
import importlib
import inspect
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import xarray as xr
from matplotlib.figure import Figure

import pbrdf_cl
from pbrdf_cl.io.measurements import from_arrays

PACKAGE = Path(pbrdf_cl.__file__).resolve().parent
PLOT_MODULES = sorted(p.stem for p in (PACKAGE / "plots").glob("*.py") if p.stem != "__init__")
#: Public functions of pbrdf_cl.plots that draw nothing (so take no axes), and what they do instead.
NOT_DRAWING = {"contour_levels": "computes contour levels", "params_text": "formats parameter values"}
#: What the package's plots may import: the rooms below them (never analysis, app or cli, which draw through plots).
BELOW_PLOTS = {"plots", "model", "compute", "fitting", "io", "errors", "results", "sizes", "ranges", "device"}
STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)


def public_functions():
    for name in PLOT_MODULES:
        module = importlib.import_module(f"pbrdf_cl.plots.{name}")
        for fname, f in vars(module).items():
            if inspect.isfunction(f) and f.__module__ == module.__name__ and not fname.startswith("_"):
                yield f


def test_every_public_plot_function_takes_axes_or_a_figure():
    found = {f.__name__ for f in public_functions()}
    assert set(NOT_DRAWING) <= found and {"plot_fit", "plot_view", "plot_dop_maps", "label_contours"} <= found
    missing = [f"{f.__module__}.{f.__name__}" for f in public_functions()
               if f.__name__ not in NOT_DRAWING and not {"ax", "axes", "fig"} & set(inspect.signature(f).parameters)]
    assert not missing, f"public plot functions without ax=, axes= or fig=: {missing}"
    for f in public_functions():
        params = inspect.signature(f).parameters
        if f.__name__.startswith("plot_"):
            (kind,) = {"ax", "fig"} & set(params)
            assert params[kind].default is None and params[kind].kind is inspect.Parameter.KEYWORD_ONLY, f.__name__
            # the path: optional, or (the paper's figures) the first argument, where None writes nothing
            assert params["path"].default is None or next(iter(params)) == "path", f.__name__


def _calls(tree):
    """(line, what) of each matplotlib.use call and each pyplot import in a module's syntax tree."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            if isinstance(f, ast.Attribute) and f.attr == "use" and isinstance(f.value, ast.Name) \
                    and f.value.id in ("matplotlib", "mpl"):
                yield node.lineno, "matplotlib.use"
        elif isinstance(node, ast.ImportFrom) and node.module == "matplotlib" \
                and any(a.name in ("use", "pyplot") for a in node.names):
            yield node.lineno, f"from matplotlib import {', '.join(a.name for a in node.names)}"
        elif isinstance(node, ast.Import) and any(a.name == "matplotlib.pyplot" for a in node.names):
            yield node.lineno, "import matplotlib.pyplot"
        elif isinstance(node, ast.ImportFrom) and node.module == "matplotlib.pyplot":
            yield node.lineno, "from matplotlib.pyplot import"


def test_no_module_chooses_the_backend_or_imports_pyplot():
    found = [f"{p.relative_to(PACKAGE.parent)}:{line}: {what}" for p in sorted(PACKAGE.rglob("*.py"))
             for line, what in _calls(ast.parse(p.read_text()))]
    assert not found, found


def _rooms_imported(path):
    """The rooms (subpackages, top-level modules) of pbrdf_cl a module of plots/ imports, anywhere in it."""
    rooms = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            rooms.add("plots")
        elif isinstance(node, ast.ImportFrom) and node.level == 2:
            rooms.add((node.module or "__init__").split(".")[0])
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("pbrdf_cl"):
            rooms.add((node.module.split(".") + ["__init__"])[1])
        elif isinstance(node, ast.Import):
            rooms |= {(a.name.split(".") + ["__init__"])[1] for a in node.names if a.name.startswith("pbrdf_cl")}
    return rooms


def test_plots_imports_only_the_rooms_below_it():
    above = {f"plots/{p.name}": sorted(_rooms_imported(p) - BELOW_PLOTS)
             for p in sorted((PACKAGE / "plots").glob("*.py"))}
    assert not any(above.values()), {k: v for k, v in above.items() if v}
    assert "plots" in _rooms_imported(PACKAGE / "analysis" / "paper.py")  # the paper draws through plots


# ---------------------------------------------------------------------------- every plot function

def _steel_data():
    ti, tr = np.repeat([30.0, 40.0, 50.0], 6), np.tile(np.arange(20.0, 66.0, 9.0), 3)
    dop = pbrdf_cl.dop(ti, tr, backend="numpy", **STEEL)
    return from_arrays(ti, tr, dop, dop_std=np.full(ti.size, 0.002), source="dir/steel.csv")


def _fits():
    return {"six-param": SimpleNamespace(x=dict(STEEL), shadowing="paper", bic=10.0),
            "specular": SimpleNamespace(x=dict(n=3.0, k=3.5), shadowing="paper", bic=20.0)}


def _joint():
    meas, six = _steel_data(), dict(STEEL)
    return SimpleNamespace(sets=["a", "b"], measurements={"a": meas, "b": meas}, x={"a": six, "b": six},
                           separate={s: SimpleNamespace(x=six, sse=1e-3) for s in "ab"},
                           ci95={s: {p: (0.0, 1.0) for p in ("n", "k", "sigma", "kd", "c")} for s in "ab"},
                           shared=["k", "sigma", "kd", "c"], set_sse={"a": 1e-3, "b": 2e-3},
                           shared_x={p: STEEL[p] for p in ("k", "sigma", "kd", "c")}, model="six-param",
                           shadowing="paper", aic=-10.0, separate_aic=-8.0)


def _batch_result():
    """A result of fit_batch's layout over 4 x 5 pixels (without running the fit)."""
    shape, names = (4, 5), ["n", "k"]
    ds = xr.Dataset(coords={"bound": ["low", "high"], "param": names})
    status = np.ones(shape, np.int8)
    status[0, 0] = -1
    for j, n in enumerate(names):
        v = np.linspace(1.0, 2.0, 20).reshape(shape) + j
        v[status < 0] = np.nan
        ds[n] = (("y", "x"), v, {"units": "1", "long_name": f"the parameter {n}"})
        ds[f"{n}_ci95"] = (("y", "x", "bound"), np.stack([v - 0.1, v + 0.1], axis=-1))
    ds["status"] = (("y", "x"), status)
    ds.attrs.update(free=" ".join(names), model="six-param")
    return ds


def _paper_inputs():
    from pbrdf_cl.compute import dense
    angle = np.linspace(10.0, 80.0, 15)
    meas = from_arrays(angle, angle, pbrdf_cl.dop(angle, angle, backend="numpy", **STEEL), 180.0,
                       dop_std=np.full(angle.size, 0.001))
    curve = pbrdf_cl.dop(angle, angle, backend="numpy", **STEEL)
    fits = _fits()
    tr = np.linspace(20.0, 65.0, 10)
    curves = {ti: pbrdf_cl.dop(ti, tr, backend="numpy", **STEEL) for ti in (30.0, 40.0)}
    angles = np.linspace(0.0, 85.0, 12)
    fixed = {k: v for k, v in STEEL.items() if k != "sigma"}
    grid = dense.grid({"theta_i": angles, "theta_r": angles, "sigma": np.array([0.35, 0.65])}, fixed,
                      dtype="float64", backend="numpy")
    return dict(fig2=("aluminum", STEEL, 0.001, meas, angle, curve, (fits["six-param"], curve),
                      (fits["specular"], curve)),
                fig4=(STEEL, tr, curves, tr, curves), fig5=(STEEL, tr, (0.35, 0.65), list(curves.values())),
                dop_maps=(grid, angles, (0.35, 0.65), fixed))


@pytest.fixture(scope="module")
def cases():
    """Plot function name -> (``ax`` or ``fig``, call(path, **kw)): each function with small inputs,
    its path (None: no file) and the axes or figure to draw into."""
    from pbrdf_cl.analysis.maps import make_map
    from pbrdf_cl.app import state
    from pbrdf_cl.plots import design, explorer, fit, images, joint, maps, paper, sensitivity
    meas = _steel_data()
    fmap = make_map("theta_r=0:85@12", "sigma=0.05:1@10", dict(theta_i=40, n=1.6, k=2.1), derivative="sigma",
                    backend="numpy")
    sob = pbrdf_cl.sobol({"n": (1.2, 2.5), "k": (0.01, 3, "log")}, {"theta_i": "0:80@3", "theta_r": "0:85@4"},
                         {"sigma": 0.5}, N=8, seed=1, backend="numpy")
    des = pbrdf_cl.design(dict(n=1.6, k=2.139, sigma=0.5), {"theta_i": "10:70:20", "theta_r": "0:80:20"},
                          noise=0.005, n_measurements=8, target=("n", "k"), backend="numpy")
    view = state.State()
    view.settings.resolution = 16
    vds = state.view_dataset(pbrdf_cl.NumpyEngine(), view, meas)
    p = _paper_inputs()
    return {
        "plot_fit": ("fig", lambda path=None, **kw: fit.plot_fit(meas, _fits(), path, **kw)),
        "plot_joint": ("fig", lambda path=None, **kw: joint.plot_joint(_joint(), path, **kw)),
        "plot_batch_maps": ("fig", lambda path=None, **kw: images.plot_batch_maps(_batch_result(), path, **kw)),
        "plot_map": ("fig", lambda path=None, **kw: maps.plot_map(fmap, path, **kw)),
        "plot_sensitivity": ("fig", lambda path=None, **kw: sensitivity.plot_sensitivity(sob, path, **kw)),
        "plot_sensitivity (one axis)": ("fig", lambda path=None, **kw: sensitivity.plot_sensitivity(
            sob.isel(theta_i=1), path, **kw)),
        "plot_design": ("fig", lambda path=None, **kw: design.plot_design(des, path, **kw)),
        "plot_view": ("fig", lambda path=None, **kw: explorer.plot_view(vds, path, **kw)),
        "plot_fig2": ("ax", lambda path=None, **kw: paper.plot_fig2(path, *p["fig2"], **kw)),
        "plot_fig4": ("ax", lambda path=None, **kw: paper.plot_fig4(path, *p["fig4"], **kw)),
        "plot_fig5": ("ax", lambda path=None, **kw: paper.plot_fig5(path, *p["fig5"], **kw)),
        "plot_dop_maps": ("fig", lambda path=None, **kw: paper.plot_dop_maps(path, *p["dop_maps"], **kw)),
    }


NAMES = ["plot_fit", "plot_joint", "plot_batch_maps", "plot_map", "plot_sensitivity", "plot_sensitivity (one axis)",
         "plot_design", "plot_view", "plot_fig2", "plot_fig4", "plot_fig5", "plot_dop_maps"]


def test_the_cases_cover_every_plot_function():
    names = {f.__name__ for f in public_functions() if f.__name__.startswith("plot_")}
    assert names == {n.split()[0] for n in NAMES}


@pytest.fixture
def saved(monkeypatch, tmp_path):
    """The figures written (Figure.savefig spied on), in an empty working folder."""
    monkeypatch.chdir(tmp_path)
    calls, savefig = [], Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: (calls.append(fig), savefig(fig, *a, **k))[1])
    return calls


def _drawn(ax):
    return len(ax.lines) + len(ax.collections) + len(ax.images) + len(ax.patches) + len(ax.containers)


@pytest.mark.parametrize("name", NAMES)
def test_draws_into_the_callers_axes_or_figure_and_writes_nothing(cases, name, saved, tmp_path):
    kind, call = cases[name]
    mine = Figure(figsize=(12, 8), layout="constrained")
    target = mine.subplots() if kind == "ax" else mine
    out = call(**{kind: target})
    assert out is target
    axes = [target] if kind == "ax" else target.axes
    assert axes and sum(_drawn(a) for a in axes) > 0 and all(a.figure is mine for a in axes)
    assert not saved and not os.listdir(tmp_path)


@pytest.mark.parametrize("name", NAMES)
def test_draws_into_a_subfigure_and_writes_the_whole_figure_where_given_a_path(cases, name, saved, tmp_path):
    kind, call = cases[name]
    mine = Figure(figsize=(16, 8), layout="constrained")
    left, right = mine.subfigures(1, 2)
    left.subplots().plot([0, 1], [0, 1])
    target = right.subplots() if kind == "ax" else right
    out = call(tmp_path / "figure.png", **{kind: target})
    assert out is target
    drawn = [target] if kind == "ax" else target.axes
    assert drawn and sum(_drawn(a) for a in drawn) > 0 and len(left.axes) == 1
    assert saved == [mine] and (tmp_path / "figure.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("name", NAMES)
def test_a_figure_of_its_own_written_only_with_a_path(cases, name, saved, tmp_path):
    kind, call = cases[name]
    out = call()
    fig = out.figure if kind == "ax" else out
    assert isinstance(fig, Figure) and fig.axes
    assert not saved and not os.listdir(tmp_path)
    out = call(tmp_path / "own.png")
    assert len(saved) == 1 and (tmp_path / "own.png").stat().st_size > 1000


def test_a_notebooks_backend_is_left_alone(tmp_path):
    """With pyplot on the svg backend (as a notebook has its inline one), importing every plots
    module, writing a figure and drawing into the user's axes leave the backend as it was, and
    the package imports no pyplot of its own."""
    script = textwrap.dedent(f"""
        import importlib, sys
        import numpy as np
        import matplotlib
        import matplotlib.pyplot as plt
        before = matplotlib.get_backend()
        for name in {PLOT_MODULES!r}:
            importlib.import_module("pbrdf_cl.plots." + name)
        from pbrdf_cl.plots import paper
        tr = np.linspace(20.0, 65.0, 10)
        rows = [np.linspace(0.1, 0.5, 10), np.linspace(0.2, 0.6, 10)]
        paper.plot_fig5(sys.argv[1], {STEEL!r}, tr, (0.35, 0.65), rows)
        fig, ax = plt.subplots()
        assert paper.plot_fig5(None, {STEEL!r}, tr, (0.35, 0.65), rows, ax=ax) is ax and len(ax.lines) == 2
        print(before, matplotlib.get_backend(), plt.get_fignums())
    """)
    env = {**os.environ, "MPLBACKEND": "svg"}
    res = subprocess.run([sys.executable, "-c", script, str(tmp_path / "f.png")], capture_output=True, text=True,
                         env=env, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["svg", "svg", "[1]"], res.stdout  # the user's one figure, no other
    assert (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"


def test_design_result_names_the_compared_parameters():
    """The figure's and the summary's columns come from the result (plots reads no analysis code)."""
    des = pbrdf_cl.design(dict(n=1.6, k=2.139, sigma=0.5), {"theta_i": "10:70:20", "theta_r": "0:80:20"},
                          noise=0.005, n_measurements=8, backend="numpy")
    assert des.compared == list(des.free) + ["ks"] and "compared" not in des
    assert list(des.to_dataset().parameter_all.values) == des.compared
