"""The house rules of the package's layout (issue #27), measured on the source: no module over
700 code lines and no function over 90 (code lines: neither blank, comment nor docstring); no
import circle between modules; no module using another's private name (``from .x import _y`` or
``x._y``); callers outside the device layer branching on the backend (``is_numpy``) 5 times at
most and never comparing a backend's name (``backend == "numpy"``: the device layer's
``engine_for`` and ``resolve_engine`` decide what a name means); no module importing the package
root (``from .. import __version__``, ``import pbrdf_cl``: it imports every public name, and
``pbrdf_cl.version`` holds the version); every exception and warning class defined in
``pbrdf_cl/errors.py`` and exported; the rooms' layers (``LAYERS``, ARCHITECTURE.md's) and no literal list
of the model's parameter names outside its registry."""
import ast
import io
import tokenize
from pathlib import Path

import pytest

import pbrdf_cl
from pbrdf_cl import errors

PKG = Path(pbrdf_cl.__file__).resolve().parent
MODULES = sorted(p for p in PKG.rglob("*.py") if "kernels" not in p.parts)
MAX_MODULE, MAX_FUNCTION, MAX_BACKEND_BRANCHES = 700, 90, 5


def dotted(path):
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def code_lines(source):
    """The line numbers that hold code: not blank, not only a comment, not in a docstring."""
    tree = ast.parse(source)
    doc = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and \
                    isinstance(first.value.value, str):
                doc.update(range(first.lineno, first.end_lineno + 1))
    lines = set()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT,
                        tokenize.ENDMARKER):
            continue
        lines.update(range(tok.start[0], tok.end[0] + 1))
    return lines - doc


SOURCES = {p: p.read_text() for p in MODULES}
TREES = {p: ast.parse(s) for p, s in SOURCES.items()}


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PKG)))
def test_module_and_function_sizes(path):
    lines = code_lines(SOURCES[path])
    assert len(lines) <= MAX_MODULE, f"{path.relative_to(PKG)}: {len(lines)} code lines (at most {MAX_MODULE})"
    long = []
    for node in ast.walk(TREES[path]):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            n = len([ln for ln in lines if node.lineno <= ln <= node.end_lineno])
            if n > MAX_FUNCTION:
                long.append(f"{node.name} ({n})")
    assert not long, f"{path.relative_to(PKG)}: functions over {MAX_FUNCTION} code lines: {', '.join(long)}"


def imports(path):
    """(module imported, names taken from it, line) for every import of the package's own modules."""
    me = dotted(path)
    package = me if path.name == "__init__.py" else me.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(TREES[path]):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if not mod.startswith("pbrdf_cl"):
                continue
            for alias in node.names:
                sub = f"{mod}.{alias.name}"
                if any(dotted(p) == sub for p in MODULES):
                    out.append((sub, [], node.lineno))
                else:
                    out.append((mod, [alias.name], node.lineno))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("pbrdf_cl"):
                    out.append((alias.name, [], node.lineno))
    return out


def test_no_import_circle():
    graph = {dotted(p): {m for m, _, _ in imports(p) if m != dotted(p)} for p in MODULES}
    packages = {dotted(p) for p in MODULES if p.name == "__init__.py"}
    # a package's face imports its modules: not circles
    graph = {m: {t for t in ts if t not in packages} for m, ts in graph.items() if m not in packages}
    circles, state = [], {}

    def visit(m, stack):
        state[m] = "open"
        for t in sorted(graph.get(m, ())):
            if state.get(t) == "open":
                circles.append(" -> ".join(stack[stack.index(t):] + [t]))
            elif t not in state:
                visit(t, stack + [t])
        state[m] = "done"
    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not circles, "import circles:\n" + "\n".join(circles)


#: The layers of ARCHITECTURE.md ("Layers: who may import whom"): each room (a subpackage, a room of
#: fitting/, or a top-level module) imports only from rooms of a lower layer.
LAYERS = {
    "errors": 0, "results": 0, "version": 0, "model": 0,
    "sizes": 1, "ranges": 1,
    "device": 2,
    "compute": 3, "outputs": 3,
    "io": 4, "store": 4,
    "fitting": 5,
    "fitting.sample": 6, "fitting.images": 6,
    "fitting.sets": 7,
    "plots": 8,
    "analysis": 9,
    "bench": 10, "app": 10,
    "cli": 11, "__main__": 12,
}
FITTING_ROOMS = ("sample", "sets", "images")


def room(module):
    """The room of a dotted module name: its subpackage (fitting's own rooms apart), or itself."""
    parts = module.split(".")
    if len(parts) > 2 and parts[1] == "fitting" and parts[2] in FITTING_ROOMS:
        return f"fitting.{parts[2]}"
    return parts[1] if len(parts) > 1 else parts[0]


def test_rooms_import_only_the_layers_below_them():
    """Every import of the package's own modules (inside functions too) goes to a room of a lower
    layer, or stays in its room: no two rooms import each other, and the floors of ARCHITECTURE.md
    hold (issue #35).  Every room has a layer."""
    bad, rooms = [], set()
    for path in MODULES:
        me = dotted(path)
        if me == "pbrdf_cl":
            continue
        rooms.add(room(me))
        for mod, _, line in imports(path):
            a, b = room(me), room(mod)
            rooms.add(b)
            if a != b and b != "pbrdf_cl" and not LAYERS.get(a, -1) > LAYERS.get(b, 99):
                bad.append(f"{path.relative_to(PKG)}:{line}: {a} (layer {LAYERS.get(a)}) imports {mod} "
                           f"({b}, layer {LAYERS.get(b)})")
    assert not (rooms - set(LAYERS) - {"pbrdf_cl"}), sorted(rooms - set(LAYERS))
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_no_private_name_of_another_module():
    found = []
    for path in MODULES:
        me = dotted(path)
        module_aliases = {}
        for mod, names, line in imports(path):
            for n in names:
                if n.startswith("_") and not n.startswith("__") and mod != me:
                    found.append(f"{path.relative_to(PKG)}:{line}: from {mod} import {n}")
        for node in ast.walk(TREES[path]):
            if isinstance(node, ast.ImportFrom) and node.module is not None or isinstance(node, ast.ImportFrom):
                for alias in node.names:
                    module_aliases[alias.asname or alias.name] = alias.name
        modules = {a for a, n in module_aliases.items()
                   if any(dotted(p).endswith("." + n) for p in MODULES)}
        for node in ast.walk(TREES[path]):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in modules
                    and node.attr.startswith("_") and not node.attr.startswith("__")):
                found.append(f"{path.relative_to(PKG)}:{node.lineno}: {node.value.id}.{node.attr}")
    assert not found, f"{len(found)} uses of another module's private names:\n" + "\n".join(found)


def test_backend_branches_outside_the_device_layer():
    found = []
    for path in MODULES:
        if "device" in path.relative_to(PKG).parts:
            continue
        for node in ast.walk(TREES[path]):
            if isinstance(node, ast.Attribute) and node.attr == "is_numpy":
                found.append(f"{path.relative_to(PKG)}:{node.lineno}")
    assert len(found) <= MAX_BACKEND_BRANCHES, f"{len(found)} branches on the backend:\n" + "\n".join(found)


BACKEND_NAMES = {"auto", "opencl", "numpy"}  # pbrdf_cl.device.engine.BACKENDS


def _strings(node):
    """The string constants of a comparison's operand, or of a tuple/list/set of them."""
    elts = node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set)) else [node]
    return {e.value for e in elts if isinstance(e, ast.Constant) and isinstance(e.value, str)}


def _names_backend(node):
    """Whether an operand is a name or attribute that holds a backend (``backend``, ``args.backend``)."""
    return isinstance(node, ast.Name) and "backend" in node.id or \
        isinstance(node, ast.Attribute) and "backend" in node.attr


def backend_name_comparisons():
    """``backend == "numpy"``, ``args.backend != "numpy"``, ``backend in ("auto", "opencl")``: every
    comparison outside ``device/`` with a backend's name or a ``backend`` variable in it."""
    found = []
    for path in MODULES:
        if "device" in path.relative_to(PKG).parts:
            continue
        for node in ast.walk(TREES[path]):
            if isinstance(node, ast.Compare):
                operands = [node.left, *node.comparators]
                if any(_strings(o) & BACKEND_NAMES or _names_backend(o) for o in operands):
                    found.append(f"{path.relative_to(PKG)}:{node.lineno}")
    return found


def test_no_backend_name_comparison_outside_the_device_layer():
    found = backend_name_comparisons()
    assert not found, (f"{len(found)} comparisons of a backend's name outside pbrdf_cl/device/ (use "
                       "device.engine.engine_for / resolve_engine):\n" + "\n".join(found))


def root_imports():
    """Every import of the package root from inside the package: ``import pbrdf_cl``, ``from pbrdf_cl
    import x`` and ``from .. import x`` where x is not a module (``__version__``), at module level or
    inside a function."""
    found = []
    for path in MODULES:
        if path == PKG / "__init__.py":
            continue
        for mod, names, line in imports(path):
            if mod == "pbrdf_cl":  # the root itself, not one of its modules (those are named in full)
                found.append(f"{path.relative_to(PKG)}:{line}: {mod} {' '.join(names)}".rstrip())
    return found


def test_no_module_imports_the_package_root():
    found = root_imports()
    assert not found, (f"{len(found)} imports of the package root (import the module that owns the name, "
                       "pbrdf_cl.version for __version__):\n" + "\n".join(found))


def test_the_checks_find_what_they_look_for():
    """The two counts above on made-up sources: they find each form (so that a count of 0 means none)."""
    source = ("def f(args, backend):\n    if backend == 'numpy' or args.backend != 'opencl':\n        pass\n"
              "    if backend in ('auto', 'opencl'):\n        pass\n    from .. import __version__\n"
              "    import pbrdf_cl\n    from pbrdf_cl import dop\n    from .. import sizes\n")
    fake = PKG / "store" / "made_up.py"
    TREES[fake] = ast.parse(source)
    MODULES.append(fake)
    try:
        assert len(backend_name_comparisons()) == 3
        assert [f.split(": ", 1)[1] for f in root_imports()] == ["pbrdf_cl __version__", "pbrdf_cl",
                                                                 "pbrdf_cl dop"]
    finally:
        MODULES.remove(fake)
        del TREES[fake]


def test_every_exception_is_defined_in_errors_and_exported():
    for path in MODULES:
        if path.name == "errors.py":
            continue
        for node in ast.walk(TREES[path]):
            if isinstance(node, ast.ClassDef):
                bases = {getattr(b, "id", getattr(b, "attr", "")) for b in node.bases}
                assert not (bases & {"Exception", "ValueError", "RuntimeError", "UserWarning", "Warning",
                                     "OSError", "MemoryError", "KeyError", "TypeError"}) and \
                    not node.name.endswith(("Error", "Warning")), \
                    f"{path.relative_to(PKG)}:{node.lineno}: exception {node.name} outside pbrdf_cl/errors.py"
    for name in dir(errors):
        obj = getattr(errors, name)
        if isinstance(obj, type) and issubclass(obj, BaseException) and obj.__module__ == errors.__name__:
            assert name in pbrdf_cl.__all__ and getattr(pbrdf_cl, name) is obj, f"{name} is not exported"


def test_parameter_names_are_listed_once_in_the_registry():
    """No tuple, list, set or dict display names three or more of the model's parameters outside
    ``model/inputs.py`` (issue #35): a path that needs several of them reads the registry
    (``PARAMETERS``, ``FITTED``, ``MEMBERS[family]``, ``DEFAULTS``, ``UNITS``, ...), so that adding an
    input is one record.  (Values for one material or one grid are data, written ``dict(n=..., ...)``.)"""
    from pbrdf_cl.model.inputs import PARAMETERS
    names = set(PARAMETERS)
    found = []
    for path in MODULES:
        if path == PKG / "model" / "inputs.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            elts = (node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set))
                    else [k for k in node.keys if k is not None] if isinstance(node, ast.Dict) else [])
            listed = {e.value for e in elts if isinstance(e, ast.Constant) and isinstance(e.value, str)} & names
            if len(listed) >= 3:
                found.append(f"{path.relative_to(PKG)}:{node.lineno}: {sorted(listed)}")
    assert not found, "literal lists of parameter names:\n" + "\n".join(found)
