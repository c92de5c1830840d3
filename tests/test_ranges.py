"""The one grammar of values, ranges, bounds and name=value items (pbrdf_cl.ranges): every form it
takes, every form it refuses with the right spelling in the message, the same values from the
command line, maps and sweep specs, and one-line errors from the CLI."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl import cli, ranges
from pbrdf_cl.analysis import maps
from pbrdf_cl.analysis.sweeps import SpecError, SweepSpec
from pbrdf_cl.compute import dense
from pbrdf_cl.ranges import RangeError

PACKAGE_ROOT = str(Path(pbrdf_cl.__file__).resolve().parent.parent)
ROOT = Path(__file__).resolve().parent.parent
FIXED = dict(theta_i=40.0, n=1.6, k=2.139, sigma=0.5)

ACCEPTED = [
    ("40", [40.0]),
    (" 40 ", [40.0]),
    ("-0.3", [-0.3]),
    ("1e-3", [1e-3]),
    ("20,30,45", [20.0, 30.0, 45.0]),
    ("45, 30 ,20", [45.0, 30.0, 20.0]),
    ("20:65:5", [20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0, 55.0, 60.0, 65.0]),
    ("60:20:-10", [60.0, 50.0, 40.0, 30.0, 20.0]),
    ("0:85:85", [0.0, 85.0]),
    ("-1:0:0.25", [-1.0, -0.75, -0.5, -0.25, 0.0]),
    ("1:3@2", [1.0, 3.0]),
    ("0:85@256", np.linspace(0.0, 85.0, 256)),
    ("80:10@8", [80.0, 70.0, 60.0, 50.0, 40.0, 30.0, 20.0, 10.0]),
    (" 0 : 1 @ 5 ", [0.0, 0.25, 0.5, 0.75, 1.0]),
]


@pytest.mark.parametrize("text,want", ACCEPTED, ids=[t for t, _ in ACCEPTED])
def test_every_accepted_form(text, want):
    got = ranges.parse_values(text)
    assert got.dtype == np.float64 and got.ndim == 1
    np.testing.assert_allclose(got, want, rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("text,count", [("0.05:1:0.05", 20), ("0:85:1.7", 51), ("0.1:0.7:0.1", 7), ("0:1:0.1", 11)])
def test_steps_that_land_on_the_stop_in_decimal_land_on_it_exactly(text, count):
    """Binary floating point misses 1 by 1e-16 in 0.05:1:0.05: the stop is hit, and is the last value."""
    start, stop, step = (float(p) for p in text.split(":"))
    got = ranges.parse_values(text)
    assert got.size == count and got[0] == start and got[-1] == stop
    np.testing.assert_allclose(np.diff(got), step, rtol=1e-9)


REFUSED = [
    # the count of the old `pbrdf-cl map` spelling, read as a step, is larger than the range
    ("0:85:256", "0:85:256: step 256 is larger than the range 0..85; for 256 values write 0:85@256"),
    ("0.05:1:8", "0.05:1:8: step 8 is larger than the range 0.05..1; for 8 values write 0.05:1@8"),
    ("0:1:1.5", "0:1:1.5: step 1.5 is larger than the range 0..1; write a step of at most 1, or 0:1@N for N values"),
    # steps that miss the stop
    ("0:10:3", "0:10:3: steps of 3 from 0 miss the stop 10 (the last is 9); write 0:9:3, or 0:10@3 for 3 values "
               "from 0 to 10"),
    ("0:85:16", "0:85:16: steps of 16 from 0 miss the stop 85 (the last is 80); write 0:80:16, or 0:85@16 for 16 "
                "values from 0 to 85"),
    ("0:1:0.3", "0:1:0.3: steps of 0.3 from 0 miss the stop 1 (the last is 0.9); write 0:0.9:0.3, or 0:1@4 for 4 "
                "values from 0 to 1"),
    ("60:20:-15", "60:20:-15: steps of -15 from 60 miss the stop 20 (the last is 30); write 60:30:-15, or 60:20@15 "
                  "for 15 values from 60 to 20"),
    # direction, zero step, equal ends
    ("60:20:5", "60:20:5: the step 5 goes up from 60 but the stop 20 is below it; write 60:20:-5 to count down, "
                "or 20:60:5"),
    ("20:60:-5", "20:60:-5: the step -5 goes down from 20 but the stop 60 is above it; write 20:60:5"),
    ("0:1:0", "0:1:0: the step must not be 0; write 0:1:STEP, or 0:1@N for N values"),
    ("40:40:5", "40:40:5: start and stop are both 40; for the single value write 40"),
    ("40:40@3", "40:40@3: start and stop are both 40; for the single value write 40"),
    # counts
    ("0:85@1", "0:85@1: count 1 is not an integer >= 2; write 0:85@N with N >= 2; for one value write 0"),
    ("0:85@0", "0:85@0: count 0 is not an integer >= 2; write 0:85@N with N >= 2"),
    ("0:85@2.5", "0:85@2.5: count 2.5 is not an integer >= 2; write 0:85@N with N >= 2"),
    ("0:85@", "0:85@: no count after '@'; write 0:85@N with N >= 2"),
    ("0:85:5@3", "0:85:5@3: give a step (0:85:5) or a count (0:85@3), not both"),
    ("0@3", "0@3: a count range is start:stop@count, e.g. 0:85@256"),
    # shapes
    ("0:85", "0:85: a range needs a step or a count; write 0:85:STEP (ends included) or 0:85@N for N values"),
    ("0:85:5:1", "0:85:5:1: too many ':'; write start:stop:step (20:65:5) or start:stop@count (0:85@256)"),
    ("20,30:40", "20,30:40: a list holds numbers only and a range stands alone; write a list (20,30,45) or one "
                 "range (20:65:5, 0:85@256)"),
    ("20,,30", "20,,30: empty item in the list; write 20,30"),
    ("20,30,", "20,30,: empty item in the list; write 20,30"),
    ("", ": empty; write a number (40), a list (20,30,45), start:stop:step (20:65:5) or start:stop@count (0:85@256)"),
    # numbers
    ("forty", "forty: value 'forty' is not a number; write a number (40), a list (20,30,45), start:stop:step "
              "(20:65:5) or start:stop@count (0:85@256)"),
    ("20:x:5", "20:x:5: stop 'x' is not a number; write a number (40)"),
    ("20,3o,45", "20,3o,45: list item '3o' is not a number"),
    ("nan", "nan: value 'nan' is not a finite number; write a finite number such as 40"),
    ("0:inf:1", "0:inf:1: stop 'inf' is not a finite number"),
]


@pytest.mark.parametrize("text,message", REFUSED, ids=[t or "empty" for t, _ in REFUSED])
def test_every_refused_form_names_the_text_and_the_right_spelling(text, message):
    with pytest.raises(RangeError) as err:
        ranges.parse_values(text, "--theta-r")
    msg = str(err.value)
    assert msg.startswith(f"--theta-r {message}"), msg
    assert "\n" not in msg and isinstance(err.value, ValueError)


@pytest.mark.parametrize("text", ["0:85:256", "0:10:3", "60:20:5", "0:85@1", "40:40:5", "20,,30", "0:1:0.3"])
def test_every_suggested_spelling_is_accepted(text):
    """The spellings a refusal offers are themselves valid texts of the grammar."""
    with pytest.raises(RangeError) as err:
        ranges.parse_values(text)
    tail = str(err.value).split("write ", 1)[1]
    suggested = [w.strip(",;") for w in tail.split()
                 if any(c.isdigit() for c in w) and "N" not in w and "STEP" not in w]
    assert suggested
    for s in suggested:
        assert ranges.parse_values(s).size >= 1


def test_bounds():
    assert ranges.parse_bounds("1:3") == (1.0, 3.0)
    assert ranges.parse_bounds(" -1 : -0.5 ") == (-1.0, -0.5)
    for text, message in [("1-3", "1-3: bounds are low:high, two numbers; write n=1:3"),
                           ("-1--0.5", "-1--0.5: bounds are low:high, two numbers; write n=-1:-0.5"),
                           ("1:3:1", "1:3:1: bounds are low:high, two numbers; write n=1:3"),
                           ("1:3@4", "1:3@4: bounds are low:high, two numbers; write n=LOW:HIGH"),
                           ("3:1", "3:1: low 3 is above high 1; write n=1:3"),
                           ("2:2", "2:2: low and high are both 2; give low < high, or hold n fixed"),
                           ("1:x", "1:x: high 'x' is not a number"),
                           ("1:inf", "1:inf: high 'inf' is not a finite number")]:
        with pytest.raises(RangeError) as err:
            ranges.parse_bounds(text, "--bounds", name="n")
        assert str(err.value).startswith(f"--bounds {message}"), str(err.value)


def test_name_value_items():
    names = dense.AXES
    assert ranges.parse_assignment("theta_i=40", names) == ("theta_i", 40.0)
    name, v = ranges.parse_assignment(" theta_r = 0:85@18 ", names, "values")
    assert name == "theta_r" and np.array_equal(v, np.linspace(0, 85, 18))
    assert ranges.parse_assignment("n=1:3", names, "bounds") == ("n", (1.0, 3.0))
    assert ranges.parse_assignments(["theta_i=40", "n=1.6"], names) == {"theta_i": 40.0, "n": 1.6}
    assert ranges.parse_assignments(None, names) == {}
    cases = [
        (("sigmaa=0.4", names), "--fix sigmaa=0.4: unknown name 'sigmaa'; did you mean sigma=0.4?"),
        (("theta-r=0:85@4", names, "values"), "--fix theta-r=0:85@4: unknown name 'theta-r'; did you mean "
                                              "theta_r=0:85@4?"),
        (("Theta_I=40", names), "--fix Theta_I=40: unknown name 'Theta_I'; did you mean theta_i=40?"),
        (("alpha=1", names), "--fix alpha=1: unknown name 'alpha'; names are theta_i, theta_r, phi, n, k, sigma, "
                             "ks, kd, c"),
        (("k", names), "--fix k: not of the form name=value; write k=VALUE"),
        (("zz", names), "--fix zz: not of the form name=value; write NAME=VALUE with NAME one of theta_i, "),
        (("=3", names), "--fix =3: not of the form name=value; write NAME=VALUE"),
        (("k=", names), "--fix k=: no value after '='; write k=VALUE"),
        (("sigma=0.1:0.5", names), "--fix sigma=0.1:0.5: one number is expected here; write sigma=0.1"),
        (("sigma=0.1,0.5", names), "--fix sigma=0.1,0.5: one number is expected here; write sigma=0.1"),
        (("theta_r=0:85:256", names, "values"), "--fix theta_r=0:85:256: step 256 is larger than the range 0..85; "
                                                "for 256 values write 0:85@256"),
        (("n=1-3", names, "bounds"), "--fix n=1-3: bounds are low:high, two numbers; write n=1:3"),
    ]
    for args, message in cases:
        with pytest.raises(RangeError) as err:
            ranges.parse_assignment(*args, where="--fix")
        assert str(err.value).startswith(message), str(err.value)
    with pytest.raises(RangeError, match=r"^--fix n=2: n is given twice; give it once$"):
        ranges.parse_assignments(["n=1.6", "n=2"], names, where="--fix")
    with pytest.raises(ValueError, match="kind must be one of value, values, bounds"):
        ranges.parse_assignment("n=1", names, "range")


def test_name_value_items_checked_against_the_model_domain():
    assert ranges.parse_assignment("k=0", dense.AXES, check=True) == ("k", 0.0)
    for item, kind, message in [("k=-1", "value", "--fix k=-1: k must be >= 0, got -1.0"),
                                ("theta_r=0:95:5", "values", "--fix theta_r=0:95:5: theta_r must be in [0, 90) "
                                                             "degrees, got 90.0"),
                                ("sigma=0:1@5", "values", "--fix sigma=0:1@5: sigma must be > 0, got 0.0")]:
        with pytest.raises(RangeError) as err:
            ranges.parse_assignment(item, dense.AXES, kind, "--fix", check=True)
        assert str(err.value).startswith(message), str(err.value)


# ---------------------------------------------------------------------------------------------
# the command line, maps and sweep specs read the same text the same way

def _sweep_axis(text):
    return SweepSpec(dict(axes=dict(theta_r=text), fixed=FIXED)).axes["theta_r"]


SAME = ["40", "20,30,45", "20:65:5", "0.05:1:0.05", "60:20:-5", "0:85@256", "10:80@141", "0:85:1.7"]


@pytest.mark.parametrize("text", SAME)
def test_cli_map_and_sweep_spec_give_the_same_values(text):
    from_cli = cli.parse_values("--theta-r", text)
    name, from_map = maps.parse_axis("--x", f"theta_r={text}")
    from_spec = _sweep_axis(text)
    assert name == "theta_r"
    np.testing.assert_array_equal(from_map, from_cli)
    np.testing.assert_array_equal(from_spec, from_cli)
    np.testing.assert_array_equal(from_cli, ranges.parse_values(text))


@pytest.mark.parametrize("text,table", [("0:85@256", {"start": 0, "stop": 85, "num": 256}),
                                        ("20:65:5", {"start": 20, "stop": 65, "step": 5}),
                                        ("60:20:-5", {"start": 60, "stop": 20, "step": -5}),
                                        ("0.05:1:0.05", {"start": 0.05, "stop": 1.0, "step": 0.05})])
def test_a_sweep_spec_range_table_is_its_string(text, table):
    np.testing.assert_array_equal(_sweep_axis(table), _sweep_axis(text))


@pytest.mark.parametrize("text", ["0:85:256", "0:10:3", "60:20:5", "0:85@1", "0:85", "20,,30", "nan"])
def test_cli_map_and_sweep_spec_refuse_the_same_text_for_the_same_reason(text):
    reasons = []
    with pytest.raises(RangeError) as err:
        cli.parse_values("--theta-r", text)
    reasons.append(str(err.value).removeprefix(f"--theta-r {text}: "))
    with pytest.raises(RangeError) as err:
        maps.parse_axis("--x", f"theta_r={text}")
    reasons.append(str(err.value).removeprefix(f"--x theta_r={text}: "))
    with pytest.raises(SpecError) as err:
        _sweep_axis(text)
    reasons.append(str(err.value).removeprefix(f'axes.theta_r = "{text}": '))
    assert reasons[0] == reasons[1] == reasons[2], reasons


def test_the_example_spec_and_the_guides_examples_parse():
    spec = pbrdf_cl.load_spec(ROOT / "examples" / "sweep_sigma_theta.toml")
    np.testing.assert_array_equal(spec.axes["theta_r"], np.linspace(0, 85, 86))
    np.testing.assert_array_equal(spec.axes["sigma"], np.linspace(0.05, 1.0, 64))
    assert "pbrdf-cl map --x theta_r=0:85@256 --y sigma=0.05:1@256" in (ROOT / "docs/guide/paper.md").read_text()
    page = (ROOT / "docs/guide/cli.md").read_text()
    section = page.split("## Ranges and name=value", 1)[1].split("\n## ", 1)[0]
    assert "pbrdf-cl: error: --x " in section and "pbrdf-cl: error: axes." in section
    for line in section.splitlines():  # the guide's sample errors are what the parser says
        if line.startswith("pbrdf-cl: error: --x "):
            item = line.split()[3].rstrip(":")
            with pytest.raises(RangeError) as err:
                maps.parse_axis("--x", item)
            assert line == f"pbrdf-cl: error: {err.value}"
        elif line.startswith("pbrdf-cl: error: axes."):
            text = line.split('"')[1]
            with pytest.raises(SpecError) as err:
                SweepSpec(dict(axes=dict(sigma=text), fixed=dict(theta_i=40, theta_r=30, n=1.6, k=2.1)))
            assert line == f"pbrdf-cl: error: {err.value}"


# ---------------------------------------------------------------------------------------------
# the command line: a refused text is one line and exit status 1, never a traceback

def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "pbrdf_cl", *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd, env=dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=PACKAGE_ROOT))


EVAL = ["eval", "--theta-i", "40", "--n", "1.6", "--k", "2.139", "--sigma", "0.5", "--backend", "numpy"]
MAP = ["--fix", "theta_i=40", "n=1.6", "k=2.139", "--backend", "numpy"]
CSV = str(ROOT / "examples" / "steel_435nm.csv")
CLI_REFUSED = [
    ([*EVAL, "--theta-r", "0:85:256"], "--theta-r 0:85:256: step 256 is larger than the range 0..85; for 256 values "
                                       "write 0:85@256"),
    ([*EVAL, "--theta-r", "20:65:4"], "--theta-r 20:65:4: steps of 4 from 20 miss the stop 65 (the last is 64); "
                                      "write 20:64:4, or 20:65@4 for 4 values from 20 to 65"),
    ([*EVAL, "--theta-r", "20:65"], "--theta-r 20:65: a range needs a step or a count"),
    (["map", "--x", "theta_r=0:85:256", "--y", "sigma=0.05:1@8", *MAP],
     "--x theta_r=0:85:256: step 256 is larger than the range 0..85; for 256 values write 0:85@256"),
    (["map", "--x", "theta_r=0:85@64", "--y", "sigma=0.05:1:8", *MAP],
     "--y sigma=0.05:1:8: step 8 is larger than the range 0.05..1; for 8 values write 0.05:1@8"),
    (["map", "--x", "theta_r=0:85@64", "--y", "sigmaa=0.05:1@8", *MAP],
     "--y sigmaa=0.05:1@8: unknown name 'sigmaa'; did you mean sigma=0.05:1@8?"),
    (["map", "--x", "theta_r=0:85@64", "--y", "sigma=0.05:1@8", "--fix", "theta_i=40", "n=1.6", "kk=2"],
     "--fix kk=2: unknown name 'kk'; did you mean k=2?"),
    (["fit", CSV, "--bounds", "n=1-3"], "--bounds n=1-3: bounds are low:high, two numbers; write n=1:3"),
    (["fit", CSV, "--bounds", "n=3:1"], "--bounds n=3:1: low 3 is above high 1; write n=1:3"),
    (["fit", CSV, "--fix", "sigmaa=0.45"], "--fix sigmaa=0.45: unknown name 'sigmaa'; did you mean sigma=0.45?"),
    (["fit", CSV, "--fix", "sigma=-1"], "--fix sigma=-1: sigma must be > 0, got -1.0"),
    (["fit", CSV, "--fix", "theta_i=40"], "--fix theta_i=40: unknown name 'theta_i'; names are n, k, sigma, kd, c, ks"),
]


@pytest.mark.parametrize("args,message", CLI_REFUSED, ids=[f"{a[0]}-{i}" for i, (a, _) in enumerate(CLI_REFUSED)])
def test_cli_refuses_with_one_line_and_exit_status_1(args, message, tmp_path):
    proc = run_cli(*args, cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"pbrdf-cl: error: {message}"), proc.stderr
    assert proc.stdout == "" and not (tmp_path / "map.png").exists()


def test_cli_sweep_spec_refusal_is_one_line(tmp_path, capsys):
    spec = tmp_path / "bad.toml"
    spec.write_text('[axes]\ntheta_r = "0:85:256"\n[fixed]\ntheta_i = 40\nn = 1.6\nk = 2.1\nsigma = 0.5\n')
    assert cli.main(["sweep", str(spec), "--out", str(tmp_path / "s.zarr"), "--backend", "numpy"]) == 1
    assert capsys.readouterr().err == ('pbrdf-cl: error: axes.theta_r = "0:85:256": step 256 is larger than the '
                                       "range 0..85; for 256 values write 0:85@256\n")
    assert not (tmp_path / "s.zarr").exists()


def test_cli_eval_and_map_take_the_same_ranges(tmp_path):
    """eval --theta-r TEXT, map --x theta_r=TEXT and a spec's theta_r = "TEXT": the same points."""
    text = "10:80@8"
    proc = run_cli(*EVAL, "--theta-r", text, "--json")
    assert proc.returncode == 0, proc.stderr
    from_eval = [r["theta_r"] for r in json.loads(proc.stdout)["rows"]]
    npz = tmp_path / "m.npz"
    proc = run_cli("map", "--x", f"theta_r={text}", "--y", "sigma=0.1:0.5:0.2", *MAP, "--out", str(tmp_path / "m.png"),
                   "--npz", str(npz))
    assert proc.returncode == 0, proc.stderr
    d = np.load(npz)
    np.testing.assert_array_equal(d["x"], from_eval)
    np.testing.assert_allclose(d["y"], [0.1, 0.3, 0.5], rtol=1e-15)
    np.testing.assert_array_equal(_sweep_axis(text), from_eval)
    np.testing.assert_array_equal(from_eval, [10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0])
