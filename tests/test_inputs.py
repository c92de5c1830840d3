"""The measurement inputs users have: CSVs as spreadsheets and instruments write them, dicts with
names in any case, DataFrames, xarray Datasets, and memory budgets given as sizes."""
import contextlib
import re
import warnings

import numpy as np
import pytest
import xarray as xr

import pbrdf_cl
from pbrdf_cl import ranges
from pbrdf_cl.analysis import sweeps
from pbrdf_cl.compute import dense
from pbrdf_cl.io.measurements import DataWarning, as_measurements, read_csv

from conftest import requires_opencl

TI = np.repeat([30.0, 40.0, 50.0], 4)
TR = np.tile([20.0, 30.0, 40.0, 50.0], 3)
STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=1.0, kd=0.15, c=-0.3)
DOP = pbrdf_cl.dop(TI, TR, 180.0, backend="numpy", **STEEL)


def write(tmp_path, text, name="d.csv", encoding="utf-8"):
    p = tmp_path / name
    p.write_bytes(text.encode(encoding))
    return p


@contextlib.contextmanager
def no_warning():
    """A DataWarning inside is an error."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        yield


# --- CSV files ----------------------------------------------------------------------------------

@pytest.mark.parametrize("name,text", [
    ("byte-order mark", "\ufefftheta_i,theta_r,dop\n40,30,0.1\n40,35,0.2\n"),
    ("semicolons", "theta_i;theta_r;dop\n40;30;0.1\n40;35;0.2\n"),
    ("semicolons, decimal commas", "theta_i;theta_r;dop\n40;30;0,1\n40;35;0,2\n"),
    ("tabs", "theta_i\ttheta_r\tdop\n40\t30\t0.1\n40\t35\t0.2\n"),
    ("runs of spaces", "  theta_i   theta_r  dop\n 40  30    0.1\n40 35 0.2\n"),
    ("quoted", '"theta_i","theta_r","dop"\n"40","30","0.1"\n40,35,0.2\n'),
    ("single-quoted, spaced", "'theta_i', 'theta_r', 'dop'\n40, 30, 0.1\n40, 35, 0.2\n"),
    ("upper case", "THETA_I,Theta_R,DOP\n40,30,0.1\n40,35,0.2\n"),
    ("trailing separators", "theta_i,theta_r,dop,\n40,30,0.1,\n40,35,0.2\n"),
    ("CRLF, comments", "# from the goniometer\r\ntheta_i,theta_r,dop # header\r\n40,30,0.1\r\n\r\n40,35,0.2 # ok\r\n"),
    ("old Mac line ends", "theta_i,theta_r,dop\r40,30,0.1\r40,35,0.2\r"),
    ("Excel's sep= line", "sep=;\ntheta_i;theta_r;dop\n40;30;0,1\n40;35;0,2\n"),
])
def test_csv_forms_read_the_same_values(tmp_path, name, text):
    with no_warning():
        m = read_csv(write(tmp_path, text))
    np.testing.assert_array_equal(m.theta_i, [40.0, 40.0])
    np.testing.assert_array_equal(m.theta_r, [30.0, 35.0])
    np.testing.assert_array_equal(m.dop, [0.1, 0.2])
    np.testing.assert_array_equal(m.phi, [180.0, 180.0])
    assert m.ignored == ()


def test_utf16_with_bom_and_line_numbers_after_a_bom(tmp_path):
    m = read_csv(write(tmp_path, "theta_i\ttheta_r\tdop\n40\t30\t0.1\n", encoding="utf-16"))
    assert m.dop.tolist() == [0.1]
    # line numbers count from the first line, the mark not being a line
    with pytest.raises(ValueError, match=r"d\.csv, line 3: dop = 1\.5 is not in \[0, 1\]$"):
        read_csv(write(tmp_path, "\ufefftheta_i,theta_r,dop\n40,30,0.1\n40,35,1.5\n"))
    # Latin-1 bytes (a degree sign in a comment) do not stop the reading
    m = read_csv(write(tmp_path, "# angles in \u00b0\ntheta_i,theta_r,dop\n40,30,0.1\n", encoding="latin-1"))
    assert m.dop.tolist() == [0.1] and m.lines.tolist() == [3]


def test_extra_columns_are_ignored_with_a_warning_naming_them(tmp_path):
    p = write(tmp_path, "# note\ntheta_i,theta_r,Wavelength,dop,sample,dop_sd\n40,30,435nm,0.1,A,0.01\n"
                        "40,35,435nm,0.2,B,0.01\n")
    with pytest.warns(DataWarning) as rec:
        m = read_csv(p)
    assert len(rec) == 1
    msg = str(rec[0].message)
    assert "\n" not in msg
    assert msg.startswith(f"{p}, line 2: ignored columns 'Wavelength', 'sample', 'dop_sd' (did you mean 'dop_std'?)")
    assert m.ignored == ("Wavelength", "sample", "dop_sd")
    assert m.dop.tolist() == [0.1, 0.2] and m.dop_std is None  # the text columns were not parsed


def test_unnamed_columns_are_named_by_position_only_when_they_hold_values(tmp_path):
    with pytest.warns(DataWarning, match=r"ignored column 'column 4 \(unnamed\)'"):
        m = read_csv(write(tmp_path, "theta_i,theta_r,dop,,\n40,30,0.1,7,\n"))
    assert m.ignored == ("column 4 (unnamed)",)


def test_s0_is_f00_in_any_case(tmp_path):
    m = read_csv(write(tmp_path, "theta_i,theta_r,dop,S0\n40,30,0.1,0.5\n"))
    assert m.f00.tolist() == [0.5]
    with pytest.raises(ValueError, match="line 1: give f00 or s0, not both"):
        read_csv(write(tmp_path, "theta_i,theta_r,dop,F00,s0\n40,30,0.1,0.5,0.5\n"))


@pytest.mark.parametrize("text,pattern", [
    ("theta_i,theta_r,dop,DOP\n40,30,0.1,0.1\n", r"line 1: 'dop' and 'DOP' name the same column; give it once$"),
    ("theta_i (deg),theta_r,dop\n40,30,0.1\n",
     r"line 1: missing column 'theta_i' \(the columns are .*\); the column 'theta_i \(deg\)' is not one of these"),
    ("theta_i,theta_r,dop\n40;30;0.1\n",
     r"line 2: 1 value for 3 columns \(the header is separated by commas, this line by semicolons\)$"),
    ("theta_i;theta_r;dop\n40;;0.1\n", r"line 2: theta_r is empty$"),
    ('"theta_i";"theta_r";"Dop"\n40;30;abc\n', r"line 2: Dop = 'abc' is not a number$"),
    ("theta_i,theta_r,dop\n40,30,0,1\n", r"line 2: 4 values for 3 columns$"),  # a decimal comma with commas
    ("theta_i\ttheta_r\tdop\n40\t30\t0.1\n40\t95\t0.1\n", r"line 3: theta_r = 95\.0 is not in \[0, 90\) degrees$"),
    ("# no header\n40,30,0.1\n", r"line 2: the first line holds numbers, not column names; start the file with a "
                                  r"header line such as theta_i,theta_r,dop$"),
])
def test_csv_errors_are_one_line_naming_file_line_and_column(tmp_path, text, pattern):
    p = write(tmp_path, text)
    with pytest.raises(ValueError) as exc:
        read_csv(p)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(str(p))
    assert re.search(pattern, msg), msg


# --- dicts, DataFrames, Datasets -----------------------------------------------------------------

def test_dict_keys_in_any_case():
    with no_warning():
        m = as_measurements({"Theta_I": TI, "THETA_R": TR, "DOP": DOP, "Phi": 180.0, "DOP_STD": 0.002, "S0": 1.0})
    np.testing.assert_array_equal(m.dop, DOP)
    np.testing.assert_array_equal(m.theta_r, TR)
    assert m.dop_std.tolist() == [0.002] * TI.size and m.f00.tolist() == [1.0] * TI.size
    with pytest.raises(ValueError, match=r"^data: 'dop' and 'DOP' name the same column; give it once$"):
        as_measurements({"theta_i": TI, "theta_r": TR, "dop": DOP, "DOP": DOP})
    with pytest.raises(ValueError, match=r"^data: give f00 or s0, not both$"):
        as_measurements({"theta_i": TI, "theta_r": TR, "dop": DOP, "F00": 1.0, "s0": 1.0})
    with pytest.raises(ValueError, match=r"^data: missing column 'theta_r' .*the column 'theta_rr' is not one"):
        as_measurements({"theta_i": TI, "theta_rr": TR, "dop": DOP})


def test_dict_extra_keys_are_ignored_with_a_warning():
    with pytest.warns(DataWarning, match=r"^data: ignored column 'wavelength': not an input of the model"):
        m = as_measurements({"theta_i": TI, "theta_r": TR, "dop": DOP, "wavelength": 435.0})
    assert m.ignored == ("wavelength",)


class Column:
    """A column with only ``__array__`` (no to_numpy)."""

    def __init__(self, values):
        self.values = np.asarray(values)

    def __array__(self, dtype=None, copy=None):
        return self.values if dtype is None else self.values.astype(dtype)


class Frame:
    """The least a DataFrame needs to be read: ``columns`` and ``frame[name]``."""

    def __init__(self, **cols):
        self._cols = {k: Column(v) for k, v in cols.items()}
        self.columns = list(cols)

    def __getitem__(self, name):
        return self._cols[name]


def test_a_duck_typed_data_frame_is_read():
    with pytest.warns(DataWarning, match="ignored column 'Sample'"):
        m = as_measurements(Frame(Theta_i=TI, Theta_r=TR, DOP=DOP, Sample=["a"] * TI.size))
    np.testing.assert_array_equal(m.dop, DOP)
    np.testing.assert_array_equal(m.theta_i, TI)


def test_pandas_data_frames_columns_and_index_levels():
    pd = pytest.importorskip("pandas")
    df = pd.DataFrame({"Theta_I": TI, "theta_r": TR, "DOP": DOP, "dop_std": 0.002})
    with no_warning():
        m = as_measurements(df)
    np.testing.assert_array_equal(m.dop, DOP)
    assert m.dop_std.tolist() == [0.002] * TI.size
    with no_warning():
        m = as_measurements(df.set_index(["Theta_I", "theta_r"]))
    np.testing.assert_array_equal(m.theta_i, TI)
    np.testing.assert_array_equal(m.theta_r, TR)
    bad = df.astype({"DOP": "Float64"})
    bad.loc[3, "DOP"] = pd.NA
    with pytest.raises(ValueError, match=r"^data, row 3: dop is nan; every value must be a finite number$"):
        as_measurements(bad)


def test_xarray_datasets_flat_and_gridded():
    flat = xr.Dataset({"theta_i": ("point", TI), "theta_r": ("point", TR), "DOP": ("point", DOP)},
                      attrs=dict(sample="steel"))
    with no_warning():
        m = as_measurements(flat)
    np.testing.assert_array_equal(m.dop, DOP)
    # a gridded Dataset (dop over theta_i x theta_r, coordinates as the angles) is flattened
    ti, tr = np.array([30.0, 40.0, 50.0]), np.array([20.0, 30.0, 40.0, 50.0])
    grid = xr.Dataset({"dop": (("theta_i", "theta_r"), DOP.reshape(3, 4).copy())},
                      coords={"theta_i": ti, "theta_r": tr, "wavelength": 435.0})
    with pytest.warns(DataWarning, match="ignored column 'wavelength'"):
        m = as_measurements(grid)
    np.testing.assert_array_equal(m.theta_i, TI)
    np.testing.assert_array_equal(m.theta_r, TR)
    np.testing.assert_array_equal(m.dop, DOP)
    grid["dop"][1, 2] = 1.5
    with pytest.raises(ValueError, match=r"^data, at theta_i=40, theta_r=40: dop = 1\.5 is not in \[0, 1\]$"):
        as_measurements(grid.drop_vars("wavelength"))


def test_unsupported_data_names_its_type():
    with pytest.raises(ValueError, match=r"^data must be a CSV path, .* got list$"):
        as_measurements([1, 2, 3])


def test_fit_compare_and_objective_take_data_frames_and_datasets():
    pd = pytest.importorskip("pandas")
    frame = pd.DataFrame({"THETA_I": TI, "theta_r": TR, "Dop": DOP})
    ds = xr.Dataset({"theta_i": ("m", TI), "theta_r": ("m", TR), "DOP": ("m", DOP)})
    grid = dict(n=np.linspace(1.2, 2.0, 5), k=np.linspace(1.5, 2.5, 5), sigma=0.5, kd=0.15, c=-0.3)
    ref = pbrdf_cl.objective(dict(theta_i=TI, theta_r=TR, dop=DOP), grid=grid, dtype="float64", backend="numpy")
    for data in (frame, ds):
        got = pbrdf_cl.objective(data, grid=grid, dtype="float64", backend="numpy")
        np.testing.assert_array_equal(got.sse.values, ref.sse.values)
    fixed = dict(sigma=0.5, kd=0.15, c=-0.3)
    a = pbrdf_cl.fit(frame, fixed=fixed, backend="numpy")
    b = pbrdf_cl.fit(ds, fixed=fixed, backend="numpy")
    assert a.x == pytest.approx(b.x) and a.sse < 1e-10
    both = pbrdf_cl.compare_models(ds, fixed=fixed, backend="numpy")
    assert both["six-param"].x == pytest.approx(a.x) and both["specular"].sse > a.sse


# --- memory budgets --------------------------------------------------------------------------------

@pytest.mark.parametrize("text,nbytes", [("64 MiB", 64 << 20), ("1 GB", 10 ** 9), ("1.5gib", 3 << 29),
                                         ("4096", 4096), (" 2 KiB ", 2048), (65536, 65536), (1e6, 10 ** 6),
                                         (np.int64(50_000), 50_000)])
def test_sizes(text, nbytes):
    assert ranges.parse_bytes("memory_budget", text) == nbytes
    assert sweeps.parse_bytes("memory_budget", text) == nbytes  # the sweep's parser is the same one


@pytest.mark.parametrize("value,message", [
    ("lots", "memory_budget: 'lots' is not a size such as 268435456, \"256 MiB\" or \"1 GB\""),
    ("64 MB/s", "memory_budget: '64 MB/s' is not a size"),
    (0, "memory_budget: must be > 0 bytes, got 0"),
    (-5, "memory_budget: must be > 0 bytes, got -5"),
    (0.5, "memory_budget: 0.5 is not a size"),
    (None, "memory_budget: None is not a size"),
    (True, "memory_budget: True is not a size"),
])
def test_bad_sizes_are_one_line_naming_memory_budget(value, message):
    for call in (lambda: pbrdf_cl.grid({"theta_r": [10.0, 20.0]}, dict(theta_i=40, n=1.6, k=2, sigma=0.5),
                                       backend="numpy", memory_budget=value),
                 lambda: pbrdf_cl.reduce_grid({"theta_r": [10.0, 20.0], "sigma": [0.3, 0.5]},
                                              dict(theta_i=40, n=1.6, k=2), over="sigma", backend="numpy",
                                              memory_budget=value),
                 lambda: pbrdf_cl.objective(dict(theta_i=TI, theta_r=TR, dop=DOP), grid=dict(n=[1.5, 1.6], k=2.0,
                                            sigma=0.5), backend="numpy", memory_budget=value)):
        with pytest.raises(ValueError) as exc:
            call()
        assert str(exc.value).startswith(message) and "\n" not in str(exc.value)
    with pytest.raises(sweeps.SpecError, match="^" + message.replace("(", r"\(").replace(")", r"\)")):
        sweeps.parse_bytes("memory_budget", value)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("opencl", marks=requires_opencl)])
def test_memory_budget_strings_through_grid_reduce_and_objective(backend):
    axes = {"theta_r": np.linspace(0, 85, 40), "sigma": np.linspace(0.1, 1, 30)}
    fixed = dict(theta_i=40.0, n=1.6, k=2.1)
    whole = dense.grid(axes, fixed, dtype="float64", backend=backend)
    # "48 KiB" forces chunks; the same values as in one piece, and as with the integer budget
    for budget in ("48 KiB", 48 << 10, "1 GB"):
        np.testing.assert_array_equal(dense.grid(axes, fixed, dtype="float64", backend=backend,
                                                 memory_budget=budget).values, whole.values)
    red = dense.reduce_grid(axes, fixed, over="sigma", dtype="float64", backend=backend)
    red_s = dense.reduce_grid(axes, fixed, over="sigma", dtype="float64", backend=backend, memory_budget="48 KiB")
    np.testing.assert_array_equal(red_s["min"].values, red["min"].values)
    # a budget too small is still refused with the number of bytes it came to
    with pytest.raises(ValueError, match=r"memory_budget=200 bytes is too small|more than half of memory_budget=200"):
        dense.grid(axes, fixed, backend=backend, memory_budget="200 B")
    data = dict(theta_i=TI, theta_r=TR, dop=DOP)
    grid = dict(n=np.linspace(1.2, 2.0, 9), k=np.linspace(1.5, 2.5, 9), sigma=np.linspace(0.3, 0.7, 5))
    ref = pbrdf_cl.objective(data, grid=grid, dtype="float64", backend=backend)
    small = pbrdf_cl.objective(data, grid=grid, dtype="float64", backend=backend, memory_budget="40 KB")
    np.testing.assert_array_equal(small.sse.values, ref.sse.values)
