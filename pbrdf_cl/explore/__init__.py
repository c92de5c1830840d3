"""Exploring the parameter space: global sensitivity, measurement design, maps, sweeps, the paper's figures."""
