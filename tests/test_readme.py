"""Docs that cannot rot: every code block of the README runs (Python in order in one namespace;
shell commands through ``python -m pbrdf_cl`` in a scratch folder), and the example sweep spec
runs with each of its optional sections enabled.

Not run, and why: the two fresh-machine commands at the top (they create a virtual environment and
install the package: ``.ci/run`` runs the second on a clean checkout, and ``tests/test_paper.py``
the main job's ``pbrdf-cl reproduce``); synopsis lines (``[--option ...]``), whose options are checked
against the parser instead; commands that need a dask cluster (``--workers``, ``--scheduler``,
``dask ...``; tests/test_sweep_faults.py runs ``--workers 2``) or a file named only as an example
(``spec.toml``, ``data.csv``), which are parsed, not run; ``text`` blocks (sample output).
"""
import argparse
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from pbrdf_cl import cli
from pbrdf_cl.explore.sweeps import load_spec

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()
PACKAGE_ROOT = str(ROOT)


def blocks(lang):
    """(line number, text) of the README's fenced blocks in ``lang``."""
    out, lines, inside, start = [], README.splitlines(), None, 0
    for i, line in enumerate(lines, 1):
        if line.startswith("```"):
            if inside is None:
                inside, start, body = line[3:].strip(), i, []
            else:
                if inside == lang:
                    out.append((start, "\n".join(body)))
                inside = None
            continue
        if inside is not None:
            body.append(line)
    return out


def shell_commands():
    """Every command of the bash blocks: (line, argv, run?)."""
    found = []
    for start, text in blocks("bash"):
        joined = re.sub(r"\\\n\s*", " ", text)
        for line in joined.splitlines():
            line = re.split(r"\s{2,}#", line)[0].strip()
            if not line or line.startswith("#"):
                continue
            found.append((start, line))
    return found


@pytest.fixture
def scratch(tmp_path, monkeypatch):
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    return tmp_path


def test_every_python_block_runs_in_order(scratch):
    py = blocks("python")
    assert len(py) >= 5
    namespace = {"__name__": "__readme__"}
    for start, text in py:
        try:
            exec(compile(text, f"README.md:{start}", "exec"), namespace)
        except Exception as exc:  # noqa: BLE001 - name the block
            raise AssertionError(f"README.md block at line {start} fails: {type(exc).__name__}: {exc}") from exc
    assert namespace["res"].complete  # the last block's sweep


def _options_of(command):
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    return {o for a in sub._actions for o in a.option_strings}


def test_every_shell_command_runs_or_parses(scratch):
    commands = shell_commands()
    ran = 0
    for start, line in commands:
        if "pip install" in line or line.startswith("dask "):
            continue  # see the module docstring
        argv = shlex.split(line)
        assert argv[0] == "pbrdf-cl", (start, line)
        options = {t.split("=")[0] for t in re.findall(r"--[a-z][a-z0-9-]*", line)}
        if argv[1] != "bench":
            unknown = options - _options_of(argv[1])
            assert not unknown, f"README.md line {start}: {argv[1]} has no option {sorted(unknown)}"
        if "[" in line or re.search(r"--workers|--scheduler|spec\.toml|data\.csv|bench", line):
            continue  # a synopsis or an example name: parsed above, not run
        proc = subprocess.run([sys.executable, "-m", "pbrdf_cl", *argv[1:]], capture_output=True, text=True,
                              timeout=600, env=dict(os.environ, PYTHONPATH=PACKAGE_ROOT))
        assert proc.returncode == 0, f"README.md line {start}: {line}\n{proc.stderr[-2000:]}"
        ran += 1
    assert ran >= 3


def _optional_variants(text):
    """The example spec, and one variant per commented optional line or section, uncommented."""
    yield "as shipped", text
    if "# points = " in text:
        lines = [ln for ln in text.splitlines() if not re.match(r"^(theta_i|theta_r) = \d+$", ln)]
        yield "chunks by points", "\n".join(ln.replace("# points = ", "points = ") for ln in lines)
    if "# [reduce]" in text:
        yield "reduce", re.sub(r"^# (\[reduce\]|over = )", r"\1", text, flags=re.M)


def test_the_example_spec_runs_with_each_optional_section(tmp_path):
    import pbrdf_cl
    text = (ROOT / "examples" / "sweep_sigma_theta.toml").read_text()
    variants = list(_optional_variants(text))
    assert [name for name, _ in variants] == ["as shipped", "chunks by points", "reduce"]
    for name, variant in variants:
        path = tmp_path / f"{name.replace(' ', '_')}.toml"
        path.write_text(variant)
        spec = load_spec(path)
        res = pbrdf_cl.sweep(spec, tmp_path / f"{path.stem}.zarr", progress=False)
        assert res.complete, name
        ds = res.open()
        if name == "reduce":
            assert set(ds.data_vars) == {"min", "mean", "argmin_phi"}
            assert ds["min"].dims == ("theta_i", "theta_r", "sigma")
        else:
            assert ds.dop.shape == (8, 86, 4, 64)
