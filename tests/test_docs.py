"""Every public function documents its parameters, what it returns and an example (numpydoc), and
the examples that need no data file run (doctest)."""
import doctest
import importlib
import inspect
import re
from pathlib import Path

import pytest

import pbrdf_cl
from pbrdf_cl.analysis import instruments, maps, sensitivity
from pbrdf_cl.compute import dense
from pbrdf_cl.compute import pointwise as api
from pbrdf_cl.fitting.images import batch, dataset, label_stage
from pbrdf_cl.fitting.images import store as batch_store
from pbrdf_cl.io import camera, imagestack, source
from pbrdf_cl.io import measurements as data
from pbrdf_cl.plots import images as batch_plots
from pbrdf_cl.plots import joint as joint_plots
from pbrdf_cl.plots import maps as map_plots
from pbrdf_cl.plots import sensitivity as sensitivity_plots

PUBLIC = [getattr(pbrdf_cl, n) for n in pbrdf_cl.__all__ if inspect.isfunction(getattr(pbrdf_cl, n))]
PUBLIC += [maps.make_map, map_plots.plot_map, data.as_measurements, sensitivity.load_sobol_spec,
           sensitivity_plots.plot_sensitivity, source.open_stack, dataset.goodness_summary, data.split_sets,
           joint_plots.plot_joint, label_stage.run_label_stage, instruments.instruments]
PUBLIC += [getattr(m, n) for m in (imagestack, camera, batch, batch_store, batch_plots) for n in dir(m)
           if not n.startswith("_") and inspect.isfunction(getattr(m, n)) and getattr(m, n).__module__ == m.__name__]


@pytest.mark.parametrize("func", PUBLIC, ids=lambda f: f.__name__)
def test_numpydoc_sections(func):
    doc = inspect.getdoc(func) or ""
    needed = ("Parameters\n----------",) if inspect.signature(func).parameters else ()
    for section in needed + ("Returns\n-------", "Examples\n--------"):
        assert section in doc, f"{func.__module__}.{func.__name__} has no {section.splitlines()[0]} section"
    params = doc.split("Parameters\n----------", 1)[-1].split("Returns\n-------", 1)[0]
    for name in inspect.signature(func).parameters:
        assert name in params, f"{func.__name__}: parameter {name!r} is not in its Parameters section"


@pytest.mark.parametrize("module", [api, dense, data, maps, map_plots, imagestack, batch, batch_store, source,
                                    batch_plots, sensitivity, sensitivity_plots, instruments],
                         ids=lambda m: m.__name__)
def test_docstring_examples_run(module):
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE,
                             extraglobs={"pbrdf_cl": pbrdf_cl})
    assert result.attempted > 0 and result.failed == 0



def test_every_public_name_is_in_the_api_reference():
    """The site's API pages (docs/api/*.rst) document every name of ``pbrdf_cl.__all__`` and every
    public function above; the build (``sphinx -W``) then checks each one's parameters (numpydoc PR01,
    PR02) and cross-references."""
    text = "\n".join(p.read_text() for p in (Path(__file__).resolve().parent.parent / "docs" / "api").glob("*.rst"))
    documented = set(re.findall(r"^\.\. auto(?:function|class|exception|data|module):: (\S+)$", text, re.M))
    objects = set()
    for name in documented:
        module, _, attr = name.rpartition(".")
        try:
            objects.add(id(getattr(importlib.import_module(module), attr)))
        except ImportError:  # pbrdf_cl.quantities.names: in a module re-exported under another name
            assert getattr(importlib.import_module(module.rpartition(".")[0]), module.rpartition(".")[2]), name
    missing = [n for n in pbrdf_cl.__all__ if n != "__version__" and f"pbrdf_cl.{n}" not in documented]
    missing += [f"{f.__module__}.{f.__name__}" for f in PUBLIC if id(f) not in objects]
    assert not missing, f"not in docs/api/*.rst: {missing}"
