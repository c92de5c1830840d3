"""The ``pbrdf-cl`` application: the parser of every command (with a suggestion for a misspelt
option) and :func:`main`, which runs one and turns every error into one line on stderr."""
from __future__ import annotations

import argparse
import os
import sys
import warnings

from .. import ranges, sizes
from ..device import engine as _engine
from ..errors import CommandError
from ..store import interrupt
from . import analysis, devices, evaluate, explorer, fit
from .common import error


def cmd_bench(args) -> int:
    from .. import bench
    return bench.main(args.rest)


class _HelpFormatter(argparse.HelpFormatter):
    """Shows each option's default after its help (not for None/False defaults, nor where the help
    says it already)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (action.option_strings and action.default not in (None, False, argparse.SUPPRESS)
                and "default" not in text):
            text += " (default: %(default)s)"
        return text


class _Parser(argparse.ArgumentParser):
    """argparse with a suggestion for a misspelt option: ``unrecognized arguments: --sigmaa; did you
    mean --sigma?``."""

    def __init__(self, *args, **kw):
        kw.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kw)

    def error(self, message):
        import difflib
        if "unrecognized arguments" in message:
            known = sorted({o for parser in _all_parsers(self) for a in parser._actions for o in a.option_strings})
            for token in message.split(":", 1)[1].split():
                if token.startswith("--"):
                    close = difflib.get_close_matches(token.split("=")[0], known, n=1, cutoff=0.6)
                    if close:
                        message += f"; did you mean {close[0]}?"
                        break
        super().error(message)


def _all_parsers(parser):
    """``parser`` and the parser of the sub-command given on this command line, if any."""
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = getattr(parser, "_chosen", None)
            found += [action.choices[chosen]] if chosen in action.choices else list(action.choices.values())
    return found


#: Options that take a list of NAME=VALUE items: a token without "=" after them is not theirs.
_ITEM_OPTIONS = ("--fix", "--bounds")


def _positionals_first(argv):
    """Move file names that follow a NAME=VALUE list option (``fit --fix sigma=0.45 data.csv``) in front
    of it, so that the list does not swallow the positional argument."""
    out, moved, in_items = [], [], False
    for token in argv:
        if token in _ITEM_OPTIONS:
            in_items = True
        elif token.startswith("-"):
            in_items = False
        elif in_items and "=" not in token and (os.path.exists(token) or "/" in token or "." in token.lstrip(".")):
            moved.append(token)  # a file name, not a malformed item (those get their own message)
            continue
        out.append(token)
    return out[:1] + moved + out[1:] if moved else out


def build_parser() -> argparse.ArgumentParser:
    from ..version import __version__
    p = _Parser(prog="pbrdf-cl", description="The six-parameter pBRDF model on OpenCL. "
                "Angles in degrees; phi = 180 is the in-plane geometry. `pbrdf-cl COMMAND --help` for each.")
    p.add_argument("--version", action="version", version=f"pbrdf-cl {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    devices.devices_parser(sub)
    evaluate.eval_parser(sub)
    analysis.sweep_parser(sub)
    analysis.verify_parser(sub)
    fit.fit_parser(sub)
    fit.fit_image_parser(sub)
    analysis.reproduce_parser(sub)
    analysis.map_parser(sub)
    analysis.sobol_parser(sub)
    analysis.design_parser(sub)
    explorer.explore_parser(sub)
    b = sub.add_parser("bench", help="benchmark every evaluation path (options: pbrdf-cl bench --help)",
                       add_help=False)
    b.add_argument("rest", nargs=argparse.REMAINDER)
    b.set_defaults(func=cmd_bench)
    return p


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings as one line each, ``pbrdf-cl: warning: ...``."""
    print(f"pbrdf-cl: warning: {message}", file=sys.stderr if file is None else file)


def _environment_error(exc):
    """The one-line report of an environment problem met while working."""
    cl = _engine.cl
    if isinstance(exc, _engine.OpenCLUnavailableError):
        return str(exc)
    if cl is not None and isinstance(exc, cl.Error):
        return (f"OpenCL: {_engine.first_error_line(exc)}; try another device (`pbrdf-cl devices`) or "
                "--backend numpy")
    if isinstance(exc, sizes.TooLargeError):
        return str(exc)  # the estimate, found before any work
    if isinstance(exc, MemoryError):
        return "out of memory; use smaller sizes (fewer points per axis, a smaller memory_budget)"
    if isinstance(exc, OSError):
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        return f"cannot access{where}: {exc.strerror or exc}; check the path and its permissions"
    return None


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["bench"]:  # its options are bench.main's own (argparse's REMAINDER drops "--x" ones)
        args = argparse.Namespace(func=cmd_bench, rest=argv[1:])
    else:
        parser = build_parser()
        if not argv:
            parser.print_help()
            return 0
        parser._chosen = argv[0]
        args = parser.parse_args(_positionals_first(argv))
    saved = warnings.showwarning
    warnings.showwarning = _show_warning
    try:
        with interrupt.recording():
            return args.func(args)
    except (CommandError, ranges.RangeError) as exc:
        return error(exc)
    except KeyboardInterrupt:
        print("pbrdf-cl: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - environment faults get one line, anything else a traceback
        text = _environment_error(exc)
        if text is None:
            raise
        return error(text)
    finally:
        warnings.showwarning = saved
