#!/usr/bin/env python3
"""Benchmark every evaluation path of pbrdf-cl (same as `pbrdf-cl bench`); see pbrdf_cl/bench.py."""
import sys

from pbrdf_cl.bench import main

if __name__ == "__main__":
    sys.exit(main())
