"""Checks of the files a command will write, made before any work (the command line, the
benchmark, the scripts): an output whose suffix is not the format written there, or that cannot
be written, is refused with a one-line :class:`pbrdf_cl.errors.CommandError` naming the option,
the path and the fix."""
from __future__ import annotations

from pathlib import Path

from .device import drivers
from .errors import CommandError


def check_output(option, path, folder=False):
    """Refuse an output that cannot be written before any work is done (:class:`CommandError`):
    its folder (``path`` itself with ``folder``) is a file or not writable; a file's folder that
    does not exist (a mistyped path: it is not made).  A folder output (``folder``) is made with
    its parents.  URLs are not checked."""
    if path is None or "://" in str(path):
        return
    target = Path(path) if folder else (Path(path).parent if str(Path(path).parent) else Path("."))
    if target.exists() and not target.is_dir():
        raise CommandError(f"{option} {path}: {target} is a file, not a folder; choose another {option}")
    above = next((a for a in target.parents if a.exists()), None)
    if not target.exists() and above is not None and not above.is_dir():
        raise CommandError(f"{option} {path}: cannot write into {target} ({above} is a file, not a folder); "
                           f"choose a writable {option}")
    if not folder and not target.exists():
        raise CommandError(f"{option} {path}: the folder {target} does not exist; create it first or choose "
                           f"another {option}")
    why = drivers.writable_dir(target)
    if why is not None:
        raise CommandError(f"{option} {path}: cannot write into {target} ({why}); choose a writable {option}")


def _suffix(path):
    """The lower-case suffix of a path or URL (``""`` for none)."""
    return Path(str(path).split("://", 1)[-1]).suffix.lower()


def figure_formats():
    """The file suffixes matplotlib writes figures as (``.png``, ``.pdf``, ``.svg``, ...)."""
    from matplotlib.backend_bases import FigureCanvasBase
    return tuple(sorted("." + f for f in FigureCanvasBase.get_supported_filetypes()))


def check_suffix(option, path, suffixes, what, allow_none=False):
    """Refuse before any work (:class:`CommandError`) an output whose suffix is not one of ``suffixes``
    (the format it will be written in): ``--out params.npz`` for a Zarr store, ``--out m.txt`` for
    a figure.  ``what`` says what is written there.  ``allow_none``: a path without a suffix is
    written as that format (a store's folder, a JSON file); where a writer would append a suffix of
    its own (matplotlib, numpy's savez) it is refused too, so that the file written is the one named."""
    if path is None:
        return
    suffix = _suffix(path)
    if suffix in suffixes or (allow_none and not suffix):
        return
    name = Path(str(path).split("://", 1)[-1]).name
    stem = name[: len(name) - len(suffix)] if suffix else name
    names = ", ".join(suffixes[:3]) + (", ..." if len(suffixes) > 3 else "") + (" or none" if allow_none else "")
    raise CommandError(f"{option} {path}: {what}, named with the suffix {names}, not "
                       f"{repr(suffix) if suffix else 'without one'}; write e.g. {option} {stem}{suffixes[0]}")


def check_figure(option, path):
    """Refuse before any work a figure path matplotlib cannot write as its suffix says."""
    if path is not None:
        formats = figure_formats()
        order = [".png", ".pdf", ".svg"] + [f for f in formats if f not in (".png", ".pdf", ".svg")]
        check_suffix(option, path, tuple(order), "a figure is written here in the format its suffix names")


def check_json_output(option, path):
    """Refuse before any work (:class:`CommandError`) a JSON output with another suffix, or that
    cannot be written."""
    check_suffix(option, path, (".json",), "JSON is written here", allow_none=True)
    check_output(option, path)


def check_json(option, path, prog="pbrdf-cl"):
    """For the scripts: refuse a JSON output with another suffix, or that cannot be written, before
    their work, in one line on stderr (``SystemExit``)."""
    try:
        check_json_output(option, path)
    except CommandError as exc:
        raise SystemExit(f"{prog}: error: {exc}") from None


def check_store(option, path):
    """Refuse before any work a Zarr store path with another format's suffix (``params.npz``)."""
    check_suffix(option, path, (".zarr",), "a Zarr store (a folder that xarray.open_zarr reads) is written here",
                 allow_none=True)
