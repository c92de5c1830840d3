#!/usr/bin/env python3
"""Reproduce Zhu et al. (2020): Fig. 2 (aluminum, black paint; synthetic data, both models
fitted), Table 1, Fig. 4, Fig. 5 and two dense DOP maps, with the arrays of every figure and a
summary.md, into one folder.  Same as ``pbrdf-cl reproduce``; options: ``--help``."""
import sys

from pbrdf_cl.cli import main

if __name__ == "__main__":
    sys.exit(main(["reproduce", *sys.argv[1:]]))
