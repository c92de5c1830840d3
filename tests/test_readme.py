"""Docs that cannot rot: every code block of the README and of the documentation site's pages
(``docs/**/*.md``) runs (each page's Python blocks in order in one namespace, in a scratch folder
with the bundled ``examples/``; shell commands through ``python -m pbrdf_cl`` in such a folder), and
the example sweep spec runs with each of its optional sections enabled.

Not run, and why: the two fresh-machine commands at the top of the README and of the getting-started
page (they create a virtual environment and install the package: ``.ci/run`` runs the second on a
clean checkout, and ``tests/test_paper.py`` the main job's ``pbrdf-cl reproduce``); synopsis lines
(``[--option ...]``), whose options are checked against the parser instead; commands that need a
dask cluster (``--workers``, ``--scheduler``, ``dask ...``; tests/test_sweep_faults.py runs
``--workers 2``) or a file named only as an example (``spec.toml``, ``data.csv``), which are parsed,
not run; ``python scripts/...`` lines (benchmarks and generators that take minutes: the script must
exist); ``text`` and ``toml`` blocks (sample output, spec files shown); a block right after a
``<!-- not run: reason -->`` line, which must give its reason (a file written elsewhere, a camera's
data); and the pages included from ``ARCHITECTURE.md`` and ``CONTRIBUTING.md`` (not under
``docs/``: their blocks are the developer's commands, the test suite itself among them). The
gallery's examples run at every build of the site (``.ci/run``), not here.
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
from pbrdf_cl.analysis.sweeps import load_spec

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_ROOT = str(ROOT)
NOT_RUN = re.compile(r"^<!-- not run: (.+) -->$")
#: the README and every Markdown page of the site (not the build's output)
PAGES = [ROOT / "README.md"] + sorted(p for p in (ROOT / "docs").rglob("*.md")
                                      if not {"_build", "auto_gallery"} & set(p.relative_to(ROOT / "docs").parts))


def page_id(path):
    return str(path.relative_to(ROOT))


def blocks(lang, page=ROOT / "README.md"):
    """(line number, text) of a page's fenced blocks in ``lang``, but those marked not run."""
    out, lines, inside, start, skip = [], page.read_text().splitlines(), None, 0, False
    for i, line in enumerate(lines, 1):
        if line.startswith("```"):
            if inside is None:
                inside, start, body = line[3:].strip(), i, []
                skip = i > 1 and bool(NOT_RUN.match(lines[i - 2].strip()))
            else:
                if inside == lang and not skip:
                    out.append((start, "\n".join(body)))
                inside = None
            continue
        if inside is not None:
            body.append(line)
    return out


def shell_commands(page=ROOT / "README.md"):
    """Every command of a page's bash blocks: (line, command)."""
    found = []
    for start, text in blocks("bash", page):
        joined = re.sub(r"\\\n\s*", " ", text)
        for line in joined.splitlines():
            line = re.split(r"\s{2,}#", line)[0].strip()
            if not line or line.startswith("#"):
                continue
            found.append((start, line))
    return found


def test_the_pages_are_found_and_every_not_run_mark_gives_a_reason():
    names = {page_id(p) for p in PAGES}
    assert {"README.md", "docs/index.md", "docs/getting_started.md", "docs/model.md", "docs/guide/fit.md",
            "docs/joint.md"} <= names
    for page in PAGES:
        for i, line in enumerate(page.read_text().splitlines(), 1):
            if line.startswith("<!-- not run"):
                match = NOT_RUN.match(line.strip())
                assert match and len(match.group(1)) > 20, f"{page_id(page)}:{i}: say why the block is not run"


@pytest.fixture
def scratch(tmp_path, monkeypatch):
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    return tmp_path


PY_PAGES = [p for p in PAGES if blocks("python", p)]


def test_the_python_blocks_are_many():
    assert sum(len(blocks("python", p)) for p in PAGES) >= 15
    assert len(PY_PAGES) >= 12


@pytest.mark.parametrize("page", PY_PAGES, ids=page_id)
def test_every_python_block_runs_in_order(scratch, page):
    namespace = {"__name__": "__docs__"}
    for start, text in blocks("python", page):
        try:
            exec(compile(text, f"{page_id(page)}:{start}", "exec"), namespace)
        except Exception as exc:  # noqa: BLE001 - name the block
            raise AssertionError(f"{page_id(page)} block at line {start} fails: {type(exc).__name__}: {exc}") from exc
    if page.name == "sweeps.md":
        assert namespace["res"].complete  # the page's sweep


def _options_of(command):
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    return {o for a in sub._actions for o in a.option_strings}


SH_PAGES = [p for p in PAGES if shell_commands(p)]


def test_the_shell_commands_are_many():
    assert sum(len(shell_commands(p)) for p in PAGES) >= 20


@pytest.mark.parametrize("page", SH_PAGES, ids=page_id)
def test_every_shell_command_runs_or_parses(scratch, page):
    for start, line in shell_commands(page):
        where = f"{page_id(page)} line {start}"
        if "pip install" in line or line.startswith("dask "):
            continue  # see the module docstring
        argv = shlex.split(line)
        if argv[:1] == ["python"] and argv[1].startswith("scripts/"):
            assert (ROOT / argv[1]).is_file(), f"{where}: no script {argv[1]}"
            continue  # see the module docstring
        assert argv[0] == "pbrdf-cl", (where, line)
        options = {t.split("=")[0] for t in re.findall(r"--[a-z][a-z0-9-]*", line)}
        if argv[1] != "bench":
            unknown = options - _options_of(argv[1])
            assert not unknown, f"{where}: {argv[1]} has no option {sorted(unknown)}"
        if "[" in line or re.search(r"--workers|--scheduler|spec\.toml|data\.csv|bench", line):
            continue  # a synopsis or an example name: parsed above, not run
        proc = subprocess.run([sys.executable, "-m", "pbrdf_cl", *argv[1:]], capture_output=True, text=True,
                              timeout=600, env=dict(os.environ, PYTHONPATH=PACKAGE_ROOT))
        assert proc.returncode == 0, f"{where}: {line}\n{proc.stderr[-2000:]}"


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
