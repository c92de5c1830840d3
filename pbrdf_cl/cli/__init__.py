"""Command line interface: ``pbrdf-cl devices|eval|fit|fit-image|reproduce|map|sweep|sobol|design|bench``.

Every problem a user can meet, bad input or a broken environment (no OpenCL, an unusable
device, an unwritable cache or output folder), ends in one line on stderr, ``pbrdf-cl: error:
...`` saying what is wrong and what to do, and a non-zero exit status; never a traceback.

The parser and :func:`main` are in ``app``; the commands in one module per group: ``devices``,
``evaluate`` (eval), ``fit`` (fit, fit-image), ``explore`` (sweep, map, sobol, design,
reproduce); what they share in ``common``; the checks of output paths in :mod:`pbrdf_cl.outputs`.
"""
from .app import build_parser, main
from .evaluate import parse_values

__all__ = ["build_parser", "main", "parse_values"]
