"""Sphinx configuration of the pbrdf-cl site.

Build: ``python -m sphinx -W --keep-going -b html docs docs/_build/html`` (what ``.ci/run`` runs).
Pages are Markdown (MyST); the API reference is autodoc with numpydoc, and numpydoc's validation
fails the build on a public function whose docstring does not document a parameter (PR01) or
documents one it does not have (PR02); ``nitpicky`` fails it on a cross-reference that resolves
to nothing.  The gallery (``docs/gallery/``) runs at every build (sphinx-gallery).
"""
import inspect
import os
import sys
import time
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path.insert(0, str(DOCS.parent))
sys.path.insert(0, str(DOCS))
os.environ.setdefault("MPLBACKEND", "Agg")

import pbrdf_cl  # noqa: E402

project = "pbrdf-cl"
author = "pbrdf-cl contributors"
copyright = "2026, pbrdf-cl contributors"
release = version = pbrdf_cl.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "sphinx-mathjax-offline",  # MathJax served from the built site: the equations render offline too
    "numpydoc",
    "sphinx_gallery.gen_gallery",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "gallery/README.rst", "gallery/*.py", "auto_gallery/*.ipynb",
                    "auto_gallery/*.py", "auto_gallery/*.zip", "auto_gallery/*.json"]

# ---- Markdown (MyST) -------------------------------------------------------------------------
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence"]
myst_heading_anchors = 3

# ---- API reference: autodoc + numpydoc --------------------------------------------------------
autodoc_typehints = "none"
autodoc_member_order = "bysource"
autodoc_default_options = {"undoc-members": False}
numpydoc_show_class_members = False
numpydoc_xref_param_type = False
numpydoc_validation_checks = {"PR01", "PR02"}
# public names only: a private helper's docstring is not validated
numpydoc_validation_exclude = {r"\._[a-z]", r"\.__[a-z]+__$"}

# a broken cross-reference is an error (with -W); the names below are other projects' objects,
# written as cross-references in docstrings, which this site does not link (no intersphinx: the
# build stays offline)
nitpicky = True
nitpick_ignore_regex = [
    ("py:.*", r"(numpy|np|xarray|xr|pandas|pd|scipy|matplotlib|pyopencl|cl|dask|zarr|SALib|nlopt|polanalyser)\..*"),
    ("py:.*", r"(float|int|str|bool|dict|list|tuple|None|callable|optional|array_like|array|ndarray)"),
]

# ---- Gallery (sphinx-gallery) -----------------------------------------------------------------


sphinx_gallery_conf = {
    "examples_dirs": "gallery",
    "gallery_dirs": "auto_gallery",
    "filename_pattern": r"/plot_",
    "image_scrapers": ("matplotlib", "gallery_hooks.png_scraper"),
    "reset_modules": ("matplotlib", "gallery_hooks.clean_outputs"),
    "reset_modules_order": "both",
    "download_all_examples": False,
    "remove_config_comments": True,
    "min_reported_time": 0,
    "abort_on_example_error": True,
    "plot_gallery": "True",
    "reference_url": {"pbrdf_cl": None},
    "show_memory": False,
    "within_subsection_order": "FileNameSortKey",
}

# ---- HTML ------------------------------------------------------------------------------------
html_theme = "furo"
html_title = f"pbrdf-cl {release}"
html_static_path = []
html_show_sourcelink = False

_start = time.monotonic()


def _report_time(app, exc):
    if exc is None:
        print(f"pbrdf-cl docs: built in {time.monotonic() - _start:.1f} s")


def _import_dotted(name):
    """The object named ``a.b.c`` (a module, then attributes), or None."""
    import importlib
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for attr in parts[cut:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return None
        return obj
    return None


_DOCUMENTED = {}


def _resolve_alias(app, env, node, contnode):
    """A reference to an object under another of its names (``pbrdf_cl.fitting.sample.inversion.fit``, or
    ``fit`` inside that module's docstrings) resolves to where the object is documented
    (``pbrdf_cl.fit``). A reference to an object that does not exist, or is documented nowhere,
    stays broken (and fails the build)."""
    if node.get("refdomain") != "py":
        return None
    domain = env.get_domain("py")
    size, index = _DOCUMENTED.get("py", (-1, {}))
    if size != len(domain.objects):  # id(object) -> the name it is documented under
        index = {}
        for fullname in domain.objects:
            obj = _import_dotted(fullname)
            if callable(obj) or inspect.ismodule(obj):
                index.setdefault(id(obj), fullname)
        _DOCUMENTED["py"] = (len(domain.objects), index)
    target = node["reftarget"].lstrip("~.")
    names = [f"{node['py:module']}.{target}"] if node.get("py:module") else []
    # in a docstring of a re-exported object (pbrdf_cl.fit_batch), a short name is one of the
    # module that defines it (pbrdf_cl.fitting.images.batch)
    source = str(node.source or "")
    if "docstring of " in source:
        owner = _import_dotted(source.split("docstring of ", 1)[1].strip())
        if getattr(owner, "__module__", None):
            names.append(f"{owner.__module__}.{target}")
    for name in names + [target]:
        obj = _import_dotted(name)
        documented = index.get(id(obj)) if (callable(obj) or inspect.ismodule(obj)) else None
        if documented:
            return domain.resolve_xref(env, node["refdoc"], app.builder, node["reftype"], documented, node,
                                       contnode)
    return None


def _link_included_pages(app, relative_path, parent_docname, content):
    """ARCHITECTURE.md and CONTRIBUTING.md link each other by file name: on the site those are the
    pages ``architecture`` and ``contributing`` that include them."""
    if relative_path.name in ("ARCHITECTURE.md", "CONTRIBUTING.md"):
        content[0] = content[0].replace("](ARCHITECTURE.md", "](architecture.md").replace(
            "](CONTRIBUTING.md", "](contributing.md")


def setup(app):
    app.connect("include-read", _link_included_pages)
    app.connect("build-finished", _report_time)
    app.connect("missing-reference", _resolve_alias)
